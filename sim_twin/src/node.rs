//! The twin served over Zenoh under an env's namespace, speaking exactly
//! what the real robot + tracker speak:
//!
//! - subscribes `cmd` ([`MotionCommand`]), executes it, then publishes
//!   `odom` (`nav_msgs/Odometry`), `pose` (`geometry_msgs/PoseStamped`, both
//!   with a [`SeqTag`] attachment) and `obs` ([`CameraFrame`], same `seq`);
//!   the frame again on `preview` for viewers, at most one every 20 ms
//!   and only while watched ([`offworld_runtime::preview`]);
//! - serves `goto` ([`GotoRequest`]): the sim teleports;
//! - obeys `estop` (per env and site-wide, independent latches, see
//!   [`offworld_runtime::estop`]): a command that would move is refused on
//!   `fault` (a zero-length one is still answered), every e-stop received
//!   is acknowledged on `estop_ack`, and `estop_state` answers the latches
//!   (a restarted twin learns them from the network);
//! - declares the liveliness token `alive/sim_twin`.
//!
//! Two clocks: [`Clock::Lockstep`] simulates a command's duration as fast as
//! possible (training); [`Clock::RealTime`] paces physics by the wall clock
//! and publishes tracker poses at the tracker rate (behaves like hardware).
//! The simulation runs on its own named thread, and Zenoh callbacks only
//! enqueue — unless a lockstep twin is told to simulate each command where
//! it arrives ([`Stepping::OnArrival`]).

mod inbox;

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError, TryLockError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use offworld_runtime::codec;
use offworld_runtime::estop::{self, Latch};
use offworld_runtime::keys::{global_estop_key, Component, EnvId, Topic};
use offworld_runtime::msg::{
    EStopAck, EStopState, GotoReply, GotoRequest, MotionCommand, MotionFault, Pose2D, SeqTag, Time,
};
use offworld_runtime::preview::{DueCopy, PreviewPublisher, ViewerCopy, WatchedPublisher};
use offworld_runtime::wire::{self, Delivery};
use offworld_runtime::WireError;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::query::{Query, Queryable};
use zenoh::sample::Sample;
use zenoh::{Session, Wait};

use crate::error::SimError;
use crate::frame_payload::FramePayloads;
use crate::overhead::OverheadStream;
use crate::physics::{PlanarPose, DT};
use crate::ros_out;
use crate::twin::SimTwin;
use inbox::{Inbox, Refused, Waited};

/// How simulated time relates to wall time.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Clock {
    /// As fast as possible: a command is simulated, then answered.
    #[default]
    Lockstep,
    /// Paced by the wall clock, like hardware.
    RealTime,
}

/// Where a lockstep twin simulates a command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Stepping {
    /// On the node's simulation thread: Zenoh's callback queues the command
    /// and wakes it. Twins of one process progress in parallel, and the
    /// thread delivering commands is never held by a step.
    #[default]
    OwnThread,
    /// On the thread that delivers the command (the Zenoh callback's), the
    /// events queued before it first, unless the simulation is busy on
    /// another thread, which then takes it. A step then costs no thread
    /// wake-up: with the controller and a client in the same process
    /// (`gymnasium.make`'s embedded env), a whole step runs on the caller's
    /// thread. For one twin per deployment only: twins whose commands come
    /// from one thread would take turns on it. The real-time clock always
    /// runs on the node's thread.
    OnArrival,
}

/// How a [`TwinNode`] runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NodeOptions {
    /// How simulated time relates to wall time.
    pub clock: Clock,
    /// Where lockstep commands are simulated.
    pub stepping: Stepping,
    /// Busy this long on one event, the simulation is stuck (see
    /// [`TwinNode::stuck`]).
    pub stuck_after: Duration,
}

impl Default for NodeOptions {
    fn default() -> Self {
        Self {
            clock: Clock::default(),
            stepping: Stepping::default(),
            stuck_after: STUCK_AFTER,
        }
    }
}

/// Queued work for the simulation.
enum Event {
    Command(Sample),
    Goto(Query),
    EStop(Latch, Sample),
    /// What the network remembers of the latches, asked again after the
    /// start ([`estop::RECALL_AGAIN`]).
    Recalled(EStopState),
}

/// Name of the simulated overhead camera (`overhead/top`).
pub const OVERHEAD_CAMERA: &str = "top";

/// Bound of the event queue (commands arrive one per step).
const QUEUE: usize = 256;
/// How long a starting twin asks the network for the e-stop latches.
const RECALL: Duration = Duration::from_millis(300);
/// A simulation thread busy with one event longer than this is stuck (a
/// command takes milliseconds, a full-size frame well under a second): its
/// node withdraws its liveliness token, so the controller reports the env
/// offline instead of timing out step after step (see [`TwinNode::stuck`]).
pub const STUCK_AFTER: Duration = Duration::from_secs(30);

/// Whether the simulation thread is working on an event, and since when;
/// watched by the node's watchdog thread.
#[derive(Debug)]
struct Busy {
    origin: Instant,
    /// Milliseconds since `origin` + 1 when the current event began; 0: idle.
    since_ms: AtomicU64,
    /// The watchdog found the thread stuck.
    stuck: AtomicBool,
    /// A panic broke the simulation: stuck for good, at once.
    broken: AtomicBool,
}

impl Busy {
    fn new() -> Self {
        Self {
            origin: Instant::now(),
            since_ms: AtomicU64::new(0),
            stuck: AtomicBool::new(false),
            broken: AtomicBool::new(false),
        }
    }

    fn begin(&self) {
        let ms = self.origin.elapsed().as_millis() as u64 + 1;
        self.since_ms.store(ms, Ordering::Release);
    }

    fn end(&self) {
        self.since_ms.store(0, Ordering::Release);
    }

    /// How long the current event has been worked on, if any.
    fn busy_for(&self) -> Option<Duration> {
        match self.since_ms.load(Ordering::Acquire) {
            0 => None,
            since => Some(
                self.origin
                    .elapsed()
                    .saturating_sub(Duration::from_millis(since - 1)),
            ),
        }
    }
}

/// What a twin node's simulation thread has done so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TwinStats {
    /// Commands answered: counted once their frame is rendered, before it
    /// is published (a failed publish is logged, not uncounted).
    pub answered: u64,
    /// Time spent computing those answers: simulating the command (lockstep
    /// clock only; the real-time clock paces physics by the wall) and
    /// rendering its frame. Publishing is not included. A step's time minus
    /// this is what Zenoh and the controller add.
    pub compute: Duration,
}

/// [`TwinStats`] shared with the simulation thread.
#[derive(Debug, Default)]
struct StatCounters {
    answered: AtomicU64,
    compute_ns: AtomicU64,
}

impl StatCounters {
    fn record(&self, compute: Duration) {
        let ns = u64::try_from(compute.as_nanos()).unwrap_or(u64::MAX);
        self.compute_ns.fetch_add(ns, Ordering::Relaxed);
        // Release: whoever sees the count also sees its compute time.
        self.answered.fetch_add(1, Ordering::Release);
    }

    fn read(&self) -> TwinStats {
        let answered = self.answered.load(Ordering::Acquire);
        TwinStats {
            answered,
            compute: Duration::from_nanos(self.compute_ns.load(Ordering::Relaxed)),
        }
    }
}

/// The simulation's state and its queue, shared by the node's thread and
/// (with [`Stepping::OnArrival`]) the callback delivering commands.
struct Simulation {
    env: EnvId,
    inbox: Inbox<Event>,
    worker: Mutex<Worker>,
    busy: Arc<Busy>,
    /// Commands are simulated where they arrive ([`Stepping::OnArrival`]).
    on_arrival: bool,
}

impl Simulation {
    /// The simulation, unless a panic broke it while it was held (a bug):
    /// it then takes no more events, and stays busy with the one it
    /// panicked on, so the watchdog withdraws the twin (see
    /// [`TwinNode::stuck`]).
    fn worker(&self) -> Option<MutexGuard<'_, Worker>> {
        match self.worker.lock() {
            Ok(worker) => Some(worker),
            Err(_) => {
                self.broken();
                None
            }
        }
    }

    fn broken(&self) {
        tracing::error!(env = %self.env, "the sim twin's simulation panicked: it takes no more commands (restart it)");
        self.busy.broken.store(true, Ordering::Release);
        self.inbox.close();
    }

    /// Works through the queued events in order, on this thread: whoever
    /// holds the simulation is the only one taking events. A panic leaves
    /// the simulation busy (no `end`): it is stuck from then on.
    fn drain(&self, worker: &mut Worker) {
        while let Some(event) = self.inbox.pop() {
            self.busy.begin();
            worker.handle_lockstep(event);
            self.busy.end();
        }
    }

    /// Queues a command and, unless the simulation is busy elsewhere (whoever
    /// holds it takes this too), simulates it and whatever was queued before
    /// it here ([`Stepping::OnArrival`]).
    fn command_on_arrival(&self, sample: Sample) {
        if let Err(refused) = self.inbox.push(Event::Command(sample), false) {
            return dropped(&refused);
        }
        let mut worker = match self.worker.try_lock() {
            Ok(worker) => worker,
            Err(TryLockError::Poisoned(_)) => return self.broken(),
            Err(TryLockError::WouldBlock) => return self.inbox.wake(),
        };
        self.drain(&mut worker);
        // A preview frame held for being early goes out at the end of its
        // period: the thread puts it, once it knows to look.
        if worker.publishers.preview.held_for().is_some() && !self.inbox.polled() {
            self.inbox.wake();
        }
    }
}

/// Logs a command the queue had no room for (one refused because the node
/// is stopping goes unsaid).
fn dropped<E>(refused: &Refused<E>) {
    if let Refused::Full(_) = refused {
        tracing::warn!("sim twin queue full: dropped a command");
    }
}

/// Ends the node: its thread stops at its next wait, and nothing more is
/// queued. Also run if the thread ends by a panic, so that no sender waits
/// forever for room in the queue, and the watchdog withdraws the twin.
struct CloseOnExit<'a>(&'a Simulation);

impl Drop for CloseOnExit<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.0.broken();
        }
        self.0.inbox.close();
    }
}

/// A running twin node; stops when dropped.
pub struct TwinNode {
    env: EnvId,
    simulation: Arc<Simulation>,
    stats: Arc<StatCounters>,
    thread: Option<JoinHandle<()>>,
    /// Ends the watchdog thread.
    watching: Arc<AtomicBool>,
    _declarations: Declarations,
}

struct Declarations {
    _cmd: Subscriber<()>,
    _heartbeat: Subscriber<()>,
    _estop: Subscriber<()>,
    _global_estop: Subscriber<()>,
    _goto: Queryable<()>,
    _estop_state: Queryable<()>,
    /// Taken (undeclared) by the watchdog when the thread is stuck.
    _token: Arc<Mutex<Option<LivelinessToken>>>,
}

impl TwinNode {
    /// Serves `twin` as `env` on `session` until dropped.
    pub fn spawn(
        session: &Session,
        env: EnvId,
        twin: SimTwin,
        clock: Clock,
    ) -> Result<Self, SimError> {
        let options = NodeOptions {
            clock,
            ..NodeOptions::default()
        };
        Self::spawn_with(session, env, twin, options)
    }

    /// [`TwinNode::spawn`] with every option.
    pub fn spawn_with(
        session: &Session,
        env: EnvId,
        twin: SimTwin,
        options: NodeOptions,
    ) -> Result<Self, SimError> {
        let NodeOptions {
            clock,
            stepping,
            stuck_after,
        } = options;
        let busy = Arc::new(Busy::new());
        let zerr = |e: zenoh::Error| SimError::Zenoh(e.to_string());
        let stats = Arc::new(StatCounters::default());
        let worker = Worker::new(session, env.clone(), twin, stats.clone())?;
        let (shared_estops, answered) = tokio::sync::watch::channel(EStopState::default());
        let simulation = Arc::new(Simulation {
            env: env.clone(),
            inbox: Inbox::new(QUEUE),
            worker: Mutex::new(Worker {
                shared_estops,
                ..worker
            }),
            busy: busy.clone(),
            on_arrival: stepping == Stepping::OnArrival && clock == Clock::Lockstep,
        });
        // E-stops first: one pressed while the latches are asked for below
        // is queued, and applied before any command.
        let estop_subscriber = |key: String, latch: Latch| {
            let simulation = simulation.clone();
            session
                .declare_subscriber(key)
                .callback(move |sample: Sample| {
                    // Never dropped while the simulation works: an e-stop
                    // waits for room in the queue. A stuck simulation would
                    // never make room (nor act on it: its twin is
                    // withdrawn), and this callback must not hold Zenoh's
                    // thread forever.
                    send_unless_stuck(&simulation, Event::EStop(latch, sample));
                })
                .wait()
                .map_err(zerr)
        };
        let estop = estop_subscriber(env.key(Topic::EStop), Latch::Env)?;
        let global_estop = estop_subscriber(global_estop_key(), Latch::Site)?;
        let estops = estop::recall_wait(session, &env, RECALL);
        if let Some(reason) = estops.refusal() {
            tracing::warn!(%env, %reason, "e-stop engaged before this start (from the network)");
        }
        if let Some(mut worker) = simulation.worker() {
            worker.shared_estops.send_replace(estops.clone());
            worker.estops = estops;
        }
        let commands = simulation.clone();
        let cmd = session
            .declare_subscriber(env.key(Topic::Cmd))
            .callback(move |sample: Sample| {
                if commands.on_arrival {
                    commands.command_on_arrival(sample);
                } else if let Err(refused) = commands.inbox.push(Event::Command(sample), true) {
                    dropped(&refused);
                }
            })
            .wait()
            .map_err(zerr)?;
        // The controller's heartbeats, echoed as received: how it knows it
        // still hears the embodiment (the same for twins and robots).
        let echo = wire::publisher(session, env.key(Topic::HeartbeatEcho), Delivery::Latest)
            .priority(wire::CONTROL_PRIORITY)
            .wait()
            .map_err(zerr)?;
        let heartbeat = session
            .declare_subscriber(env.key(Topic::Heartbeat))
            .callback(move |sample: Sample| {
                if let Err(e) = echo.put(sample.payload().clone()).wait() {
                    tracing::warn!("heartbeat echo failed: {e}");
                }
            })
            .wait()
            .map_err(zerr)?;
        let estop_state = session
            .declare_queryable(env.key(Topic::EStopState))
            .callback(estop::state_replier(&env, answered))
            .wait()
            .map_err(zerr)?;
        let gotos = simulation.clone();
        let goto = session
            .declare_queryable(env.key(Topic::Goto))
            .callback(move |query: Query| {
                if let Err(Refused::Full(Event::Goto(q))) =
                    gotos.inbox.push(Event::Goto(query), true)
                {
                    tracing::warn!("sim twin queue full: refused a goto");
                    reply_blocking::<GotoReply>(&q, Err(WireError::busy("sim twin overloaded")));
                }
            })
            .wait()
            .map_err(zerr)?;
        let token = session
            .liveliness()
            .declare_token(env.alive_key(Component::SimTwin))
            .wait()
            .map_err(zerr)?;
        // A fresh session may not reach every `estop_state` yet: ask again
        // (without keeping a dropped node's simulation alive meanwhile).
        let (again_session, again_env) = (session.clone(), env.clone());
        let again = Arc::downgrade(&simulation);
        std::thread::Builder::new()
            .name(format!("sim_twin/{env}/estop"))
            .spawn(move || {
                for delay in estop::RECALL_AGAIN {
                    std::thread::sleep(delay);
                    let network = estop::recall_wait(&again_session, &again_env, RECALL);
                    let Some(simulation) = again.upgrade() else {
                        return;
                    };
                    if !send_unless_stuck(&simulation, Event::Recalled(network)) {
                        return;
                    }
                }
            })
            .map_err(|e| SimError::Io(e.to_string()))?;
        let thread = {
            let simulation = simulation.clone();
            std::thread::Builder::new()
                .name(format!("sim_twin/{env}"))
                .spawn(move || run(&simulation, clock))
                .map_err(|e| SimError::Io(e.to_string()))?
        };
        let token = Arc::new(Mutex::new(Some(token)));
        let watching = Arc::new(AtomicBool::new(true));
        {
            let (busy, token, watching, env) =
                (busy.clone(), token.clone(), watching.clone(), env.clone());
            std::thread::Builder::new()
                .name(format!("sim_twin/{env}/watchdog"))
                .spawn(move || watchdog(&env, &busy, &token, &watching, stuck_after))
                .map_err(|e| SimError::Io(e.to_string()))?;
        }
        Ok(Self {
            env,
            simulation,
            stats,
            watching,
            thread: Some(thread),
            _declarations: Declarations {
                _cmd: cmd,
                _heartbeat: heartbeat,
                _estop: estop,
                _global_estop: global_estop,
                _goto: goto,
                _estop_state: estop_state,
                _token: token,
            },
        })
    }

    /// The env served.
    pub fn env(&self) -> &EnvId {
        &self.env
    }

    /// What the simulation thread has done so far. Counted before the
    /// answer is published: once a command's frame has been received, its
    /// compute time is in here.
    pub fn stats(&self) -> TwinStats {
        self.stats.read()
    }

    /// Whether the simulation thread is stuck: busy with one event longer
    /// than the node's limit ([`STUCK_AFTER`]). The node has then withdrawn
    /// its liveliness token (the env shows offline); a process serving it
    /// should exit so that its supervisor starts a fresh one — the stuck
    /// thread cannot be stopped, and dropping the node leaves it running.
    pub fn stuck(&self) -> bool {
        self.simulation.busy.stuck.load(Ordering::Acquire)
    }
}

impl Drop for TwinNode {
    fn drop(&mut self) {
        // The watchdog keeps watching until the thread has ended: a thread
        // stuck but not yet called so must not hang the drop forever.
        self.simulation.inbox.close();
        if let Some(thread) = self.thread.take() {
            while !thread.is_finished() && !self.stuck() {
                std::thread::sleep(Duration::from_millis(5));
            }
            if thread.is_finished() {
                let _ = thread.join();
            }
            // Else left running: it cannot be stopped (see `stuck`).
        }
        self.watching.store(false, Ordering::Release);
    }
}

/// Queues `event`, waiting for room while the simulation drains (it does,
/// fast) — but not once it is stuck; false if not queued.
fn send_unless_stuck(simulation: &Simulation, event: Event) -> bool {
    let mut event = event;
    loop {
        match simulation.inbox.push(event, true) {
            Ok(()) => return true,
            Err(Refused::Closed(_)) => return false,
            Err(Refused::Full(_)) if simulation.busy.stuck.load(Ordering::Acquire) => return false,
            Err(Refused::Full(back)) => {
                event = back;
                std::thread::sleep(Duration::from_millis(1));
            }
        }
    }
}

/// The node's simulation thread.
fn run(simulation: &Simulation, clock: Clock) {
    let _close = CloseOnExit(simulation);
    let env = &simulation.env;
    tracing::info!(%env, ?clock, "sim twin serving");
    let Some(mut worker) = (match clock {
        Clock::Lockstep => run_lockstep(simulation),
        Clock::RealTime => simulation.worker().map(|mut worker| {
            worker.run_real_time(simulation);
            worker
        }),
    }) else {
        return;
    };
    // What was queued before the stop is handled, as it would have been.
    if clock == Clock::Lockstep {
        simulation.drain(&mut worker);
    }
    tracing::info!(%env, rejected = worker.rejected, "sim twin stopped");
}

/// Lockstep: each command simulated as fast as possible, then answered.
/// Returns the simulation once the node stops (`None`: a panic broke it).
fn run_lockstep(simulation: &Simulation) -> Option<MutexGuard<'_, Worker>> {
    loop {
        // A preview frame held for being early goes out when its period
        // ends, unless the next step's frame replaces it first (one held
        // on another thread wakes this one: `command_on_arrival`).
        let wait = simulation.worker()?.publishers.preview.held_for();
        match simulation.inbox.wait(wait) {
            Waited::Closed => return simulation.worker(),
            Waited::TimedOut | Waited::Woken => {
                simulation.worker()?.publishers.preview.flush();
            }
            Waited::Ready => {
                let mut worker = simulation.worker()?;
                simulation.drain(&mut worker);
            }
        }
    }
}

/// Watches the simulation thread until the node is dropped: stuck on one
/// event longer than `stuck_after`, it is reported (once) and the node's
/// liveliness token is withdrawn.
fn watchdog(
    env: &EnvId,
    busy: &Busy,
    token: &Mutex<Option<LivelinessToken>>,
    watching: &AtomicBool,
    stuck_after: Duration,
) {
    let period = (stuck_after / 4).clamp(Duration::from_millis(10), Duration::from_secs(1));
    while watching.load(Ordering::Acquire) {
        std::thread::sleep(period);
        let broken = busy.broken.load(Ordering::Acquire);
        let for_how_long = busy.busy_for().unwrap_or_default();
        if !broken && for_how_long < stuck_after {
            continue;
        }
        busy.stuck.store(true, Ordering::Release);
        tracing::error!(
            %env,
            broken,
            busy_s = for_how_long.as_secs_f64(),
            "the sim twin's simulation is stuck on one event or broken: withdrawing this twin \
             (the env shows offline); restart it"
        );
        drop(token.lock().unwrap_or_else(PoisonError::into_inner).take());
        return;
    }
}

fn reply_blocking<T: serde::Serialize>(query: &Query, result: Result<&T, WireError>) {
    if let Err(e) = wire::reply_now(query, result) {
        tracing::warn!("reply failed: {e}");
    }
}

/// A motion being executed on the real-time clock.
struct ActiveMotion {
    seq: u64,
    /// End of the drive on the simulated clock, s since the loop started.
    drive_until: f64,
}

/// The simulation thread's state.
struct Worker {
    /// Held, not used: Zenoh's publishers and subscribers hold their
    /// session weakly, and the node serves until dropped whatever its
    /// caller does with its own handle.
    _session: Session,
    env: EnvId,
    twin: SimTwin,
    /// The site and env e-stop latches in force.
    estops: EStopState,
    /// Presses applied lately (`estop::RecentPresses`).
    presses: estop::RecentPresses,
    /// What the `estop_state` queryable answers.
    shared_estops: tokio::sync::watch::Sender<EStopState>,
    publishers: Publishers,
    /// Camera frame payloads (recycled).
    frames: FramePayloads,
    rejected: u64,
    /// The overhead view, put through its viewers' stream.
    overhead: Option<(OverheadStream, ViewerCopy)>,
    stats: Arc<StatCounters>,
}

/// Declared once: a declared publisher skips the per-put key resolution.
struct Publishers {
    /// The answers to a command: a dropped one fails the step.
    obs: Publisher<'static>,
    /// The frames for viewers: thinned, droppable, only while watched.
    preview: PreviewPublisher,
    odom: WatchedPublisher,
    pose: WatchedPublisher,
    /// The tracker-rate pose stream between commands: the next supersedes.
    pose_stream: WatchedPublisher,
    /// Commands refused (e-stop).
    fault: Publisher<'static>,
    estop_ack: Publisher<'static>,
}

impl Worker {
    fn new(
        session: &Session,
        env: EnvId,
        twin: SimTwin,
        stats: Arc<StatCounters>,
    ) -> Result<Self, SimError> {
        let declare = |topic: Topic, delivery: Delivery| {
            wire::publisher(session, env.key(topic), delivery)
                .wait()
                .map_err(|e| SimError::Zenoh(e.to_string()))
        };
        // Viewers read a copy of what the controller reads whole.
        let watched = |topic: Topic, delivery: Delivery| {
            Ok::<_, SimError>(WatchedPublisher::new(
                session,
                &env,
                topic,
                declare(topic, delivery)?,
            ))
        };
        let publishers = Publishers {
            obs: declare(Topic::Obs, Delivery::Every)?,
            preview: PreviewPublisher::declare(session, &env)
                .map_err(|e| SimError::Zenoh(e.to_string()))?,
            odom: watched(Topic::Odom, Delivery::Every)?,
            pose: watched(Topic::Pose, Delivery::Every)?,
            pose_stream: watched(Topic::Pose, Delivery::Latest)?,
            fault: declare(Topic::Fault, Delivery::Every)?,
            estop_ack: declare(Topic::EStopAck, Delivery::Every)?,
        };
        // For spectators only: one that cannot be declared is logged and
        // left out, and the twin works on.
        let overhead = env.overhead_key(OVERHEAD_CAMERA).ok().and_then(|key| {
            let copy = ViewerCopy::declare_on(session, key)
                .inspect_err(|e| tracing::warn!("no overhead view: {e}"))
                .ok()?;
            let stream =
                OverheadStream::new(twin.scene(), copy.watch(), OverheadStream::DEFAULT_HZ);
            Some((stream, copy))
        });
        Ok(Self {
            overhead,
            _session: session.clone(),
            env,
            twin,
            estops: EStopState::default(),
            presses: estop::RecentPresses::default(),
            shared_estops: tokio::sync::watch::channel(EStopState::default()).0,
            publishers,
            frames: FramePayloads::new(),
            rejected: 0,
            stats,
        })
    }

    /// One event in lockstep.
    fn handle_lockstep(&mut self, event: Event) {
        match event {
            Event::Command(sample) => {
                let Some(cmd) = self.decode_command(&sample) else {
                    return;
                };
                let started = Instant::now();
                let Some((v, w)) = self.allowed(&cmd) else {
                    return;
                };
                match self.twin.execute(v, w, cmd.duration_s) {
                    Ok(_) => self.answer(cmd.seq, started),
                    Err(e) => self.reject(&e),
                }
            }
            Event::Goto(query) => self.goto(&query),
            Event::EStop(latch, sample) => self.estop(latch, &sample),
            Event::Recalled(network) => self.recalled(&network),
        }
    }

    /// Real time, holding the simulation for good (commands are only queued).
    fn run_real_time(&mut self, simulation: &Simulation) {
        let (inbox, busy) = (&simulation.inbox, &simulation.busy);
        let start = Instant::now();
        let sim_start = self.twin.physics().time();
        let tracker_period = 1.0 / f64::from(self.twin.tracker_config().rate_hz.max(1.0));
        let mut next_pose = 0.0;
        let mut motion: Option<ActiveMotion> = None;
        loop {
            let now = start.elapsed().as_secs_f64();
            let sim_now = self.twin.physics().time() - sim_start;
            let next_step = sim_now + f64::from(DT);
            let wait = (next_step.min(next_pose) - now).max(0.0);
            let event = match inbox.wait(Some(Duration::from_secs_f64(wait))) {
                Waited::Closed => return,
                Waited::TimedOut | Waited::Woken => None,
                Waited::Ready => inbox.pop(),
            };
            busy.begin();
            match event {
                Some(Event::Command(sample)) => {
                    if let Some(cmd) = self.decode_command(&sample) {
                        if !(cmd.duration_s.is_finite() && (0.0..=10.0).contains(&cmd.duration_s)) {
                            self.reject(&SimError::BadCommand(format!(
                                "duration {}",
                                cmd.duration_s
                            )));
                            continue;
                        }
                        let Some((v, w)) = self.allowed(&cmd) else {
                            continue;
                        };
                        // A new command replaces the one in progress, as on hardware.
                        self.twin.physics_mut().set_targets(v as f32, w as f32);
                        // Timed on the simulated clock: a late thread catches up
                        // without cutting the motion short.
                        let sim_now = self.twin.physics().time() - sim_start;
                        motion = Some(ActiveMotion {
                            seq: cmd.seq,
                            drive_until: sim_now + cmd.duration_s,
                        });
                    }
                }
                Some(Event::Goto(query)) => self.goto(&query),
                Some(Event::EStop(latch, sample)) => {
                    self.estop(latch, &sample);
                    if self.estops.engaged() {
                        self.twin.physics_mut().set_targets(0.0, 0.0);
                    }
                }
                Some(Event::Recalled(network)) => {
                    self.recalled(&network);
                    if self.estops.engaged() {
                        self.twin.physics_mut().set_targets(0.0, 0.0);
                    }
                }
                None => {}
            }
            let now = start.elapsed().as_secs_f64();
            while self.twin.physics().time() - sim_start + f64::from(DT) <= now {
                if let Some(m) = &motion {
                    if self.twin.physics().time() - sim_start >= m.drive_until {
                        self.twin.physics_mut().set_targets(0.0, 0.0);
                    }
                }
                self.twin.physics_mut().substep();
            }
            if let Some(m) = &motion {
                let servo = self.twin.physics().servo();
                let stopped = servo.linear == 0.0
                    && servo.angular == 0.0
                    && servo.target_linear == 0.0
                    && servo.target_angular == 0.0
                    // A profile's latency may still hold the motion or its stop.
                    && !self.twin.physics().targets_pending();
                if self.twin.physics().time() - sim_start >= m.drive_until && stopped {
                    let seq = m.seq;
                    motion = None;
                    self.answer(seq, Instant::now());
                }
            }
            if now >= next_pose {
                let msg = ros_out::world_pose(&self.twin.tracker_reading(), Time::now());
                if let Err(e) = self.publishers.pose_stream.publish(&msg) {
                    tracing::warn!("pose put failed: {e}");
                }
                next_pose = now + tracker_period;
                self.publish_overhead();
            }
            // This loop wakes every substep: a held preview frame goes out
            // on time.
            self.publishers.preview.flush();
            busy.end();
        }
    }

    /// The velocities to simulate, or `None` when the command would move
    /// under an e-stop: refused on `fault` (as the robot agent does), so
    /// the controller fails the step instead of scoring a motion that
    /// never happened. A zero-length command (an observation request) is
    /// still answered.
    fn allowed(&mut self, cmd: &MotionCommand) -> Option<(f64, f64)> {
        let Some(reason) = self.estops.refusal() else {
            return Some((cmd.linear_x, cmd.angular_z));
        };
        let moves = cmd.duration_s > 0.0 && (cmd.linear_x != 0.0 || cmd.angular_z != 0.0);
        if !moves {
            return Some((0.0, 0.0));
        }
        let fault = MotionFault {
            seq: cmd.seq,
            reason: format!("motion refused: {reason}"),
        };
        tracing::warn!(env = %self.env, seq = cmd.seq, "{}", fault.reason);
        if let Err(e) = wire::publish(&self.publishers.fault, &fault) {
            tracing::warn!("cannot report the refusal: {e}");
        }
        None
    }

    fn decode_command(&mut self, sample: &Sample) -> Option<MotionCommand> {
        match codec::decode_payload::<MotionCommand>(sample.payload()) {
            Ok(cmd) => Some(cmd),
            Err(e) => {
                self.rejected += 1;
                tracing::warn!(env = %self.env, "rejected a malformed command: {e}");
                None
            }
        }
    }

    fn reject(&mut self, e: &SimError) {
        self.rejected += 1;
        tracing::warn!(env = %self.env, "rejected a command: {e}");
    }

    /// Merges what the network remembers (the newer report per latch).
    fn recalled(&mut self, network: &EStopState) {
        if self.estops.merge(network) {
            tracing::warn!(env = %self.env, now = self.estops.summary(), "e-stop latches learnt late from the network");
        }
        self.shared_estops.send_replace(self.estops.clone());
    }

    /// Applies an e-stop to its latch and acknowledges it.
    fn estop(&mut self, latch: Latch, sample: &Sample) {
        let stop = estop::decode(sample.payload());
        // A copy of a press, or an outdated release, is acknowledged, not applied.
        match self
            .presses
            .apply(&mut self.estops, latch, &stop, Time::now())
        {
            estop::Pressed::Applied => {
                tracing::warn!(env = %self.env, latch = latch.as_str(), engaged = stop.engaged, reason = %stop.reason, now = self.estops.summary(), "e-stop");
                self.shared_estops.send_replace(self.estops.clone());
            }
            estop::Pressed::Outdated => {
                tracing::warn!(env = %self.env, latch = latch.as_str(), reason = %stop.reason, now = self.estops.summary(), "an outdated e-stop release ignored: the latch changed after it was pressed");
            }
            estop::Pressed::Repeated => {}
        }
        let ack = EStopAck {
            press_id: stop.press_id,
            component: Component::SimTwin.as_str().to_owned(),
            env: self.env.to_string(),
            state: self.estops.clone(),
        };
        if let Err(e) = wire::publish(&self.publishers.estop_ack, &ack) {
            tracing::warn!("cannot acknowledge the e-stop: {e}");
        }
    }

    fn goto(&mut self, query: &Query) {
        let refusal = self.estops.refusal();
        let result = wire::decode_query::<GotoRequest>(query).and_then(|req| {
            // As the robot agent: a reset never moves an e-stopped robot.
            if let Some(reason) = refusal {
                return Err(WireError::invalid_state(reason));
            }
            let target = PlanarPose {
                x: req.target.x as f32,
                y: req.target.y as f32,
                yaw: req.target.yaw as f32,
            };
            self.twin.teleport(target).map_err(WireError::from)?;
            let p = self.twin.ground_truth();
            Ok(GotoReply {
                seq: req.seq,
                achieved: Pose2D {
                    x: f64::from(p.position[0]),
                    y: f64::from(p.position[1]),
                    yaw: f64::from(p.yaw),
                },
                elapsed_s: 0.0,
            })
        });
        reply_blocking(query, result.as_ref().map_err(Clone::clone));
    }

    /// The overhead view, rate-limited, while spectators watch.
    fn publish_overhead(&mut self) {
        if let Some((stream, copy)) = self.overhead.as_mut().filter(|(s, _)| s.watched()) {
            let pose = self.twin.ground_truth();
            if let Some(bytes) = stream.maybe_encode(self.twin.scene(), &pose) {
                copy.put(bytes.into(), None);
            }
        }
    }

    /// Publishes the pose and the odometry answering `seq`, then its camera
    /// frames: the frame completes an answer, so whoever has it has the
    /// rest (the controller may reply to the client on receiving it). The
    /// compute for it began at `compute_started`.
    fn answer(&mut self, seq: u64, compute_started: Instant) {
        let stamp = Time::now();
        let tag = SeqTag { seq };
        let pose = ros_out::world_pose(&self.twin.tracker_reading(), Time::now());
        // Rendered into its payload: a local controller reads these very
        // bytes, and hands the buffer back when done.
        let frame = self.frames.render(&mut self.twin, seq, stamp);
        self.stats.record(compute_started.elapsed());
        let pose_copy = answer(&self.publishers.pose, &pose, tag);
        let odom = ros_out::odometry(&self.twin, stamp);
        let odom_copy = answer(&self.publishers.odom, &odom, tag);
        match frame {
            Ok(payload) => match self.publishers.obs.put(payload.clone()).wait() {
                // After the answer, like the overhead view.
                Ok(()) => {
                    self.publishers.preview.offer(&payload);
                }
                Err(e) => tracing::warn!("obs put failed: {e}"),
            },
            Err(e) => tracing::error!("cannot encode frame: {e}"),
        }
        // After the answer: the step never waits for the viewers.
        for copy in [pose_copy, odom_copy].into_iter().flatten() {
            copy.put();
        }
        self.publish_overhead();
    }
}

/// Publishes `msg`, tagged with the command it answers; its copy for
/// viewers is due once the answer is out.
fn answer<'a, T: serde::Serialize>(
    publisher: &'a WatchedPublisher,
    msg: &T,
    tag: SeqTag,
) -> Option<DueCopy<'a>> {
    publisher
        .answer_tagged(msg, tag)
        .inspect_err(|e| tracing::warn!("put on {} failed: {e}", publisher.key_expr()))
        .ok()
}
