//! Fault injection against the emulated enclosure (worst-case base: it
//! holds the last velocity forever): a real process of the deployment is
//! killed, terminated or frozen while a step turns the robot, and what
//! follows is measured from the base's own odometry and the gym client —
//! how long the base kept moving, how far it turned, which typed error the
//! client got and when. Shared by the fault tests (`tests/integration/faults.rs`) and
//! the report program (`fault_matrix`, figures for `docs/safety.md`).

use std::fmt;
use std::io::{BufRead, BufReader};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use offworld_client::EnvClient;
use offworld_runtime::codec;
use offworld_runtime::msg::{
    Action, AlgorithmMode, Channels, DepthFormat, ObsOptions, Odometry, OpenRequest, Seed,
};
use offworld_runtime::ros2::{RobotTopics, RosGraph, RosType};
use offworld_runtime::session::Mode;
use offworld_runtime::{ErrorCode, SessionConfig, WireError};
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;
use zenoh::Session;

use anyhow::Context;

use crate::emulated::{EmulatedEnclosure, Part};
use crate::link::Impairment;
use crate::{Process, Spawn};

/// What is done to a part.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// SIGKILL: a crash, the OOM killer.
    Kill,
    /// SIGTERM: systemd, `kill`, a container stop.
    Terminate,
    /// SIGSTOP for this long, then SIGCONT: a hang, a debugger, swap.
    Freeze(Duration),
    /// The robot's link impaired for this long, then clear again (the part
    /// is [`Part::RobotLink`]).
    Link(Impairment, Duration),
}

impl fmt::Display for Fault {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Fault::Kill => f.write_str("kill -9"),
            Fault::Terminate => f.write_str("SIGTERM"),
            Fault::Freeze(d) => write!(f, "SIGSTOP {} s", d.as_secs()),
            Fault::Link(impairment, d) => {
                let s = d.as_secs();
                match impairment {
                    Impairment::Clear => write!(f, "clear {s} s"),
                    Impairment::Cut => write!(f, "cut {s} s"),
                    Impairment::Delay(by) => write!(f, "{} ms delay {s} s", by.as_millis()),
                    Impairment::Loss { percent } => write!(f, "{percent} % loss {s} s"),
                }
            }
        }
    }
}

/// The base as its odometry shows it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaseState {
    /// Heading, rad.
    pub yaw: f64,
    /// Position, m.
    pub x: f64,
    /// Position, m.
    pub y: f64,
    /// Whether the base reports a velocity.
    pub moving: bool,
}

impl BaseState {
    /// Reads an odometry message.
    pub fn of(odom: &Odometry) -> Self {
        let (pose, twist) = (&odom.pose.pose, &odom.twist.twist);
        Self {
            yaw: pose.orientation.yaw(),
            x: pose.position.x,
            y: pose.position.y,
            moving: twist.linear.x.abs() > 1e-3 || twist.angular.z.abs() > 1e-3,
        }
    }
}

/// One line of `test_helper base-probe`'s output: `yaw x y moving`.
impl fmt::Display for BaseState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let moving = u8::from(self.moving);
        write!(f, "{} {} {} {moving}", self.yaw, self.x, self.y)
    }
}

impl std::str::FromStr for BaseState {
    type Err = String;

    fn from_str(line: &str) -> Result<Self, String> {
        let fields: Vec<f64> = line
            .split_whitespace()
            .map(|f| f.parse().map_err(|e| format!("{line:?}: {e}")))
            .collect::<Result<_, _>>()?;
        match fields[..] {
            [yaw, x, y, moving] => Ok(Self {
                yaw,
                x,
                y,
                moving: moving != 0.0,
            }),
            _ => Err(format!("{line:?}: expected `yaw x y moving`")),
        }
    }
}

/// The base's state when it was heard.
#[derive(Debug, Clone, Copy)]
struct OdomSample {
    at: Instant,
    base: BaseState,
}

/// Watches the base's odometry over a direct link to the hardware (it
/// keeps working while the robot's router or link is down).
pub struct BaseObserver {
    samples: Arc<Mutex<Vec<OdomSample>>>,
    _feed: Feed,
}

/// Where the samples come from.
enum Feed {
    /// A Zenoh peer session of this process.
    Direct {
        _subscriber: Subscriber<()>,
        _session: Session,
    },
    /// A `test_helper base-probe` inside the robot's network namespace.
    Probe { _process: Process },
}

fn record(samples: &Mutex<Vec<OdomSample>>, sample: OdomSample) {
    if let Ok(mut v) = samples.lock() {
        v.push(sample);
    }
}

impl BaseObserver {
    /// Connects to the deployment's hardware as a peer, or through a probe
    /// inside the robot's namespace when the robot runs in one.
    pub async fn connect(deployment: &EmulatedEnclosure) -> anyhow::Result<Self> {
        let samples = Arc::new(Mutex::new(Vec::new()));
        if let Some(netns) = deployment.robot_netns() {
            let mut probe = Process::spawn_piped_in(
                Some(netns),
                "test_helper",
                &["base-probe", "--connect", &deployment.hardware_endpoint],
                "warn",
            )?;
            let stdout = probe.0.stdout.take().context("the probe's stdout")?;
            let sink = samples.clone();
            std::thread::spawn(move || {
                for line in BufReader::new(stdout).lines() {
                    let Ok(line) = line else { return };
                    if let Ok(base) = line.parse() {
                        let at = Instant::now();
                        record(&sink, OdomSample { at, base });
                    }
                }
            });
            return Ok(Self {
                samples,
                _feed: Feed::Probe { _process: probe },
            });
        }
        let mut config = SessionConfig::connecting(&deployment.hardware_endpoint);
        config.mode = Mode::Peer;
        let session = config.open().await.map_err(|e| anyhow::anyhow!("{e}"))?;
        let key = RosGraph::new(Default::default(), "")?
            .subscription_key(&RobotTopics::default().odom, RosType::Odometry)?;
        let sink = samples.clone();
        let subscriber = session
            .declare_subscriber(key)
            .callback(move |s: Sample| {
                let Ok(odom) = codec::decode_payload::<Odometry>(s.payload()) else {
                    return;
                };
                let at = Instant::now();
                record(
                    &sink,
                    OdomSample {
                        at,
                        base: BaseState::of(&odom),
                    },
                );
            })
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(Self {
            samples,
            _feed: Feed::Direct {
                _subscriber: subscriber,
                _session: session,
            },
        })
    }

    fn since(&self, t: Instant) -> Vec<OdomSample> {
        self.samples
            .lock()
            .map(|v| v.iter().filter(|s| s.at >= t).copied().collect())
            .unwrap_or_default()
    }

    /// Whether the newest sample shows the base moving.
    pub fn moving(&self) -> bool {
        self.samples
            .lock()
            .ok()
            .and_then(|v| v.last().map(|s| s.base.moving))
            .unwrap_or(false)
    }

    /// Whether odometry arrived since `t`.
    pub fn heard_since(&self, t: Instant) -> bool {
        !self.since(t).is_empty()
    }
}

/// What a fault did.
#[derive(Debug, Clone)]
pub struct FaultOutcome {
    /// Which process.
    pub part: Part,
    /// What was done to it.
    pub fault: Fault,
    /// Whether the base's odometry was heard after the fault (not when the
    /// hardware itself was killed).
    pub observed: bool,
    /// From the fault to the last odometry sample that showed the base
    /// moving (`None`: it was still moving at the end of the window).
    pub moved_for: Option<Duration>,
    /// How far the base turned after the fault, rad.
    pub turned_rad: f64,
    /// How far it travelled after the fault, m.
    pub travelled_m: f64,
    /// The step's result: its error, if it failed.
    pub client_error: Option<WireError>,
    /// From the fault to the step's result.
    pub result_after: Duration,
}

impl FaultOutcome {
    /// Whether the base stopped within `limit` of the fault and stayed
    /// stopped.
    pub fn stopped_within(&self, limit: Duration) -> bool {
        self.moved_for.is_some_and(|d| d <= limit)
    }

    /// The client error's code, if any.
    pub fn error_code(&self) -> Option<ErrorCode> {
        self.client_error.as_ref().map(|e| e.code)
    }
}

/// A training session on `experiment` (small depth-only observations: the
/// faults are the point, not the pixels).
pub fn open_request(token: &str, experiment: &str, resume: bool) -> OpenRequest {
    OpenRequest {
        token: token.to_owned(),
        experiment_name: experiment.to_owned(),
        resume_experiment: resume,
        algorithm_mode: AlgorithmMode::Train,
        ..OpenRequest::anonymous(ObsOptions {
            channels: Channels::DepthOnly,
            height: 24,
            width: 32,
            depth_format: DepthFormat::Uint8,
        })
    }
}

/// The step a fault interrupts: turning in place at 60 % of the range
/// (1.5 rad/s for 1 s on `MonolithContinuous`), so the robot never meets a
/// wall that would stop it for us.
pub fn turning_step() -> Action {
    Action::Continuous(vec![0.0, 0.6])
}

/// Resets until an episode starts (the deployment may be recovering from
/// the previous fault), bounded by `limit`.
pub async fn reset_when_ready(
    gym: &mut EnvClient,
    seed: u64,
    limit: Duration,
) -> Result<(), WireError> {
    let deadline = Instant::now() + limit;
    loop {
        match gym.reset(Seed::Fixed(seed)).await {
            Ok(_) => return Ok(()),
            Err(e)
                if matches!(e.code, ErrorCode::Unavailable | ErrorCode::Timeout)
                    && Instant::now() < deadline =>
            {
                tokio::time::sleep(Duration::from_millis(250)).await;
            }
            Err(e) => return Err(e),
        }
    }
}

/// Starts a turning step, applies `fault` to `part` once the base moves,
/// and measures for `window` after the fault. Leaves the part faulted
/// (killed, terminated, or frozen and then continued): [`recover`] brings
/// the deployment back.
pub async fn inject(
    deployment: &mut EmulatedEnclosure,
    gym: EnvClient,
    base: &BaseObserver,
    part: Part,
    fault: Fault,
    window: Duration,
) -> (EnvClient, FaultOutcome) {
    let mut gym = gym;
    let stepping = tokio::spawn(async move {
        let result = gym.step(turning_step()).await;
        (gym, result, Instant::now())
    });
    let started = Instant::now();
    while !base.moving() && started.elapsed() < Duration::from_secs(10) {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    // Past the acceleration ramp (1.5 rad/s at 12 rad/s² takes 125 ms), well
    // inside the 1 s motion: the fault hits the base at full speed.
    tokio::time::sleep(Duration::from_millis(250)).await;
    let at = Instant::now();
    match fault {
        Fault::Kill => deployment.kill(part),
        Fault::Terminate => deployment.signal(part, "TERM"),
        Fault::Freeze(d) => {
            deployment.signal(part, "STOP");
            tokio::time::sleep(d).await;
            deployment.signal(part, "CONT");
        }
        Fault::Link(impairment, d) => {
            let link = deployment
                .robot_link
                .as_ref()
                .expect("a link fault needs Options::isolated_robot");
            link.impair(impairment);
            tokio::time::sleep(d).await;
            link.impair(Impairment::Clear);
        }
    }
    let (gym, result, returned) =
        match tokio::time::timeout(Duration::from_secs(40), stepping).await {
            Ok(Ok(done)) => done,
            _ => panic!("{part:?} {fault}: the step never returned"),
        };
    let elapsed = at.elapsed();
    if elapsed < window {
        tokio::time::sleep(window - elapsed).await;
    }
    let after = base.since(at);
    let moved_for = match after.iter().rposition(|s| s.base.moving) {
        Some(i) if i + 1 == after.len() => None,
        Some(i) => Some(after[i].at.saturating_duration_since(at)),
        None => Some(Duration::ZERO),
    };
    let mut turned = 0.0;
    let mut travelled = 0.0;
    for pair in after.windows(2) {
        let (a, b) = (pair[0].base, pair[1].base);
        let d = b.yaw - a.yaw;
        turned += d.sin().atan2(d.cos()).abs();
        travelled += (b.x - a.x).hypot(b.y - a.y);
    }
    let outcome = FaultOutcome {
        part,
        fault,
        observed: !after.is_empty(),
        moved_for,
        turned_rad: turned,
        travelled_m: travelled,
        client_error: result.err(),
        result_after: returned.saturating_duration_since(at),
    };
    (gym, outcome)
}

/// Brings a faulted part back: a killed or terminated one is started
/// again (a frozen one was continued, a link cleared, by [`inject`]); then
/// waits until the env is online and tracked again.
pub async fn recover(
    deployment: &mut EmulatedEnclosure,
    part: Part,
    fault: Fault,
) -> anyhow::Result<()> {
    if matches!(fault, Fault::Kill | Fault::Terminate) {
        // A terminated part exits by itself; make sure before restarting.
        deployment.wait_exit(part, Duration::from_secs(5));
        deployment.kill(part);
        deployment.start_part(part)?;
    }
    deployment
        .ready(Duration::from_secs(60))
        .await
        .map_err(anyhow::Error::msg)
}
