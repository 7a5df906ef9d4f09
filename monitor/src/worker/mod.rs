//! The logging worker: one thread that decodes what the callbacks queued and
//! logs it to rerun. Nothing here runs on a Zenoh thread; malformed
//! messages are counted and skipped, never panicked on. Here: the worker,
//! its per-env view and the routing of each sample to its handler; the
//! handlers by job below.
//!
//! - [`world`]: each env's world, asked of its controller, and the scene.
//! - [`images`]: camera and overhead frames.
//! - [`motion`]: commands, poses, odometry and the trajectory.
//! - [`events`]: episodes, tracking, status, e-stops, liveliness, health.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use offworld_runtime::estop::{Latch, Pressed, RecentPresses};
use offworld_runtime::keys::global_estop_key;
use offworld_runtime::msg::{
    CameraFrame, EStop, EStopState, EnvState, EnvStatus, EpisodeEvent, Image, ImageError,
    MotionCommand, Odometry, PixelEncoding, PoseStamped, SeqTag, Time, TrackingStatus,
};
use offworld_runtime::world::WorldSpec;
use offworld_runtime::{codec, wire, EnvId};
use rerun::components::ImageFormat;
use rerun::datatypes::{ChannelDatatype, ColorModel};
use rerun::{RecordingStream, ViewCoordinates};
use zenoh::sample::{Sample, SampleKind};
use zenoh::Session;

use crate::columns::{Columns, Row, Stamp};
use crate::paths::{self, env_path, env_root};
use crate::queue::{Lane, Queue};
use crate::{layout, scene, MonitorStats};

mod events;
mod images;
mod motion;
mod world;

/// The world used when an env's controller does not say.
pub(crate) const FALLBACK_WORLD: &str = "monolith";

/// The built-in [`FALLBACK_WORLD`] (compiled into offworld-runtime and
/// covered by its tests; `None` only if that data were broken).
pub(crate) fn fallback_world() -> Option<WorldSpec> {
    WorldSpec::builtin(FALLBACK_WORLD).ok()
}
/// Longest trajectory kept per episode (oldest points go first).
const MAX_TRAJECTORY: usize = 4096;
/// A tracker pose extends the trajectory once it moved this far, m.
const TRAJECTORY_STEP_M: f32 = 0.01;
/// The trajectory is re-logged at most this often (it grows all episode).
const TRAJECTORY_PERIOD: Duration = Duration::from_millis(100);
/// Rows go to rerun at least this often (as one chunk per entity) …
const COLUMN_PERIOD: Duration = Duration::from_millis(100);
/// … or once this many bytes (images, text, trajectories) are pending.
const COLUMN_MAX_BYTES: usize = 8 << 20;
/// How often the monitor logs its own health.
const HEALTH_PERIOD: Duration = Duration::from_secs(1);

/// What the callbacks and helpers hand the worker.
pub(crate) enum Event {
    /// A publication under the monitored key expression.
    Sample {
        /// The sample as received.
        sample: Sample,
        /// When the callback ran.
        wall: SystemTime,
    },
    /// A liveliness token appeared or vanished.
    Alive {
        /// The token's key.
        key: String,
        /// Appeared (true) or vanished.
        online: bool,
        /// When the callback ran.
        wall: SystemTime,
    },
    /// The world of an env was resolved (or given up on).
    World {
        /// The env.
        env: EnvId,
        /// The world to draw (`None`: nothing to draw).
        world: Option<Box<WorldSpec>>,
        /// Where it came from, for the event log.
        source: WorldSource,
    },
}

/// Where an env's world came from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum WorldSource {
    /// The monitor's configuration.
    Configured,
    /// The controller's `spec` reply.
    Spec,
    /// The recorded episode's `EpisodeInfo` (a replay).
    Recording,
    /// Nobody said; the default world (with the reason).
    Fallback(String),
}

impl Event {
    /// The camera (its key) a camera frame comes from; `None` for anything
    /// else (a deletion included: it supersedes nothing).
    fn camera(&self) -> Option<&str> {
        match self {
            Event::Sample { sample, .. } if sample.kind() == SampleKind::Put => {
                let key = sample.key_expr().as_str();
                (lane_of(key) == Lane::Frame).then_some(key)
            }
            _ => None,
        }
    }

    /// Whether this camera frame replaces `older`, a queued frame of the
    /// same camera, for a live view (which shows each camera's newest).
    /// The newest is chosen before decoding: a malformed newest frame is
    /// counted as such, the frames it replaced as superseded.
    pub(crate) fn supersedes(&self, older: &Event) -> bool {
        self.camera()
            .is_some_and(|camera| older.camera() == Some(camera))
    }
}

/// The lane a sample travels in: camera images are big and expendable.
pub(crate) fn lane_of(key: &str) -> Lane {
    let topic = topic_of(key).unwrap_or_default();
    if matches!(topic, "obs" | "preview") || topic.starts_with("overhead/") {
        Lane::Frame
    } else {
        Lane::Message
    }
}

/// An env key's topic (`cmd`, `overhead/top`, …): what follows
/// `offworld/@v1/<realm>/<name>/`.
pub(crate) fn topic_of(key: &str) -> Option<&str> {
    key.splitn(5, '/').nth(4)
}

/// Counters the worker keeps (read by the handle at any time).
#[derive(Debug, Default)]
pub(crate) struct WorkerCounters {
    pub decode_errors: AtomicU64,
    pub log_errors: AtomicU64,
    pub frames: AtomicU64,
    pub poses: AtomicU64,
    pub odometry: AtomicU64,
    pub commands: AtomicU64,
    pub rewards: AtomicU64,
    pub statuses: AtomicU64,
    pub overhead_frames: AtomicU64,
    pub envs: AtomicU64,
}

/// Everything the handle and the worker share.
pub(crate) struct Shared {
    pub queue: Queue<Event>,
    pub counters: WorkerCounters,
}

impl Shared {
    pub fn stats(&self) -> MonitorStats {
        let q = &self.queue.counters;
        let c = &self.counters;
        let get = |a: &AtomicU64| a.load(Ordering::Relaxed);
        MonitorStats {
            received: get(&q.received),
            dropped_frames: get(&q.dropped_frames),
            dropped_messages: get(&q.dropped_messages),
            decode_errors: get(&c.decode_errors),
            log_errors: get(&c.log_errors),
            superseded_frames: get(&q.superseded_frames),
            frames: get(&c.frames),
            poses: get(&c.poses),
            odometry: get(&c.odometry),
            commands: get(&c.commands),
            rewards: get(&c.rewards),
            statuses: get(&c.statuses),
            overhead_frames: get(&c.overhead_frames),
            envs: get(&c.envs),
        }
    }
}

/// A planar pose with height, for trajectories and odometry anchoring.
#[derive(Debug, Clone, Copy)]
struct Planar {
    x: f64,
    y: f64,
    z: f64,
    yaw: f64,
}

#[derive(Default)]
struct EnvView {
    world: Option<WorldSpec>,
    world_source: Option<WorldSource>,
    resolving: bool,
    retried: bool,
    /// Latest motion-command seq (the `step` timeline).
    seq: Option<u64>,
    /// Resolution of the last camera frame, and the one the pinhole has.
    camera_res: Option<(u32, u32)>,
    pinhole_res: Option<(u32, u32)>,
    last_pose: Option<Planar>,
    last_odom: Option<Planar>,
    trajectory: Vec<[f32; 3]>,
    /// When the trajectory was last logged; points added since then.
    trajectory_logged: Option<SystemTime>,
    trajectory_dirty: bool,
    episode: Option<u64>,
    tracking: Option<bool>,
    status: Option<EnvState>,
    estop: Option<bool>,
    /// The env latch as its obeyers apply presses (a refused or repeated
    /// copy changes nothing here either).
    env_latch: Obeyed,
    /// When the last reset logged ended (Unix ms).
    last_reset_ms: Option<i64>,
}

/// Settings the worker needs.
pub(crate) struct WorkerConfig {
    pub world: Option<String>,
    pub spec_timeout: Duration,
    pub blueprint: bool,
    pub batch_interval: Duration,
}

pub(crate) struct Worker {
    rec: RecordingStream,
    shared: Arc<Shared>,
    /// Where `spec` is asked for an env's world (`None`: a replay, whose
    /// worlds come from the recording).
    session: Option<Session>,
    config: WorkerConfig,
    envs: HashMap<EnvId, EnvView>,
    order: Vec<EnvId>,
    last_health: Option<Instant>,
    site_estop: Option<bool>,
    /// The site-wide e-stop's key (compared with every sample's).
    site_estop_key: String,
    site_latch: Obeyed,
    columns: Columns,
}

/// A latch followed by the obeyers' rule ([`RecentPresses::apply`]).
#[derive(Debug, Default)]
pub(super) struct Obeyed {
    latches: EStopState,
    presses: RecentPresses,
}

impl Obeyed {
    /// Whether `stop`, received at `wall` (the recording's time in a
    /// replay), changed `latch` as an obeyer would apply it.
    pub(super) fn applies(&mut self, latch: Latch, stop: &EStop, wall: SystemTime) -> bool {
        let now = Time::from_unix_nanos(Time::unix_nanos(wall));
        self.presses.apply(&mut self.latches, latch, stop, now) == Pressed::Applied
    }
}

/// Why a message was skipped.
#[derive(Debug)]
pub(crate) enum Skip {
    Decode(String),
    Log(rerun::RecordingStreamError),
}

impl From<rerun::RecordingStreamError> for Skip {
    fn from(e: rerun::RecordingStreamError) -> Self {
        Skip::Log(e)
    }
}

impl From<offworld_runtime::DecodeError> for Skip {
    fn from(e: offworld_runtime::DecodeError) -> Self {
        Skip::Decode(e.to_string())
    }
}

impl From<ImageError> for Skip {
    fn from(e: ImageError) -> Self {
        Skip::Decode(e.to_string())
    }
}

fn finite(values: &[f64]) -> Result<(), Skip> {
    if values.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(Skip::Decode("non-finite value".into()))
    }
}

fn stamp_duration(stamp: &Time) -> Option<Duration> {
    (stamp.sec >= 0 && (stamp.sec, stamp.nanosec) != (0, 0) && stamp.nanosec < 1_000_000_000)
        .then(|| Duration::new(stamp.sec as u64, stamp.nanosec))
}

impl Worker {
    pub fn new(
        rec: RecordingStream,
        shared: Arc<Shared>,
        session: Option<Session>,
        config: WorkerConfig,
    ) -> Self {
        Self {
            rec,
            shared,
            session,
            config,
            envs: HashMap::new(),
            order: Vec::new(),
            last_health: None,
            site_estop: None,
            site_estop_key: global_estop_key(),
            site_latch: Obeyed::default(),
            columns: Columns::new(COLUMN_PERIOD, COLUMN_MAX_BYTES),
        }
    }

    /// Runs until the queue is closed and drained, then completes the worlds
    /// nobody resolved and logs final health.
    pub fn run(mut self) {
        self.start();
        loop {
            match self
                .shared
                .queue
                .pop_batch(Duration::from_millis(100), self.config.batch_interval)
            {
                Ok(batch) => {
                    for event in batch {
                        self.handle(event);
                    }
                }
                Err(()) => break,
            }
            self.flush_columns_if_due();
            if self
                .last_health
                .is_none_or(|t| t.elapsed() >= HEALTH_PERIOD)
            {
                self.log_health();
            }
        }
        // Health first: `finish` sends every pending row.
        self.log_health();
        self.finish();
    }

    /// Sends the layout (if configured): before the first data.
    pub fn start(&self) {
        if self.config.blueprint {
            self.send_blueprint();
        }
    }

    /// Draws the default world for the envs nobody resolved and logs every
    /// pending row.
    pub fn finish(&mut self) {
        let unresolved: Vec<EnvId> = self
            .order
            .iter()
            .filter(|env| self.envs.get(*env).is_some_and(|v| v.world.is_none()))
            .cloned()
            .collect();
        for env in unresolved {
            if let Some(world) = fallback_world() {
                self.apply_world(
                    &env,
                    world,
                    WorldSource::Fallback("world unresolved at shutdown".into()),
                    SystemTime::now(),
                );
            }
        }
        self.flush_columns();
    }

    /// Logs the pending rows if they are due (old or big enough).
    pub fn flush_columns_if_due(&mut self) {
        if self.columns.due() {
            self.flush_columns();
        }
    }

    /// Logs every pending row now.
    pub fn flush_columns(&mut self) {
        if let Err((rows, e)) = self.columns.flush(&self.rec) {
            self.shared
                .counters
                .log_errors
                .fetch_add(rows as u64, Ordering::Relaxed);
            tracing::debug!("monitor could not log {rows} rows: {e}");
        }
    }

    /// Queues one row of `env`'s entity at `relative` (see [`paths`]).
    fn row(&mut self, env: &EnvId, relative: &str, stamp: Stamp, row: Row) {
        self.columns.push(env_path(env, relative), stamp, row);
    }

    fn count(&self, counter: &AtomicU64) {
        counter.fetch_add(1, Ordering::Relaxed);
    }

    fn handle(&mut self, event: Event) {
        let result = match event {
            Event::Sample { sample, wall } => self.on_sample(&sample, wall),
            Event::Alive { key, online, wall } => self.on_alive(&key, online, wall),
            Event::World { env, world, source } => {
                match world {
                    Some(world) => self.apply_world(&env, *world, source, SystemTime::now()),
                    None => self.view(&env).resolving = false,
                }
                Ok(())
            }
        };
        self.account(result);
    }

    /// Counts a message that could not be logged (malformed, or refused by
    /// rerun); the monitor goes on.
    pub fn account(&self, result: Result<(), Skip>) {
        match result {
            Ok(()) => {}
            Err(Skip::Decode(e)) => {
                self.count(&self.shared.counters.decode_errors);
                tracing::debug!("monitor skipped a message: {e}");
            }
            Err(Skip::Log(e)) => {
                self.count(&self.shared.counters.log_errors);
                tracing::debug!("monitor could not log: {e}");
            }
        }
    }

    // ---- time ----------------------------------------------------------

    /// A row's place on the timelines (for [`Columns`]).
    fn stamp(step: Option<u64>, stamp: Option<&Time>, wall: SystemTime) -> Stamp {
        let wall_nanos = wall
            .duration_since(SystemTime::UNIX_EPOCH)
            .map_or(0, |d| i64::try_from(d.as_nanos()).unwrap_or(i64::MAX));
        Stamp {
            step: step.and_then(|s| i64::try_from(s).ok()),
            sim_nanos: stamp
                .and_then(stamp_duration)
                .and_then(|d| i64::try_from(d.as_nanos()).ok()),
            wall_nanos,
        }
    }

    // ---- envs and worlds -------------------------------------------------

    /// The view of `env`, created (and its world resolution started) on
    /// first sight.
    fn view(&mut self, env: &EnvId) -> &mut EnvView {
        if !self.envs.contains_key(env) {
            self.envs.insert(env.clone(), EnvView::default());
            self.order.push(env.clone());
            self.count(&self.shared.counters.envs);
            self.rec.reset_time();
            if let Err(e) = self
                .rec
                .log_static(env_root(env), &ViewCoordinates::RIGHT_HAND_Z_UP())
            {
                tracing::debug!("monitor could not log: {e}");
            }
            if self.config.blueprint {
                self.send_blueprint();
            }
            self.resolve_world(env);
        }
        self.envs.entry(env.clone()).or_default()
    }

    fn on_sample(&mut self, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        if sample.kind() == SampleKind::Delete {
            return Ok(());
        }
        let key = sample.key_expr().as_str();
        if key == self.site_estop_key {
            return self.on_site_estop(sample, wall);
        }
        let Ok(env) = EnvId::from_key(key) else {
            return Err(Skip::Decode(format!("`{key}` is not an env key")));
        };
        // Each message (a file) or the viewers' copy (a live view).
        match topic_of(key).unwrap_or_default() {
            "cmd" | "preview_cmd" => self.on_cmd(&env, sample, wall),
            "obs" | "preview" => self.on_obs(&env, sample, wall),
            "pose" | "preview_pose" => self.on_pose(&env, sample, wall),
            "odom" | "preview_odom" => self.on_odom(&env, sample, wall),
            "reward" => self.on_reward(&env, sample, wall),
            "tracking" => self.on_tracking(&env, sample, wall),
            "status" => self.on_status(&env, sample, wall),
            "estop" => self.on_env_estop(&env, sample, wall),
            t if t.starts_with("overhead/") => {
                let camera = &t["overhead/".len()..];
                self.on_overhead(&env, camera, sample, wall)
            }
            // Heartbeats and anything newer than this monitor: not drawn.
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The monitor shows a latch as its obeyers hold it: a repeated copy or
    /// a release overtaken by an engage changes nothing; in a replay the
    /// recording's times order the presses.
    #[test]
    fn a_latch_is_followed_as_its_obeyers_apply_presses() {
        let at = |ms: u64| SystemTime::UNIX_EPOCH + Duration::from_millis(ms);
        let press = |engaged: bool, ms: u64| EStop {
            engaged,
            reason: format!("at {ms}"),
            press_id: ms * 1_000_000,
        };
        let mut latch = Obeyed::default();
        assert!(latch.applies(Latch::Env, &press(true, 1_000), at(1_010)));
        assert!(
            !latch.applies(Latch::Env, &press(true, 1_000), at(1_300)),
            "a copy"
        );
        assert!(latch.applies(Latch::Env, &press(false, 2_000), at(2_010)));
        assert!(latch.applies(Latch::Env, &press(true, 3_000), at(3_010)));
        assert!(
            !latch.applies(Latch::Env, &press(false, 2_900), at(3_020)),
            "pressed before the engage arrived"
        );
        assert!(latch.latches.env.engaged);
        assert_eq!(latch.latches.env.reason, "at 3000");
    }
}
