//! The controller's view of whatever embodies the robot under an env's
//! namespace (sim twin, or robot_agent + tracker_agent): it sends motion
//! commands and waits for the frame and the pose that answer them. It never
//! knows which embodiment it drives.

use std::sync::Arc;
use std::time::{Duration, Instant};

use offworld_runtime::codec;
use offworld_runtime::keys::{Component, EnvId, Topic};
use offworld_runtime::msg::{
    CameraFrameView, GotoReply, GotoRequest, MotionCommand, MotionFault, ObsOptions, Pose2D,
    PoseStamped, SeqTag, TrackingStatus,
};
use offworld_runtime::pool::BufferPool;
use offworld_runtime::preview::WatchedPublisher;
use offworld_runtime::seal::{Gate, SealKey, Sealer};
use offworld_runtime::wire::{self, Delivery};
use offworld_runtime::WireError;
use tokio::sync::watch;
use zenoh::bytes::ZBytes;
use zenoh::pubsub::Subscriber;
use zenoh::sample::{Sample, SampleKind};
use zenoh::Session;

use crate::error::ControllerError;
use crate::observation::assemble_into;
use crate::step::AwaitingFrame;

/// A pose as received.
#[derive(Debug, Clone)]
pub struct PoseSample {
    /// The message.
    pub pose: PoseStamped,
    /// The command it answers, if the embodiment tags poses (sim twin).
    pub seq: Option<u64>,
    /// When it arrived.
    pub received: Instant,
}

impl PoseSample {
    /// Planar pose.
    pub fn planar(&self) -> Pose2D {
        let p = &self.pose.pose;
        Pose2D {
            x: p.position.x,
            y: p.position.y,
            yaw: p.orientation.yaw(),
        }
    }
}

/// A received camera frame, kept as its (contiguous) payload: a frame is
/// decoded in place, never copied out, on its way to the observation.
pub struct Frame {
    seq: u64,
    payload: ZBytes,
}

impl Frame {
    /// Checks that `payload` decodes as a frame and keeps it.
    fn accept(payload: &ZBytes) -> Result<Self, offworld_runtime::DecodeError> {
        let payload = codec::contiguous(payload);
        let seq = codec::decode_borrowed::<CameraFrameView>(&payload.to_bytes())?.seq;
        Ok(Self { seq, payload })
    }

    /// The command this frame answers.
    pub fn seq(&self) -> u64 {
        self.seq
    }

    /// The frame's payload (`CameraFrame` CDR), as received.
    pub fn payload(&self) -> &ZBytes {
        &self.payload
    }

    /// Reads the frame in place.
    pub fn with_view<R>(
        &self,
        read: impl FnOnce(&CameraFrameView) -> Result<R, WireError>,
    ) -> Result<R, WireError> {
        let bytes = self.payload.to_bytes();
        let view = codec::decode_borrowed::<CameraFrameView>(&bytes)
            .map_err(|e| WireError::internal(format!("robot sent a bad frame: {e}")))?;
        read(&view)
    }

    /// The observation `request` asks for, built from this frame into a
    /// buffer of `buffers`.
    pub(crate) fn build(
        &self,
        request: &ObservationRequest,
        buffers: &BufferPool,
    ) -> Result<ZBytes, WireError> {
        let mut data = buffers.take(request.options.shape().shape_len() as usize);
        self.with_view(|frame| {
            assemble_into(frame, &request.options, request.depth_max_m, &mut data)
        })?;
        Ok(buffers.payload(data))
    }
}

/// The observation to build from the frames that answer a command.
#[derive(Debug, Clone, Copy)]
pub struct ObservationRequest {
    /// Channels, size and depth format.
    pub options: ObsOptions,
    /// Depth mapped to uint8 255.
    pub depth_max_m: f32,
}

/// The command waiting for its frame, if any ([`crate::step`]).
type Pending = Arc<std::sync::Mutex<Option<Box<dyn AwaitingFrame>>>>;

/// Locks the pending slot; a panic elsewhere while it was held leaves
/// nothing half-done in it (it is only ever replaced or taken).
fn lock_pending(pending: &Pending) -> std::sync::MutexGuard<'_, Option<Box<dyn AwaitingFrame>>> {
    pending
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Timeouts of the link.
#[derive(Debug, Clone, Copy)]
pub struct LinkTimeouts {
    /// Added to a motion's duration while waiting for its frame.
    pub answer_margin: Duration,
    /// How long to wait for a fresh pose after the frame arrived.
    pub pose_wait: Duration,
    /// Longest reset drive.
    pub goto: Duration,
    /// A step in flight fails when the embodiment's heartbeat echoes
    /// (`heartbeat_echo`) stopped this long: the link to it is cut or it
    /// is frozen. Three times the robot's watchdog window, which has
    /// stopped the robot by then.
    pub silence: Duration,
}

impl Default for LinkTimeouts {
    fn default() -> Self {
        Self {
            answer_margin: Duration::from_secs(5),
            pose_wait: Duration::from_millis(500),
            goto: Duration::from_secs(60),
            silence: Duration::from_millis(600),
        }
    }
}

/// What a real site seals ([`offworld_runtime::seal`]); none by default.
#[derive(Debug, Clone, Default)]
pub struct LinkSeals {
    /// Seals every command, heartbeat and reset drive sent to a robot (its
    /// agent, given the same key, obeys nothing else).
    pub command: Option<Arc<Sealer>>,
    /// The tracker agent's key: a real env believes only poses and
    /// tracking reports sealed with it.
    pub tracker: Option<SealKey>,
}

impl LinkSeals {
    /// The gate of a tracker stream of `env`, if the site seals them
    /// (twins do not: a sim env's poses are the twin's own).
    fn tracker_gate(&self, env: &EnvId, what: &'static str) -> Option<Gate> {
        let key = self
            .tracker
            .clone()
            .filter(|_| env.realm() == offworld_runtime::Realm::Real)?;
        Some(Gate::new(key, what))
    }
}

/// Subscriptions to one env's robot-side keys.
pub struct RobotLink {
    session: Session,
    env: EnvId,
    /// Commands, and their copy for viewers (never waited for).
    cmd: WatchedPublisher,
    sealer: Option<Arc<Sealer>>,
    frames: watch::Receiver<Option<Arc<Frame>>>,
    pending: Pending,
    faults: watch::Receiver<Option<MotionFault>>,
    poses: watch::Receiver<Option<PoseSample>>,
    /// True while the tracker reports (or its vanished token means) that
    /// tracking is lost; a step in flight wakes on it.
    tracking_lost: Arc<watch::Sender<bool>>,
    embodiment_alive: watch::Receiver<bool>,
    /// When the embodiment last echoed a heartbeat (`None`: never, e.g. an
    /// embodiment from before the echo existed: not held against it).
    heard: watch::Receiver<Option<Instant>>,
    /// Set when the controller stops: commands in flight fail at once.
    closing: watch::Sender<bool>,
    timeouts: LinkTimeouts,
    _subscribers: Vec<Subscriber<()>>,
}

impl RobotLink {
    /// Subscribes to `obs`, `fault`, `pose`, `tracking` and the
    /// embodiment's liveliness tokens of `env`.
    pub async fn connect(
        session: &Session,
        env: &EnvId,
        timeouts: LinkTimeouts,
        seals: &LinkSeals,
    ) -> Result<Self, ControllerError> {
        let (frame_tx, frames) = watch::channel(None);
        let pending = Pending::default();
        let building = pending.clone();
        // Observation buffers, recycled once a reply is sent.
        let buffers = BufferPool::new();
        let (pose_tx, poses) = watch::channel(None::<PoseSample>);
        let latest_pose = poses.clone();
        let tracking_lost = Arc::new(watch::channel(false).0);
        let lost = tracking_lost.clone();
        // The observation is built here, from the frame just received (still
        // in this thread's cache; for a local twin, the very thread that
        // rendered it).
        let obs = session
            .declare_subscriber(env.key(Topic::Obs))
            .callback(
                move |sample: Sample| match Frame::accept(sample.payload()) {
                    Ok(frame) => {
                        let frame = Arc::new(frame);
                        let announce = |frame| {
                            frame_tx.send_replace(Some(frame));
                        };
                        let waiting = lock_pending(&building).take_if(|p| p.seq() == frame.seq());
                        match waiting {
                            Some(step) => {
                                let pose = latest_pose.borrow().clone().filter(|_| !*lost.borrow());
                                step.on_frame(frame, &buffers, pose, &announce);
                            }
                            None => announce(frame),
                        }
                    }
                    Err(e) => tracing::warn!("rejected a malformed frame: {e}"),
                },
            )
            .await?;
        let (fault_tx, faults) = watch::channel(None);
        let fault = subscribe_decoded(
            session,
            env.key(Topic::Fault),
            "fault",
            None,
            move |fault, _| {
                fault_tx.send_replace(Some(fault));
            },
        )
        .await?;
        let pose = subscribe_decoded(
            session,
            env.key(Topic::Pose),
            "pose",
            seals.tracker_gate(env, "tracker pose"),
            move |pose, sample| {
                let seq = wire::decode_attachment::<SeqTag>(sample).map(|t| t.seq);
                pose_tx.send_replace(Some(PoseSample {
                    pose,
                    seq,
                    received: Instant::now(),
                }));
            },
        )
        .await?;
        let lost = tracking_lost.clone();
        let tracking = subscribe_decoded(
            session,
            env.key(Topic::Tracking),
            "tracking status",
            seals.tracker_gate(env, "tracking status"),
            move |status: TrackingStatus, _| {
                lost.send_replace(!status.tracking);
            },
        )
        .await?;
        // The env is online while a sim twin or a robot agent declares itself.
        let (alive_tx, embodiment_alive) = watch::channel(false);
        let twin_key = env.alive_key(Component::SimTwin);
        let robot_key = env.alive_key(Component::RobotAgent);
        let tracker_key = env.alive_key(Component::TrackerAgent);
        // A crashed tracker agent cannot say that tracking is lost: its
        // vanished token says it for it.
        let tracker_lost = tracking_lost.clone();
        let present = std::sync::Mutex::new(std::collections::BTreeSet::<String>::new());
        let liveliness = session
            .liveliness()
            .declare_subscriber(env.components_alive_selector())
            .history(true)
            .callback(move |sample: Sample| {
                let key = sample.key_expr().as_str().to_owned();
                if key == tracker_key && sample.kind() == SampleKind::Delete {
                    tracker_lost.send_replace(true);
                }
                if key != twin_key && key != robot_key {
                    return;
                }
                let Ok(mut set) = present.lock() else { return };
                match sample.kind() {
                    SampleKind::Put => set.insert(key),
                    SampleKind::Delete => set.remove(&key),
                };
                alive_tx.send_replace(!set.is_empty());
            })
            .await?;
        let (heard_tx, heard) = watch::channel(None);
        let echo = session
            .declare_subscriber(env.key(Topic::HeartbeatEcho))
            .callback(move |_: Sample| {
                heard_tx.send_replace(Some(Instant::now()));
            })
            .await?;
        let cmd = wire::publisher(session, env.key(Topic::Cmd), Delivery::Every)
            .priority(wire::CONTROL_PRIORITY)
            .await?;
        let cmd = WatchedPublisher::new(session, env, Topic::Cmd, cmd);
        Ok(Self {
            session: session.clone(),
            env: env.clone(),
            cmd,
            sealer: seals.command.clone(),
            frames,
            pending,
            faults,
            poses,
            tracking_lost,
            embodiment_alive,
            heard,
            closing: watch::channel(false).0,
            timeouts,
            _subscribers: vec![obs, fault, pose, tracking, liveliness, echo],
        })
    }

    /// How long the robot has been silent, when longer than the link's
    /// `silence` limit. Real robots only: a twin's silence moves nothing,
    /// and a loaded training host must not fail sim steps for it (its
    /// answer timeout still applies).
    fn silent_for(&self) -> Option<Duration> {
        if self.env.realm() != offworld_runtime::Realm::Real {
            return None;
        }
        let heard = (*self.heard.borrow())?;
        Some(heard.elapsed()).filter(|d| *d > self.timeouts.silence)
    }

    /// Whether a twin or robot agent is present.
    pub fn online(&self) -> bool {
        *self.embodiment_alive.borrow()
    }

    /// Waits (bounded) until the embodiment is present.
    pub async fn wait_online(&self, timeout: Duration) -> bool {
        let mut alive = self.embodiment_alive.clone();
        tokio::time::timeout(timeout, alive.wait_for(|a| *a))
            .await
            .is_ok_and(|r| r.is_ok())
    }

    /// Refuses a command that cannot be answered now: no robot, the
    /// controller stopping, or tracking lost (the robot is stopped then).
    pub(crate) async fn ready_to_send(&self) -> Result<(), WireError> {
        if !self.online() {
            return Err(self.gone());
        }
        if *self.closing.borrow() {
            return Err(WireError::unavailable("the controller is stopping"));
        }
        if *self.tracking_lost.borrow() {
            self.stop().await;
            return Err(WireError::unavailable(
                "tracking lost: the robot's pose is unknown",
            ));
        }
        Ok(())
    }

    /// Hands the next frame of `step`'s command to it, on the frame's thread.
    pub(crate) fn expect(&self, step: Box<dyn AwaitingFrame>) {
        *lock_pending(&self.pending) = Some(step);
    }

    /// Withdraws the command `seq` from the frame's thread; false if that
    /// thread has taken it already.
    pub(crate) fn withdraw(&self, seq: u64) -> bool {
        lock_pending(&self.pending)
            .take_if(|p| p.seq() == seq)
            .is_some()
    }

    /// Sends `cmd` and waits until its frame is in and the pose that
    /// answers it: tagged with the command, or (a tracker streaming) the
    /// first after the frame. Fails fast on whatever makes an answer
    /// impossible.
    pub(crate) async fn send_and_await(
        &self,
        cmd: &MotionCommand,
    ) -> Result<PoseSample, WireError> {
        let mut frames = self.frames.clone();
        frames.mark_unchanged();
        let mut faults = self.faults.clone();
        faults.mark_unchanged();
        let mut alive = self.embodiment_alive.clone();
        alive.mark_unchanged();
        let mut lost = self.tracking_lost.subscribe();
        lost.mark_unchanged();
        let mut closing = self.closing.subscribe();
        closing.mark_unchanged();
        self.cmd
            .publish_sealed(cmd, self.sealer.as_deref())
            .map_err(|e| WireError::internal(format!("cannot send the command: {e}")))?;
        let limit = Duration::from_secs_f64(cmd.duration_s.max(0.0)) + self.timeouts.answer_margin;
        let seq = cmd.seq;
        let period = self.timeouts.silence / 6;
        let mut listen = tokio::time::interval_at(tokio::time::Instant::now() + period, period);
        let answer = tokio::time::timeout(limit, async {
            loop {
                tokio::select! {
                    _ = listen.tick() => {
                        if let Some(silent) = self.silent_for() {
                            return Some(Err(WireError::unavailable(format!(
                                "no word from the robot of {} for {} ms (its heartbeat echoes stopped): \
                                 the link to it is cut or it is frozen",
                                self.env,
                                silent.as_millis()
                            ))));
                        }
                    }
                    changed = frames.changed() => {
                        if changed.is_err() {
                            return None;
                        }
                        if frames.borrow_and_update().as_ref().is_some_and(|f| f.seq() == seq) {
                            return Some(Ok(()));
                        }
                    }
                    Ok(()) = faults.changed() => {
                        let fault = faults.borrow_and_update().clone();
                        let ours = |f: &MotionFault| f.seq == seq || f.seq == MotionFault::ANY_COMMAND;
                        if let Some(fault) = fault.filter(ours) {
                            return Some(Err(WireError::unavailable(format!(
                                "the robot cannot answer command {seq}: {}",
                                fault.reason
                            ))));
                        }
                    }
                    // Fail fast: what the controller knows is gone fails
                    // the step now, not after the answer timeout.
                    Ok(()) = alive.changed() => {
                        if !*alive.borrow_and_update() {
                            return Some(Err(self.gone()));
                        }
                    }
                    Ok(()) = closing.changed() => {
                        if *closing.borrow_and_update() {
                            return Some(Err(WireError::unavailable("the controller is stopping")));
                        }
                    }
                    Ok(()) = lost.changed() => {
                        if *lost.borrow_and_update() {
                            self.stop().await;
                            return Some(Err(WireError::unavailable(format!(
                                "tracking lost during command {seq}: the robot's pose is unknown"
                            ))));
                        }
                    }
                }
            }
        })
        .await
        .ok()
        .flatten()
        .ok_or_else(|| {
            WireError::timeout(format!(
                "the robot did not answer command {seq} within {:.1} s",
                limit.as_secs_f64()
            ))
        })?;
        answer?;
        let arrived = Instant::now();
        // A tagged pose answers this command exactly; an untagged one (a
        // tracker streaming) must have arrived after the frame.
        let fresh = |p: &Option<PoseSample>| {
            p.as_ref()
                .is_some_and(|p| p.seq == Some(seq) || (p.seq.is_none() && p.received >= arrived))
        };
        let mut poses = self.poses.clone();
        let pose = match tokio::time::timeout(self.timeouts.pose_wait, poses.wait_for(fresh)).await
        {
            Ok(Ok(p)) => p.clone(),
            _ => None,
        };
        let Some(pose) = pose else {
            self.stop().await;
            return Err(WireError::unavailable(format!(
                "tracking lost: no pose for command {seq} within {:.1} s",
                self.timeouts.pose_wait.as_secs_f64()
            )));
        };
        if *self.tracking_lost.borrow() {
            self.stop().await;
            return Err(WireError::unavailable("tracking lost during the step"));
        }
        Ok(pose)
    }

    /// Moves the robot to a spawn pose (sim: teleport; real: drive there).
    pub async fn goto(&self, seq: u64, target: Pose2D) -> Result<GotoReply, WireError> {
        let request = GotoRequest {
            seq,
            target,
            timeout_s: self.timeouts.goto.as_secs_f64(),
        };
        if !self.online() {
            return Err(self.gone());
        }
        let mut alive = self.embodiment_alive.clone();
        let key = self.env.key(Topic::Goto);
        let drive = wire::request_sealed(
            &self.session,
            &key,
            &request,
            self.timeouts.goto + Duration::from_secs(1),
            self.sealer.as_deref(),
        );
        tokio::select! {
            reply = drive => reply.map_err(|e| match e.into_wire() {
                e if e.code == offworld_runtime::ErrorCode::NotFound => WireError::unavailable(
                    format!("no robot or twin serves {}: {}", self.env, e.message),
                ),
                e => e,
            }),
            // A reset drive fails as soon as its robot is known to be gone.
            _ = alive.wait_for(|a| !*a) => Err(self.gone()),
        }
    }

    /// The error of a step or reset whose robot (or twin) vanished.
    fn gone(&self) -> WireError {
        WireError::unavailable(format!(
            "the robot of {} is gone: its agent's (or twin's) liveliness token vanished \
             (process stopped, or the link to it is cut)",
            self.env
        ))
    }

    /// The controller is stopping: commands in flight fail now (their
    /// episodes are recorded as aborted) and new ones are refused.
    pub fn close(&self) {
        self.closing.send_replace(true);
    }

    /// Commands zero velocity at once (best effort).
    pub async fn stop(&self) {
        let halt = MotionCommand {
            seq: u64::MAX,
            linear_x: 0.0,
            angular_z: 0.0,
            duration_s: 0.0,
        };
        if let Err(e) = self.cmd.publish_sealed(&halt, self.sealer.as_deref()) {
            tracing::error!(env = %self.env, "cannot send stop: {e}");
        }
    }
}

/// Subscribes to `key`, handing each sample that decodes as `T` (with the
/// sample, for its attachment) to `on`; malformed ones, and with a `gate`
/// unsealed ones, are logged and dropped.
async fn subscribe_decoded<T: serde::de::DeserializeOwned>(
    session: &Session,
    key: String,
    what: &'static str,
    gate: Option<Gate>,
    on: impl Fn(T, &Sample) + Send + Sync + 'static,
) -> Result<Subscriber<()>, zenoh::Error> {
    session
        .declare_subscriber(key)
        .callback(move |sample: Sample| {
            if gate.as_ref().is_some_and(|g| !g.admit(&sample)) {
                return;
            }
            match codec::decode_payload::<T>(sample.payload()) {
                Ok(msg) => on(msg, &sample),
                Err(e) => tracing::warn!("rejected a malformed {what}: {e}"),
            }
        })
        .await
}
