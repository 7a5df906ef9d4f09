//! The agent node: motion commands from the controller become velocity on
//! the robot; camera frames captured after each motion answer it; reset
//! requests drive the robot to a pose; the watchdog and the e-stop can stop
//! everything at any time.
//!
//! One task owns all state. Zenoh callbacks only enqueue [`Event`]s; a
//! control tick (`control_hz`) does the rest, so safety decisions never wait
//! on a network reply.

use std::time::{Duration, Instant};

use offworld_runtime::codec;
use offworld_runtime::estop::{self, Latch, Pressed, RecentPresses};
use offworld_runtime::keys::{global_estop_key, Component, EnvId, Topic};
use offworld_runtime::msg::{
    CameraFrame, EStop, EStopAck, EStopState, GotoReply, GotoRequest, MotionCommand, MotionFault,
    Pose2D, PoseStamped, SeqTag, Time, TrackingStatus,
};
use offworld_runtime::preview::{PreviewPublisher, WatchedPublisher};
use offworld_runtime::seal::{Gate, SealKey, Sealed};
use offworld_runtime::wire::{self, Delivery, RequestError};
use offworld_runtime::WireError;
use tokio::sync::{mpsc, oneshot, watch};
use tokio::task::JoinHandle;
use zenoh::bytes::ZBytes;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Sample, SampleKind};
use zenoh::Session;
use zenoh::Wait;

use crate::base_check::{BaseCheck, CheckStep};
use crate::config::AgentConfig;
use crate::error::AgentError;
use crate::hardware::{RobotHardware, Sensors};
use crate::latch::EStopLatch;
use crate::limiter::{Velocity, VelocityLimiter};
use crate::nav::{NavCommand, Navigator, OccupancyGrid};
use crate::watchdog::{Transition, Watchdog};

/// The controller's stop command carries this sequence number.
const STOP_SEQ: u64 = u64::MAX;
/// Longest motion accepted, s.
const MAX_MOTION_S: f64 = 10.0;
/// Longest reset drive accepted, s.
const MAX_GOTO_S: f64 = 300.0;
/// Zero velocity keeps being sent this long after a stop.
const ZERO_TAIL: Duration = Duration::from_millis(500);
/// Event queue bound.
const QUEUE: usize = 256;
/// Odometry older than this says nothing about the base now.
const ODOM_STALE: Duration = Duration::from_millis(200);
/// How long a starting agent asks the network for the e-stop latches.
const RECALL: Duration = Duration::from_millis(500);

/// Everything that reaches the agent from the network.
enum Event {
    Command(MotionCommand),
    /// The controller's heartbeat, as received (echoed back).
    Heartbeat(ZBytes),
    EStop(Latch, EStop),
    /// What the network remembers of the latches, asked again after the
    /// start ([`estop::RECALL_AGAIN`]).
    Recalled(EStopState),
    ControllerPresent(bool),
    GuardPresent(bool),
    Tracking(bool),
    Goto(Query),
}

/// A running agent; stops the robot and ends when dropped or shut down.
pub type AgentHandle = NodeHandle;

/// A node running on its own task until told to stop: dropping the handle
/// tells it, [`NodeHandle::shutdown`] also waits for it to end.
pub struct NodeHandle {
    shutdown: Option<oneshot::Sender<()>>,
    task: Option<JoinHandle<()>>,
}

impl NodeHandle {
    /// Runs `node` (told to stop through the receiver it is given).
    pub(crate) fn spawn<F>(node: impl FnOnce(oneshot::Receiver<()>) -> F) -> Self
    where
        F: std::future::Future<Output = ()> + Send + 'static,
    {
        let (shutdown, stop) = oneshot::channel();
        Self {
            shutdown: Some(shutdown),
            task: Some(tokio::spawn(node(stop))),
        }
    }

    /// Stops the node (for the agent: the robot first) and waits for it.
    pub async fn shutdown(mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
        if let Some(task) = self.task.take() {
            let _ = task.await;
        }
    }
}

impl Drop for NodeHandle {
    fn drop(&mut self) {
        if let Some(tx) = self.shutdown.take() {
            let _ = tx.send(());
        }
    }
}

/// Serves `env` with `robot` on `session` until the handle is dropped.
pub async fn spawn<H: RobotHardware>(
    session: &Session,
    env: EnvId,
    config: AgentConfig,
    robot: H,
) -> Result<AgentHandle, AgentError> {
    config.validate()?;
    let grid = OccupancyGrid::from_world(&config.world_spec()?, &config.nav)
        .map_err(|e| AgentError::Config(format!("navigation map: {e}")))?;
    let latch = config.estop_latch.clone().map(EStopLatch::new);
    let estops = recall_estops(session, &env, latch.as_ref()).await;
    if let Some(file) = &latch {
        // Written now: an agent that could not remember an e-stop must not
        // run (it would come back released after a restart).
        file.store(&estops).map_err(|e| {
            AgentError::Config(format!(
                "cannot write the e-stop latch {}: {e} (choose a writable file with --estop-latch)",
                file.path().display()
            ))
        })?;
    }
    let (estop_tx, estop_rx) = watch::channel(estops.clone());
    let (tx, events) = mpsc::channel::<Event>(QUEUE);
    let (pose_tx, poses) = watch::channel(None);
    let seals = Seals::load(&config)?;
    // A fresh session may not reach every `estop_state` yet: ask again.
    let (again_session, again_env, again_tx) = (session.clone(), env.clone(), tx.clone());
    tokio::spawn(async move {
        for delay in estop::RECALL_AGAIN {
            tokio::time::sleep(delay).await;
            let network = estop::recall(&again_session, &again_env, RECALL).await;
            if again_tx.send(Event::Recalled(network)).await.is_err() {
                return;
            }
        }
    });
    let declarations = Declarations::declare(session, &env, tx, pose_tx, estop_rx, seals).await?;
    let odometry = OdometryStream::start(session, &env, robot.sensors()).await?;
    let agent = Agent {
        outbox: Outbox::declare(session, &env).await?,
        env,
        watchdog: if config.require_base_guard {
            Watchdog::new(config.watchdog()).require_guard()
        } else {
            Watchdog::new(config.watchdog())
        },
        limiter: VelocityLimiter::new(config.limits),
        base_check: config.base_check(),
        sensors: robot.sensors(),
        robot,
        grid,
        poses,
        latch,
        config,
        estops,
        estop_tx,
        presses: RecentPresses::default(),
        tracking: true,
        activity: Activity::Idle,
        last_motion: None,
        last_tick: Instant::now(),
        watch_camera_from: Instant::now(),
        _declarations: declarations,
        _odometry: odometry,
    };
    Ok(NodeHandle::spawn(|stop| agent.run(events, stop)))
}

/// The gates of the sealed streams ([`offworld_runtime::seal`]), with
/// the site's keys: what moves the robot must be sealed by the controller,
/// what steers navigation by the tracker agent.
#[derive(Default)]
struct Seals {
    cmd: Option<Gate>,
    heartbeat: Option<Gate>,
    goto: Option<Gate>,
    pose: Option<Gate>,
    tracking: Option<Gate>,
}

impl Seals {
    fn load(config: &AgentConfig) -> Result<Self, AgentError> {
        let load = |path: &Option<std::path::PathBuf>| {
            path.as_deref()
                .map(SealKey::load)
                .transpose()
                .map_err(|e| AgentError::Config(e.to_string()))
        };
        let command = load(&config.command_key)?;
        let tracker = load(&config.tracker_key)?;
        if command.is_none() {
            tracing::warn!("commands are not checked for the site's seal (no command key): the router's access control is their only guard");
        }
        let gate = |key: &Option<SealKey>, what| key.clone().map(|k| Gate::new(k, what));
        Ok(Self {
            cmd: gate(&command, "motion command"),
            heartbeat: gate(&command, "controller heartbeat"),
            goto: gate(&command, "reset drive request"),
            pose: gate(&tracker, "tracker pose"),
            tracking: gate(&tracker, "tracking status"),
        })
    }
}

/// Whether `gate` (if any) admits `message`.
fn admitted(gate: &Option<Gate>, message: &impl Sealed) -> bool {
    gate.as_ref().is_none_or(|g| g.admit(message))
}

/// Zenoh declarations kept alive with the agent.
struct Declarations {
    _subscribers: Vec<Subscriber<()>>,
    _goto: Queryable<()>,
    _estop_state: Queryable<()>,
    _token: LivelinessToken,
}

impl Declarations {
    async fn declare(
        session: &Session,
        env: &EnvId,
        tx: mpsc::Sender<Event>,
        pose_tx: watch::Sender<Option<(Pose2D, Instant)>>,
        estops: watch::Receiver<EStopState>,
        seals: Seals,
    ) -> Result<Self, AgentError> {
        let Seals {
            cmd: cmd_gate,
            heartbeat: heartbeat_gate,
            goto: goto_gate,
            pose: pose_gate,
            tracking: tracking_gate,
        } = seals;
        let enqueue = |tx: &mpsc::Sender<Event>, event: Event| {
            if tx.try_send(event).is_err() {
                tracing::warn!("robot agent queue full: dropped a message");
            }
        };
        let mut subscribers = Vec::new();
        let t = tx.clone();
        subscribers.push(
            session
                .declare_subscriber(env.key(Topic::Cmd))
                .callback(move |s: Sample| {
                    if !admitted(&cmd_gate, &s) {
                        return;
                    }
                    match codec::decode_payload::<MotionCommand>(s.payload()) {
                        Ok(cmd) => enqueue(&t, Event::Command(cmd)),
                        Err(e) => tracing::warn!("rejected a malformed command: {e}"),
                    }
                })
                .await?,
        );
        let t = tx.clone();
        subscribers.push(
            session
                .declare_subscriber(env.key(Topic::Heartbeat))
                .callback(move |s: Sample| {
                    if admitted(&heartbeat_gate, &s) {
                        enqueue(&t, Event::Heartbeat(s.payload().clone()));
                    }
                })
                .await?,
        );
        for (key, latch) in [
            (env.key(Topic::EStop), Latch::Env),
            (global_estop_key(), Latch::Site),
        ] {
            let t = tx.clone();
            subscribers.push(
                session
                    .declare_subscriber(key)
                    .callback(move |s: Sample| {
                        let stop = estop::decode(s.payload());
                        // Never dropped: an e-stop must get through.
                        let t = t.clone();
                        tokio::spawn(async move {
                            let _ = t.send(Event::EStop(latch, stop)).await;
                        });
                    })
                    .await?,
            );
        }
        let t = tx.clone();
        subscribers.push(
            session
                .declare_subscriber(env.key(Topic::Tracking))
                .callback(move |s: Sample| {
                    if !admitted(&tracking_gate, &s) {
                        return;
                    }
                    match codec::decode_payload::<TrackingStatus>(s.payload()) {
                        Ok(status) => enqueue(&t, Event::Tracking(status.tracking)),
                        Err(e) => tracing::warn!("rejected a malformed tracking status: {e}"),
                    }
                })
                .await?,
        );
        subscribers.push(
            session
                .declare_subscriber(env.key(Topic::Pose))
                .callback(move |s: Sample| {
                    if !admitted(&pose_gate, &s) {
                        return;
                    }
                    match codec::decode_payload::<PoseStamped>(s.payload()) {
                        Ok(p) => {
                            let pose = Pose2D {
                                x: p.pose.position.x,
                                y: p.pose.position.y,
                                yaw: p.pose.orientation.yaw(),
                            };
                            if pose.x.is_finite() && pose.y.is_finite() && pose.yaw.is_finite() {
                                pose_tx.send_replace(Some((pose, Instant::now())));
                            }
                        }
                        Err(e) => tracing::warn!("rejected a malformed pose: {e}"),
                    }
                })
                .await?,
        );
        // Presence changes are never dropped: each one arms or disarms.
        type Presence = fn(bool) -> Event;
        let presence: [(Component, Presence); 2] = [
            (Component::Controller, Event::ControllerPresent),
            (Component::BaseGuard, Event::GuardPresent),
        ];
        for (component, event) in presence {
            let t = tx.clone();
            subscribers.push(
                session
                    .liveliness()
                    .declare_subscriber(env.alive_key(component))
                    .history(true)
                    .callback(move |s: Sample| {
                        let present = event(s.kind() == SampleKind::Put);
                        let t = t.clone();
                        tokio::spawn(async move {
                            let _ = t.send(present).await;
                        });
                    })
                    .await?,
            );
        }
        let t = tx;
        let goto = session
            .declare_queryable(env.key(Topic::Goto))
            .callback(move |q: Query| {
                if !admitted(&goto_gate, &q) {
                    // Refused openly: the asker learns why it is ignored.
                    tokio::spawn(async move {
                        let refused = WireError::unauthorized(
                            "reset drive refused: not sealed with the site's command key",
                        );
                        let _ = wire::reply::<GotoReply>(&q, Err(refused)).await;
                    });
                    return;
                }
                if let Err(mpsc::error::TrySendError::Full(Event::Goto(q))) =
                    t.try_send(Event::Goto(q))
                {
                    tokio::spawn(async move {
                        let busy = WireError::busy("robot agent overloaded");
                        let _ = wire::reply::<GotoReply>(&q, Err(busy)).await;
                    });
                }
            })
            .await?;
        let estop_state = session
            .declare_queryable(env.key(Topic::EStopState))
            .callback(estop::state_replier(env, estops))
            .await?;
        let token = session
            .liveliness()
            .declare_token(env.alive_key(Component::RobotAgent))
            .await?;
        Ok(Self {
            _subscribers: subscribers,
            _goto: goto,
            _estop_state: estop_state,
            _token: token,
        })
    }
}

/// What the agent tells the controller and operators.
enum Outgoing {
    /// A command's answer: its odometry, then its frame (the frame
    /// completes an answer).
    Answer {
        seq: u64,
        odom: Option<std::sync::Arc<offworld_runtime::msg::Odometry>>,
        frame: Box<CameraFrame>,
    },
    Fault(MotionFault),
    Ack(EStopAck),
    /// A controller heartbeat echoed back.
    Echo(ZBytes),
}

/// The agent's outgoing messages, published in order by a thread of their
/// own. A dropped answer fails the step, so they wait out a congested link
/// instead — and that wait must never hold the control task, which brakes
/// the robot: an e-stop or a watchdog trip is acted on while a frame is
/// still queued.
struct Outbox {
    queue: std::sync::mpsc::Sender<Outgoing>,
}

impl Outbox {
    async fn declare(session: &Session, env: &EnvId) -> Result<Self, AgentError> {
        let obs = wire::publisher(session, env.key(Topic::Obs), Delivery::Every).await?;
        let mut preview = PreviewPublisher::declare(session, env)?;
        let odom_out = wire::publisher(session, env.key(Topic::Odom), Delivery::Every).await?;
        let odom_out = WatchedPublisher::new(session, env, Topic::Odom, odom_out);
        let fault = wire::publisher(session, env.key(Topic::Fault), Delivery::Every).await?;
        let ack = wire::publisher(session, env.key(Topic::EStopAck), Delivery::Every).await?;
        let echo = wire::publisher(session, env.key(Topic::HeartbeatEcho), Delivery::Latest)
            .priority(wire::CONTROL_PRIORITY)
            .await?;
        let (queue, outgoing) = std::sync::mpsc::channel::<Outgoing>();
        std::thread::Builder::new()
            .name("robot_agent/outbox".into())
            .spawn(move || {
                // Ends when the agent (the only sender) is gone. A preview
                // frame held for being early goes out when its period ends,
                // unless the next answer's replaces it.
                while let Ok(message) = preview.recv_flushing(&outgoing) {
                    let result = match message {
                        Outgoing::Answer { seq, odom, frame } => {
                            let odom_copy = odom.and_then(|odom| {
                                odom_out
                                    .answer_tagged(&*odom, SeqTag { seq })
                                    .inspect_err(|e| tracing::warn!("odom put failed: {e}"))
                                    .ok()
                            });
                            // Encoded once: the same bytes go to viewers.
                            let sent = match codec::encode(&*frame) {
                                Ok(bytes) => {
                                    let bytes = ZBytes::from(bytes);
                                    let sent = obs
                                        .put(bytes.clone())
                                        .wait()
                                        .map_err(|e| RequestError::Zenoh(e.to_string()));
                                    if sent.is_ok() {
                                        preview.offer(&bytes);
                                    }
                                    sent
                                }
                                Err(e) => Err(e.into()),
                            };
                            // The viewers' copy once the answer is out.
                            if let Some(copy) = odom_copy {
                                copy.put();
                            }
                            sent
                        }
                        Outgoing::Fault(f) => wire::publish(&fault, &f),
                        Outgoing::Ack(a) => wire::publish(&ack, &a),
                        Outgoing::Echo(beat) => {
                            if let Err(e) = echo.put(beat).wait() {
                                tracing::warn!("heartbeat echo failed: {e}");
                            }
                            continue;
                        }
                    };
                    if let Err(e) = result {
                        tracing::warn!("robot agent publication failed: {e}");
                    }
                }
            })
            .map_err(|e| AgentError::Config(format!("cannot start the outbox thread: {e}")))?;
        Ok(Self { queue })
    }

    fn send(&self, message: Outgoing) {
        if self.queue.send(message).is_err() {
            tracing::error!("the robot agent's outbox is gone: a message was lost");
        }
    }
}

/// Forwards every odometry message of the base on the env's `odom` key, as
/// it arrives (the one answering a command also goes out with its
/// `SeqTag`, through the outbox): recordings then hold the base's speed
/// over time, which `parity identify` fits latency and settle time to, and
/// monitors draw the wheel odometry between steps. A stream: dropped, not
/// queued, on a congested link.
struct OdometryStream {
    task: JoinHandle<()>,
}

impl OdometryStream {
    async fn start(
        session: &Session,
        env: &EnvId,
        mut sensors: watch::Receiver<Sensors>,
    ) -> Result<Self, AgentError> {
        let out = wire::publisher(session, env.key(Topic::Odom), Delivery::Latest).await?;
        let out = WatchedPublisher::new(session, env, Topic::Odom, out);
        let task = tokio::spawn(async move {
            let mut last = None;
            // Ends when the robot's sensors are gone (or on drop, aborted).
            while sensors.changed().await.is_ok() {
                let odom = sensors
                    .borrow_and_update()
                    .odom
                    .as_ref()
                    .map(|o| o.msg.clone());
                let Some(odom) = odom else { continue };
                // Colour and depth frames change the sensors too.
                if last
                    .as_ref()
                    .is_some_and(|l| std::sync::Arc::ptr_eq(l, &odom))
                {
                    continue;
                }
                if let Err(e) = out.publish(&*odom) {
                    tracing::debug!("odometry stream put failed: {e}");
                }
                last = Some(odom);
            }
        });
        Ok(Self { task })
    }
}

impl Drop for OdometryStream {
    fn drop(&mut self) {
        self.task.abort();
    }
}

/// What the robot is doing.
enum Activity {
    Idle,
    /// Holding a commanded velocity until `until`.
    Driving {
        seq: u64,
        target: Velocity,
        until: Instant,
    },
    /// Motion over: waiting for the wheels to stop and the body to settle.
    Settling {
        seq: u64,
        still_since: Option<Instant>,
    },
    /// Waiting for colour and depth captured after `after`.
    Capturing {
        seq: u64,
        after: Time,
        deadline: Instant,
    },
    /// Driving to a reset pose.
    Navigating(Box<Navigation>),
}

struct Navigation {
    query: Query,
    request: GotoRequest,
    navigator: Navigator,
    started: Instant,
    deadline: Instant,
    arrived_still_since: Option<Instant>,
    /// Since when, and why, the drive is held still.
    held: Option<(Instant, String)>,
}

/// What a safety stop does to a reset drive in progress.
#[derive(Clone, Copy, PartialEq, Eq)]
enum OnHalt {
    /// End it with an error reply (e-stop, controller gone, shutdown).
    Abandon,
    /// Hold it still; it drives on when motion is allowed again (a
    /// heartbeat gap: the controller is late, not gone).
    Hold,
}

struct Agent<H: RobotHardware> {
    env: EnvId,
    outbox: Outbox,
    config: AgentConfig,
    robot: H,
    sensors: watch::Receiver<Sensors>,
    grid: OccupancyGrid,
    poses: watch::Receiver<Option<(Pose2D, Instant)>>,
    watchdog: Watchdog,
    base_check: BaseCheck,
    limiter: VelocityLimiter,
    /// The site and env e-stop latches in force.
    estops: EStopState,
    /// What the `estop_state` queryable answers.
    estop_tx: watch::Sender<EStopState>,
    /// Presses applied lately: a repeated copy is acknowledged, not applied.
    presses: RecentPresses,
    /// Where the latches are remembered across restarts.
    latch: Option<EStopLatch>,
    tracking: bool,
    activity: Activity,
    /// When a non-zero velocity was last sent.
    last_motion: Option<Instant>,
    /// The previous control tick (a long gap: the agent itself stalled).
    last_tick: Instant,
    /// Camera silence counts from here (reset after the agent's own stall:
    /// silence it did not watch is no evidence against the camera).
    watch_camera_from: Instant,
    _declarations: Declarations,
    _odometry: OdometryStream,
}

impl<H: RobotHardware> Agent<H> {
    async fn run(mut self, mut events: mpsc::Receiver<Event>, mut stop: oneshot::Receiver<()>) {
        tracing::info!(env = %self.env, graph = %self.config.graph().map(|g| g.to_string()).unwrap_or_default(), "robot agent serving");
        if let Some(reason) = self.estops.refusal() {
            tracing::warn!(env = %self.env, %reason, "E-STOP engaged before this start: motion refused until an operator releases it");
        }
        let period = Duration::from_secs_f64(1.0 / self.config.control_hz);
        let mut tick = tokio::time::interval(period);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        loop {
            tokio::select! {
                _ = &mut stop => break,
                event = events.recv() => match event {
                    Some(event) => self.handle(event).await,
                    None => break,
                },
                _ = tick.tick() => self.tick(period.as_secs_f64()).await,
            }
        }
        self.halt("agent shutting down", OnHalt::Abandon).await;
        tracing::info!(env = %self.env, "robot agent stopped");
    }

    async fn handle(&mut self, event: Event) {
        let now = Instant::now();
        match event {
            Event::Heartbeat(beat) => {
                // Echoed from the control loop: proof that it runs.
                self.outbox.send(Outgoing::Echo(beat));
                self.watchdog.sign_of_life(now);
                self.check_watchdog(now).await;
            }
            Event::ControllerPresent(present) => {
                self.watchdog.controller_present(present);
                // Check at once: a vanished controller stops the robot now.
                self.check_watchdog(now).await;
            }
            Event::GuardPresent(present) => {
                if present {
                    tracing::info!(env = %self.env, "base guard present");
                } else {
                    tracing::error!(env = %self.env, "the base guard is gone: motion refused until it is back");
                }
                self.watchdog.guard_present(present);
                self.check_watchdog(now).await;
            }
            Event::Tracking(tracking) => self.tracking = tracking,
            Event::EStop(latch, stop) => self.estop(latch, stop).await,
            Event::Recalled(network) => self.recalled(&network).await,
            Event::Command(cmd) => {
                self.watchdog.sign_of_life(now);
                self.check_watchdog(now).await;
                self.command(cmd, now).await;
            }
            Event::Goto(query) => {
                self.check_watchdog(now).await;
                self.goto(query, now).await;
            }
        }
    }

    /// Applies an e-stop to its latch: stops the robot first, then
    /// remembers the latches on disk, then acknowledges.
    async fn estop(&mut self, latch: Latch, stop: EStop) {
        match self
            .presses
            .apply(&mut self.estops, latch, &stop, Time::now())
        {
            Pressed::Applied if stop.engaged => {
                tracing::warn!(env = %self.env, latch = latch.as_str(), reason = %stop.reason, "E-STOP engaged");
                self.halt(&format!("e-stop: {}", stop.reason), OnHalt::Abandon)
                    .await;
            }
            Pressed::Applied => {
                tracing::warn!(env = %self.env, latch = latch.as_str(), reason = %stop.reason, still = self.estops.summary(), "e-stop released");
            }
            Pressed::Outdated => {
                tracing::warn!(env = %self.env, latch = latch.as_str(), reason = %stop.reason, still = self.estops.summary(), "an outdated e-stop release ignored: the latch changed after it was pressed");
            }
            Pressed::Repeated => {}
        }
        // Every copy stores the latches again: a write that failed for the
        // first is retried.
        if let Some(file) = &self.latch {
            if let Err(e) = file.store(&self.estops) {
                tracing::error!(path = %file.path().display(), "cannot write the e-stop latch: {e}");
            }
        }
        self.estop_tx.send_replace(self.estops.clone());
        let ack = EStopAck {
            press_id: stop.press_id,
            component: Component::RobotAgent.as_str().to_owned(),
            env: self.env.to_string(),
            state: self.estops.clone(),
        };
        self.outbox.send(Outgoing::Ack(ack));
    }

    /// Merges what the network remembers (the newer report per latch): a
    /// latch engaged while this agent was down stops it as a press would.
    async fn recalled(&mut self, network: &EStopState) {
        let was_engaged = self.estops.engaged();
        if !self.estops.merge(network) {
            return;
        }
        tracing::warn!(env = %self.env, now = self.estops.summary(), "e-stop latches learnt late from the network");
        if self.estops.engaged() && !was_engaged {
            let reason = self.estops.refusal().unwrap_or_default();
            self.halt(&reason, OnHalt::Abandon).await;
        }
        if let Some(file) = &self.latch {
            if let Err(e) = file.store(&self.estops) {
                tracing::error!(path = %file.path().display(), "cannot write the e-stop latch: {e}");
            }
        }
        self.estop_tx.send_replace(self.estops.clone());
    }

    /// Why motion is refused right now, if it is.
    fn refusal(&self, now: Instant) -> Option<String> {
        if let Some(reason) = self.estops.refusal() {
            return Some(reason);
        }
        if !self.watchdog.armed() {
            return Some(format!(
                "watchdog: {}",
                self.watchdog
                    .fault(now)
                    .unwrap_or_else(|| "not armed".into())
            ));
        }
        self.base_check.refusal()
    }

    /// Runs the start-up check of the base's command timeout; `true` when
    /// it drove (or silenced) the base this tick.
    async fn check_base(&mut self, now: Instant, dt: f64) -> bool {
        let may_move = self.estops.refusal().is_none()
            && self.watchdog.armed()
            && matches!(self.activity, Activity::Idle);
        let moving = self.sensors.borrow().odom.as_ref().and_then(|odom| {
            let fresh = now.saturating_duration_since(odom.at) < ODOM_STALE;
            let twist = &odom.msg.twist.twist;
            fresh.then(|| twist.linear.x.abs() > 1e-3 || twist.angular.z.abs() > 1e-3)
        });
        match self.base_check.step(now, may_move, moving) {
            CheckStep::Idle => false,
            CheckStep::Drive(velocity) => {
                let velocity = self.limiter.ramp(velocity, dt);
                self.send(velocity).await;
                true
            }
            CheckStep::Hold => {
                // Silence: the base must stop by itself. Nothing to ramp
                // down from afterwards.
                self.limiter.halt();
                self.last_motion = None;
                true
            }
            CheckStep::Stop => {
                self.limiter.halt();
                self.send(Velocity::ZERO).await;
                true
            }
        }
    }

    async fn command(&mut self, cmd: MotionCommand, now: Instant) {
        if cmd.seq == STOP_SEQ {
            tracing::info!(env = %self.env, "stop requested by the controller");
            self.abandon("stopped by the controller").await;
            self.activity = Activity::Idle;
            self.limiter.halt();
            self.send(Velocity::ZERO).await;
            return;
        }
        if !(cmd.duration_s.is_finite() && (0.0..=MAX_MOTION_S).contains(&cmd.duration_s)) {
            tracing::warn!(
                seq = cmd.seq,
                "rejected a command: duration {} s",
                cmd.duration_s
            );
            return;
        }
        let (target, clamped) = self.limiter.clamp(Velocity {
            linear: cmd.linear_x,
            angular: cmd.angular_z,
        });
        if clamped {
            tracing::warn!(
                seq = cmd.seq,
                asked_linear = cmd.linear_x,
                asked_angular = cmd.angular_z,
                linear = target.linear,
                angular = target.angular,
                "command beyond the robot's limits: clamped"
            );
        }
        self.abandon("preempted by a motion command").await;
        let moves = cmd.duration_s > 0.0 && !target.is_zero();
        if let Some(reason) = self.refusal(now) {
            if moves {
                // Not answered as if it had moved: the controller fails the
                // step with this reason at once.
                let fault = MotionFault {
                    seq: cmd.seq,
                    reason: format!("motion refused: {reason}"),
                };
                tracing::warn!(seq = cmd.seq, "{}", fault.reason);
                self.outbox.send(Outgoing::Fault(fault));
                self.activity = Activity::Idle;
                return;
            }
            tracing::warn!(
                seq = cmd.seq,
                "motion refused ({reason}); answering the observation request"
            );
            self.activity = Activity::Settling {
                seq: cmd.seq,
                still_since: None,
            };
            return;
        }
        self.activity = if moves {
            Activity::Driving {
                seq: cmd.seq,
                target,
                until: now + Duration::from_secs_f64(cmd.duration_s),
            }
        } else {
            Activity::Settling {
                seq: cmd.seq,
                still_since: None,
            }
        };
    }

    /// Ends a navigation in progress with an error reply (motion commands,
    /// stops and safety trips supersede it).
    async fn abandon(&mut self, reason: &str) {
        if let Activity::Navigating(nav) = std::mem::replace(&mut self.activity, Activity::Idle) {
            let err = WireError::invalid_state(format!("reset navigation aborted: {reason}"));
            reply_goto(&nav.query, Err(err)).await;
        }
    }

    async fn goto(&mut self, query: Query, now: Instant) {
        let request = match wire::decode_query::<GotoRequest>(&query) {
            Ok(r) => r,
            Err(e) => return reply_goto(&query, Err(e)).await,
        };
        if let Some(reason) = self.estops.refusal() {
            return reply_goto(&query, Err(WireError::invalid_state(reason))).await;
        }
        if let Some(reason) = self.refusal(now) {
            return reply_goto(&query, Err(WireError::unavailable(reason))).await;
        }
        let Some(pose) = self.fresh_pose(now) else {
            let err = WireError::unavailable("no fresh tracker pose: cannot navigate");
            return reply_goto(&query, Err(err)).await;
        };
        if !(request.timeout_s.is_finite() && request.timeout_s > 0.0) {
            let err = WireError::bad_request(format!("timeout {} s", request.timeout_s));
            return reply_goto(&query, Err(err)).await;
        }
        let navigator = match Navigator::new(&self.grid, pose, request.target) {
            Ok(navigator) => navigator,
            Err(e) => {
                let err = WireError::bad_request(format!("cannot plan a reset drive: {e}"));
                return reply_goto(&query, Err(err)).await;
            }
        };
        self.abandon("superseded by a new reset").await;
        tracing::info!(
            seq = request.seq,
            from = ?pose,
            to = ?request.target,
            estimate_s = navigator.estimated_time(&self.config.nav),
            "reset navigation"
        );
        let timeout = Duration::from_secs_f64(request.timeout_s.min(MAX_GOTO_S));
        self.activity = Activity::Navigating(Box::new(Navigation {
            navigator,
            query,
            request,
            started: now,
            deadline: now + timeout,
            arrived_still_since: None,
            held: None,
        }));
    }

    fn fresh_pose(&self, now: Instant) -> Option<Pose2D> {
        let stale = Duration::from_millis(self.config.pose_stale_ms);
        match *self.poses.borrow() {
            Some((pose, at)) if self.tracking && now.saturating_duration_since(at) <= stale => {
                Some(pose)
            }
            _ => None,
        }
    }

    async fn check_watchdog(&mut self, now: Instant) {
        match self.watchdog.check(now) {
            Some(Transition::Tripped(reason)) => {
                tracing::error!(env = %self.env, %reason, "WATCHDOG: stopping the robot");
                let on_nav = if self.watchdog.controller_is_present() {
                    OnHalt::Hold
                } else {
                    OnHalt::Abandon
                };
                self.halt(&format!("watchdog: {reason}"), on_nav).await;
            }
            Some(Transition::Rearmed) => tracing::info!(env = %self.env, "watchdog armed"),
            None => {}
        }
    }

    /// Safety stop: zero velocity now, cut the motion short (its answer is
    /// still sent after the robot settles), abandon or hold navigation.
    async fn halt(&mut self, reason: &str, on_nav: OnHalt) {
        self.limiter.halt();
        self.send(Velocity::ZERO).await;
        match std::mem::replace(&mut self.activity, Activity::Idle) {
            Activity::Driving { seq, .. } => {
                // Cut short: answering it would score a motion that did not
                // happen as commanded. The controller fails the step.
                let fault = MotionFault {
                    seq,
                    reason: format!("motion stopped before the command's end: {reason}"),
                };
                tracing::warn!(seq, "{}", fault.reason);
                self.outbox.send(Outgoing::Fault(fault));
            }
            Activity::Navigating(mut nav) if on_nav == OnHalt::Hold => {
                tracing::warn!(env = %self.env, %reason, "reset navigation held");
                nav.held.get_or_insert((Instant::now(), reason.to_owned()));
                nav.arrived_still_since = None;
                self.activity = Activity::Navigating(nav);
            }
            Activity::Navigating(nav) => {
                let err = WireError::unavailable(format!("reset navigation stopped: {reason}"));
                reply_goto(&nav.query, Err(err)).await;
            }
            other => self.activity = other,
        }
    }

    async fn tick(&mut self, dt: f64) {
        let now = Instant::now();
        self.check_watchdog(now).await;
        self.check_camera(now).await;
        if self.check_base(now, dt).await {
            return;
        }
        let settle = Duration::from_millis(self.config.settle_ms);
        let still = self.limiter.current().is_zero();
        let mut target = Velocity::ZERO;
        let activity = std::mem::replace(&mut self.activity, Activity::Idle);
        self.activity = match activity {
            Activity::Idle => Activity::Idle,
            Activity::Driving {
                seq,
                target: t,
                until,
            } => {
                if now >= until {
                    Activity::Settling {
                        seq,
                        still_since: None,
                    }
                } else {
                    target = t;
                    Activity::Driving {
                        seq,
                        target: t,
                        until,
                    }
                }
            }
            Activity::Settling { seq, still_since } => {
                let since = if still {
                    still_since.or(Some(now))
                } else {
                    None
                };
                match since {
                    Some(t) if now.saturating_duration_since(t) >= settle => Activity::Capturing {
                        seq,
                        after: Time::now(),
                        deadline: now + Duration::from_millis(self.config.frame_timeout_ms),
                    },
                    _ => Activity::Settling {
                        seq,
                        still_since: since,
                    },
                }
            }
            Activity::Capturing {
                seq,
                after,
                deadline,
            } => {
                if self.answer(seq, after).await {
                    Activity::Idle
                } else if now >= deadline {
                    let fault = MotionFault {
                        seq,
                        reason: format!(
                            "no camera frames within {} ms after the motion",
                            self.config.frame_timeout_ms
                        ),
                    };
                    tracing::error!(seq, "{}: not answered", fault.reason);
                    self.outbox.send(Outgoing::Fault(fault));
                    Activity::Idle
                } else {
                    Activity::Capturing {
                        seq,
                        after,
                        deadline,
                    }
                }
            }
            Activity::Navigating(nav) => self.navigate(nav, now, still, &mut target).await,
        };
        if self.refusal(now).is_some() {
            target = Velocity::ZERO;
            self.limiter.halt();
        }
        let velocity = self.limiter.ramp(target, dt);
        let recently_moved = self
            .last_motion
            .is_some_and(|t| now.saturating_duration_since(t) < ZERO_TAIL);
        if !velocity.is_zero() || recently_moved || !matches!(self.activity, Activity::Idle) {
            self.send(velocity).await;
        }
    }

    /// Fails the command in progress at once when the camera went silent
    /// (hardware, driver or robot computer down): the controller learns it
    /// now, not after the answer timeouts.
    async fn check_camera(&mut self, now: Instant) {
        let stale = Duration::from_millis(self.config.camera_stale_ms);
        if now.saturating_duration_since(self.last_tick) > stale / 2 {
            self.watch_camera_from = now;
        }
        self.last_tick = now;
        let seq = match &self.activity {
            Activity::Driving { seq, .. }
            | Activity::Settling { seq, .. }
            | Activity::Capturing { seq, .. } => *seq,
            Activity::Idle | Activity::Navigating(_) => return,
        };
        let newest = self.sensors.borrow().color.as_ref().map(|c| c.at);
        let since = newest.map_or(self.watch_camera_from, |t| t.max(self.watch_camera_from));
        let silent = now.saturating_duration_since(since);
        if silent <= stale {
            return;
        }
        let fault = MotionFault {
            seq,
            reason: format!(
                "the robot's camera is silent for {} ms (limit {} ms): camera, driver or robot computer down",
                silent.as_millis(),
                stale.as_millis()
            ),
        };
        tracing::error!(seq, "{}: command failed", fault.reason);
        // Idle first: this fault, not the halt's, tells the controller why.
        self.activity = Activity::Idle;
        self.halt(&fault.reason, OnHalt::Abandon).await;
        self.outbox.send(Outgoing::Fault(fault));
    }

    async fn navigate(
        &mut self,
        mut nav: Box<Navigation>,
        now: Instant,
        still: bool,
        target: &mut Velocity,
    ) -> Activity {
        if now >= nav.deadline {
            let err = WireError::timeout(format!(
                "the robot did not reach ({:.2}, {:.2}) within {:.0} s",
                nav.request.target.x,
                nav.request.target.y,
                nav.request.timeout_s.min(MAX_GOTO_S)
            ));
            reply_goto(&nav.query, Err(err)).await;
            return Activity::Idle;
        }
        let pose = match (self.refusal(now), self.fresh_pose(now)) {
            (None, Some(pose)) => {
                if let Some((since, reason)) = nav.held.take() {
                    tracing::info!(
                        env = %self.env,
                        held_ms = now.saturating_duration_since(since).as_millis() as u64,
                        %reason,
                        "reset navigation drives on"
                    );
                }
                pose
            }
            (refusal, _) => {
                let reason = refusal.unwrap_or_else(|| "tracking lost".to_owned());
                // A vanished controller is not late: nobody waits for this
                // drive any more, even if it was held for another reason.
                if !self.watchdog.controller_is_present() {
                    let err = WireError::unavailable(format!("reset navigation stopped: {reason}"));
                    reply_goto(&nav.query, Err(err)).await;
                    return Activity::Idle;
                }
                // Hold still (the target stays zero) and drive on when the
                // heartbeats or poses are back, unless that takes too long.
                let since = nav.held.get_or_insert((now, reason.clone())).0;
                let held = now.saturating_duration_since(since);
                if held >= Duration::from_millis(self.config.nav_hold_ms) {
                    let err = WireError::unavailable(format!(
                        "reset navigation stopped: held still {} ms (limit {} ms): {reason}",
                        held.as_millis(),
                        self.config.nav_hold_ms
                    ));
                    reply_goto(&nav.query, Err(err)).await;
                    return Activity::Idle;
                }
                nav.arrived_still_since = None;
                return Activity::Navigating(nav);
            }
        };
        let command = match nav.navigator.step(&self.grid, pose) {
            Ok(command) => command,
            Err(e) => {
                let err = WireError::invalid_state(format!("reset navigation failed: {e}"));
                reply_goto(&nav.query, Err(err)).await;
                return Activity::Idle;
            }
        };
        match command {
            NavCommand::Drive { linear, angular } => {
                *target = Velocity { linear, angular };
                nav.arrived_still_since = None;
            }
            NavCommand::Arrived => {
                let since = if still {
                    nav.arrived_still_since.or(Some(now))
                } else {
                    None
                };
                nav.arrived_still_since = since;
                let settle = Duration::from_millis(self.config.settle_ms);
                if since.is_some_and(|t| now.saturating_duration_since(t) >= settle) {
                    let reply = GotoReply {
                        seq: nav.request.seq,
                        achieved: pose,
                        elapsed_s: now.saturating_duration_since(nav.started).as_secs_f64(),
                    };
                    tracing::info!(
                        seq = reply.seq,
                        elapsed_s = reply.elapsed_s,
                        "reset navigation arrived"
                    );
                    reply_goto(&nav.query, Ok(&reply)).await;
                    return Activity::Idle;
                }
            }
        }
        Activity::Navigating(nav)
    }

    /// Publishes the odometry and then the frames answering `seq` (the
    /// frame completes an answer) once colour and depth captured after
    /// `after` are both there.
    async fn answer(&mut self, seq: u64, after: Time) -> bool {
        let (frame, odom) = {
            let sensors = self.sensors.borrow();
            let fresh = |stamp: &Time| stamp.as_secs_f64() >= after.as_secs_f64();
            match (&sensors.color, &sensors.depth) {
                (Some(c), Some(d)) if fresh(&c.msg.header.stamp) && fresh(&d.msg.header.stamp) => (
                    CameraFrame {
                        seq,
                        color: (*c.msg).clone(),
                        depth: (*d.msg).clone(),
                    },
                    sensors.odom.as_ref().map(|o| o.msg.clone()),
                ),
                _ => return false,
            }
        };
        self.outbox.send(Outgoing::Answer {
            seq,
            odom,
            frame: Box::new(frame),
        });
        true
    }

    async fn send(&mut self, velocity: Velocity) {
        if !velocity.is_zero() {
            self.last_motion = Some(Instant::now());
        }
        if let Err(e) = self.robot.drive(velocity).await {
            tracing::error!("cannot command the base: {e}");
        }
    }
}

async fn reply_goto(query: &Query, result: Result<&GotoReply, WireError>) {
    if let Err(e) = wire::reply(query, result).await {
        tracing::warn!("goto reply failed: {e}");
    }
}

/// The latches kept on disk merged with what the network remembers (the
/// newer report per latch wins).
async fn recall_estops(session: &Session, env: &EnvId, latch: Option<&EStopLatch>) -> EStopState {
    let mut state = latch.and_then(EStopLatch::load).unwrap_or_default();
    let network = estop::recall(session, env, RECALL).await;
    if state.merge(&network) {
        tracing::warn!(env = %env, now = state.summary(), "e-stop latches updated from the network");
    }
    state
}
