//! The emulated enclosure deployment: the real stack (env_controller,
//! robot_agent, base_guard, tracker_agent) as separate processes under a
//! `real/…` namespace, driving `offworld emulate-hardware` as if it were
//! the physical robot and lighthouse tracker. Used by the launcher binary
//! `emulated_enclosure`, the end-to-end tests and the fault matrix.
//!
//! The robot computer is laid out as a ROSbot on rmw_zenoh is: a Zenoh
//! router (`zenohd`, as `rmw_zenohd`) for discovery, and the nodes that
//! move the robot — the base driver (the emulator), `robot_agent` and its
//! independent `base_guard` — as Zenoh peers that talk to each other
//! directly once discovered, so the router's death never cuts the agent
//! or the guard off the base. The tracker agent is a client of the router;
//! the controller a peer that reaches the robot through it and listens for
//! gym clients.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use offworld_client as client;
use offworld_deploy::hardware::default_world_from_tracking;
use offworld_runtime::codec;
use offworld_runtime::msg::{EnvState, TrackingStatus};
use offworld_runtime::seal::SealKey;
use offworld_runtime::session::{free_loopback_port, loopback_endpoint, Mode};
use offworld_runtime::{EnvId, Resolution, SessionConfig, Topic};

use crate::link::ImpairedLink;
use crate::netns::RobotNamespace;
use crate::{binary_dir, Process};

/// The site's command key file in [`EmulatedEnclosure::dir`]: the
/// controller seals with it, the robot agent obeys only what it seals.
pub const COMMAND_KEY: &str = "command.key";
/// The site's tracker key file: the tracker agent seals its poses with it.
pub const TRACKER_KEY: &str = "tracker.key";

/// What to start.
#[derive(Debug, Clone)]
pub struct Options {
    /// Env served, e.g. `real/monolith-0` (what Python's `…Real-v0` ids use
    /// by default).
    pub env: EnvId,
    /// Task name (`MonolithDiscrete`, `MonolithObstacleContinuous`, …).
    pub task: String,
    /// Route the tracker stream through a [`LineProxy`] the caller can pause
    /// (tracker silence).
    pub pausable_tracker: bool,
    /// Robot agent watchdog window, ms.
    pub watchdog_ms: u64,
    /// The emulated base stops after this long without a velocity command
    /// (a base with a command timeout); `None` holds the last velocity
    /// forever — the worst case, the default, what fault tests run against.
    pub base_cmd_timeout_ms: Option<u64>,
    /// Run the robot's `base_guard` (default). Without it the robot agent
    /// is started with `require_base_guard = false` and checks the base's
    /// command timeout before the first motion (skipped, on the operator's
    /// override, for the worst-case base).
    pub base_guard: bool,
    /// Run the robot computer (its router, the hardware, robot agent, base
    /// guard and tracker agent) in a network namespace of its own, which
    /// the controller reaches only through [`EmulatedEnclosure::robot_link`]:
    /// a link a test can cut, delay or make lossy. Needs CAP_NET_ADMIN.
    pub isolated_robot: bool,
    /// Also run a sim twin process for this env (same task, on the robot's
    /// router), served by the same controller: [`Part::Twin`].
    pub twin: Option<EnvId>,
    /// Log filter of the children (default: this process's `RUST_LOG`, else `warn`).
    pub log: String,
    /// The controller records every episode under this directory
    /// (`serve --record`).
    pub record: Option<std::path::PathBuf>,
    /// The emulated "physical" robot behaves per this twin profile
    /// (`offworld emulate-hardware --profile`, `docs/twin-profile.md`):
    /// how a test perturbs the hardware away from the nominal twin.
    pub hardware_profile: Option<std::path::PathBuf>,
    /// The emulated camera's resolution; default the world
    /// camera's own (`offworld emulate-hardware --camera-resolution`).
    pub hardware_camera: Option<Resolution>,
}

impl Options {
    /// `task` on `real/<world>-0`, the env id Python's `…Real-v0` ids use
    /// by default.
    pub fn new(task: &str) -> Result<Self, offworld_runtime::ContractError> {
        Ok(Self {
            env: EnvId::real(&format!("{}-0", world_of(task)))?,
            task: task.to_owned(),
            pausable_tracker: false,
            watchdog_ms: 200,
            base_cmd_timeout_ms: None,
            base_guard: true,
            isolated_robot: false,
            twin: None,
            log: std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into()),
            record: None,
            hardware_profile: None,
            hardware_camera: None,
        })
    }

    fn world(&self) -> &'static str {
        world_of(&self.task)
    }
}

fn world_of(task: &str) -> &'static str {
    if task.starts_with("MonolithObstacle") {
        "monolith_obstacle"
    } else {
        "monolith"
    }
}

/// The processes of the deployment.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Part {
    /// The robot computer's Zenoh router (`zenohd`, as `rmw_zenohd`).
    Router,
    /// The emulated hardware: base driver, camera, lighthouse tracker.
    Hardware,
    /// The gym server.
    Controller,
    /// The robot agent.
    RobotAgent,
    /// The robot's independent base guard.
    BaseGuard,
    /// The tracker agent.
    TrackerAgent,
    /// A sim twin beside the robot, with [`Options::twin`] (not in
    /// [`Part::ALL`]: started after the hardware when asked for).
    Twin,
    /// Not a process: the network link between the site (controller) and
    /// the robot computer, with [`Options::isolated_robot`].
    RobotLink,
}

impl Part {
    /// Every part, in start order.
    pub const ALL: [Part; 6] = [
        Part::Router,
        Part::Hardware,
        Part::Controller,
        Part::TrackerAgent,
        Part::BaseGuard,
        Part::RobotAgent,
    ];

    /// The part's name (its binary, but `router` for zenohd and `hardware`
    /// for the emulator).
    pub fn name(self) -> &'static str {
        match self {
            Part::Router => "router",
            Part::Hardware => "hardware",
            Part::Controller => "env_controller",
            Part::RobotAgent => "robot_agent",
            Part::BaseGuard => "base_guard",
            Part::TrackerAgent => "tracker_agent",
            Part::Twin => "sim_twin",
            Part::RobotLink => "robot_link",
        }
    }

    /// Whether the part runs on the robot computer (in its namespace, with
    /// [`Options::isolated_robot`]).
    pub fn on_robot(self) -> bool {
        !matches!(self, Part::Controller | Part::RobotLink | Part::Twin)
    }
}

/// A running emulated deployment; every process is killed when dropped.
pub struct EmulatedEnclosure {
    /// The Zenoh endpoint the controller listens on (gym clients connect here).
    pub endpoint: String,
    /// The robot computer's Zenoh router (the ROS 2 side: `cmd_vel`,
    /// camera, odometry).
    pub robot_endpoint: String,
    /// Where the emulated hardware (a Zenoh peer) listens: an observer of
    /// the base that must not depend on the router connects here too.
    pub hardware_endpoint: String,
    /// The env served.
    pub env: EnvId,
    /// An access token of a registered user.
    pub token: String,
    /// An access token of a registered operator (maintenance, leases, the
    /// web page's console).
    pub operator_token: String,
    /// Scratch directory (database, calibration).
    pub dir: PathBuf,
    /// The tracker stream proxy, when requested.
    pub tracker_proxy: Option<LineProxy>,
    /// The link between the site's router and the robot's, with
    /// [`Options::isolated_robot`].
    pub robot_link: Option<ImpairedLink>,
    /// The site's router and its endpoint, with [`Options::isolated_robot`]:
    /// the controller connects here.
    site_router: Option<(Process, String)>,
    options: Options,
    tracker_listen: String,
    processes: BTreeMap<Part, Process>,
    /// Declared last: removed after the processes stopped.
    robot_netns: Option<RobotNamespace>,
}

impl EmulatedEnclosure {
    /// Starts the router, emulator, controller, tracker agent, base guard
    /// and robot agent.
    pub fn start(options: &Options) -> std::io::Result<Self> {
        let dir = std::env::temp_dir().join(format!(
            "offworld-emulated-{}-{}",
            std::process::id(),
            offworld_runtime::keys::random_id()
        ));
        std::fs::create_dir_all(&dir)?;
        if options.isolated_robot && options.pausable_tracker {
            return Err(std::io::Error::other(
                "a pausable tracker needs the tracker stream on this host: not with an isolated robot",
            ));
        }
        let robot_netns = if options.isolated_robot {
            Some(RobotNamespace::create().map_err(|e| {
                std::io::Error::other(format!("the robot's network namespace: {e:#}"))
            })?)
        } else {
            None
        };
        let db = dir.join("gym.db");
        let token = register_user(&db.to_string_lossy(), "researcher", false)?;
        let operator_token = register_user(&db.to_string_lossy(), "operator", true)?;
        std::fs::write(
            dir.join("tracker_calibration.toml"),
            emulator_calibration_toml(),
        )?;
        // The site's keys, as `deploy/certs/generate.sh` issues them.
        for name in [COMMAND_KEY, TRACKER_KEY] {
            SealKey::generate().save(&dir.join(name))?;
        }
        // An isolated robot meets the site as a robot on a radio link
        // does: its router connects to the site's router through the link
        // (a proxy on the host's side of the namespace); nothing on the
        // host can reach the robot's own loopback, where its nodes meet,
        // so no Zenoh peer finds a way around the link.
        let (site_router, robot_link) = match &robot_netns {
            Some(ns) => {
                let endpoint = loopback_endpoint()?;
                let router = Process::spawn_from_path(
                    "zenohd",
                    &["--listen", &endpoint, "--no-multicast-scouting"],
                    &options.log,
                )?;
                wait_until_listening(&endpoint, Duration::from_secs(20))?;
                let host_ip = ns.host_ip.parse().map_err(std::io::Error::other)?;
                let upstream = endpoint_addr(&endpoint)?;
                let seed = std::process::id().into();
                let link = ImpairedLink::start(host_ip, upstream, seed)?;
                (Some((router, endpoint)), Some(link))
            }
            None => (None, None),
        };
        let mut deployment = Self {
            endpoint: loopback_endpoint()?,
            robot_endpoint: loopback_endpoint()?,
            hardware_endpoint: loopback_endpoint()?,
            env: options.env.clone(),
            token,
            operator_token,
            dir,
            tracker_proxy: None,
            robot_link,
            site_router,
            options: options.clone(),
            tracker_listen: format!("127.0.0.1:{}", free_loopback_port("127.0.0.1")?),
            processes: BTreeMap::new(),
            robot_netns,
        };
        for part in Part::ALL {
            deployment.start_part(part)?;
            if part == Part::Hardware {
                if options.pausable_tracker {
                    let addr: SocketAddr = deployment
                        .tracker_listen
                        .parse()
                        .map_err(|e| std::io::Error::other(format!("{e}")))?;
                    deployment.tracker_proxy = Some(LineProxy::start(addr)?);
                }
                deployment.start_part(Part::Twin)?;
            }
        }
        Ok(deployment)
    }

    /// Starts (or restarts) one part with the deployment's settings.
    pub fn start_part(&mut self, part: Part) -> std::io::Result<()> {
        let options = &self.options;
        let env = self.env.to_string();
        let robot = self.robot_endpoint.as_str();
        // The robot's nodes are peers: they listen (loopback, any port) so
        // the others reach them directly, not only through the router.
        let peer = [
            "--mode",
            "peer",
            "--connect",
            robot,
            "--listen",
            "tcp/127.0.0.1:0",
        ];
        let mut args: Vec<String> = Vec::new();
        let mut push = |items: &[&str]| args.extend(items.iter().map(|s| s.to_string()));
        let binary = match part {
            Part::Router => {
                push(&["--listen", robot, "--no-multicast-scouting"]);
                if let Some(link) = &self.robot_link {
                    push(&["--connect", &link.endpoint()]);
                }
                "zenohd"
            }
            Part::Hardware => {
                push(&["emulate-hardware", "--world", options.world()]);
                push(&[
                    "--tracker-listen",
                    &self.tracker_listen,
                    "--overhead-env",
                    &env,
                ]);
                // Half the Astra's rate: the whole site shares 2 cores here.
                push(&["--camera-hz", "15"]);
                let timeout = options.base_cmd_timeout_ms.unwrap_or(0).to_string();
                push(&["--base-cmd-timeout-ms", &timeout]);
                if let Some(profile) = &options.hardware_profile {
                    push(&["--profile", &profile.to_string_lossy()]);
                }
                if let Some(camera) = options.hardware_camera {
                    push(&["--camera-resolution", &camera.to_string()]);
                }
                push(&["--mode", "peer", "--connect", robot]);
                push(&["--listen", &self.hardware_endpoint]);
                "offworld"
            }
            Part::Controller => {
                let db = self.dir.join("gym.db");
                push(&["--db", &db.to_string_lossy(), "serve"]);
                push(&["--env", &format!("{env}={}", options.task)]);
                push(&["--command-key", &self.key_path(COMMAND_KEY)]);
                push(&["--tracker-key", &self.key_path(TRACKER_KEY)]);
                if let Some(twin) = &options.twin {
                    push(&["--env", &format!("{twin}={}", options.task)]);
                }
                if let Some(dir) = &options.record {
                    push(&["--record", &dir.to_string_lossy()]);
                }
                push(&[
                    "--listen",
                    &self.endpoint,
                    "--connect",
                    self.site_endpoint(),
                ]);
                "env_controller"
            }
            Part::TrackerAgent => {
                let source = match &self.tracker_proxy {
                    Some(proxy) => format!("tcp://{}", proxy.addr()),
                    None => format!("tcp://{}", self.tracker_listen),
                };
                let calibration = self.dir.join("tracker_calibration.toml");
                push(&["run", "--env", &env, "--source", &source]);
                push(&["--calibration", &calibration.to_string_lossy()]);
                push(&["--tracker-key", &self.key_path(TRACKER_KEY)]);
                push(&["--mode", "client", "--connect", robot]);
                "tracker_agent"
            }
            Part::BaseGuard => {
                if !options.base_guard {
                    return Ok(());
                }
                push(&["--env", &env]);
                push(&peer);
                "base_guard"
            }
            Part::RobotLink => return Ok(()),
            Part::Twin => {
                let Some(twin) = &options.twin else {
                    return Ok(());
                };
                let twin = twin.to_string();
                push(&["--env", &twin, "--world", options.world()]);
                push(&["--resolution", "84x84"]);
                // A peer others reach directly, as the robot's nodes.
                let site = self.site_endpoint().to_owned();
                push(&["--mode", "peer", "--connect", &site]);
                push(&["--listen", "tcp/127.0.0.1:0"]);
                "sim_twin"
            }
            Part::RobotAgent => {
                let config = self.dir.join("robot.toml");
                std::fs::write(&config, robot_config_toml(options))?;
                push(&["--env", &env, "--world", options.world()]);
                push(&["--robot-config", &config.to_string_lossy()]);
                push(&["--watchdog-ms", &options.watchdog_ms.to_string()]);
                let latch = self.dir.join("robot_agent.estop");
                push(&["--estop-latch", &latch.to_string_lossy()]);
                push(&["--command-key", &self.key_path(COMMAND_KEY)]);
                push(&["--tracker-key", &self.key_path(TRACKER_KEY)]);
                push(&peer);
                "robot_agent"
            }
        };
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let netns = self.robot_netns().filter(|_| part.on_robot());
        let process = if part == Part::Router {
            Process::spawn_from_path_in(netns, binary, &args, &options.log)?
        } else {
            Process::spawn_in(netns, binary, &args, &options.log)?
        };
        self.processes.insert(part, process);
        // Zenoh clients give up when their router is not there yet.
        match part {
            Part::Router => match self.robot_netns() {
                Some(ns) => {
                    wait_until_listening_in(ns, &self.robot_endpoint, Duration::from_secs(20))
                }
                None => wait_until_listening(&self.robot_endpoint, Duration::from_secs(20)),
            },
            Part::Controller => wait_until_listening(&self.endpoint, Duration::from_secs(20)),
            _ => Ok(()),
        }
    }

    /// The path of one of the site's key files ([`COMMAND_KEY`],
    /// [`TRACKER_KEY`]).
    pub fn key_path(&self, name: &str) -> String {
        self.dir.join(name).to_string_lossy().into_owned()
    }

    /// Waits (bounded) until the env is online and the tracker agent reports
    /// tracking, so a first `reset` can navigate.
    pub async fn ready(&self, limit: Duration) -> Result<(), String> {
        let mut config = SessionConfig::connecting(self.site_endpoint());
        config.mode = Mode::Client;
        let session = config.open().await.map_err(|e| e.to_string())?;
        let tracking = session
            .declare_subscriber(self.env.key(Topic::Tracking))
            .await
            .map_err(|e| e.to_string())?;
        let deadline = tokio::time::Instant::now() + limit;
        let tracked = tokio::time::timeout_at(deadline, async {
            while let Ok(sample) = tracking.recv_async().await {
                if codec::decode_payload::<TrackingStatus>(sample.payload())
                    .is_ok_and(|s| s.tracking)
                {
                    return true;
                }
            }
            false
        })
        .await
        .unwrap_or(false);
        if !tracked {
            return Err(format!("{}: no tracking within {limit:?}", self.env));
        }
        let hub = SessionConfig::connecting(&self.endpoint)
            .open()
            .await
            .map_err(|e| e.to_string())?;
        while tokio::time::Instant::now() < deadline {
            let status = client::status(&hub, &self.env, Duration::from_secs(1)).await;
            if status.is_ok_and(|s| !matches!(s.state, EnvState::Offline { .. })) {
                return Ok(());
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        Err(format!("{} stayed offline for {limit:?}", self.env))
    }

    /// Where the site reaches the robot's data: the site's router with an
    /// isolated robot, else the robot's router.
    pub fn site_endpoint(&self) -> &str {
        match &self.site_router {
            Some((_, endpoint)) => endpoint,
            None => &self.robot_endpoint,
        }
    }

    /// The robot's network namespace, with [`Options::isolated_robot`].
    pub fn robot_netns(&self) -> Option<&str> {
        self.robot_netns.as_ref().map(|ns| ns.name.as_str())
    }

    /// Sends a signal (`STOP`, `CONT`, `TERM`, …) to one part.
    pub fn signal(&self, part: Part, signal: &str) {
        if let Some(process) = self.processes.get(&part) {
            process.signal(signal);
        }
    }

    /// Kills one part at once (SIGKILL), like a crash.
    pub fn kill(&mut self, part: Part) {
        drop(self.processes.remove(&part));
    }

    /// Waits (bounded) for a part to exit by itself (after a signal);
    /// returns its exit status.
    pub fn wait_exit(&mut self, part: Part, limit: Duration) -> Option<std::process::ExitStatus> {
        let process = self.processes.get_mut(&part)?;
        let deadline = std::time::Instant::now() + limit;
        while std::time::Instant::now() < deadline {
            if let Ok(Some(status)) = process.0.try_wait() {
                self.processes.remove(&part);
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        None
    }

    /// Sends a signal (`STOP`, `CONT`, …) to the controller process.
    pub fn signal_controller(&self, signal: &str) {
        self.signal(Part::Controller, signal);
    }

    /// Kills the controller process at once (SIGKILL), like a crash.
    pub fn kill_controller(&mut self) {
        self.kill(Part::Controller);
    }
}

impl Drop for EmulatedEnclosure {
    fn drop(&mut self) {
        // The controller first: its vanishing token stops the robot before
        // the robot side goes.
        self.processes.remove(&Part::Controller);
        self.processes.clear();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// The robot agent's settings: without the base guard, the base's own
/// command timeout is what the agent checks before the first motion; the
/// worst-case base (none) is run on the operator's override, so that tests
/// can show what it does.
fn robot_config_toml(options: &Options) -> String {
    let mut toml = format!("require_base_guard = {}\n", options.base_guard);
    if !options.base_guard {
        match options.base_cmd_timeout_ms {
            Some(ms) => toml += &format!("base_cmd_timeout_ms = {ms}\n"),
            None => toml += "skip_base_timeout_check = true\n",
        }
    }
    toml
}

/// The tracker agent's calibration matching the emulator's lighthouse
/// placement (what `tracker_agent calibrate` finds on a real site).
pub fn emulator_calibration_toml() -> String {
    let world_from_tracking = default_world_from_tracking();
    let t = world_from_tracking.translation.vector;
    let q = world_from_tracking.rotation.coords;
    format!(
        "# Written by the emulated deployment: the emulator's lighthouse placement.\n\
         [world_from_tracking]\n\
         translation = [{:.12}, {:.12}, {:.12}]\n\
         rotation = [{:.12}, {:.12}, {:.12}, {:.12}]\n\n\
         [tracker_in_base_link]\n\
         translation = [-0.03, 0.0, 0.14]\n\
         rotation = [0.0, 0.0, 0.0, 1.0]\n",
        t.x, t.y, t.z, q.x, q.y, q.z, q.w
    )
}

fn register_user(db: &str, name: &str, operator: bool) -> std::io::Result<String> {
    let mut args = vec!["--db", db, "users", "add", name];
    if operator {
        args.push("--operator");
    }
    let out = Command::new(binary_dir().join("env_controller"))
        .args(args)
        .env("RUST_LOG", "warn")
        .output()?;
    if !out.status.success() {
        return Err(std::io::Error::other(format!(
            "users add failed: {}",
            String::from_utf8_lossy(&out.stderr)
        )));
    }
    Ok(String::from_utf8_lossy(&out.stdout).trim().to_owned())
}

fn endpoint_addr(endpoint: &str) -> std::io::Result<SocketAddr> {
    endpoint
        .trim_start_matches("tcp/")
        .parse()
        .map_err(|e| std::io::Error::other(format!("{endpoint}: {e}")))
}

/// Waits until something accepts TCP connections at `tcp/HOST:PORT` inside
/// network namespace `netns`.
fn wait_until_listening_in(netns: &str, endpoint: &str, limit: Duration) -> std::io::Result<()> {
    let addr = endpoint_addr(endpoint)?;
    let probe = format!("exec 3<>/dev/tcp/{}/{}", addr.ip(), addr.port());
    let deadline = std::time::Instant::now() + limit;
    loop {
        let connected = Command::new("ip")
            .args(["netns", "exec", netns, "bash", "-c", &probe])
            .stderr(std::process::Stdio::null())
            .status()?
            .success();
        if connected {
            return Ok(());
        }
        if std::time::Instant::now() >= deadline {
            return Err(std::io::Error::other(format!(
                "nothing listens at {endpoint} in {netns} after {limit:?}"
            )));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Waits until something accepts TCP connections at `tcp/HOST:PORT`.
fn wait_until_listening(endpoint: &str, limit: Duration) -> std::io::Result<()> {
    let addr = endpoint_addr(endpoint)?;
    let deadline = std::time::Instant::now() + limit;
    loop {
        if TcpStream::connect_timeout(&addr, Duration::from_millis(200)).is_ok() {
            return Ok(());
        }
        if std::time::Instant::now() >= deadline {
            return Err(std::io::Error::other(format!(
                "nothing listens at {endpoint} after {limit:?}"
            )));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Forwards a line stream from `upstream` to whoever connects, and can be
/// paused: tracker silence (occluded lighthouse) on demand.
pub struct LineProxy {
    addr: SocketAddr,
    paused: Arc<AtomicBool>,
    stop: Arc<AtomicBool>,
}

impl LineProxy {
    /// Listens on a free loopback port.
    pub fn start(upstream: SocketAddr) -> std::io::Result<Self> {
        let listener = TcpListener::bind("127.0.0.1:0")?;
        let addr = listener.local_addr()?;
        let paused = Arc::new(AtomicBool::new(false));
        let stop = Arc::new(AtomicBool::new(false));
        let (p, s) = (paused.clone(), stop.clone());
        std::thread::Builder::new()
            .name("tracker-proxy".into())
            .spawn(move || {
                for downstream in listener.incoming() {
                    if s.load(Ordering::SeqCst) {
                        return;
                    }
                    let Ok(downstream) = downstream else { continue };
                    let (p, s) = (p.clone(), s.clone());
                    std::thread::spawn(move || forward(upstream, downstream, &p, &s));
                }
            })?;
        Ok(Self { addr, paused, stop })
    }

    /// Where tracker agents connect.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Stops (true) or resumes (false) forwarding lines.
    pub fn pause(&self, paused: bool) {
        self.paused.store(paused, Ordering::SeqCst);
    }
}

impl Drop for LineProxy {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        // Wake the acceptor so it sees the flag.
        let _ = TcpStream::connect_timeout(&self.addr, Duration::from_millis(100));
    }
}

fn forward(
    upstream: SocketAddr,
    mut downstream: TcpStream,
    paused: &AtomicBool,
    stop: &AtomicBool,
) {
    // The emulator may still be starting: retry for a while.
    let mut source = None;
    for _ in 0..100 {
        if let Ok(s) = TcpStream::connect(upstream) {
            source = Some(s);
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let Some(source) = source else { return };
    let mut reader = BufReader::new(source);
    let mut line = String::new();
    while !stop.load(Ordering::SeqCst) {
        line.clear();
        match reader.read_line(&mut line) {
            Ok(0) | Err(_) => return,
            Ok(_) => {}
        }
        if paused.load(Ordering::SeqCst) {
            continue;
        }
        if downstream.write_all(line.as_bytes()).is_err() {
            return;
        }
    }
}
