//! Recording from outside the controller (`recorder record`): a Zenoh
//! subscriber, like the monitor, that joins any deployment and writes the
//! same episode files as `env_controller serve --record`, through the same
//! [`EnvRecorder`], from what the env publishes:
//!
//! - `reward` ([`EpisodeEvent`]): every reset and step, with its
//!   experiment id and the `seq` of the command whose frame answered it;
//! - `obs` ([`offworld_runtime::msg::CameraFrame`]), kept by `seq` (the
//!   last [`KEEP`]);
//! - `cmd` ([`MotionCommand`]), kept by `seq`: `/cmd_vel` at the time it
//!   was received (or its Zenoh timestamp, when the publisher's session
//!   stamps samples);
//! - `pose` (`PoseStamped`): the one tagged with the command's `seq`, else
//!   the last received (a streaming tracker's poses are untagged);
//! - `status` ([`EnvStatus`]): a lease that ends (close, expiry, a client
//!   gone) ends the open episode, which the controller announces no
//!   other way.
//!
//! A step 0, or an event of another (experiment, episode), ends the open
//! episode and begins a new one; a terminated or truncated step ends it.
//! A step whose frame has not arrived [`FollowConfig::frame_wait`] after
//! its event is skipped (counted in [`FollowStats::skipped_steps`]).
//!
//! What a subscriber cannot know is left empty and named in the file's
//! metadata record (`unknown`): the learning type, algorithm mode, seed,
//! requested start and the action index (`action_discrete` −1,
//! `action_continuous` empty; the commanded velocities are recorded).
//! The subscriber never waits for the disk (`lossless: false`); real envs
//! are recorded durable, as the controller records them.

use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use offworld_runtime::codec;
use offworld_runtime::keys::{components_alive_selector, Component, EnvId, Topic};
use offworld_runtime::msg::{
    CameraFrameView, EnvSpec, EnvState, EnvStatus, EpisodeEvent, Header, MotionCommand,
    PoseStamped, SeqTag, Time, Twist,
};
use offworld_runtime::{wire, Realm};
use tokio::sync::{mpsc, watch, Notify};
use tokio::task::JoinHandle;
use zenoh::bytes::ZBytes;
use zenoh::pubsub::Subscriber;
use zenoh::sample::{Sample, SampleKind};
use zenoh::Session;

use crate::msg::{EpisodeEnd, EpisodeInfo, Step};
use crate::{EnvRecorder, RecordError, RecordTo, StepRecord};

/// Frames, commands and poses kept per env, by `seq`.
pub const KEEP: usize = 32;

/// Events waiting for an env's follower, at most (more are dropped and
/// counted: a subscriber never stalls the publisher).
const EVENT_QUEUE: usize = 1024;

/// Fields of `EpisodeInfo` and `Step` a subscriber cannot know, as the
/// metadata record's `unknown` names them.
pub const UNKNOWN_FIELDS: &str =
    "learning_type algorithm_mode seeded seed requested_start action_discrete action_continuous";

/// What to follow.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum FollowScope {
    /// These envs, from the start.
    Envs(Vec<EnvId>),
    /// Every env whose controller is alive (liveliness), as they appear.
    All,
}

/// A finished episode file, for progress reports.
#[derive(Debug, Clone, PartialEq)]
pub struct FinishedEpisode {
    /// Its env.
    pub env: EnvId,
    /// The experiment's id.
    pub experiment_id: u64,
    /// The episode's id.
    pub episode_id: u64,
    /// The file's name (a name already taken gets `ep-N.K.mcap` instead).
    pub path: PathBuf,
    /// Steps written (the reset included).
    pub recorded: u32,
    /// Steps skipped (no frame or pose in time).
    pub skipped: u32,
    /// Why it ended (`EpisodeEnd.end_reason`).
    pub end_reason: String,
}

/// Called once per finished episode.
pub type OnFinished = Arc<dyn Fn(&FinishedEpisode) + Send + Sync>;

/// How the follower records.
#[derive(Clone)]
pub struct FollowConfig {
    /// The root of the recordings (`DIR/<realm>/<env>/exp-N/ep-N.mcap`).
    pub dir: PathBuf,
    /// How long a step waits for its camera frame after its event.
    pub frame_wait: Duration,
    /// How long the controller may take to answer `spec`.
    pub spec_timeout: Duration,
    /// Told about each finished episode.
    pub on_finished: Option<OnFinished>,
}

impl FollowConfig {
    /// Records into `dir`, waiting up to 500 ms for a step's frame.
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self {
            dir: dir.into(),
            frame_wait: Duration::from_millis(500),
            spec_timeout: Duration::from_secs(2),
            on_finished: None,
        }
    }
}

/// What a follower has done so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FollowStats {
    /// Envs followed.
    pub envs: u64,
    /// Episode files begun.
    pub episodes: u64,
    /// Episode files ended.
    pub finished: u64,
    /// Steps recorded (resets included).
    pub steps: u64,
    /// Steps skipped: no frame with the event's `command_seq` in time, or
    /// no pose at all.
    pub skipped_steps: u64,
    /// Steps never seen (a gap in an episode's step indices: an event
    /// lost on a congested link, or joined mid-episode).
    pub missed_events: u64,
    /// Samples that did not decode (skipped).
    pub malformed: u64,
    /// Events dropped because the follower fell behind.
    pub dropped_events: u64,
}

#[derive(Default)]
struct Counters {
    envs: AtomicU64,
    episodes: AtomicU64,
    finished: AtomicU64,
    steps: AtomicU64,
    skipped_steps: AtomicU64,
    missed_events: AtomicU64,
    malformed: AtomicU64,
    dropped_events: AtomicU64,
}

impl Counters {
    fn add(counter: &AtomicU64, n: u64) {
        counter.fetch_add(n, Ordering::Relaxed);
    }

    fn snapshot(&self) -> FollowStats {
        let get = |c: &AtomicU64| c.load(Ordering::Relaxed);
        FollowStats {
            envs: get(&self.envs),
            episodes: get(&self.episodes),
            finished: get(&self.finished),
            steps: get(&self.steps),
            skipped_steps: get(&self.skipped_steps),
            missed_events: get(&self.missed_events),
            malformed: get(&self.malformed),
            dropped_events: get(&self.dropped_events),
        }
    }
}

struct Inner {
    session: Session,
    config: FollowConfig,
    counters: Counters,
    envs: tokio::sync::Mutex<BTreeMap<EnvId, EnvTask>>,
}

struct EnvTask {
    stop: watch::Sender<bool>,
    task: JoinHandle<()>,
}

/// Records the episodes of the envs in a scope from their publications.
/// [`Follower::stop`] finishes the open files.
pub struct Follower {
    inner: Arc<Inner>,
    discovery: Option<(Subscriber<()>, JoinHandle<()>)>,
}

impl Follower {
    /// Checks `config.dir` ([`RecordTo::check`]) and starts following
    /// `scope` on `session`.
    pub async fn start(
        session: &Session,
        scope: FollowScope,
        config: FollowConfig,
    ) -> Result<Self, RecordError> {
        RecordTo::check(&config.dir)?;
        let inner = Arc::new(Inner {
            session: session.clone(),
            config,
            counters: Counters::default(),
            envs: tokio::sync::Mutex::new(BTreeMap::new()),
        });
        let discovery = match scope {
            FollowScope::Envs(envs) => {
                for env in envs {
                    inner.follow(env).await;
                }
                None
            }
            FollowScope::All => {
                let (found, mut appeared) = mpsc::unbounded_channel::<EnvId>();
                let controller = Component::Controller.as_str();
                let subscriber = session
                    .liveliness()
                    .declare_subscriber(components_alive_selector())
                    .history(true)
                    .callback(move |sample: Sample| {
                        let key = sample.key_expr().as_str();
                        let is_controller = key
                            .rsplit_once("/alive/")
                            .is_some_and(|(_, c)| c == controller);
                        if sample.kind() == SampleKind::Put && is_controller {
                            if let Ok(env) = EnvId::from_key(key) {
                                let _ = found.send(env);
                            }
                        }
                    })
                    .await
                    .map_err(|e| RecordError::Zenoh(format!("liveliness: {e}")))?;
                let follower = inner.clone();
                let task = tokio::spawn(async move {
                    while let Some(env) = appeared.recv().await {
                        follower.follow(env).await;
                    }
                });
                Some((subscriber, task))
            }
        };
        Ok(Self { inner, discovery })
    }

    /// What has been recorded so far.
    pub fn stats(&self) -> FollowStats {
        self.inner.counters.snapshot()
    }

    /// Stops following: events already received are recorded (without
    /// waiting for frames), open episodes end as `recorder_stopped`, and
    /// every file is finished before this returns.
    pub async fn stop(mut self) -> FollowStats {
        if let Some((subscriber, task)) = self.discovery.take() {
            drop(subscriber);
            task.abort();
            let _ = task.await;
        }
        let envs = std::mem::take(&mut *self.inner.envs.lock().await);
        for (_, env) in envs.iter() {
            let _ = env.stop.send(true);
        }
        for (env, task) in envs {
            if let Err(e) = task.task.await {
                tracing::error!(%env, "the env's follower failed: {e}");
            }
        }
        self.inner.counters.snapshot()
    }
}

impl Inner {
    /// Starts following `env` unless it is followed already.
    async fn follow(self: &Arc<Self>, env: EnvId) {
        let mut envs = self.envs.lock().await;
        if envs.contains_key(&env) {
            return;
        }
        let (stop, stopped) = watch::channel(false);
        let task = tokio::spawn(follow_env(self.clone(), env.clone(), stopped));
        envs.insert(env, EnvTask { stop, task });
        Counters::add(&self.counters.envs, 1);
    }
}

/// What an env's subscribers hand its follower, in arrival order.
enum Notice {
    Event(EpisodeEvent),
    Status(EnvStatus),
}

/// The env's recent frames, commands and poses (each the last [`KEEP`]).
#[derive(Default)]
struct Recent {
    frames: Mutex<VecDeque<(u64, ZBytes)>>,
    commands: Mutex<VecDeque<(MotionCommand, Time)>>,
    /// Poses by the `seq` of their tag (untagged: none), newest last.
    poses: Mutex<VecDeque<(Option<u64>, PoseStamped)>>,
    frame_arrived: Notify,
}

fn keep<T>(ring: &Mutex<VecDeque<T>>, item: T) {
    let mut ring = ring.lock().unwrap_or_else(PoisonError::into_inner);
    if ring.len() >= KEEP {
        ring.pop_front();
    }
    ring.push_back(item);
}

impl Recent {
    fn frame(&self, seq: u64) -> Option<ZBytes> {
        let frames = self.frames.lock().unwrap_or_else(PoisonError::into_inner);
        frames
            .iter()
            .rev()
            .find(|(s, _)| *s == seq)
            .map(|(_, f)| f.clone())
    }

    /// The frame answering `seq`, waiting up to `wait` for it.
    async fn wait_frame(&self, seq: u64, wait: Duration) -> Option<ZBytes> {
        let deadline = tokio::time::Instant::now() + wait;
        loop {
            let arrived = self.frame_arrived.notified();
            tokio::pin!(arrived);
            arrived.as_mut().enable();
            if let Some(frame) = self.frame(seq) {
                return Some(frame);
            }
            if tokio::time::timeout_at(deadline, arrived).await.is_err() {
                return self.frame(seq);
            }
        }
    }

    fn command(&self, seq: u64) -> Option<(MotionCommand, Time)> {
        let commands = self.commands.lock().unwrap_or_else(PoisonError::into_inner);
        commands.iter().rev().find(|(c, _)| c.seq == seq).copied()
    }

    /// The pose tagged with `seq`, else the last received.
    fn pose(&self, seq: u64) -> Option<PoseStamped> {
        let poses = self.poses.lock().unwrap_or_else(PoisonError::into_inner);
        poses
            .iter()
            .rev()
            .find(|(tag, _)| *tag == Some(seq))
            .or_else(|| poses.back())
            .map(|(_, pose)| pose.clone())
    }
}

/// When a sample was sent: its Zenoh timestamp if the publisher's session
/// stamps samples, else now (received).
fn sent_at(sample: &Sample) -> Time {
    sample
        .timestamp()
        .and_then(|ts| {
            ts.get_time()
                .to_system_time()
                .duration_since(std::time::UNIX_EPOCH)
                .ok()
        })
        .map_or_else(Time::now, |d| Time::from_secs_f64(d.as_secs_f64()))
}

/// Declares the env's subscribers: samples that do not decode are counted
/// and skipped; events and statuses go to `notices`.
async fn subscribe(
    session: &Session,
    env: &EnvId,
    inner: &Arc<Inner>,
    recent: &Arc<Recent>,
    notices: mpsc::Sender<Notice>,
) -> Result<Vec<Subscriber<()>>, RecordError> {
    type Handler = Box<dyn Fn(&Sample) -> Result<(), ()> + Send + Sync>;
    let handlers: Vec<(Topic, Handler)> = vec![
        (Topic::Obs, {
            let recent = recent.clone();
            Box::new(move |sample| {
                let payload = codec::contiguous(sample.payload());
                let seq = codec::decode_borrowed::<CameraFrameView>(&payload.to_bytes())
                    .map_err(drop)?
                    .seq;
                keep(&recent.frames, (seq, payload));
                recent.frame_arrived.notify_waiters();
                Ok(())
            })
        }),
        (Topic::Cmd, {
            let recent = recent.clone();
            Box::new(move |sample| {
                let cmd: MotionCommand = codec::decode_payload(sample.payload()).map_err(drop)?;
                keep(&recent.commands, (cmd, sent_at(sample)));
                Ok(())
            })
        }),
        (Topic::Pose, {
            let recent = recent.clone();
            Box::new(move |sample| {
                let pose: PoseStamped = codec::decode_payload(sample.payload()).map_err(drop)?;
                let tag = wire::decode_attachment::<SeqTag>(sample).map(|t| t.seq);
                keep(&recent.poses, (tag, pose));
                Ok(())
            })
        }),
        (Topic::Reward, {
            let (notices, inner) = (notices.clone(), inner.clone());
            Box::new(move |sample| {
                let event = codec::decode_payload(sample.payload()).map_err(drop)?;
                if notices.try_send(Notice::Event(event)).is_err() {
                    Counters::add(&inner.counters.dropped_events, 1);
                }
                Ok(())
            })
        }),
        (Topic::Status, {
            let (notices, inner) = (notices, inner.clone());
            Box::new(move |sample| {
                let status = codec::decode_payload(sample.payload()).map_err(drop)?;
                if notices.try_send(Notice::Status(status)).is_err() {
                    Counters::add(&inner.counters.dropped_events, 1);
                }
                Ok(())
            })
        }),
    ];
    let mut subscribers = Vec::new();
    for (topic, handler) in handlers {
        let inner = inner.clone();
        let subscriber = session
            .declare_subscriber(env.key(topic))
            .callback(move |sample: Sample| {
                if handler(&sample).is_err() {
                    Counters::add(&inner.counters.malformed, 1);
                }
            })
            .await
            .map_err(|e| RecordError::Zenoh(format!("subscribing to {}: {e}", env.key(topic))))?;
        subscribers.push(subscriber);
    }
    Ok(subscribers)
}

/// One env's follower: records its episodes until `stop`.
async fn follow_env(inner: Arc<Inner>, env: EnvId, mut stop: watch::Receiver<bool>) {
    let to = RecordTo {
        dir: inner.config.dir.clone(),
        // A subscriber must never hold the publishers back.
        lossless: false,
        durable: env.realm() == Realm::Real,
    };
    let recorder = match EnvRecorder::start(&inner.session, &env, to).await {
        Ok(recorder) => recorder,
        Err(e) => {
            tracing::error!(%env, "cannot record this env: {e}");
            return;
        }
    };
    let recent = Arc::new(Recent::default());
    let (notices, mut received) = mpsc::channel(EVENT_QUEUE);
    let subscribers = match subscribe(&inner.session, &env, &inner, &recent, notices).await {
        Ok(subscribers) => subscribers,
        Err(e) => {
            tracing::error!(%env, "cannot follow this env: {e}");
            let _ = tokio::task::spawn_blocking(move || drop(recorder)).await;
            return;
        }
    };
    tracing::info!(%env, "following");
    let mut env_follower = EnvFollower {
        spec: offworld_client::spec(&inner.session, &env, inner.config.spec_timeout)
            .await
            .map_err(|e| tracing::warn!(%env, "no spec yet ({}); asked again at the next episode", e.message))
            .ok(),
        inner,
        env,
        recorder,
        recent,
        open: None,
    };
    let frame_wait = env_follower.inner.config.frame_wait;
    loop {
        let notice = tokio::select! {
            _ = stop.wait_for(|stop| *stop) => None,
            notice = received.recv() => notice,
        };
        let Some(notice) = notice else { break };
        env_follower.on_notice(notice, frame_wait).await;
    }
    // Stopping: what was received is recorded, without waiting for frames.
    drop(subscribers);
    while let Ok(notice) = received.try_recv() {
        env_follower.on_notice(notice, Duration::ZERO).await;
    }
    env_follower
        .end("recorder_stopped: the subscriber stopped")
        .await;
    let EnvFollower { recorder, env, .. } = env_follower;
    // The recorder's drop waits for its writer to finish the files.
    if tokio::task::spawn_blocking(move || drop(recorder))
        .await
        .is_err()
    {
        tracing::error!(%env, "the recorder's writer failed while finishing");
    }
}

/// The episode being recorded.
struct OpenEpisode {
    info: EpisodeInfo,
    experiment_id: i64,
    /// The last event's step (recorded or not).
    last: Step,
    recorded: u32,
    skipped: u32,
}

struct EnvFollower {
    inner: Arc<Inner>,
    env: EnvId,
    spec: Option<EnvSpec>,
    recorder: EnvRecorder,
    recent: Arc<Recent>,
    open: Option<OpenEpisode>,
}

impl EnvFollower {
    async fn on_notice(&mut self, notice: Notice, frame_wait: Duration) {
        match notice {
            Notice::Event(event) => self.on_event(event, frame_wait).await,
            Notice::Status(status) => {
                let why = match &status.state {
                    EnvState::Leased { .. } => return,
                    EnvState::Free => "the lease ended: closed, expired or its client gone",
                    EnvState::Maintenance { .. } => "the env went into maintenance",
                    EnvState::Offline { .. } => "the env went offline",
                };
                self.end(&format!("aborted: {why} (seen by a subscriber)"))
                    .await;
            }
        }
    }

    async fn on_event(&mut self, event: EpisodeEvent, frame_wait: Duration) {
        let same = self.open.as_ref().is_some_and(|o| {
            o.experiment_id == event.experiment_id && o.info.episode_id == event.episode_id
        });
        if event.step == 0 || !same {
            self.end("aborted: the next episode began (seen by a subscriber)")
                .await;
            self.begin(&event).await;
        } else if let Some(open) = &self.open {
            if event.step <= open.last.step {
                // Stale or repeated: already past it.
                return;
            }
            let gap = event.step - open.last.step - 1;
            if gap > 0 {
                tracing::warn!(env = %self.env, episode = event.episode_id, "{gap} steps before step {} were never seen", event.step);
                Counters::add(&self.inner.counters.missed_events, u64::from(gap));
            }
        }
        self.record(&event, frame_wait).await;
        if event.terminated || event.truncated {
            let reason = event.end_reason.clone();
            self.end(&reason).await;
        }
    }

    async fn begin(&mut self, event: &EpisodeEvent) {
        if self.spec.is_none() {
            let timeout = self.inner.config.spec_timeout;
            self.spec = offworld_client::spec(&self.inner.session, &self.env, timeout)
                .await
                .ok();
        }
        let mut unknown = UNKNOWN_FIELDS.to_owned();
        let (task, world, max_episode_steps) = match &self.spec {
            Some(spec) => (
                spec.task.clone(),
                spec.world.clone(),
                spec.max_episode_steps,
            ),
            None => {
                unknown.push_str(" task world max_episode_steps");
                (String::new(), String::new(), 0)
            }
        };
        let info = EpisodeInfo {
            header: Header::new(Time::now(), "world"),
            env_id: self.env.to_string(),
            task,
            world,
            experiment_id: u64::try_from(event.experiment_id).unwrap_or_default(),
            experiment: event.experiment.clone(),
            learning_type: String::new(),
            algorithm_mode: String::new(),
            episode_id: event.episode_id,
            seeded: false,
            seed: 0,
            embodiment: match self.env.realm() {
                Realm::Sim => "twin",
                Realm::Real => "robot",
            }
            .to_owned(),
            software_version: env!("CARGO_PKG_VERSION").to_owned(),
            max_episode_steps,
            requested_start: [f64::NAN; 3],
        };
        let mut notes = BTreeMap::from([
            ("recorder".to_owned(), "subscriber".to_owned()),
            ("unknown".to_owned(), unknown),
        ]);
        if event.step != 0 {
            notes.insert("first_step".to_owned(), event.step.to_string());
            Counters::add(&self.inner.counters.missed_events, u64::from(event.step));
        }
        self.recorder.begin_annotated(info.clone(), notes).await;
        Counters::add(&self.inner.counters.episodes, 1);
        self.open = Some(OpenEpisode {
            info,
            experiment_id: event.experiment_id,
            last: Step::from_event(event, None, None),
            recorded: 0,
            skipped: 0,
        });
    }

    /// Records the step `event` reports, with its frame, pose and command.
    async fn record(&mut self, event: &EpisodeEvent, frame_wait: Duration) {
        let seq = event.command_seq;
        let frame = self.recent.wait_frame(seq, frame_wait).await;
        let pose = self.recent.pose(seq);
        // The reset's observing command is not a motion of the episode.
        let command = (event.step > 0).then(|| self.recent.command(seq)).flatten();
        let step = Step::from_event(event, None, command.as_ref().map(|(c, _)| c));
        let Some(open) = self.open.as_mut() else {
            return;
        };
        open.last = step.clone();
        let (Some(frame), Some(pose)) = (frame, pose) else {
            tracing::warn!(
                env = %self.env,
                episode = event.episode_id,
                step = event.step,
                "step skipped: no camera frame for command {seq} within {frame_wait:?} (or no pose)"
            );
            open.skipped += 1;
            Counters::add(&self.inner.counters.skipped_steps, 1);
            return;
        };
        open.recorded += 1;
        self.recorder
            .step(StepRecord {
                step,
                frame,
                pose,
                command: command.map(|(c, sent)| (Twist::planar(c.linear_x, c.angular_z), sent)),
            })
            .await;
        Counters::add(&self.inner.counters.steps, 1);
    }

    /// Ends the open episode (if any) for `end_reason`.
    async fn end(&mut self, end_reason: &str) {
        let Some(open) = self.open.take() else {
            return;
        };
        let episode_id = open.info.episode_id;
        self.recorder
            .end(EpisodeEnd::after(episode_id, Some(&open.last), end_reason))
            .await;
        Counters::add(&self.inner.counters.finished, 1);
        if let Some(report) = &self.inner.config.on_finished {
            report(&FinishedEpisode {
                env: self.env.clone(),
                experiment_id: open.info.experiment_id,
                episode_id,
                path: self.recorder.episode_path(&open.info),
                recorded: open.recorded,
                skipped: open.skipped,
                end_reason: end_reason.to_owned(),
            });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(x: f64) -> PoseStamped {
        let mut pose = PoseStamped::default();
        pose.pose.position.x = x;
        pose
    }

    #[test]
    fn rings_keep_the_last_few() {
        let recent = Recent::default();
        for seq in 0..(KEEP as u64 + 5) {
            let cmd = MotionCommand {
                seq,
                linear_x: 0.0,
                angular_z: 0.0,
                duration_s: 0.0,
            };
            keep(&recent.commands, (cmd, Time::default()));
        }
        assert_eq!(recent.commands.lock().expect("lock").len(), KEEP);
        assert!(recent.command(4).is_none(), "dropped");
        assert_eq!(
            recent.command(KEEP as u64 + 4).map(|(c, _)| c.seq),
            Some(KEEP as u64 + 4)
        );
    }

    #[test]
    fn a_step_takes_its_tagged_pose_else_the_last() {
        let recent = Recent::default();
        assert!(recent.pose(1).is_none());
        keep(&recent.poses, (Some(1), pose(1.0)));
        keep(&recent.poses, (None, pose(2.0)));
        keep(&recent.poses, (Some(3), pose(3.0)));
        assert_eq!(recent.pose(1).map(|p| p.pose.position.x), Some(1.0));
        assert_eq!(recent.pose(3).map(|p| p.pose.position.x), Some(3.0));
        // No pose answers command 7 (a streaming tracker): the last one.
        assert_eq!(recent.pose(7).map(|p| p.pose.position.x), Some(3.0));
    }

    #[tokio::test]
    async fn a_frame_is_waited_for_briefly() {
        let recent = Arc::new(Recent::default());
        let started = tokio::time::Instant::now();
        assert!(recent
            .wait_frame(5, Duration::from_millis(50))
            .await
            .is_none());
        assert!(started.elapsed() >= Duration::from_millis(50));
        let arriving = recent.clone();
        let late = tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(20)).await;
            keep(&arriving.frames, (6, ZBytes::from(vec![1u8, 2, 3])));
            arriving.frame_arrived.notify_waiters();
        });
        let frame = recent.wait_frame(6, Duration::from_secs(5)).await;
        assert_eq!(
            frame.map(|f| f.to_bytes().into_owned()),
            Some(vec![1, 2, 3])
        );
        late.await.expect("late frame");
    }
}
