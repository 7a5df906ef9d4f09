//! robot_agent end to end over real Zenoh, with only the robot's hardware
//! doubled: a [`RecordingRobot`] records every velocity the agent commands
//! and serves synthetic camera frames, while all traffic (commands,
//! heartbeats, liveliness, e-stops, answers, poses, `goto` queries) crosses
//! two real Zenoh sessions joined over TCP on loopback. The test plays the
//! controller (liveliness token + heartbeats every 50 ms) and, for reset
//! navigation, the tracker.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use offworld_robot_agent::hardware::{Received, RobotHardware, Sensors};
use offworld_robot_agent::latch::EStopLatch;
use offworld_robot_agent::limiter::Velocity;
use offworld_robot_agent::nav::NavConfig;
use offworld_robot_agent::{AgentConfig, AgentError, AgentHandle, Limits};
use offworld_runtime::codec;
use offworld_runtime::keys::{global_estop_key, Component, EnvId, Topic};
use offworld_runtime::msg::{
    CameraFrame, EStop, EStopAck, GotoReply, GotoRequest, Header, Heartbeat, Image, MotionCommand,
    MotionFault, Odometry, PixelEncoding, Point, Pose, Pose2D, PoseStamped, Quaternion, SeqTag,
    Time,
};
use offworld_runtime::seal::{SealKey, Sealer};
use offworld_runtime::session::loopback_pair;
use offworld_runtime::wire::{self, RequestError};
use offworld_runtime::{ErrorCode, WireError};
use tokio::sync::{mpsc, watch};
use tokio::task::JoinHandle;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;
use zenoh::Session;

/// Synthetic camera size.
const WIDTH: u32 = 8;
const HEIGHT: u32 = 6;
/// The agent's control period at the default 50 Hz: every ramp step is
/// computed with exactly this dt, however late the tick runs.
const DT: f64 = 0.02;
/// Generous bound for anything that must happen "at once" or within the
/// 200 ms watchdog window (the machine may be loaded).
const PROMPTLY: Duration = Duration::from_secs(1);

/// The agent's defaults with a 1 s watchdog window: nine rigs run at once
/// on 2 cores, and a heartbeat delayed past the real 200 ms window would
/// rightly brake tests that are not about the watchdog (which has its own).
/// The hardware double has no base to guard, so no base guard is required
/// (its own test requires one).
fn config() -> AgentConfig {
    AgentConfig {
        watchdog_ms: 1_000,
        require_base_guard: false,
        // The double has no odometry to check a command timeout on (the
        // check has tests of its own).
        skip_base_timeout_check: true,
        ..AgentConfig::default()
    }
}
/// Bound for a command's answer.
const ANSWER: Duration = Duration::from_secs(5);
/// Cruise speed the stop tests drive at, m/s.
const CRUISE: f64 = 0.3;

// ---------------------------------------------------------------- hardware

/// One velocity the agent sent to the base.
#[derive(Debug, Clone, Copy)]
struct Sent {
    at: Instant,
    wall: SystemTime,
    velocity: Velocity,
}

/// The hardware double: records every velocity, serves camera frames the
/// test feeds through its `watch::Sender`.
#[derive(Clone)]
struct RecordingRobot {
    sent: Arc<Mutex<Vec<Sent>>>,
    sensors: Arc<watch::Sender<Sensors>>,
}

impl RecordingRobot {
    fn new() -> Self {
        Self {
            sent: Arc::new(Mutex::new(Vec::new())),
            sensors: Arc::new(watch::channel(Sensors::default()).0),
        }
    }

    /// Everything sent so far.
    fn sent(&self) -> Vec<Sent> {
        self.sent.lock().expect("log").clone()
    }

    /// Everything sent at or after `t`.
    fn sent_since(&self, t: Instant) -> Vec<Sent> {
        self.sent().into_iter().filter(|s| s.at >= t).collect()
    }

    fn clear(&self) {
        self.sent.lock().expect("log").clear();
    }

    /// The velocity last sent (zero before any).
    fn last(&self) -> Velocity {
        self.sent
            .lock()
            .expect("log")
            .last()
            .map_or(Velocity::ZERO, |s| s.velocity)
    }

    /// Publishes a colour and a depth frame stamped `Time::now()` at 30 Hz.
    fn feed_camera(&self) -> JoinHandle<()> {
        let sensors = self.sensors.clone();
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_millis(33));
            for k in 0usize.. {
                tick.tick().await;
                let stamp = Time::now();
                let color = color_image(k, stamp);
                let depth = depth_image(k, stamp);
                let at = Instant::now();
                sensors.send_modify(|s| {
                    s.color = Some(Received {
                        msg: Arc::new(color),
                        at,
                    });
                    s.depth = Some(Received {
                        msg: Arc::new(depth),
                        at,
                    });
                });
            }
        })
    }
}

impl RecordingRobot {
    /// Publishes wheel odometry at 50 Hz showing the last velocity sent,
    /// as a base does that holds it until `timeout` after the last command
    /// (`None`: forever, a base without a command timeout).
    fn simulate_base(&self, timeout: Option<Duration>) -> JoinHandle<()> {
        let (sensors, sent) = (self.sensors.clone(), self.sent.clone());
        tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_millis(20));
            loop {
                tick.tick().await;
                let last = sent.lock().expect("log").last().copied();
                let velocity = match last {
                    Some(s) if timeout.is_none_or(|t| s.at.elapsed() < t) => s.velocity,
                    _ => Velocity::ZERO,
                };
                let mut odom = Odometry::default();
                odom.twist.twist.linear.x = velocity.linear;
                odom.twist.twist.angular.z = velocity.angular;
                let at = Instant::now();
                sensors.send_modify(|s| {
                    s.odom = Some(Received {
                        msg: Arc::new(odom),
                        at,
                    })
                });
            }
        })
    }
}

impl RobotHardware for RecordingRobot {
    async fn drive(&self, velocity: Velocity) -> Result<(), AgentError> {
        self.sent.lock().expect("log").push(Sent {
            at: Instant::now(),
            wall: SystemTime::now(),
            velocity,
        });
        Ok(())
    }

    fn sensors(&self) -> watch::Receiver<Sensors> {
        self.sensors.subscribe()
    }
}

fn color_pattern(k: usize) -> Vec<u8> {
    (0..(WIDTH * HEIGHT * 3) as usize)
        .map(|i| ((i * 7 + k) % 256) as u8)
        .collect()
}

fn depth_pattern(k: usize) -> Vec<u8> {
    (0..(WIDTH * HEIGHT) as usize)
        .flat_map(|i| ((1000 + (k % 1000) + i) as u16).to_le_bytes())
        .collect()
}

fn color_image(k: usize, stamp: Time) -> Image {
    let header = Header::new(stamp, &format!("frame-{k}"));
    Image::packed(header, WIDTH, HEIGHT, PixelEncoding::Rgb8, color_pattern(k))
}

fn depth_image(k: usize, stamp: Time) -> Image {
    let header = Header::new(stamp, &format!("frame-{k}"));
    Image::packed(
        header,
        WIDTH,
        HEIGHT,
        PixelEncoding::Depth16UC1,
        depth_pattern(k),
    )
}

fn wall_clock(t: Time) -> SystemTime {
    UNIX_EPOCH + Duration::new(t.sec as u64, t.nanosec)
}

// ---------------------------------------------------------------- the rig

/// Agent on one session, the test (as controller) on the other.
struct Rig {
    env: EnvId,
    ctl: Session,
    _agent_session: Session,
    robot: RecordingRobot,
    agent: Option<AgentHandle>,
    token: Option<LivelinessToken>,
    beating: Arc<AtomicBool>,
    /// Clear to silence the tracker poses [`Rig::track`] publishes.
    tracking: Arc<AtomicBool>,
    frames: mpsc::UnboundedReceiver<CameraFrame>,
    /// Sequence numbers of every answer received, in order.
    seen: Vec<u64>,
    /// Every fault (refused or unanswerable command) received, in order.
    faults: mpsc::UnboundedReceiver<MotionFault>,
    /// Every e-stop acknowledgement received, in order.
    acks: mpsc::UnboundedReceiver<EStopAck>,
    tasks: Vec<JoinHandle<()>>,
    /// Seals commands and heartbeats with the agent's command key (the
    /// real-site controller's part), when it has one.
    sealer: Option<Arc<Sealer>>,
    _subscribers: [Subscriber<()>; 3],
}

impl Rig {
    /// Starts the agent, plays the controller and waits until a probe
    /// command makes the robot move (subscriptions propagated both ways,
    /// watchdog armed); the velocity log is then cleared.
    async fn start(name: &str, config: AgentConfig) -> Rig {
        let mut rig = Rig::launch(name, config).await;
        rig.until_motion_allowed().await;
        rig
    }

    /// Starts the agent and plays the controller, without waiting for
    /// motion to be allowed.
    async fn launch(name: &str, config: AgentConfig) -> Rig {
        let (agent_session, ctl) = loopback_pair().await.expect("loopback sessions");
        let env = EnvId::real(name).expect("env id");
        let sealer = config
            .command_key
            .as_deref()
            .map(|path| Arc::new(Sealer::new(SealKey::load(path).expect("command key"))));
        let robot = RecordingRobot::new();
        let mut tasks = vec![robot.feed_camera()];
        let agent = offworld_robot_agent::spawn(&agent_session, env.clone(), config, robot.clone())
            .await
            .expect("agent");
        let (tx, frames) = mpsc::unbounded_channel();
        let obs = ctl
            .declare_subscriber(env.key(Topic::Obs))
            .callback(move |s: Sample| {
                let frame: CameraFrame = codec::decode_payload(s.payload()).expect("CameraFrame");
                let _ = tx.send(frame);
            })
            .await
            .expect("obs subscriber");
        let (tx, faults) = mpsc::unbounded_channel();
        let fault = ctl
            .declare_subscriber(env.key(Topic::Fault))
            .callback(move |s: Sample| {
                let _ = tx.send(codec::decode_payload(s.payload()).expect("MotionFault"));
            })
            .await
            .expect("fault subscriber");
        let (tx, acks) = mpsc::unbounded_channel();
        let ack = ctl
            .declare_subscriber(env.key(Topic::EStopAck))
            .callback(move |s: Sample| {
                let _ = tx.send(codec::decode_payload(s.payload()).expect("EStopAck"));
            })
            .await
            .expect("ack subscriber");
        let token = ctl
            .liveliness()
            .declare_token(env.alive_key(Component::Controller))
            .await
            .expect("controller token");
        let beating = Arc::new(AtomicBool::new(true));
        let (beat_session, beat_key, flag, beat_sealer) = (
            ctl.clone(),
            env.key(Topic::Heartbeat),
            beating.clone(),
            sealer.clone(),
        );
        tasks.push(tokio::spawn(async move {
            for counter in 0.. {
                if flag.load(Ordering::SeqCst) {
                    let beat = Heartbeat {
                        stamp: Time::now(),
                        counter,
                    };
                    let sealer = beat_sealer.as_deref();
                    let _ = wire::put_control_sealed(&beat_session, &beat_key, &beat, sealer).await;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
        }));
        Rig {
            env,
            ctl,
            _agent_session: agent_session,
            robot,
            agent: Some(agent),
            token: Some(token),
            beating,
            tracking: Arc::new(AtomicBool::new(true)),
            frames,
            seen: Vec::new(),
            faults,
            acks,
            tasks,
            sealer,
            _subscribers: [obs, fault, ack],
        }
    }

    /// Probes with short commands until one moves the robot (bounded), then
    /// clears the log and the answers seen.
    async fn until_motion_allowed(&mut self) {
        let deadline = Instant::now() + Duration::from_secs(15);
        for (attempt, probe) in (1_000_000u64..).enumerate() {
            assert!(
                Instant::now() < deadline,
                "the agent never allowed motion on {}",
                self.env
            );
            let since = Instant::now();
            self.cmd(probe, 0.1, 0.0, 0.3).await;
            // An answer takes ~0.7 s; the first probes may be lost while
            // the declarations propagate, later ones get more time.
            let patience = Duration::from_millis(1200 + 400 * attempt.min(5) as u64);
            if self.try_answer(probe, patience).await.is_some()
                && moved(&self.robot.sent_since(since))
            {
                break;
            }
        }
        self.robot.clear();
        self.seen.clear();
    }

    async fn cmd(&self, seq: u64, linear_x: f64, angular_z: f64, duration_s: f64) {
        let cmd = MotionCommand {
            seq,
            linear_x,
            angular_z,
            duration_s,
        };
        let sealer = self.sealer.as_deref();
        wire::put_sealed(&self.ctl, &self.env.key(Topic::Cmd), &cmd, sealer)
            .await
            .expect("put cmd");
    }

    async fn put_raw(&self, key: &str, bytes: Vec<u8>) {
        self.ctl.put(key, bytes).await.expect("raw put");
    }

    async fn estop(&self, key: &str, engaged: bool) {
        let reason = format!("test ({})", if engaged { "engage" } else { "release" });
        wire::put(&self.ctl, key, &EStop::new(engaged, reason))
            .await
            .expect("put estop");
    }

    /// Presses `stop` as an operator does (a new press id: the clock) and
    /// returns its acknowledgement.
    async fn estop_acked(&mut self, key: &str, engaged: bool, reason: &str) -> EStopAck {
        let press_id = offworld_runtime::estop::new_press_id();
        let stop = EStop {
            engaged,
            reason: reason.to_owned(),
            press_id,
        };
        wire::put(&self.ctl, key, &stop).await.expect("put estop");
        loop {
            let ack = tokio::time::timeout(ANSWER, self.acks.recv())
                .await
                .expect("an acknowledgement within the answer bound")
                .expect("ack channel");
            if ack.press_id == press_id {
                return ack;
            }
        }
    }

    /// The fault reported for `seq` (earlier faults are skipped).
    async fn fault(&mut self, seq: u64) -> MotionFault {
        loop {
            let fault = tokio::time::timeout(ANSWER, self.faults.recv())
                .await
                .unwrap_or_else(|_| panic!("no fault for command {seq} within {ANSWER:?}"))
                .expect("fault channel");
            if fault.seq == seq {
                return fault;
            }
        }
    }

    /// The answer to `seq`, if it arrives within `timeout`.
    async fn try_answer(&mut self, seq: u64, timeout: Duration) -> Option<CameraFrame> {
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            let frame = tokio::time::timeout_at(deadline, self.frames.recv())
                .await
                .ok()?
                .expect("obs channel");
            self.seen.push(frame.seq);
            if frame.seq == seq {
                return Some(frame);
            }
        }
    }

    async fn answer(&mut self, seq: u64) -> CameraFrame {
        match self.try_answer(seq, ANSWER).await {
            Some(frame) => frame,
            None => panic!("command {seq} was not answered within {ANSWER:?}"),
        }
    }

    /// Waits until the robot is driving at exactly `v` (the ramp is over).
    async fn until_driving_at(&self, v: Velocity) {
        let robot = self.robot.clone();
        let reached = wait_until(Duration::from_secs(5), move || robot.last() == v).await;
        assert!(reached, "the robot never reached {v:?}");
    }

    async fn goto_raw(
        &self,
        payload: Vec<u8>,
        timeout: Duration,
    ) -> Result<GotoReply, RequestError> {
        let key = self.env.key(Topic::Goto);
        // The queryable's declaration may still be propagating.
        for _ in 0..50 {
            match wire::request_raw(&self.ctl, &key, payload.clone(), timeout).await {
                Err(RequestError::NoResponder(_)) => {
                    tokio::time::sleep(Duration::from_millis(100)).await
                }
                other => return other,
            }
        }
        panic!("nothing serves {key}");
    }

    async fn goto(
        &self,
        request: &GotoRequest,
        timeout: Duration,
    ) -> Result<GotoReply, RequestError> {
        self.goto_raw(codec::encode(request).expect("encode"), timeout)
            .await
    }

    /// Publishes the tracker pose `pose` (world frame) at 50 Hz, moving it
    /// with the velocities the agent sends (a unicycle integrated over real
    /// time) when `closed_loop`. Returns the live pose.
    fn track(&mut self, start: Pose2D, closed_loop: bool) -> Arc<Mutex<Pose2D>> {
        let pose = Arc::new(Mutex::new(start));
        let (session, key, robot, shared, tracking) = (
            self.ctl.clone(),
            self.env.key(Topic::Pose),
            self.robot.clone(),
            pose.clone(),
            self.tracking.clone(),
        );
        self.tasks.push(tokio::spawn(async move {
            let mut tick = tokio::time::interval(Duration::from_millis(20));
            let mut last = Instant::now();
            loop {
                tick.tick().await;
                let now = Instant::now();
                let dt = now.duration_since(last).as_secs_f64();
                last = now;
                let p = {
                    let mut p = shared.lock().expect("pose");
                    if closed_loop {
                        let v = robot.last();
                        p.x += v.linear * p.yaw.cos() * dt;
                        p.y += v.linear * p.yaw.sin() * dt;
                        p.yaw += v.angular * dt;
                    }
                    *p
                };
                let msg = PoseStamped {
                    header: Header::new(Time::now(), "world"),
                    pose: Pose {
                        position: Point {
                            x: p.x,
                            y: p.y,
                            z: 0.0,
                        },
                        orientation: Quaternion::from_yaw(p.yaw),
                    },
                };
                if tracking.load(Ordering::SeqCst) {
                    let _ = wire::put(&session, &key, &msg).await;
                }
            }
        }));
        pose
    }

    /// `goto`, retried while the first tracker poses are still arriving.
    async fn goto_when_tracked(&self, request: &GotoRequest) -> Result<GotoReply, RequestError> {
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            match self.goto(request, Duration::from_secs(30)).await {
                Err(RequestError::Remote(e))
                    if e.code == ErrorCode::Unavailable && Instant::now() < deadline =>
                {
                    tokio::time::sleep(Duration::from_millis(50)).await
                }
                other => return other,
            }
        }
    }

    /// Silences `signal` (heartbeats or tracker poses) for `gap` once the
    /// robot moves; returns when the signal was cut and when it resumed.
    async fn gap_while_moving(&self, signal: &AtomicBool, gap: Duration) -> (Instant, Instant) {
        let robot = self.robot.clone();
        let since = Instant::now();
        let moving = wait_until(Duration::from_secs(30), move || {
            moved(&robot.sent_since(since))
        })
        .await;
        assert!(moving, "the reset drive moved the robot");
        signal.store(false, Ordering::SeqCst);
        let cut = Instant::now();
        tokio::time::sleep(gap).await;
        signal.store(true, Ordering::SeqCst);
        (cut, Instant::now())
    }

    async fn finish(mut self) {
        if let Some(agent) = self.agent.take() {
            agent.shutdown().await;
        }
        for task in &self.tasks {
            task.abort();
        }
        let last = self.robot.sent().last().map(|s| s.velocity);
        assert_eq!(last, Some(Velocity::ZERO), "the agent ends stopped");
    }
}

// ---------------------------------------------------------------- helpers

/// A reset drive to `target` within `timeout_s`.
fn goto_request(seq: u64, target: Pose2D, timeout_s: f64) -> GotoRequest {
    GotoRequest {
        seq,
        target,
        timeout_s,
    }
}

/// Polls `cond` every 5 ms until true or `timeout`.
async fn wait_until(timeout: Duration, cond: impl Fn() -> bool) -> bool {
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline {
        if cond() {
            return true;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    cond()
}

fn moved(log: &[Sent]) -> bool {
    log.iter().any(|s| !s.velocity.is_zero())
}

fn v(linear: f64, angular: f64) -> Velocity {
    Velocity { linear, angular }
}

/// The robot was driving at `cruise` and, after `since`, was stopped at
/// once: the first velocity that is not `cruise` is exactly zero (a brake,
/// not a ramp-down), it came within [`PROMPTLY`], and nothing but zero
/// followed. Returns when the stop was sent.
fn assert_braked(log: &[Sent], since: Instant, cruise: Velocity, what: &str) -> Instant {
    let after: Vec<&Sent> = log.iter().filter(|s| s.at >= since).collect();
    let Some(stop) = after.iter().position(|s| s.velocity != cruise) else {
        panic!(
            "{what}: the robot never stopped ({} velocities)",
            after.len()
        );
    };
    assert_eq!(
        after[stop].velocity,
        Velocity::ZERO,
        "{what}: braked to zero at once, no ramp-down"
    );
    let delay = after[stop].at.duration_since(since);
    assert!(delay < PROMPTLY, "{what}: stopped only after {delay:?}");
    assert!(
        after[stop..].iter().all(|s| s.velocity.is_zero()),
        "{what}: nothing but zero after the stop"
    );
    after[stop].at
}

fn assert_code(result: Result<GotoReply, RequestError>, code: ErrorCode, what: &str) -> WireError {
    match result {
        Err(RequestError::Remote(e)) => {
            assert_eq!(e.code, code, "{what}: {e}");
            assert_eq!(e.code as u16, code as u16);
            e
        }
        other => panic!("{what}: expected {code:?}, got {other:?}"),
    }
}

fn pose(x: f64, y: f64, yaw: f64) -> Pose2D {
    Pose2D { x, y, yaw }
}

fn angle_diff(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(std::f64::consts::TAU);
    d.min(std::f64::consts::TAU - d)
}

// ---------------------------------------------------------------- tests

/// A command moves the robot at the commanded velocity for its duration,
/// then stops; the answer carries its seq and the robot's own frames,
/// captured after the motion ended (no odometry needed).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_motion_command_is_driven_then_answered_with_frames_captured_after_it() {
    let mut rig = Rig::start("motion", config()).await;
    let sent_at = Instant::now();
    rig.cmd(7, 0.2, -0.5, 0.5).await;
    let frame = rig.answer(7).await;
    let log = rig.robot.sent();

    // Driving: every velocity on the way from and back to rest lies between
    // zero and the command, and the command itself was held.
    assert!(log
        .iter()
        .all(|s| (0.0..=0.2).contains(&s.velocity.linear)
            && (-0.5..=0.0).contains(&s.velocity.angular)));
    assert!(
        log.iter().any(|s| s.velocity == v(0.2, -0.5)),
        "the commanded velocity was reached"
    );
    let last_moving = log
        .iter()
        .rposition(|s| !s.velocity.is_zero())
        .expect("the robot moved");
    assert!(
        log[last_moving].at >= sent_at + Duration::from_millis(500),
        "the velocity was held for the command's 0.5 s"
    );
    // ... then zero.
    let stopped = log
        .get(last_moving + 1)
        .expect("a stop followed the motion");
    assert_eq!(stopped.velocity, Velocity::ZERO);
    assert_eq!(rig.robot.last(), Velocity::ZERO);

    // The answer: seq 7, the camera's own bytes, captured after the stop.
    assert_eq!(frame.seq, 7);
    assert_eq!(rig.seen, vec![7], "exactly one answer");
    for (image, encoding) in [(&frame.color, "rgb8"), (&frame.depth, "16UC1")] {
        assert_eq!(image.encoding, encoding);
        assert_eq!((image.width, image.height), (WIDTH, HEIGHT));
        image.validate().expect("valid image");
        assert!(
            wall_clock(image.header.stamp) >= stopped.wall,
            "{encoding} frame captured after the motion ended"
        );
    }
    let k: usize = frame.color.header.frame_id[6..].parse().expect("frame-<k>");
    assert_eq!(frame.color.data, color_pattern(k));
    let k: usize = frame.depth.header.frame_id[6..].parse().expect("frame-<k>");
    assert_eq!(frame.depth.data, depth_pattern(k));
    rig.finish().await;
}

/// A viewer subscribed to the env's preview gets the very frame each answer
/// carries (a real robot answers far less often than the preview's period).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watched_agent_shows_each_answers_frame_as_the_preview() {
    let mut rig = Rig::start("preview", config()).await;
    let preview = rig
        .ctl
        .declare_subscriber(rig.env.key(Topic::Preview))
        .await
        .expect("preview subscriber");
    // Until the subscription has reached the agent (bounded).
    for seq in 1..=20 {
        rig.cmd(seq, 0.0, 0.0, 0.0).await;
        let answer = rig.answer(seq).await;
        if let Ok(Ok(sample)) =
            tokio::time::timeout(Duration::from_secs(1), preview.recv_async()).await
        {
            let shown: CameraFrame = codec::decode_payload(sample.payload()).expect("CameraFrame");
            assert_eq!(shown, answer);
            rig.finish().await;
            return;
        }
    }
    panic!("no preview while watched");
}

/// A viewer of the odometry reads its copy (`preview_odom`, never holding
/// the agent up): the answer to a command, tagged with it, comes through.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watched_agent_copies_each_answers_odometry_for_viewers() {
    let mut rig = Rig::start("odom-copy", config()).await;
    let base = rig.robot.simulate_base(None);
    let copies = rig
        .ctl
        .declare_subscriber(rig.env.key(Topic::PreviewOdom))
        .await
        .expect("copy subscriber");
    // Until the subscription has reached the agent (bounded); the base's
    // untagged stream is copied too.
    for seq in 1..=20 {
        rig.cmd(seq, 0.0, 0.0, 0.0).await;
        rig.answer(seq).await;
        let deadline = Instant::now() + Duration::from_secs(1);
        while let Ok(Ok(sample)) =
            tokio::time::timeout_at(deadline.into(), copies.recv_async()).await
        {
            codec::decode_payload::<Odometry>(sample.payload()).expect("Odometry");
            if wire::decode_attachment::<SeqTag>(&sample).map(|t| t.seq) == Some(seq) {
                base.abort();
                rig.finish().await;
                return;
            }
        }
    }
    panic!("no tagged odometry copy while watched");
}

/// 2.0 m/s and −9 rad/s are clamped to exactly the ROSbot's 0.7 m/s and
/// −2.5 rad/s, reached through a ramp within the acceleration limits.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn commands_beyond_the_limits_are_clamped_and_ramped() {
    // A wide watchdog window: on a starved machine a late heartbeat would
    // rightly brake mid-ramp, which is not what this test is about.
    let config = AgentConfig {
        watchdog_ms: 2_000,
        ..config()
    };
    let mut rig = Rig::start("limits", config).await;
    rig.cmd(8, 2.0, -9.0, 1.2).await;
    assert_eq!(rig.answer(8).await.seq, 8);
    let log: Vec<Velocity> = rig.robot.sent().iter().map(|s| s.velocity).collect();

    let limits = Limits::default();
    let max_linear = log.iter().map(|v| v.linear).fold(f64::MIN, f64::max);
    let min_angular = log.iter().map(|v| v.angular).fold(f64::MAX, f64::min);
    assert_eq!(max_linear, 0.7);
    assert_eq!(min_angular, -2.5);
    assert!(log.contains(&v(0.7, -2.5)), "both limits held together");
    assert!(log
        .iter()
        .all(|v| (0.0..=0.7).contains(&v.linear) && (-2.5..=0.0).contains(&v.angular)));

    // Ramped: the first step is one control period of acceleration, and no
    // step (up or down) exceeds it.
    let first = log.iter().find(|v| !v.is_zero()).expect("moved");
    assert!((first.linear - limits.max_linear_accel * DT).abs() < 1e-12);
    assert!((first.angular + limits.max_angular_accel * DT).abs() < 1e-12);
    let mut previous = Velocity::ZERO;
    for v in &log {
        assert!((v.linear - previous.linear).abs() <= limits.max_linear_accel * DT + 1e-9);
        assert!((v.angular - previous.angular).abs() <= limits.max_angular_accel * DT + 1e-9);
        previous = *v;
    }
    assert_eq!(previous, Velocity::ZERO, "ramped back down to rest");
    rig.finish().await;
}

/// The env e-stop brakes mid-motion at once; the interrupted command is
/// still answered; while engaged, a command that would move is refused on
/// `fault` (naming the e-stop) and `goto` is refused (InvalidState); a
/// release lets the robot move again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn estop_brakes_at_once_refuses_motion_and_release_restores_it() {
    let mut rig = Rig::start("estop", config()).await;
    let estop_key = rig.env.key(Topic::EStop);
    let cruise = v(CRUISE, 0.0);

    rig.cmd(10, CRUISE, 0.0, 5.0).await;
    rig.until_driving_at(cruise).await;
    let engaged = Instant::now();
    rig.estop(&estop_key, true).await;
    assert_eq!(
        rig.fault(10).await.reason,
        "motion stopped before the command's end: e-stop: test (engage)",
        "the cut motion fails, it is not answered as if driven"
    );
    let stopped = assert_braked(&rig.robot.sent(), engaged, cruise, "env e-stop");

    // Engaged: refused, never moved.
    rig.cmd(11, CRUISE, 0.5, 0.5).await;
    assert_eq!(
        rig.fault(11).await.reason,
        "motion refused: e-stop engaged: env (test (engage))"
    );
    let request = goto_request(1, pose(0.5, 0.5, 0.0), 10.0);
    let refused = rig.goto(&request, Duration::from_secs(5)).await;
    assert_code(refused, ErrorCode::InvalidState, "goto under e-stop");
    assert!(
        !moved(&rig.robot.sent_since(stopped)),
        "no motion while engaged"
    );
    assert!(rig.seen.is_empty(), "nothing answered: {:?}", rig.seen);

    // Released: motion again. (The release and the next command travel
    // different internal paths, so give the release a head start.)
    rig.estop(&estop_key, false).await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let released = Instant::now();
    rig.cmd(12, CRUISE, 0.0, 0.5).await;
    assert_eq!(rig.answer(12).await.seq, 12);
    let log = rig.robot.sent_since(released);
    assert!(moved(&log), "the robot moves after the release: {log:?}");
    rig.finish().await;
}

/// The site-wide e-stop acts like the env one, and a malformed e-stop
/// payload (on either key) engages rather than being ignored.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn site_wide_and_malformed_estops_engage() {
    let mut rig = Rig::start("estop-site", config()).await;
    let cruise = v(CRUISE, 0.0);

    // Site-wide.
    rig.cmd(20, CRUISE, 0.0, 5.0).await;
    rig.until_driving_at(cruise).await;
    let engaged = Instant::now();
    rig.estop(&global_estop_key(), true).await;
    let cut = rig.fault(20).await.reason;
    assert!(
        cut.starts_with("motion stopped before the command's end: e-stop"),
        "{cut}"
    );
    let stopped = assert_braked(&rig.robot.sent(), engaged, cruise, "site-wide e-stop");
    rig.cmd(21, CRUISE, 0.0, 0.5).await;
    let refused = rig.fault(21).await.reason;
    assert!(refused.contains("site (test (engage))"), "{refused}");
    assert!(!moved(&rig.robot.sent_since(stopped)));
    rig.estop(&global_estop_key(), false).await;
    tokio::time::sleep(Duration::from_millis(300)).await;

    // Malformed payloads: garbage on the env key, truncated CDR on the
    // site-wide key.
    let valid = codec::encode(&EStop::new(false, "a release cut short")).expect("encode");
    let malformed = [
        (
            rig.env.key(Topic::EStop),
            vec![0xde, 0xad, 0xbe, 0xef, 0x01],
        ),
        (global_estop_key(), valid[..valid.len() - 3].to_vec()),
    ];
    for (i, (key, bytes)) in malformed.into_iter().enumerate() {
        let seq = 22 + 10 * i as u64;
        rig.cmd(seq, CRUISE, 0.0, 5.0).await;
        rig.until_driving_at(cruise).await;
        let engaged = Instant::now();
        rig.put_raw(&key, bytes).await;
        let cut = rig.fault(seq).await.reason;
        assert!(cut.contains("malformed e-stop"), "{cut}");
        let stopped = assert_braked(
            &rig.robot.sent(),
            engaged,
            cruise,
            &format!("malformed {key}"),
        );
        rig.cmd(seq + 1, CRUISE, 0.0, 0.5).await;
        let refused = rig.fault(seq + 1).await.reason;
        assert!(refused.contains("malformed e-stop"), "{refused}");
        assert!(
            !moved(&rig.robot.sent_since(stopped)),
            "malformed e-stop holds"
        );
        rig.estop(&key, false).await;
        tokio::time::sleep(Duration::from_millis(300)).await;
    }
    assert!(rig.seen.is_empty(), "nothing answered: {:?}", rig.seen);
    rig.finish().await;
}

/// Heartbeats stop mid-motion (and no command comes): the watchdog brakes
/// within its window. With heartbeats still absent a new command is a sign
/// of life by design, so it moves the robot only until the window runs out
/// again (not for its 3 s); both are answered. Heartbeats back: commands
/// run their full duration again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn watchdog_brakes_when_heartbeats_stop_and_rearms_when_they_resume() {
    // 500 ms (default 200): the behaviour is the same, and a heartbeat
    // delayed by a starved CI machine does not cut the re-armed motion.
    let config = AgentConfig {
        watchdog_ms: 500,
        ..config()
    };
    let mut rig = Rig::start("watchdog", config).await;
    let cruise = v(CRUISE, 0.0);

    rig.cmd(40, CRUISE, 0.0, 5.0).await;
    rig.until_driving_at(cruise).await;
    let silent = Instant::now();
    rig.beating.store(false, Ordering::SeqCst);
    let cut = rig.fault(40).await.reason;
    assert!(
        cut.starts_with(
            "motion stopped before the command's end: watchdog: no command or controller heartbeat"
        ),
        "the cut motion fails: {cut}"
    );
    assert_braked(&rig.robot.sent(), silent, cruise, "heartbeat loss");

    // Heartbeats still absent: the command's own arrival is the only sign
    // of life, so its motion ends when the window (200 ms) does.
    let sent_at = Instant::now();
    rig.cmd(41, CRUISE, 0.0, 3.0).await;
    let cut = rig.fault(41).await.reason;
    assert!(cut.contains("watchdog"), "{cut}");
    let log = rig.robot.sent_since(sent_at);
    let first = log.iter().find(|s| !s.velocity.is_zero());
    let last = log.iter().rev().find(|s| !s.velocity.is_zero());
    if let (Some(first), Some(last)) = (first, last) {
        let span = last.at.duration_since(first.at);
        assert!(
            span < PROMPTLY,
            "moved {span:?} on a 3 s command without heartbeats"
        );
    }
    assert_eq!(rig.robot.last(), Velocity::ZERO);

    // Heartbeats back: the full duration is driven again.
    rig.beating.store(true, Ordering::SeqCst);
    tokio::time::sleep(Duration::from_millis(300)).await;
    let sent_at = Instant::now();
    rig.cmd(42, CRUISE, 0.0, 0.6).await;
    assert_eq!(rig.answer(42).await.seq, 42);
    let log = rig.robot.sent_since(sent_at);
    let last = log
        .iter()
        .rposition(|s| !s.velocity.is_zero())
        .expect("moved with heartbeats back");
    assert!(
        log[last].at >= sent_at + Duration::from_millis(600),
        "held for the full 0.6 s"
    );
    assert_eq!(rig.seen, vec![42]);
    rig.finish().await;
}

/// The controller's liveliness token vanishes mid-motion (heartbeats keep
/// coming): the robot brakes at once; commands are refused on `fault`
/// until the token is back.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn losing_the_controller_token_brakes_and_refuses_motion() {
    let mut rig = Rig::start("token", config()).await;
    let cruise = v(CRUISE, 0.0);

    rig.cmd(50, CRUISE, 0.0, 5.0).await;
    rig.until_driving_at(cruise).await;
    let gone = Instant::now();
    rig.token
        .take()
        .expect("token")
        .undeclare()
        .await
        .expect("undeclare");
    let cut = rig.fault(50).await.reason;
    assert!(cut.contains("liveliness token is gone"), "{cut}");
    let stopped = assert_braked(&rig.robot.sent(), gone, cruise, "controller token gone");

    rig.cmd(51, CRUISE, 0.0, 1.0).await;
    let refused = rig.fault(51).await.reason;
    assert!(refused.contains("liveliness token is gone"), "{refused}");
    assert!(
        !moved(&rig.robot.sent_since(stopped)),
        "no motion without the token"
    );
    assert!(rig.seen.is_empty(), "nothing answered: {:?}", rig.seen);

    rig.token = Some(
        rig.ctl
            .liveliness()
            .declare_token(rig.env.alive_key(Component::Controller))
            .await
            .expect("token"),
    );
    rig.until_motion_allowed().await;
    rig.finish().await;
}

/// Undecodable commands are dropped, commands with a NaN, infinite,
/// negative or over-long (> 10 s) duration are not executed (nor
/// answered); the agent keeps serving the valid commands that follow.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_and_invalid_commands_are_ignored() {
    let mut rig = Rig::start("malformed", config()).await;
    let key = rig.env.key(Topic::Cmd);
    let valid = codec::encode(&MotionCommand {
        seq: 60,
        linear_x: 0.5,
        angular_z: 0.5,
        duration_s: 1.0,
    })
    .expect("encode");
    rig.put_raw(&key, vec![0xff; 7]).await;
    rig.put_raw(&key, b"not cdr at all, but long enough to be read".to_vec())
        .await;
    rig.put_raw(&key, valid[..valid.len() - 4].to_vec()).await;
    rig.put_raw(&key, Vec::new()).await;
    for (seq, duration) in [(61, f64::NAN), (62, f64::INFINITY), (63, -1.0), (64, 10.5)] {
        rig.cmd(seq, 0.5, 0.5, duration).await;
    }
    // Give any wrongly accepted command ample time to start moving.
    tokio::time::sleep(Duration::from_secs(1)).await;
    assert!(!moved(&rig.robot.sent()), "nothing invalid was executed");

    // Still serving: a look (duration 0) and a motion are both answered.
    rig.cmd(65, 0.0, 0.0, 0.0).await;
    assert_eq!(rig.answer(65).await.seq, 65);
    assert!(!moved(&rig.robot.sent()));
    rig.cmd(66, 0.1, 0.0, 0.2).await;
    assert_eq!(rig.answer(66).await.seq, 66);
    assert!(moved(&rig.robot.sent()));
    assert_eq!(rig.seen, vec![65, 66], "invalid commands are not answered");
    rig.finish().await;
}

/// `goto` failures are typed: no tracker pose → Unavailable (503); a goal
/// inside a boulder, a NaN timeout or undecodable request bytes →
/// BadRequest (400). The robot never moves.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn goto_failures_are_typed_errors() {
    let config = AgentConfig {
        world: "monolith_obstacle".into(),
        ..config()
    };
    let mut rig = Rig::start("goto-errors", config).await;
    let timeout = Duration::from_secs(5);
    let free = goto_request(1, pose(0.1, 0.3, 0.0), 10.0);

    let e = assert_code(
        rig.goto(&free, timeout).await,
        ErrorCode::Unavailable,
        "no pose",
    );
    assert!(e.message.contains("pose"), "{e}");
    let garbage = rig
        .goto_raw(vec![0x00, 0x01, 0x00, 0x00, 0x07], timeout)
        .await;
    assert_code(garbage, ErrorCode::BadRequest, "malformed request");
    assert_code(
        rig.goto_raw(Vec::new(), timeout).await,
        ErrorCode::BadRequest,
        "empty request",
    );

    // A fresh pose in free space, then a goal inside a boulder
    // (runtime/worlds/monolith_obstacle.toml: centre (0.762, −0.241)).
    rig.track(pose(-0.2, 0.2, 0.0), false);
    let boulder = goto_request(2, pose(0.762, -0.241, 0.0), 10.0);
    let deadline = Instant::now() + Duration::from_secs(10);
    let result = loop {
        match rig.goto(&boulder, timeout).await {
            // The first poses may still be on their way.
            Err(RequestError::Remote(e))
                if e.code == ErrorCode::Unavailable && Instant::now() < deadline =>
            {
                tokio::time::sleep(Duration::from_millis(50)).await
            }
            other => break other,
        }
    };
    let e = assert_code(result, ErrorCode::BadRequest, "goal in a boulder");
    assert!(e.message.contains("obstacle"), "{e}");
    let nan_timeout = GotoRequest {
        timeout_s: f64::NAN,
        ..free
    };
    assert_code(
        rig.goto(&nan_timeout, timeout).await,
        ErrorCode::BadRequest,
        "NaN timeout",
    );
    assert!(!moved(&rig.robot.sent()), "no failed goto moved the robot");
    rig.finish().await;
}

/// `goto` to a nearby free pose with the loop closed: the test integrates
/// the commanded velocities (unicycle) and publishes the result as the
/// tracker pose at 50 Hz; the reply comes with the achieved pose on target.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn goto_drives_to_a_free_pose_on_tracker_poses() {
    let config = AgentConfig {
        world: "monolith_obstacle".into(),
        ..config()
    };
    let mut rig = Rig::start("goto-drive", config).await;
    let live = rig.track(pose(-0.2, 0.2, 0.0), true);
    let request = goto_request(77, pose(0.1, 0.35, 0.5), 25.0);
    let reply = rig.goto_when_tracked(&request).await.expect("goto reply");
    assert_eq!(reply.seq, 77);
    let (target, achieved) = (request.target, reply.achieved);
    let miss = (achieved.x - target.x).hypot(achieved.y - target.y);
    assert!(
        miss < 0.1,
        "achieved {achieved:?}, {miss:.3} m from {target:?}"
    );
    assert!(
        angle_diff(achieved.yaw, target.yaw) < 0.15,
        "achieved heading {achieved:?}"
    );
    assert!(reply.elapsed_s > 0.0 && reply.elapsed_s < 30.0);
    let now = *live.lock().expect("pose");
    assert!(
        (now.x - target.x).hypot(now.y - target.y) < 0.1,
        "the robot is there: {now:?}"
    );

    // Driven within the navigation's own speed limits.
    let nav = NavConfig::default();
    for s in rig.robot.sent() {
        assert!(s.velocity.linear.abs() <= nav.cruise_speed + 1e-9, "{s:?}");
        assert!(
            s.velocity.angular.abs() <= nav.max_turn_rate + 1e-9,
            "{s:?}"
        );
    }
    rig.finish().await;
}

/// Held still from `after` (a stop within [`PROMPTLY`]) until `until`:
/// a zero velocity was sent and nothing else.
fn assert_held(log: &[Sent], after: Instant, until: Instant, what: &str) {
    let held: Vec<&Sent> = log
        .iter()
        .filter(|s| s.at >= after + PROMPTLY && s.at < until)
        .collect();
    assert!(
        held.iter().all(|s| s.velocity.is_zero()),
        "{what}: moved while held: {:?}",
        held.iter().find(|s| !s.velocity.is_zero())
    );
    assert!(
        log.iter()
            .any(|s| s.at >= after && s.at < until && s.velocity.is_zero()),
        "{what}: the robot was stopped"
    );
}

/// A reset drive rides out a heartbeat gap longer than the watchdog
/// window and a tracker gap: each time the robot stops, then drives on
/// when the signal is back, and the drive arrives. Held still longer than
/// `nav_hold_ms`, the drive ends with a typed Unavailable naming why; held
/// when the controller's token vanishes, it ends on that.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reset_drive_holds_through_short_gaps_and_gives_up_on_long_ones() {
    let config = AgentConfig {
        world: "monolith_obstacle".into(),
        watchdog_ms: 300,
        nav_hold_ms: 4_000,
        ..config()
    };
    let mut rig = Rig::start("goto-hold", config).await;
    let _live = rig.track(pose(-0.2, 0.2, 0.0), true);
    let gap = PROMPTLY + Duration::from_millis(700);

    // A heartbeat gap (the controller late, its token still there).
    let request = goto_request(81, pose(0.1, 0.35, 0.5), 25.0);
    let (reply, (cut, resumed)) = tokio::join!(
        rig.goto_when_tracked(&request),
        rig.gap_while_moving(&rig.beating, gap)
    );
    let reply = reply.expect("the drive arrives after the heartbeat gap");
    assert_held(&rig.robot.sent(), cut, resumed, "heartbeat gap");
    assert!(
        rig.robot
            .sent_since(resumed)
            .iter()
            .any(|s| !s.velocity.is_zero()),
        "drove on after the heartbeat gap"
    );
    let miss = (reply.achieved.x - 0.1).hypot(reply.achieved.y - 0.35);
    assert!(miss < 0.1, "arrived: {:?}", reply.achieved);

    // A tracker gap.
    rig.robot.clear();
    let request = goto_request(82, pose(-0.2, 0.2, 0.0), 25.0);
    let (reply, (cut, resumed)) = tokio::join!(
        rig.goto_when_tracked(&request),
        rig.gap_while_moving(&rig.tracking, gap)
    );
    let reply = reply.expect("the drive arrives after the tracker gap");
    assert_held(&rig.robot.sent(), cut, resumed, "tracker gap");
    let miss = (reply.achieved.x + 0.2).hypot(reply.achieved.y - 0.2);
    assert!(miss < 0.1, "arrived: {:?}", reply.achieved);

    // A tracker gap past the hold limit.
    let request = goto_request(83, pose(0.1, 0.35, 0.5), 25.0);
    // (Tracked now: no retry, the Unavailable is the hold's.)
    let (result, _) = tokio::join!(
        rig.goto(&request, Duration::from_secs(30)),
        rig.gap_while_moving(&rig.tracking, Duration::from_secs(8))
    );
    let err = assert_code(result, ErrorCode::Unavailable, "held past the limit");
    assert!(
        err.message.contains("held still") && err.message.contains("tracking lost"),
        "{err}"
    );
    assert_eq!(rig.robot.last(), Velocity::ZERO);

    // Held by a heartbeat gap, then the controller's token vanishes: the
    // drive ends on that, not on the hold limit.
    let request = goto_request(84, pose(-0.2, 0.2, 0.0), 25.0);
    let token = rig.token.take().expect("token");
    let drive = async {
        // Retried while the tracker poses are coming back after the gap.
        let deadline = Instant::now() + Duration::from_secs(30);
        loop {
            match rig.goto(&request, Duration::from_secs(30)).await {
                Err(RequestError::Remote(e))
                    if e.message.contains("no fresh tracker pose") && Instant::now() < deadline =>
                {
                    tokio::time::sleep(Duration::from_millis(50)).await
                }
                other => return other,
            }
        }
    };
    let (result, ()) = tokio::join!(drive, async {
        let since = Instant::now();
        let robot = rig.robot.clone();
        let moving = wait_until(Duration::from_secs(30), move || {
            moved(&robot.sent_since(since))
        })
        .await;
        assert!(moving, "the reset drive moved the robot");
        rig.beating.store(false, Ordering::SeqCst);
        tokio::time::sleep(PROMPTLY).await;
        token.undeclare().await.expect("undeclare");
    });
    let err = assert_code(result, ErrorCode::Unavailable, "controller gone while held");
    assert!(
        err.message.contains("liveliness token is gone") && !err.message.contains("held still"),
        "{err}"
    );
    assert_eq!(rig.robot.last(), Velocity::ZERO);
    rig.beating.store(true, Ordering::SeqCst);
    rig.finish().await;
}

/// An e-stop engaged before the agent restarts (crash, reboot, update) is
/// still engaged after it: commands are refused and `goto` is refused,
/// naming the reason, until an operator releases it; the release is
/// written to the latch file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_estop_survives_an_agent_restart() {
    let dir = std::env::temp_dir().join(format!(
        "offworld-agent-latch-{}",
        offworld_runtime::keys::random_id()
    ));
    let config = AgentConfig {
        estop_latch: Some(dir.join("estop")),
        ..config()
    };
    let rig = Rig::start("estop-latch", config.clone()).await;
    let estop_key = rig.env.key(Topic::EStop);
    rig.estop(&estop_key, true).await;
    let latch = EStopLatch::new(dir.join("estop"));
    let latched = wait_until(PROMPTLY * 5, || latch.load().is_some_and(|s| s.env.engaged)).await;
    assert!(latched, "the engaged e-stop is on disk");
    rig.finish().await;

    // A new agent on the same latch: engaged from its first moment.
    let mut rig = Rig::launch("estop-latch", config).await;
    let deadline = Instant::now() + Duration::from_secs(15);
    for probe in 2_000_000u64.. {
        assert!(Instant::now() < deadline, "no probe was refused");
        rig.cmd(probe, CRUISE, 0.0, 0.3).await;
        let refused = tokio::time::timeout(Duration::from_millis(1500), rig.faults.recv()).await;
        if let Ok(Some(fault)) = refused {
            assert!(fault.reason.contains("env (test (engage))"), "{fault:?}");
            break;
        }
    }
    assert!(!moved(&rig.robot.sent()), "no motion after the restart");
    let request = goto_request(9, pose(0.5, 0.5, 0.0), 10.0);
    let refused = rig.goto(&request, Duration::from_secs(5)).await;
    let err = assert_code(
        refused,
        ErrorCode::InvalidState,
        "goto under a latched e-stop",
    );
    assert!(err.message.contains("test (engage)"), "{err}");

    // The operator's release restores motion and clears the latch.
    rig.estop(&estop_key, false).await;
    rig.until_motion_allowed().await;
    let after = latch.load().expect("still written");
    assert!(
        !after.env.engaged && !after.site.engaged,
        "released on disk: {after:?}"
    );
    rig.finish().await;
    std::fs::remove_dir_all(dir).expect("scratch");
}

/// The camera goes silent: a command is driven but cannot be answered, so
/// the agent says so on `fault` (seq and reason) once the frame timeout
/// runs out, instead of leaving the controller to its answer timeout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_camera_is_reported_as_a_fault_of_the_command() {
    let config = AgentConfig {
        frame_timeout_ms: 600,
        // Only the frame timeout here; the silence limit has its own test.
        camera_stale_ms: 10_000,
        ..config()
    };
    let mut rig = Rig::start("camera-silent", config).await;
    let camera = rig.tasks.remove(0);
    camera.abort();
    let _ = camera.await;
    // Frames already captured before the motion ends are too old to answer.
    rig.cmd(70, CRUISE, 0.0, 0.3).await;
    let fault = rig.fault(70).await;
    assert_eq!(
        fault,
        MotionFault {
            seq: 70,
            reason: "no camera frames within 600 ms after the motion".into(),
        }
    );
    assert!(
        rig.try_answer(70, Duration::from_millis(300))
            .await
            .is_none(),
        "no frame answers it"
    );
    rig.finish().await;
}

/// The site and env latches are independent (releasing one never clears
/// the other; motion resumes only when both are released), and every
/// e-stop is acknowledged with its press id and the latches now in force,
/// after the robot has braked.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn site_and_env_latches_are_independent_and_every_press_is_acknowledged() {
    let mut rig = Rig::start("estop-scopes", config()).await;
    let (env_key, site_key) = (rig.env.key(Topic::EStop), global_estop_key());
    let cruise = v(CRUISE, 0.0);

    rig.cmd(80, CRUISE, 0.0, 5.0).await;
    rig.until_driving_at(cruise).await;
    let engaged = Instant::now();
    let ack = rig.estop_acked(&site_key, true, "fire alarm").await;
    assert_eq!(
        (ack.component.as_str(), ack.env.as_str()),
        ("robot_agent", "real/estop-scopes")
    );
    assert!(ack.state.site.engaged && !ack.state.env.engaged);
    assert_eq!(ack.state.site.reason, "fire alarm");
    assert_braked(&rig.robot.sent(), engaged, cruise, "site e-stop");
    assert_eq!(
        rig.robot.last(),
        Velocity::ZERO,
        "braked before the acknowledgement"
    );
    assert_eq!(
        rig.fault(80).await.reason,
        "motion stopped before the command's end: e-stop: fire alarm"
    );

    let ack = rig.estop_acked(&env_key, true, "person inside").await;
    assert_eq!(ack.state.summary(), "site+env");
    // The env release leaves the site latch: still refused.
    let ack = rig.estop_acked(&env_key, false, "person out").await;
    assert_eq!(ack.state.summary(), "site");
    rig.cmd(81, CRUISE, 0.0, 0.5).await;
    assert_eq!(
        rig.fault(81).await.reason,
        "motion refused: e-stop engaged: site (fire alarm)"
    );
    // Engage the env again, release the site: still refused, by the env.
    rig.estop_acked(&env_key, true, "maintenance").await;
    let ack = rig.estop_acked(&site_key, false, "all clear").await;
    assert_eq!(ack.state.summary(), "env");
    rig.cmd(82, CRUISE, 0.0, 0.5).await;
    assert_eq!(
        rig.fault(82).await.reason,
        "motion refused: e-stop engaged: env (maintenance)"
    );
    assert!(!moved(
        &rig.robot.sent_since(engaged + Duration::from_millis(500))
    ));
    // Both released: motion again.
    let ack = rig.estop_acked(&env_key, false, "done").await;
    assert_eq!(ack.state.summary(), "none");
    rig.until_motion_allowed().await;
    rig.finish().await;
}

/// An agent that could not remember an e-stop across a restart refuses to
/// run: its latch is written at start, and a path it cannot write (here a
/// directory that is a file) is a configuration error naming the file.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_agent_that_cannot_write_its_latch_refuses_to_start() {
    let file = std::env::temp_dir().join(format!(
        "offworld-agent-latch-file-{}",
        offworld_runtime::keys::random_id()
    ));
    std::fs::write(&file, b"not a directory").expect("a plain file");
    let config = AgentConfig {
        estop_latch: Some(file.join("estop")),
        ..config()
    };
    let (_listener, session) = loopback_pair().await.expect("sessions");
    let env = EnvId::real("latch-unwritable").expect("env");
    let refused = offworld_robot_agent::spawn(&session, env, config, RecordingRobot::new()).await;
    let _ = std::fs::remove_file(&file);
    match refused {
        Err(AgentError::Config(why)) => {
            assert!(why.contains("cannot write the e-stop latch"), "{why}");
            assert!(why.contains("--estop-latch"), "{why}");
            assert!(
                why.contains(&*file.to_string_lossy()),
                "the file is named: {why}"
            );
        }
        Err(other) => panic!("not a configuration error: {other}"),
        Ok(_) => panic!("an agent without a writable latch started"),
    }
}

/// A starting agent without a latch file learns the site latch from the
/// network: another agent of the site answers `estop_state`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_starting_agent_learns_the_site_estop_from_the_network() {
    let mut first = Rig::start("estop-net-a", config()).await;
    first.estop_acked(&global_estop_key(), true, "drill").await;
    // A second agent on the first one's network (its session), no latch.
    let env = EnvId::real("estop-net-b").expect("env");
    let robot = RecordingRobot::new();
    let second = offworld_robot_agent::spawn(&first.ctl, env.clone(), config(), robot.clone())
        .await
        .expect("second agent");
    let state: offworld_runtime::msg::EStopState = wire::request(
        &first.ctl,
        &env.key(Topic::EStopState),
        &(),
        Duration::from_secs(5),
    )
    .await
    .expect("the second agent answers its e-stop state");
    assert!(state.site.engaged, "{state:?}");
    assert_eq!(state.site.reason, "drill");
    assert!(!state.env.engaged);
    second.shutdown().await;
    assert!(!moved(&robot.sent()));
    first.estop(&global_estop_key(), false).await;
    first.until_motion_allowed().await;
    first.finish().await;
}

/// With `require_base_guard` (the default), the agent refuses motion until
/// the robot's base guard declares itself, and again when it vanishes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn motion_needs_the_base_guard_when_required() {
    let config = AgentConfig {
        require_base_guard: true,
        ..config()
    };
    let mut rig = Rig::launch("guarded", config).await;
    // Probes until one is refused for the missing guard (the controller's
    // token and first heartbeat must have arrived first).
    let deadline = Instant::now() + Duration::from_secs(15);
    for probe in 3_000_000u64.. {
        assert!(
            Instant::now() < deadline,
            "never refused for the missing guard"
        );
        rig.cmd(probe, CRUISE, 0.0, 0.3).await;
        if let Ok(Some(fault)) =
            tokio::time::timeout(Duration::from_millis(1500), rig.faults.recv()).await
        {
            if fault.reason.contains("no base guard") {
                break;
            }
        }
    }
    assert!(!moved(&rig.robot.sent()), "never moved without a guard");
    let guard = rig
        .ctl
        .liveliness()
        .declare_token(rig.env.alive_key(Component::BaseGuard))
        .await
        .expect("guard token");
    rig.until_motion_allowed().await;

    rig.cmd(90, CRUISE, 0.0, 5.0).await;
    rig.until_driving_at(v(CRUISE, 0.0)).await;
    let gone = Instant::now();
    guard.undeclare().await.expect("undeclare");
    let cut = rig.fault(90).await.reason;
    assert!(cut.contains("base guard"), "{cut}");
    assert_braked(&rig.robot.sent(), gone, v(CRUISE, 0.0), "base guard gone");
    rig.finish().await;
}

/// The camera stops mid-drive (hardware or driver down): the command fails
/// on `fault` within the silence limit, long before its 5 s motion would
/// end, and the robot brakes.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_camera_silent_mid_drive_fails_the_command_at_once() {
    let config = AgentConfig {
        camera_stale_ms: 300,
        ..config()
    };
    let mut rig = Rig::start("camera-dies", config).await;
    let cruise = v(CRUISE, 0.0);
    rig.cmd(71, CRUISE, 0.0, 5.0).await;
    rig.until_driving_at(cruise).await;
    let camera = rig.tasks.remove(0);
    camera.abort();
    let _ = camera.await;
    let silenced = Instant::now();
    let fault = rig.fault(71).await;
    let after = silenced.elapsed();
    assert!(fault.reason.contains("camera is silent"), "{fault:?}");
    assert!(
        after < Duration::from_secs(3),
        "failed after {after:?}, not at the motion's end"
    );
    assert_braked(&rig.robot.sent(), silenced, cruise, "camera silent");
    rig.finish().await;
}

/// Without a base guard, the agent checks the base's own command timeout
/// before the first motion: a slow turn, then silence. A base that stops
/// by itself passes, and commands move it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_base_that_honours_its_command_timeout_passes_the_start_check() {
    let config = AgentConfig {
        skip_base_timeout_check: false,
        base_cmd_timeout_ms: 300,
        ..config()
    };
    let mut rig = Rig::launch("base-check-ok", config).await;
    let base = rig.robot.simulate_base(Some(Duration::from_millis(300)));
    rig.tasks.push(base);
    let robot = rig.robot.clone();
    assert!(
        wait_until(Duration::from_secs(10), || robot.sent().iter().any(|s| s
            .velocity
            .angular
            == 0.3
            && s.velocity.linear == 0.0))
        .await,
        "the check's slow turn"
    );
    rig.until_motion_allowed().await;
    rig.finish().await;
}

/// A base that holds its last velocity forever fails the check: the agent
/// stops it and refuses every motion, saying what to do.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_base_without_a_command_timeout_is_never_armed() {
    let config = AgentConfig {
        skip_base_timeout_check: false,
        base_cmd_timeout_ms: 300,
        ..config()
    };
    let mut rig = Rig::launch("base-check-fails", config).await;
    let base = rig.robot.simulate_base(None);
    rig.tasks.push(base);
    let deadline = Instant::now() + Duration::from_secs(15);
    let mut reason = String::new();
    for probe in 4_000_000u64.. {
        assert!(Instant::now() < deadline, "never refused: {reason}");
        rig.cmd(probe, CRUISE, 0.0, 0.3).await;
        if let Ok(Some(fault)) =
            tokio::time::timeout(Duration::from_millis(1500), rig.faults.recv()).await
        {
            reason = fault.reason;
            if reason.contains("no working command timeout") {
                break;
            }
        }
    }
    assert!(
        reason.contains("within 600 ms of its last command (it kept moving)"),
        "{reason}"
    );
    assert!(reason.contains("require_base_guard = true"), "{reason}");
    assert_eq!(rig.robot.last(), Velocity::ZERO, "stopped by the agent");
    let sent = rig.robot.sent();
    assert!(
        sent.iter().all(|s| s.velocity.linear == 0.0),
        "only the check's turn ever moved the base: {sent:?}"
    );
    rig.finish().await;
}

/// A command key file, private to its owner, in a fresh directory.
fn command_key_file(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "offworld-agent-{name}-{}-{}",
        std::process::id(),
        offworld_runtime::keys::random_id()
    ));
    std::fs::create_dir_all(&dir).expect("key dir");
    let path = dir.join("command.seal");
    SealKey::generate().save(&path).expect("command key");
    path
}

/// Issue 22: with the site's command key, the agent obeys only what the
/// controller sealed with it. An unsealed command, one sealed with another
/// key, the replay of a sealed one and an unsealed reset drive move
/// nothing (the drive is refused `Unauthorized`); forged heartbeats do not
/// keep a command going (the watchdog brakes as if they were silent).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn with_a_command_key_only_what_the_controller_sealed_moves_the_robot() {
    let key_file = command_key_file("sealed");
    let config = AgentConfig {
        command_key: Some(key_file.clone()),
        watchdog_ms: 500,
        ..config()
    };
    // Its probes are sealed: motion is allowed.
    let mut rig = Rig::start("sealed", config).await;
    let sealer = rig.sealer.clone().expect("the rig seals");
    let key = rig.env.key(Topic::Cmd);
    let command = |seq| MotionCommand {
        seq,
        linear_x: CRUISE,
        angular_z: 0.0,
        duration_s: 0.3,
    };
    wire::put(&rig.ctl, &key, &command(10))
        .await
        .expect("unsealed");
    let stranger = Sealer::new(SealKey::generate());
    wire::put_sealed(&rig.ctl, &key, &command(11), Some(&stranger))
        .await
        .expect("sealed with another key");
    let payload = codec::encode(&command(12)).expect("encode");
    let seal = sealer.seal(&key, &payload, &[]);
    rig.ctl
        .put(&key, payload.clone())
        .attachment(seal.clone())
        .await
        .expect("sealed");
    assert_eq!(rig.answer(12).await.seq, 12);
    assert!(
        !rig.seen.contains(&10) && !rig.seen.contains(&11),
        "a forged command was answered: {:?}",
        rig.seen
    );
    let replayed = Instant::now();
    rig.ctl
        .put(&key, payload)
        .attachment(seal)
        .await
        .expect("replay");
    assert!(
        rig.try_answer(12, Duration::from_millis(1500))
            .await
            .is_none(),
        "the replay was obeyed"
    );
    assert!(!moved(&rig.robot.sent_since(replayed)), "the replay moved");
    // (The probes before may have left faults of their own.)
    while let Ok(fault) = rig.faults.try_recv() {
        assert!(
            ![10, 11, 12].contains(&fault.seq),
            "forgeries are ignored, not answered: {fault:?}"
        );
    }

    let drive = rig
        .goto(&goto_request(13, pose(0.1, 0.3, 0.0), 5.0), ANSWER)
        .await;
    let e = assert_code(drive, ErrorCode::Unauthorized, "unsealed reset drive");
    assert!(e.message.contains("not sealed"), "{e}");

    // Forged heartbeats in place of the sealed ones: the watchdog brakes.
    rig.cmd(14, CRUISE, 0.0, 5.0).await;
    let cruise = v(CRUISE, 0.0);
    rig.until_driving_at(cruise).await;
    rig.beating.store(false, Ordering::SeqCst);
    let forged_from = Instant::now();
    let (ctl, beat_key) = (rig.ctl.clone(), rig.env.key(Topic::Heartbeat));
    rig.tasks.push(tokio::spawn(async move {
        for counter in 0.. {
            let beat = Heartbeat {
                stamp: Time::now(),
                counter,
            };
            let _ = wire::put_control(&ctl, &beat_key, &beat).await;
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }));
    let cut = rig.fault(14).await.reason;
    assert!(cut.contains("watchdog"), "{cut}");
    assert_braked(&rig.robot.sent(), forged_from, cruise, "forged heartbeats");
    rig.beating.store(true, Ordering::SeqCst);
    rig.until_motion_allowed().await;
    rig.finish().await;
    let _ = std::fs::remove_dir_all(key_file.parent().expect("dir"));
}
