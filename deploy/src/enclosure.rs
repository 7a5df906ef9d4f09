//! The emulated enclosure: the real stack — gym server, robot agent, its
//! base guard, tracker agent — as separate `offworld` processes under a
//! `real/…` namespace, driving `offworld emulate-hardware` as if it were
//! the physical robot and lighthouse tracker. `offworld emulate-enclosure`
//! runs it; the end-to-end tests and the fault matrix start it with their
//! faults around it.
//!
//! The robot computer is laid out as a ROSbot on rmw_zenoh is: a Zenoh
//! router (`zenohd`, as `rmw_zenohd`) for discovery, and the nodes that
//! move the robot — the base driver (the emulator), the robot agent and its
//! independent base guard — as Zenoh peers that talk to each other
//! directly once discovered, so the router's death never cuts the agent
//! or the guard off the base. The tracker agent is a client of the router;
//! the gym server a peer that reaches the robot through it and listens for
//! gym clients.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::Stdio;
use std::time::Duration;

use offworld_client as client;
use offworld_env_controller::{Store, Task};
use offworld_runtime::codec;
use offworld_runtime::msg::{EnvState, TrackingStatus};
use offworld_runtime::seal::SealKey;
use offworld_runtime::session::{free_loopback_port, loopback_endpoint, Mode};
use offworld_runtime::{EnvId, Resolution, SessionConfig, Topic};

use crate::hardware::default_world_from_tracking;
use crate::process::{offworld_command, wait_until_listening, Process};

/// The site's command key file in [`Enclosure::dir`]: the gym server
/// seals with it, the robot agent obeys only what it seals.
pub const COMMAND_KEY: &str = "command.key";
/// The site's tracker key file: the tracker agent seals its poses with it.
pub const TRACKER_KEY: &str = "tracker.key";

/// How long a router or gym server may take to listen.
const LISTEN_LIMIT: Duration = Duration::from_secs(20);

/// What to start.
#[derive(Debug, Clone)]
pub struct Options {
    /// Env served, e.g. `real/monolith-0` (what Python's `…Real-v0` ids use
    /// by default).
    pub env: EnvId,
    /// Task name (`MonolithDiscrete`, `MonolithObstacleContinuous`, …).
    pub task: String,
    /// The task's world (`tasks.toml`).
    world: String,
    /// Robot agent watchdog window, ms.
    pub watchdog_ms: u64,
    /// The emulated base stops after this long without a velocity command
    /// (a base with a command timeout); `None` holds the last velocity
    /// forever — the worst case, the default, what fault tests run against.
    pub base_cmd_timeout_ms: Option<u64>,
    /// Run the robot's base guard (default). Without it the robot agent
    /// is started with `require_base_guard = false` and checks the base's
    /// command timeout before the first motion (skipped, on the operator's
    /// override, for the worst-case base).
    pub base_guard: bool,
    /// Also run a sim twin process for this env (same task), served by the
    /// same gym server: [`Part::Twin`].
    pub twin: Option<EnvId>,
    /// Log filter of the children (default: this process's `RUST_LOG`, else `warn`).
    pub log: String,
    /// The gym server records every episode under this directory
    /// (`serve --record`).
    pub record: Option<PathBuf>,
    /// The emulated "physical" robot behaves per this twin profile
    /// (`offworld emulate-hardware --profile`, `docs/twin-profile.md`).
    pub hardware_profile: Option<PathBuf>,
    /// The emulated camera's resolution; default the world camera's own
    /// (`offworld emulate-hardware --camera-resolution`).
    pub hardware_camera: Option<Resolution>,
    /// Run the robot computer's processes (its router, the hardware, robot
    /// agent, base guard, tracker agent) in this network namespace, made
    /// beforehand (`ip netns add`; needs CAP_NET_ADMIN).
    pub robot_netns: Option<String>,
    /// The site's own router, when the robot computer is elsewhere: the
    /// gym server and a twin connect to it, the robot's router to it.
    pub site_router: Option<SiteRouter>,
}

/// The site's router between the gym server and the robot computer.
#[derive(Debug, Clone)]
pub struct SiteRouter {
    /// Where the gym server (and a twin) connect.
    pub endpoint: String,
    /// Where the robot's router connects to reach it (its side of the link).
    pub robot_uplink: String,
}

impl Options {
    /// `task` (a task of `tasks.toml`) on `real/<world>-0`, the env id
    /// Python's `…Real-v0` ids use by default.
    pub fn new(task: &str) -> anyhow::Result<Self> {
        let world = Task::by_name(task)?.world.name;
        Ok(Self {
            env: EnvId::real(&format!("{world}-0"))?,
            world,
            task: task.to_owned(),
            watchdog_ms: 200,
            base_cmd_timeout_ms: None,
            base_guard: true,
            twin: None,
            log: std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into()),
            record: None,
            hardware_profile: None,
            hardware_camera: None,
            robot_netns: None,
            site_router: None,
        })
    }

    fn world(&self) -> &str {
        &self.world
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
    /// Not a process: the network link between the site (gym server) and
    /// the robot computer, with [`Options::site_router`].
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

    /// The part's name (its component, `router` for zenohd and `hardware`
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

    /// Whether the part runs on the robot computer (in
    /// [`Options::robot_netns`]).
    pub fn on_robot(self) -> bool {
        !matches!(self, Part::Controller | Part::RobotLink | Part::Twin)
    }
}

/// A running emulated enclosure; every process is killed when dropped.
pub struct Enclosure {
    /// The Zenoh endpoint the gym server listens on (gym clients connect here).
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
    /// Scratch directory (database, keys, calibration), removed on drop.
    pub dir: PathBuf,
    /// Where the emulated lighthouse serves its raw line stream.
    pub tracker_listen: String,
    /// Where the tracker agent reads the tracker stream: the emulator's,
    /// unless set (e.g. a proxy in between) before the agent starts.
    pub tracker_source: Option<String>,
    options: Options,
    offworld: PathBuf,
    processes: BTreeMap<Part, Process>,
}

impl Enclosure {
    /// Starts the router, hardware, gym server, tracker agent, base guard
    /// and robot agent (and a twin, if asked for) in that order.
    pub fn start(options: &Options) -> std::io::Result<Self> {
        Self::start_with(options, |_, _| Ok(()))
    }

    /// Like [`Enclosure::start`], calling `after` once each part has
    /// started (e.g. to put something between the hardware and the agents
    /// that read it: [`Enclosure::tracker_source`]).
    pub fn start_with(
        options: &Options,
        mut after: impl FnMut(&mut Self, Part) -> std::io::Result<()>,
    ) -> std::io::Result<Self> {
        let mut enclosure = Self::prepare(options)?;
        for part in Part::ALL {
            enclosure.start_part(part)?;
            after(&mut enclosure, part)?;
            if part == Part::Hardware {
                enclosure.start_part(Part::Twin)?;
                after(&mut enclosure, Part::Twin)?;
            }
        }
        Ok(enclosure)
    }

    /// Everything but the processes: the scratch directory, a database with
    /// a researcher and an operator, the site's keys, the tracker
    /// calibration, free ports. [`Enclosure::start_part`] starts them.
    fn prepare(options: &Options) -> std::io::Result<Self> {
        let dir = std::env::temp_dir().join(format!(
            "offworld-emulated-{}-{}",
            std::process::id(),
            offworld_runtime::keys::random_id()
        ));
        std::fs::create_dir_all(&dir)?;
        let store = Store::open(&dir.join("gym.db")).map_err(std::io::Error::other)?;
        let token = store
            .add_user("researcher", false)
            .map_err(std::io::Error::other)?;
        let operator_token = store
            .add_user("operator", true)
            .map_err(std::io::Error::other)?;
        drop(store);
        std::fs::write(
            dir.join("tracker_calibration.toml"),
            emulator_calibration_toml(),
        )?;
        // The site's keys, as `deploy/certs/generate.sh` issues them.
        for name in [COMMAND_KEY, TRACKER_KEY] {
            SealKey::generate().save(&dir.join(name))?;
        }
        Ok(Self {
            endpoint: loopback_endpoint()?,
            robot_endpoint: loopback_endpoint()?,
            hardware_endpoint: loopback_endpoint()?,
            env: options.env.clone(),
            token,
            operator_token,
            dir,
            tracker_listen: format!("127.0.0.1:{}", free_loopback_port("127.0.0.1")?),
            tracker_source: None,
            options: options.clone(),
            offworld: offworld_command(),
            processes: BTreeMap::new(),
        })
    }

    /// Starts (or restarts) one part with the deployment's settings, and
    /// waits for a router or gym server to listen (Zenoh clients give up
    /// when their router is not there yet).
    pub fn start_part(&mut self, part: Part) -> std::io::Result<()> {
        let Some((program, args)) = self.command(part)? else {
            return Ok(());
        };
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        let netns = self
            .robot_netns()
            .filter(|_| part.on_robot())
            .map(str::to_owned);
        let netns = netns.as_deref();
        let process = Process::start(netns, &program, &args, &self.options.log, Stdio::null())?;
        self.processes.insert(part, process);
        match part {
            Part::Router => wait_until_listening(netns, &self.robot_endpoint, LISTEN_LIMIT),
            Part::Controller => wait_until_listening(None, &self.endpoint, LISTEN_LIMIT),
            _ => Ok(()),
        }
    }

    /// The program and arguments of one part; `None` for a part not run.
    fn command(&self, part: Part) -> std::io::Result<Option<(PathBuf, Vec<String>)>> {
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
        match part {
            Part::Router => {
                push(&["--listen", robot, "--no-multicast-scouting"]);
                if let Some(site) = &options.site_router {
                    push(&["--connect", &site.robot_uplink]);
                }
                return Ok(Some((PathBuf::from("zenohd"), args)));
            }
            Part::Hardware => {
                push(&["emulate-hardware", "--world", options.world()]);
                push(&[
                    "--tracker-listen",
                    &self.tracker_listen,
                    "--overhead-env",
                    &env,
                ]);
                // Half the Astra's rate: the whole site shares one machine.
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
            }
            Part::TrackerAgent => {
                let source = self
                    .tracker_source
                    .clone()
                    .unwrap_or_else(|| format!("tcp://{}", self.tracker_listen));
                let calibration = self.dir.join("tracker_calibration.toml");
                push(&["tracker", "run", "--env", &env, "--source", &source]);
                push(&["--calibration", &calibration.to_string_lossy()]);
                push(&["--tracker-key", &self.key_path(TRACKER_KEY)]);
                push(&["--mode", "client", "--connect", robot]);
            }
            Part::BaseGuard => {
                if !options.base_guard {
                    return Ok(None);
                }
                push(&["guard", "--env", &env]);
                push(&peer);
            }
            Part::RobotLink => return Ok(None),
            Part::Twin => {
                let Some(twin) = &options.twin else {
                    return Ok(None);
                };
                let twin = twin.to_string();
                push(&["twin", "--env", &twin, "--world", options.world()]);
                push(&["--resolution", "84x84"]);
                // A peer others reach directly, as the robot's nodes.
                let site = self.site_endpoint().to_owned();
                push(&["--mode", "peer", "--connect", &site]);
                push(&["--listen", "tcp/127.0.0.1:0"]);
            }
            Part::RobotAgent => {
                let config = self.dir.join("robot.toml");
                std::fs::write(&config, robot_config_toml(options))?;
                push(&["robot", "--env", &env, "--world", options.world()]);
                push(&["--robot-config", &config.to_string_lossy()]);
                push(&["--watchdog-ms", &options.watchdog_ms.to_string()]);
                let latch = self.dir.join("robot_agent.estop");
                push(&["--estop-latch", &latch.to_string_lossy()]);
                push(&["--command-key", &self.key_path(COMMAND_KEY)]);
                push(&["--tracker-key", &self.key_path(TRACKER_KEY)]);
                push(&peer);
            }
        }
        Ok(Some((self.offworld.clone(), args)))
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

    /// Where the site reaches the robot's data: the site's router with a
    /// robot elsewhere, else the robot's router.
    pub fn site_endpoint(&self) -> &str {
        match &self.options.site_router {
            Some(site) => &site.endpoint,
            None => &self.robot_endpoint,
        }
    }

    /// The robot computer's network namespace, with [`Options::robot_netns`].
    pub fn robot_netns(&self) -> Option<&str> {
        self.options.robot_netns.as_deref()
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
        let status = self.processes.get_mut(&part)?.wait_exit(limit)?;
        self.processes.remove(&part);
        Some(status)
    }
}

impl Drop for Enclosure {
    fn drop(&mut self) {
        // The gym server first: its vanishing token stops the robot before
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
/// placement (what `offworld tracker calibrate` finds on a real site).
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
