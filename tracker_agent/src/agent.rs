//! The tracker node: source samples in, calibrated base_link poses and
//! tracking status out, under one env's namespace.
//!
//! Shaped like a dora node: [`TrackerNode::init`] declares everything
//! (liveliness token, the source pump), then [`TrackerNode::run`] loops on
//! events — a sample, a malformed line, the end of the source, a timer, a
//! shutdown — until the source ends or shutdown is asked.
//!
//! Per accepted sample it publishes `pose` (`geometry_msgs/PoseStamped`,
//! frame `world`, stamped with the receipt wall clock, no attachment). It
//! publishes `tracking` ([`TrackingStatus`]) on every change and again every
//! `status_period` for late joiners: false with `no pose yet` until the
//! first accepted pose, true while poses are accepted, false once none has
//! been accepted for `lost_after` (silence or outliers), false when the
//! source ends or the agent stops.

use std::future::Future;
use std::sync::Arc;
use std::time::Duration;

use nalgebra::Isometry3;
use offworld_runtime::keys::{Component, EnvId, Topic};
use offworld_runtime::msg::{Header, Point, Pose, PoseStamped, Quaternion, Time, TrackingStatus};
use offworld_runtime::preview::WatchedPublisher;
use offworld_runtime::seal::{SealKey, Sealer};
use offworld_runtime::wire::{self, Delivery};
use tokio::sync::{mpsc, oneshot, watch};
use tokio::task::JoinHandle;
use tokio::time::Instant;
use zenoh::{Session, Wait};

use crate::calibration::Calibration;
use crate::filter::{FilterConfig, OutlierFilter, Verdict};
use crate::protocol::TrackerSample;
use crate::source::{PoseSource, SourceError};

/// Frame of published poses.
pub const WORLD_FRAME: &str = "world";

/// Tuning of the agent.
#[derive(Debug, Clone, PartialEq)]
pub struct AgentConfig {
    /// Outlier limits.
    pub filter: FilterConfig,
    /// Tracking is lost when no pose has been accepted for this long.
    pub lost_after: Duration,
    /// Period of the status re-publication (late joiners).
    pub status_period: Duration,
    /// Only use poses of this device id. Without it the agent locks onto
    /// the first device it sees and ignores the others (with a warning).
    pub device: Option<String>,
    /// The site's tracker key ([`offworld_runtime::seal`]): poses and
    /// tracking reports are sealed with it, so that the controller and the
    /// robot agent, given the same key, believe no other pose.
    pub seal_key: Option<SealKey>,
}

impl Default for AgentConfig {
    fn default() -> Self {
        Self {
            filter: FilterConfig::default(),
            lost_after: Duration::from_millis(300),
            status_period: Duration::from_secs(1),
            device: None,
            seal_key: None,
        }
    }
}

/// Counters of a running agent.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AgentStats {
    /// Well-formed samples received (any device).
    pub received: u64,
    /// Poses published.
    pub published: u64,
    /// Malformed lines skipped.
    pub malformed: u64,
    /// Poses rejected as outliers.
    pub rejected: u64,
    /// Re-locks after a rejection streak.
    pub relocks: u64,
    /// Samples of other devices, ignored.
    pub other_device: u64,
    /// Times tracking went from true to false.
    pub losses: u64,
}

/// What stops the agent.
#[derive(Debug, thiserror::Error)]
pub enum AgentError {
    /// Zenoh refused a declaration or a put.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// The source failed for good.
    #[error("pose source: {0}")]
    Source(#[from] SourceError),
    /// The node's task panicked or was cancelled.
    #[error("agent task: {0}")]
    Task(String),
}

/// Converts an isometry into a `geometry_msgs/Pose`.
pub fn to_pose_msg(iso: &Isometry3<f64>) -> Pose {
    let t = iso.translation.vector;
    let q = iso.rotation.quaternion();
    Pose {
        position: Point {
            x: t.x,
            y: t.y,
            z: t.z,
        },
        orientation: Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        },
    }
}

/// Aborts a task when dropped.
struct AbortOnDrop(JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

type SourceItem = Result<Option<TrackerSample>, SourceError>;

/// Samples queued between the source pump and the node.
const QUEUE: usize = 256;

/// Reads the source on its own task, so a timer or shutdown never cancels
/// a read half-way.
async fn pump(mut source: Box<dyn PoseSource>, tx: mpsc::Sender<SourceItem>) {
    loop {
        let item = source.next().await;
        let last = match &item {
            Ok(None) => true,
            Ok(Some(_)) => false,
            Err(e) => e.is_fatal(),
        };
        if tx.send(item).await.is_err() || last {
            return;
        }
    }
}

/// Which device's poses are used.
enum DeviceChoice {
    Only(String),
    First(Option<Option<String>>),
}

impl DeviceChoice {
    fn accepts(&mut self, device: &Option<String>) -> bool {
        match self {
            DeviceChoice::Only(id) => device.as_deref() == Some(id.as_str()),
            DeviceChoice::First(locked @ None) => {
                tracing::info!(
                    "using device {}; pass --device to choose",
                    device.as_deref().unwrap_or("<unnamed>")
                );
                *locked = Some(device.clone());
                true
            }
            DeviceChoice::First(Some(locked)) => locked == device,
        }
    }
}

/// Why tracking is in its current state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum State {
    NoPoseYet,
    Tracking,
    Silent,
    Rejecting,
    SourceEnded,
    SourceFailed,
    Stopped,
}

/// The tracker node of one env, initialised but not yet running.
pub struct TrackerNode {
    session: Session,
    env: EnvId,
    calibration: Calibration,
    config: AgentConfig,
    /// Poses (`Latest`: the next supersedes), and their copy for viewers.
    pose: WatchedPublisher,
    tracking_key: String,
    sealer: Option<Arc<Sealer>>,
    samples: mpsc::Receiver<SourceItem>,
    source_name: String,
    stats: AgentStats,
    stats_tx: watch::Sender<AgentStats>,
    status_tx: watch::Sender<TrackingStatus>,
    filter: OutlierFilter,
    device: DeviceChoice,
    started: Instant,
    last_accepted: Option<Instant>,
    state: State,
    /// Reason of the current state, as published.
    reason: String,
    /// Why the latest pose was rejected.
    last_rejection: String,
    next_status: Instant,
    _pump: AbortOnDrop,
    _token: zenoh::liveliness::LivelinessToken,
}

impl TrackerNode {
    /// Declares the liveliness token and starts reading `source` (needs a
    /// Tokio runtime).
    pub async fn init(
        session: &Session,
        env: EnvId,
        calibration: Calibration,
        source: Box<dyn PoseSource>,
        config: AgentConfig,
    ) -> Result<Self, AgentError> {
        let token = session
            .liveliness()
            .declare_token(env.alive_key(Component::TrackerAgent))
            .await
            .map_err(|e| AgentError::Zenoh(e.to_string()))?;
        let pose = wire::publisher(session, env.key(Topic::Pose), Delivery::Latest)
            .await
            .map_err(|e| AgentError::Zenoh(e.to_string()))?;
        let pose = WatchedPublisher::new(session, &env, Topic::Pose, pose);
        let source_name = source.describe();
        let (tx, samples) = mpsc::channel(QUEUE);
        let pump = AbortOnDrop(tokio::spawn(pump(source, tx)));
        let now = Instant::now();
        let reason = "no pose yet".to_owned();
        let (status_tx, _) = watch::channel(TrackingStatus {
            tracking: false,
            last_pose_age_s: 0.0,
            reason: reason.clone(),
        });
        Ok(Self {
            session: session.clone(),
            pose,
            tracking_key: env.key(Topic::Tracking),
            sealer: config.seal_key.clone().map(|k| Arc::new(Sealer::new(k))),
            env,
            calibration,
            filter: OutlierFilter::new(config.filter),
            device: match &config.device {
                Some(id) => DeviceChoice::Only(id.clone()),
                None => DeviceChoice::First(None),
            },
            config,
            samples,
            source_name,
            stats: AgentStats::default(),
            stats_tx: watch::channel(AgentStats::default()).0,
            status_tx,
            started: now,
            last_accepted: None,
            state: State::NoPoseYet,
            reason,
            last_rejection: String::new(),
            next_status: now,
            _pump: pump,
            _token: token,
        })
    }

    /// The counters, updated after every event.
    pub fn stats(&self) -> watch::Receiver<AgentStats> {
        self.stats_tx.subscribe()
    }

    /// The tracking status as last published.
    pub fn status(&self) -> watch::Receiver<TrackingStatus> {
        self.status_tx.subscribe()
    }

    /// Runs until the source ends (`Ok`), fails (`Err`) or `shutdown`
    /// completes (`Ok`). Publishes a final not-tracking status either way.
    pub async fn run(
        mut self,
        shutdown: impl Future<Output = ()> + Send,
    ) -> Result<AgentStats, AgentError> {
        tracing::info!(env = %self.env, source = %self.source_name, "tracker agent running");
        self.publish_status().await?;
        tokio::pin!(shutdown);
        loop {
            let wake = self.next_wake();
            tokio::select! {
                biased;
                () = &mut shutdown => {
                    self.finish(State::Stopped, "tracker agent stopped".to_owned()).await?;
                    break;
                }
                item = self.samples.recv() => match item {
                    Some(Ok(Some(sample))) => self.on_sample(sample).await?,
                    Some(Err(SourceError::Malformed(e))) => {
                        self.stats.malformed += 1;
                        let n = self.stats.malformed;
                        if n <= 5 || n.is_power_of_two() {
                            tracing::warn!(source = %self.source_name, malformed = n, "skipped {e}");
                        }
                    }
                    Some(Err(e)) => {
                        self.finish(State::SourceFailed, format!("pose source failed: {e}")).await?;
                        return Err(AgentError::Source(e));
                    }
                    Some(Ok(None)) | None => {
                        self.finish(State::SourceEnded, "pose source ended".to_owned()).await?;
                        break;
                    }
                },
                () = tokio::time::sleep_until(wake) => {}
            }
            self.tick().await?;
        }
        tracing::info!(env = %self.env, stats = ?self.stats, "tracker agent stopped");
        Ok(self.stats)
    }

    fn next_wake(&self) -> Instant {
        match (self.state, self.last_accepted) {
            (State::Tracking, Some(last)) => (last + self.config.lost_after).min(self.next_status),
            _ => self.next_status,
        }
    }

    async fn on_sample(&mut self, sample: TrackerSample) -> Result<(), AgentError> {
        self.stats.received += 1;
        if !self.device.accepts(&sample.device) {
            self.stats.other_device += 1;
            if self.stats.other_device == 1 {
                tracing::warn!(
                    "ignoring poses of device {} (not the one in use)",
                    sample.device.as_deref().unwrap_or("<unnamed>")
                );
            }
            return Ok(());
        }
        let pose = self.calibration.base_link_in_world(&sample.pose);
        match self.filter.check(sample.timestamp_s, &pose) {
            Verdict::Rejected(why) => {
                self.stats.rejected += 1;
                if self.filter.rejected_in_streak() == 1 {
                    tracing::debug!("rejected a pose: {why}");
                }
                self.last_rejection = why.to_string();
                return Ok(());
            }
            Verdict::Relocked { rejected_for_s } => {
                self.stats.relocks += 1;
                tracing::warn!(
                    "re-locked on the newest pose after rejecting poses for {rejected_for_s:.2} s \
                     (the robot was probably carried)"
                );
            }
            Verdict::Accepted => {}
        }
        let msg = PoseStamped {
            header: Header::new(Time::now(), WORLD_FRAME),
            pose: to_pose_msg(&pose),
        };
        self.pose
            .publish_sealed(&msg, self.sealer.as_deref())
            .map_err(|e| AgentError::Zenoh(e.to_string()))?;
        self.stats.published += 1;
        self.last_accepted = Some(Instant::now());
        if self.state != State::Tracking {
            tracing::info!(env = %self.env, "tracking");
            self.set_state(State::Tracking, "tracking".to_owned())
                .await?;
        }
        Ok(())
    }

    /// Loss detection, periodic status and counters; runs after every event.
    async fn tick(&mut self) -> Result<(), AgentError> {
        let now = Instant::now();
        if let (State::Tracking, Some(last)) = (self.state, self.last_accepted) {
            if now.duration_since(last) >= self.config.lost_after {
                let (state, reason) = if self.filter.is_rejecting() {
                    (
                        State::Rejecting,
                        format!("poses rejected as outliers ({})", self.last_rejection),
                    )
                } else {
                    (
                        State::Silent,
                        format!(
                            "no pose for {:.2} s (lost after {:.2} s)",
                            now.duration_since(last).as_secs_f64(),
                            self.config.lost_after.as_secs_f64()
                        ),
                    )
                };
                self.stats.losses += 1;
                tracing::warn!(env = %self.env, "tracking lost: {reason}");
                self.set_state(state, reason).await?;
            }
        }
        if now >= self.next_status {
            self.publish_status().await?;
        }
        self.stats_tx.send_replace(self.stats.clone());
        Ok(())
    }

    async fn set_state(&mut self, state: State, reason: String) -> Result<(), AgentError> {
        self.state = state;
        self.reason = reason;
        self.publish_status().await
    }

    async fn finish(&mut self, state: State, reason: String) -> Result<(), AgentError> {
        if self.state == State::Tracking {
            self.stats.losses += 1;
        }
        self.set_state(state, reason).await?;
        self.stats_tx.send_replace(self.stats.clone());
        Ok(())
    }

    async fn publish_status(&mut self) -> Result<(), AgentError> {
        // Whoever sees this status sees counters at least this fresh.
        self.stats_tx.send_replace(self.stats.clone());
        let now = Instant::now();
        let since = self.last_accepted.unwrap_or(self.started);
        let status = TrackingStatus {
            tracking: self.state == State::Tracking,
            last_pose_age_s: now.duration_since(since).as_secs_f64(),
            reason: self.reason.clone(),
        };
        wire::put_sealed(
            &self.session,
            &self.tracking_key,
            &status,
            self.sealer.as_deref(),
        )
        .await
        .map_err(|e| AgentError::Zenoh(e.to_string()))?;
        self.status_tx.send_replace(status);
        self.next_status = now + self.config.status_period;
        Ok(())
    }
}

/// Initialises and runs a tracker node until `shutdown` completes or the
/// source ends (the binary's entry point).
pub async fn run(
    session: &Session,
    env: EnvId,
    calibration: Calibration,
    source: Box<dyn PoseSource>,
    config: AgentConfig,
    shutdown: impl Future<Output = ()> + Send,
) -> Result<AgentStats, AgentError> {
    TrackerNode::init(session, env, calibration, source, config)
        .await?
        .run(shutdown)
        .await
}

/// A tracker node running on its own task; stops when dropped.
pub struct TrackerAgent {
    session: Session,
    env: EnvId,
    stats: watch::Receiver<AgentStats>,
    status: watch::Receiver<TrackingStatus>,
    stop: Option<oneshot::Sender<()>>,
    task: Option<JoinHandle<Result<AgentStats, AgentError>>>,
    sealer: Option<Arc<Sealer>>,
}

impl TrackerAgent {
    /// Starts a node serving `env` on `session` from `source` (needs a Tokio
    /// runtime). The liveliness token is declared before this returns.
    pub async fn spawn(
        session: &Session,
        env: EnvId,
        calibration: Calibration,
        source: Box<dyn PoseSource>,
        config: AgentConfig,
    ) -> Result<Self, AgentError> {
        let node = TrackerNode::init(session, env.clone(), calibration, source, config).await?;
        let stats = node.stats();
        let status = node.status();
        let sealer = node.sealer.clone();
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(node.run(async move {
            // Dropping the sender also stops the node.
            let _ = stopped.await;
        }));
        Ok(Self {
            session: session.clone(),
            env,
            stats,
            status,
            stop: Some(stop),
            task: Some(task),
            sealer,
        })
    }

    /// The env served.
    pub fn env(&self) -> &EnvId {
        &self.env
    }

    /// Counters so far.
    pub fn stats(&self) -> AgentStats {
        self.stats.borrow().clone()
    }

    /// The tracking status as last published.
    pub fn status(&self) -> TrackingStatus {
        self.status.borrow().clone()
    }

    /// Whether the node has ended (source ended or failed).
    pub fn is_finished(&self) -> bool {
        self.task.as_ref().is_none_or(JoinHandle::is_finished)
    }

    /// Waits until the node ends by itself (a finite source ended, or the
    /// source failed) and returns its outcome.
    pub async fn join(mut self) -> Result<AgentStats, AgentError> {
        self.await_task().await
    }

    /// Stops the node (publishing a final not-tracking status) and returns
    /// its counters.
    pub async fn stop(mut self) -> Result<AgentStats, AgentError> {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        self.await_task().await
    }

    async fn await_task(&mut self) -> Result<AgentStats, AgentError> {
        match self.task.take() {
            Some(task) => match task.await {
                Ok(result) => result,
                Err(e) => Err(AgentError::Task(e.to_string())),
            },
            None => Ok(self.stats()),
        }
    }
}

impl Drop for TrackerAgent {
    /// Aborts the node; if it was still running, tells the controller that
    /// tracking is gone (best effort) so it never scores on a stale pose.
    fn drop(&mut self) {
        let Some(task) = self.task.take() else {
            return;
        };
        let was_running = !task.is_finished();
        task.abort();
        if was_running {
            let status = TrackingStatus {
                tracking: false,
                last_pose_age_s: self.status.borrow().last_pose_age_s,
                reason: "tracker agent stopped".to_owned(),
            };
            if let Ok(bytes) = offworld_runtime::codec::encode(&status) {
                let key = self.env.key(Topic::Tracking);
                let seal = self.sealer.as_ref().map(|s| s.seal(&key, &bytes, &[]));
                let _ = self
                    .session
                    .put(key, bytes)
                    .encoding(zenoh::bytes::Encoding::APPLICATION_CDR)
                    .attachment(seal.map(zenoh::bytes::ZBytes::from))
                    .wait();
            }
        }
    }
}
