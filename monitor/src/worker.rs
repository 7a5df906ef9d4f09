//! The logging worker: one thread that decodes what the callbacks queued and
//! logs it to rerun. Nothing here runs on a Zenoh thread; malformed
//! messages are counted and skipped, never panicked on.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use offworld_runtime::keys::global_estop_key;
use offworld_runtime::msg::{
    CameraFrame, EStop, EnvState, EnvStatus, EpisodeEvent, Image, ImageError, MotionCommand,
    Odometry, PixelEncoding, PoseStamped, SeqTag, Time, TrackingStatus,
};
use offworld_runtime::world::WorldSpec;
use offworld_runtime::{codec, wire, EnvId};
use rerun::components::ImageFormat;
use rerun::datatypes::{ChannelDatatype, ColorModel};
use rerun::{Color, LineStrips3D, RecordingStream, Scalars, TextLog, Transform3D, ViewCoordinates};
use zenoh::sample::{Sample, SampleKind};
use zenoh::Session;

use crate::columns::{Columns, Row, Stamp};
use crate::paths::{self, env_path, env_root};
use crate::queue::{Lane, Queue};
use crate::{layout, scene, MonitorStats};

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
/// High-rate rows go to rerun at least this often (as one chunk per entity).
const COLUMN_PERIOD: Duration = Duration::from_millis(100);
/// … or once this many image bytes are pending.
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

/// The lane a sample travels in: camera images are big and expendable.
pub(crate) fn lane_of(key: &str) -> Lane {
    if key.ends_with("/obs") || key.contains("/overhead/") {
        Lane::Frame
    } else {
        Lane::Message
    }
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
    columns: Columns,
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

/// Rows without padding: `data` as-is when already packed.
fn packed_rows(image: Image, bytes_per_pixel: u32) -> Vec<u8> {
    let row = (image.width * bytes_per_pixel) as usize;
    let step = image.step as usize;
    if step == row {
        return image.data;
    }
    let mut out = Vec::with_capacity(row * image.height as usize);
    for chunk in image.data.chunks_exact(step) {
        out.extend_from_slice(&chunk[..row]);
    }
    out
}

/// A validated ROS image as an `Image` or `DepthImage` row; `None` for an
/// absent (0×0) image.
fn picture(image: Image) -> Result<Option<Row>, Skip> {
    if image.width == 0 || image.height == 0 {
        return Ok(None);
    }
    let encoding = image.validate()?;
    let size = [image.width, image.height];
    let data = packed_rows(image, encoding.bytes_per_pixel());
    let color = |model| ImageFormat::from_color_model(size, model, ChannelDatatype::U8);
    Ok(Some(match encoding {
        PixelEncoding::Rgb8 => Row::Image(data, color(ColorModel::RGB)),
        PixelEncoding::Bgr8 => Row::Image(data, color(ColorModel::BGR)),
        PixelEncoding::Depth32FC1 => {
            Row::Depth(data, ImageFormat::depth(size, ChannelDatatype::F32), 1.0)
        }
        PixelEncoding::Depth16UC1 => {
            Row::Depth(data, ImageFormat::depth(size, ChannelDatatype::U16), 1000.0)
        }
    }))
}

/// This episode's path: a thick orange line just above the ground.
fn trajectory(strip: Vec<[f32; 3]>) -> LineStrips3D {
    LineStrips3D::new([strip])
        .with_colors([Color::from_rgb(235, 120, 30)])
        .with_radii([rerun::Radius::new_scene_units(0.008)])
}

fn stamp_duration(stamp: &Time) -> Option<Duration> {
    (stamp.sec >= 0 && (stamp.sec, stamp.nanosec) != (0, 0) && stamp.nanosec < 1_000_000_000)
        .then(|| Duration::new(stamp.sec as u64, stamp.nanosec))
}

fn yaw_of(q: &offworld_runtime::msg::Quaternion) -> f64 {
    q.yaw()
}

/// Normalised (x, y, z, w) or identity when degenerate.
fn unit_quat(q: &offworld_runtime::msg::Quaternion) -> [f32; 4] {
    let n = (q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w).sqrt();
    if !(n.is_finite() && n > 1e-9) {
        return [0.0, 0.0, 0.0, 1.0];
    }
    [
        (q.x / n) as f32,
        (q.y / n) as f32,
        (q.z / n) as f32,
        (q.w / n) as f32,
    ]
}

fn status_text(state: &EnvState) -> String {
    match state {
        EnvState::Free => "status: free".into(),
        EnvState::Leased { .. } => "status: leased".into(),
        EnvState::Maintenance { message, by, .. } => {
            format!("status: maintenance by {by} ({message})")
        }
        EnvState::Offline { reason } => format!("status: offline ({reason})"),
    }
}

fn same_status_kind(a: &EnvState, b: &EnvState) -> bool {
    match (a, b) {
        // A lease renewal is not news.
        (EnvState::Leased { .. }, EnvState::Leased { .. }) => true,
        _ => a == b,
    }
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
        self.finish();
        self.log_health();
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

    fn set_times(&self, step: Option<u64>, stamp: Option<&Time>, wall: SystemTime) {
        self.rec.reset_time();
        if let Some(step) = step.and_then(|s| i64::try_from(s).ok()) {
            self.rec.set_time_sequence(paths::TIMELINE_STEP, step);
        }
        if let Some(d) = stamp.and_then(stamp_duration) {
            self.rec.set_time(paths::TIMELINE_SIM_TIME, d);
        }
        self.rec.set_time(paths::TIMELINE_WALL_TIME, wall);
    }

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

    fn send_blueprint(&self) {
        let blueprint = layout::blueprint(&self.order);
        if let Err(e) = blueprint.send(&self.rec, rerun::blueprint::BlueprintActivation::default())
        {
            tracing::debug!("monitor could not send its blueprint: {e}");
        }
    }

    /// Starts finding out which world `env` uses: the configured one at
    /// once, else the controller's `spec` on a helper thread (the worker
    /// never waits on the network).
    fn resolve_world(&mut self, env: &EnvId) {
        if let Some(name) = self.config.world.clone() {
            let (world, source) = match WorldSpec::builtin(&name) {
                Ok(w) => (w, WorldSource::Configured),
                Err(e) => match fallback_world() {
                    Some(w) => (w, WorldSource::Fallback(e.to_string())),
                    None => return,
                },
            };
            self.apply_world(env, world, source, SystemTime::now());
            return;
        }
        let Some(session) = self.session.clone() else {
            // A replay: the recording says.
            return;
        };
        if let Some(view) = self.envs.get_mut(env) {
            if view.resolving {
                return;
            }
            view.resolving = true;
        }
        let (shared, env, timeout) = (self.shared.clone(), env.clone(), self.config.spec_timeout);
        let spawned = std::thread::Builder::new()
            .name("monitor-spec".into())
            .spawn(move || {
                let (world, source) = query_world(&session, &env, timeout);
                shared.queue.push(
                    Lane::Control,
                    Event::World {
                        env,
                        world: world.map(Box::new),
                        source,
                    },
                );
            });
        if let Err(e) = spawned {
            tracing::warn!("monitor could not start a spec query: {e}");
        }
    }

    /// A fallback world gets one more chance once the env's controller shows
    /// signs of life.
    fn maybe_retry_world(&mut self, env: &EnvId) {
        let Some(view) = self.envs.get_mut(env) else {
            return;
        };
        if view.retried || view.resolving || self.config.world.is_some() {
            return;
        }
        if matches!(view.world_source, Some(WorldSource::Fallback(_))) {
            view.retried = true;
            self.resolve_world(env);
        }
    }

    /// Draws `world` for `env` (if it is not drawn already); its event is
    /// logged at `wall`.
    pub fn apply_world(
        &mut self,
        env: &EnvId,
        world: WorldSpec,
        source: WorldSource,
        wall: SystemTime,
    ) {
        let view = self.view(env);
        view.resolving = false;
        let previous = view.world.take();
        let changed = previous.as_ref().is_none_or(|p| p.name != world.name);
        let camera_res = view.camera_res;
        view.world_source = Some(source.clone());
        let result = (|| -> Result<(), rerun::RecordingStreamError> {
            if changed {
                self.rec.reset_time();
                scene::log_world(&self.rec, env, &world, previous.as_ref())?;
                scene::log_robot_bodies(&self.rec, env, &world.robot)?;
                if let Some((w, h)) = camera_res {
                    scene::log_camera(&self.rec, env, &world.camera, w, h)?;
                }
                let text = match &source {
                    WorldSource::Configured => format!("world: {} (configured)", world.name),
                    WorldSource::Spec => format!("world: {} (from the env's spec)", world.name),
                    WorldSource::Recording => format!("world: {} (recorded)", world.name),
                    WorldSource::Fallback(why) => {
                        format!("world: {} (default; {why})", world.name)
                    }
                };
                self.set_times(None, None, wall);
                self.rec.log(
                    env_path(env, paths::EVENTS),
                    &TextLog::new(text).with_level(rerun::TextLogLevel::DEBUG),
                )?;
            }
            Ok(())
        })();
        if let Err(e) = result {
            self.count(&self.shared.counters.log_errors);
            tracing::debug!("monitor could not log the world: {e}");
        }
        let view = self.view(env);
        if let Some((w, h)) = camera_res {
            view.pinhole_res = Some((w, h));
        }
        view.world = Some(world);
    }

    // ---- samples ---------------------------------------------------------

    fn on_sample(&mut self, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        if sample.kind() == SampleKind::Delete {
            return Ok(());
        }
        let key = sample.key_expr().as_str();
        if key == global_estop_key() {
            return self.on_site_estop(sample, wall);
        }
        let Ok(env) = EnvId::from_key(key) else {
            return Err(Skip::Decode(format!("`{key}` is not an env key")));
        };
        let topic = key.splitn(5, '/').nth(4).unwrap_or_default().to_owned();
        match topic.as_str() {
            "cmd" => self.on_cmd(&env, sample, wall),
            "obs" => self.on_obs(&env, sample, wall),
            "pose" => self.on_pose(&env, sample, wall),
            "odom" => self.on_odom(&env, sample, wall),
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

    fn on_cmd(&mut self, env: &EnvId, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        let cmd: MotionCommand = codec::decode_payload(sample.payload())?;
        // u64::MAX is the controller's halt: not a step of its own.
        let seq = (cmd.seq != u64::MAX).then_some(cmd.seq);
        self.log_command(env, seq, cmd.linear_x, cmd.angular_z, wall);
        Ok(())
    }

    /// Makes `seq` the env's current step: data without a seq of its own
    /// is logged at it.
    pub fn set_seq(&mut self, env: &EnvId, seq: u64) {
        self.view(env).seq = Some(seq);
    }

    /// A motion command (`cmd`, or a recording's `/cmd_vel`); `seq` (the
    /// command's) becomes the env's current step.
    pub fn log_command(
        &mut self,
        env: &EnvId,
        seq: Option<u64>,
        linear_x: f64,
        angular_z: f64,
        wall: SystemTime,
    ) {
        let view = self.view(env);
        if seq.is_some() {
            view.seq = seq;
        }
        let stamp = Self::stamp(view.seq, None, wall);
        self.columns
            .push(env_path(env, paths::LINEAR_X), stamp, Row::Scalar(linear_x));
        self.columns.push(
            env_path(env, paths::ANGULAR_Z),
            stamp,
            Row::Scalar(angular_z),
        );
        self.count(&self.shared.counters.commands);
    }

    fn on_obs(&mut self, env: &EnvId, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        let frame: CameraFrame = codec::decode_payload(sample.payload())?;
        self.log_frame(env, Some(frame.seq), frame.color, frame.depth, wall)
    }

    /// A camera frame (`obs`, or a recording's colour and depth images): a
    /// 0×0 image is absent, not both. At `seq`, else the env's current step.
    pub fn log_frame(
        &mut self,
        env: &EnvId,
        seq: Option<u64>,
        color: Image,
        depth: Image,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let stamp = if color.width > 0 {
            color.header.stamp
        } else {
            depth.header.stamp
        };
        let size = if color.width > 0 {
            (color.width, color.height)
        } else {
            (depth.width, depth.height)
        };
        let color = picture(color)?;
        let depth = picture(depth)?;
        if color.is_none() && depth.is_none() {
            return Err(Skip::Decode("camera frame without images".into()));
        }
        self.set_camera_resolution(env, size)?;
        let seq = seq.or(self.view(env).seq);
        let stamp = Self::stamp(seq, Some(&stamp), wall);
        for row in [color, depth].into_iter().flatten() {
            let path = match row {
                Row::Depth(..) => paths::DEPTH,
                _ => paths::COLOR,
            };
            self.columns.push(env_path(env, path), stamp, row);
        }
        self.count(&self.shared.counters.frames);
        Ok(())
    }

    /// Logs the pinhole for this resolution once the world's camera is known.
    fn set_camera_resolution(&mut self, env: &EnvId, size: (u32, u32)) -> Result<(), Skip> {
        let view = self.view(env);
        view.camera_res = Some(size);
        if view.pinhole_res == Some(size) {
            return Ok(());
        }
        let Some(camera) = view.world.as_ref().map(|w| w.camera.clone()) else {
            return Ok(());
        };
        view.pinhole_res = Some(size);
        self.rec.reset_time();
        scene::log_camera(&self.rec, env, &camera, size.0, size.1)?;
        Ok(())
    }

    fn on_pose(&mut self, env: &EnvId, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        let pose: PoseStamped = codec::decode_payload(sample.payload())?;
        let tag = wire::decode_attachment::<SeqTag>(sample).map(|t| t.seq);
        self.log_pose(env, &pose, tag, wall)
    }

    /// A tracker pose (`pose`, or a recording's `/tracker/pose`): the robot
    /// and its trajectory. At `tag`, else the env's current step.
    pub fn log_pose(
        &mut self,
        env: &EnvId,
        pose: &PoseStamped,
        tag: Option<u64>,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let p = &pose.pose.position;
        let q = &pose.pose.orientation;
        finite(&[p.x, p.y, p.z, q.x, q.y, q.z, q.w])?;
        let here = [p.x as f32, p.y as f32, p.z as f32];
        let planar = Planar {
            x: p.x,
            y: p.y,
            z: p.z,
            yaw: yaw_of(q),
        };
        let view = self.view(env);
        let step = tag.or(view.seq);
        view.last_pose = Some(planar);
        let extend = view.trajectory.last().is_none_or(|last| {
            let d = [here[0] - last[0], here[1] - last[1], here[2] - last[2]];
            (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() >= TRAJECTORY_STEP_M
        });
        if extend {
            if view.trajectory.len() >= MAX_TRAJECTORY {
                view.trajectory.remove(0);
            }
            view.trajectory.push(here);
            view.trajectory_dirty = true;
        }
        let due = view.trajectory_logged.is_none_or(|at| {
            wall.duration_since(at)
                .map_or(true, |since| since >= TRAJECTORY_PERIOD)
        });
        let strip = (view.trajectory_dirty && due).then(|| {
            view.trajectory_dirty = false;
            view.trajectory_logged = Some(wall);
            view.trajectory.clone()
        });
        self.columns.push(
            env_path(env, paths::ROBOT),
            Self::stamp(step, Some(&pose.header.stamp), wall),
            Row::Transform(here, unit_quat(q)),
        );
        if let Some(strip) = strip {
            self.set_times(step, Some(&pose.header.stamp), wall);
            self.rec
                .log(env_path(env, paths::TRAJECTORY), &trajectory(strip))?;
        }
        self.count(&self.shared.counters.poses);
        Ok(())
    }

    fn on_odom(&mut self, env: &EnvId, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        let odom: Odometry = codec::decode_payload(sample.payload())?;
        let tag = wire::decode_attachment::<SeqTag>(sample).map(|t| t.seq);
        self.log_odom(env, &odom, tag, wall)
    }

    /// Odometry (`odom`, or a recording's `/odom`). At `tag`, else the env's
    /// current step.
    pub fn log_odom(
        &mut self,
        env: &EnvId,
        odom: &Odometry,
        tag: Option<u64>,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let p = &odom.pose.pose.position;
        let q = &odom.pose.pose.orientation;
        finite(&[p.x, p.y, p.z, q.x, q.y, q.z, q.w])?;
        let view = self.view(env);
        let step = tag.or(view.seq);
        let first = view.last_odom.is_none();
        view.last_odom = Some(Planar {
            x: p.x,
            y: p.y,
            z: p.z,
            yaw: yaw_of(q),
        });
        self.set_times(step, Some(&odom.header.stamp), wall);
        if first {
            // Until the first reset anchors it, draw odom as if it were the world.
            self.anchor_odom(env)?;
        }
        self.columns.push(
            env_path(env, paths::ODOM_ROBOT),
            Self::stamp(step, Some(&odom.header.stamp), wall),
            Row::Transform([p.x as f32, p.y as f32, p.z as f32], unit_quat(q)),
        );
        self.count(&self.shared.counters.odometry);
        Ok(())
    }

    /// Places the odom frame in the world so that the odometry pose
    /// coincides with the tracker pose now (planar). Identity without both.
    fn anchor_odom(&mut self, env: &EnvId) -> Result<(), Skip> {
        let view = self.view(env);
        let (translation, yaw) = match (view.last_pose, view.last_odom) {
            (Some(w), Some(o)) => {
                let yaw = w.yaw - o.yaw;
                let (s, c) = yaw.sin_cos();
                (
                    [
                        (w.x - (c * o.x - s * o.y)) as f32,
                        (w.y - (s * o.x + c * o.y)) as f32,
                        (w.z - o.z) as f32,
                    ],
                    yaw,
                )
            }
            _ => ([0.0; 3], 0.0),
        };
        let half = (yaw * 0.5) as f32;
        self.rec.log(
            env_path(env, paths::ODOM),
            &Transform3D::from_translation_rotation(
                translation,
                rerun::Quaternion::from_xyzw([0.0, 0.0, half.sin(), half.cos()]),
            ),
        )?;
        Ok(())
    }

    fn on_reward(&mut self, env: &EnvId, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        let event: EpisodeEvent = codec::decode_payload(sample.payload())?;
        self.maybe_retry_world(env);
        self.log_episode_event(env, &event, None, wall)
    }

    /// An episode's reset or step (`reward`, or a recording's
    /// `/offworld/step`): reward and return, episode start and end, the
    /// trajectory restarted at a reset. At the env's current step; on
    /// `sim_time` too when `stamp` is given (the step's frame).
    pub fn log_episode_event(
        &mut self,
        env: &EnvId,
        event: &EpisodeEvent,
        stamp: Option<&Time>,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let view = self.view(env);
        let step = view.seq;
        let new_episode = event.step == 0 || view.episode != Some(event.episode_id);
        view.episode = Some(event.episode_id);
        if event.step == 0 {
            // The reset's pose is this episode's first point.
            view.trajectory.clear();
            if let Some(p) = view.last_pose {
                view.trajectory.push([p.x as f32, p.y as f32, p.z as f32]);
            }
        }
        let ended = event.terminated || event.truncated;
        let strip = (event.step == 0 || (ended && view.trajectory_dirty)).then(|| {
            view.trajectory_dirty = false;
            view.trajectory_logged = Some(wall);
            view.trajectory.clone()
        });
        self.set_times(step, stamp, wall);
        if event.step == 0 {
            self.anchor_odom(env)?;
        }
        if let Some(strip) = strip {
            self.rec
                .log(env_path(env, paths::TRAJECTORY), &trajectory(strip))?;
        }
        let stamp = Self::stamp(step, stamp, wall);
        self.columns.push(
            env_path(env, paths::REWARD),
            stamp,
            Row::Scalar(event.reward),
        );
        self.columns.push(
            env_path(env, paths::RETURN),
            stamp,
            Row::Scalar(event.episode_return),
        );
        if new_episode {
            let experiment = if event.experiment.is_empty() {
                String::new()
            } else {
                format!(" ({})", event.experiment)
            };
            self.rec.log(
                env_path(env, paths::EVENTS),
                &TextLog::new(format!("episode {} started{experiment}", event.episode_id))
                    .with_level(rerun::TextLogLevel::INFO),
            )?;
        }
        if ended {
            self.rec.log(
                env_path(env, paths::SUCCESS),
                &Scalars::single(if event.success { 1.0 } else { 0.0 }),
            )?;
            self.rec.log(
                env_path(env, paths::EPISODE_LENGTH),
                &Scalars::single(f64::from(event.step)),
            )?;
            let how = if event.end_reason.is_empty() {
                if event.truncated {
                    "truncated"
                } else {
                    "terminated"
                }
            } else {
                event.end_reason.as_str()
            };
            self.log_end_text(env, event, how)?;
        }
        self.count(&self.shared.counters.rewards);
        Ok(())
    }

    /// An episode that ended without a terminal step (a reset or a close
    /// came first, or its recording stopped), as a recording's
    /// `/offworld/episode_end` tells: the event log only (success and
    /// length are for episodes that terminated or were truncated). `last`
    /// is its last step, `how` why it ended.
    pub fn log_episode_stopped(
        &mut self,
        env: &EnvId,
        last: &EpisodeEvent,
        how: &str,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let step = self.view(env).seq;
        self.set_times(step, None, wall);
        self.log_end_text(env, last, how)
    }

    /// "episode … ended after … steps" in the env's event log (at the times
    /// set).
    fn log_end_text(&self, env: &EnvId, last: &EpisodeEvent, how: &str) -> Result<(), Skip> {
        self.rec.log(
            env_path(env, paths::EVENTS),
            &TextLog::new(format!(
                "episode {} ended after {} steps: {how} (return {:.3}{})",
                last.episode_id,
                last.step,
                last.episode_return,
                if last.success { ", success" } else { "" }
            ))
            .with_level(if last.success {
                rerun::TextLogLevel::INFO
            } else {
                rerun::TextLogLevel::WARN
            }),
        )?;
        Ok(())
    }

    fn on_tracking(&mut self, env: &EnvId, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        let status: TrackingStatus = codec::decode_payload(sample.payload())?;
        let view = self.view(env);
        let step = view.seq;
        if view.tracking == Some(status.tracking) {
            return Ok(());
        }
        view.tracking = Some(status.tracking);
        self.set_times(step, None, wall);
        let (text, level) = if status.tracking {
            ("tracking ok".to_owned(), rerun::TextLogLevel::INFO)
        } else {
            (
                format!("tracking lost: {}", status.reason),
                rerun::TextLogLevel::WARN,
            )
        };
        self.rec.log(
            env_path(env, paths::EVENTS),
            &TextLog::new(text).with_level(level),
        )?;
        Ok(())
    }

    fn on_status(&mut self, env: &EnvId, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        let status: EnvStatus = codec::decode_payload(sample.payload())?;
        self.count(&self.shared.counters.statuses);
        self.maybe_retry_world(env);
        let view = self.view(env);
        let step = view.seq;
        let reset = status.last_reset;
        if reset.measured && view.last_reset_ms != Some(reset.unix_ms) {
            view.last_reset_ms = Some(reset.unix_ms);
            self.set_times(step, None, wall);
            for (path, value) in [
                (paths::RESET_POSITION_ERROR, reset.position_error_m),
                (paths::RESET_YAW_ERROR, reset.yaw_error_rad),
                (paths::RESET_DURATION, reset.duration_s),
            ] {
                self.rec.log(env_path(env, path), &Scalars::single(value))?;
            }
        }
        let view = self.view(env);
        if view
            .status
            .as_ref()
            .is_some_and(|s| same_status_kind(s, &status.state))
        {
            return Ok(());
        }
        let level = match status.state {
            EnvState::Free | EnvState::Leased { .. } => rerun::TextLogLevel::INFO,
            EnvState::Maintenance { .. } | EnvState::Offline { .. } => rerun::TextLogLevel::WARN,
        };
        let text = status_text(&status.state);
        view.status = Some(status.state);
        self.set_times(step, None, wall);
        self.rec.log(
            env_path(env, paths::EVENTS),
            &TextLog::new(text).with_level(level),
        )?;
        Ok(())
    }

    fn estop_log(&self, path: String, stop: &EStop) -> Result<(), Skip> {
        let (text, level) = if stop.engaged {
            (
                format!("e-stop engaged: {}", stop.reason),
                rerun::TextLogLevel::ERROR,
            )
        } else {
            (
                format!("e-stop released: {}", stop.reason),
                rerun::TextLogLevel::INFO,
            )
        };
        self.rec.log(path, &TextLog::new(text).with_level(level))?;
        Ok(())
    }

    fn on_env_estop(&mut self, env: &EnvId, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        let stop: EStop = codec::decode_payload(sample.payload())?;
        let view = self.view(env);
        let step = view.seq;
        if view.estop == Some(stop.engaged) {
            return Ok(());
        }
        view.estop = Some(stop.engaged);
        self.set_times(step, None, wall);
        self.estop_log(env_path(env, paths::EVENTS), &stop)
    }

    fn on_site_estop(&mut self, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        let stop: EStop = codec::decode_payload(sample.payload())?;
        if self.site_estop == Some(stop.engaged) {
            return Ok(());
        }
        self.site_estop = Some(stop.engaged);
        self.set_times(None, None, wall);
        self.estop_log(paths::SITE_EVENTS.to_owned(), &stop)
    }

    fn on_overhead(
        &mut self,
        env: &EnvId,
        camera: &str,
        sample: &Sample,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        if EnvId::sim(camera).is_err() {
            return Err(Skip::Decode(format!("bad overhead camera name `{camera}`")));
        }
        let image: Image = codec::decode_payload(sample.payload())?;
        let stamp = image.header.stamp;
        let Some(row) = picture(image)? else {
            return Err(Skip::Decode("empty overhead image".into()));
        };
        let step = self.view(env).seq;
        self.columns.push(
            env_path(env, &paths::overhead(camera)),
            Self::stamp(step, Some(&stamp), wall),
            row,
        );
        self.count(&self.shared.counters.overhead_frames);
        Ok(())
    }

    fn on_alive(&mut self, key: &str, online: bool, wall: SystemTime) -> Result<(), Skip> {
        let Ok(env) = EnvId::from_key(key) else {
            return Err(Skip::Decode(format!("`{key}` is not an env key")));
        };
        let component = key.splitn(6, '/').nth(5).unwrap_or(key).to_owned();
        if online && component == "controller" {
            self.maybe_retry_world(&env);
        }
        let step = self.view(&env).seq;
        self.set_times(step, None, wall);
        let text = format!("{component} {}", if online { "online" } else { "offline" });
        let level = if online {
            rerun::TextLogLevel::DEBUG
        } else {
            rerun::TextLogLevel::WARN
        };
        self.rec.log(
            env_path(&env, paths::EVENTS),
            &TextLog::new(text).with_level(level),
        )?;
        Ok(())
    }

    fn log_health(&mut self) {
        self.last_health = Some(Instant::now());
        let stats = self.shared.stats();
        self.set_times(None, None, SystemTime::now());
        let result = (|| -> Result<(), rerun::RecordingStreamError> {
            self.rec.log(
                paths::MONITOR_DROPPED_FRAMES,
                &Scalars::single(stats.dropped_frames as f64),
            )?;
            self.rec.log(
                paths::MONITOR_DROPPED_MESSAGES,
                &Scalars::single(stats.dropped_messages as f64),
            )?;
            self.rec.log(
                paths::MONITOR_DECODE_ERRORS,
                &Scalars::single(stats.decode_errors as f64),
            )?;
            Ok(())
        })();
        if let Err(e) = result {
            self.count(&self.shared.counters.log_errors);
            tracing::debug!("monitor could not log its health: {e}");
        }
    }
}

/// Asks the env's controller which world it serves; falls back to
/// [`FALLBACK_WORLD`] when nobody answers or the world is unknown.
fn query_world(
    session: &Session,
    env: &EnvId,
    timeout: Duration,
) -> (Option<WorldSpec>, WorldSource) {
    let fallback = |why: String| (fallback_world(), WorldSource::Fallback(why));
    let runtime = match tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => return fallback(format!("no runtime for the spec query: {e}")),
    };
    let reply = runtime.block_on(offworld_runtime::client::spec(session, env, timeout));
    match reply {
        Ok(spec) => match WorldSpec::builtin(&spec.world) {
            Ok(world) => (Some(world), WorldSource::Spec),
            Err(e) => fallback(format!("the env's world: {e}")),
        },
        Err(e) => fallback(format!("no spec: {}", e.message)),
    }
}
