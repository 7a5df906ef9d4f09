//! The emulated enclosure deployment: the real stack (env_controller,
//! robot_agent, tracker_agent) as separate processes under a `real/…`
//! namespace, driving `sim_twin --emulate-hardware` as if it were the
//! physical robot and lighthouse tracker. Used by the launcher binary
//! `emulated_enclosure` and by the end-to-end tests.

use std::io::{BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::path::PathBuf;
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use offworld_runtime::client;
use offworld_runtime::codec;
use offworld_runtime::msg::{EnvState, TrackingStatus};
use offworld_runtime::session::{loopback_endpoint, Mode};
use offworld_runtime::{EnvId, SessionConfig, Topic};
use offworld_sim_twin::enclosure::default_world_from_tracking;

use crate::{binary_dir, Process};

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
    /// Log filter of the children (default: this process's `RUST_LOG`, else `warn`).
    pub log: String,
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
            log: std::env::var("RUST_LOG").unwrap_or_else(|_| "warn".into()),
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

/// A running emulated deployment; every process is killed when dropped.
pub struct EmulatedEnclosure {
    /// The Zenoh endpoint the controller listens on (gym clients connect here).
    pub endpoint: String,
    /// The robot computer's Zenoh router (the ROS 2 side: `cmd_vel`,
    /// camera, odometry; the agents are its clients).
    pub robot_endpoint: String,
    /// The env served.
    pub env: EnvId,
    /// An access token of a registered user.
    pub token: String,
    /// Scratch directory (database, calibration).
    pub dir: PathBuf,
    /// The tracker stream proxy, when requested.
    pub tracker_proxy: Option<LineProxy>,
    controller: Option<Process>,
    others: Vec<Process>,
}

impl EmulatedEnclosure {
    /// Starts controller, emulator, tracker agent and robot agent.
    pub fn start(options: &Options) -> std::io::Result<Self> {
        let dir = std::env::temp_dir().join(format!(
            "offworld-emulated-{}-{}",
            std::process::id(),
            offworld_runtime::client::random_id()
        ));
        std::fs::create_dir_all(&dir)?;
        let db = dir.join("gym.db");
        let db_arg = db.to_string_lossy().into_owned();
        let token = register_user(&db_arg, "researcher")?;
        let endpoint = loopback_endpoint()?;
        let robot_endpoint = loopback_endpoint()?;
        let env = options.env.to_string();
        let spawn = |binary: &str, args: &[&str]| Process::spawn_logged(binary, args, &options.log);
        // The robot's computer: on a real ROSbot, rmw_zenoh's router runs
        // there and the ROS nodes and robot_agent are its clients, so the
        // agent always reaches the motors, whatever happens to the
        // controller or the site network.
        let tracker_listen = format!("127.0.0.1:{}", free_port()?);
        let emulator = spawn(
            "sim_twin",
            &[
                "--emulate-hardware",
                "--world",
                options.world(),
                "--tracker-listen",
                &tracker_listen,
                "--overhead-env",
                &env,
                // Half the Astra's rate: the whole site shares 2 cores here.
                "--camera-hz",
                "15",
                "--mode",
                "router",
                "--listen",
                &robot_endpoint,
            ],
        )?;
        // Zenoh clients give up when their router is not there yet.
        wait_until_listening(&robot_endpoint, Duration::from_secs(20))?;
        let controller = spawn(
            "env_controller",
            &[
                "--db",
                &db_arg,
                "serve",
                "--env",
                &format!("{env}={}", options.task),
                "--listen",
                &endpoint,
                "--connect",
                &robot_endpoint,
            ],
        )?;
        wait_until_listening(&endpoint, Duration::from_secs(20))?;
        let tracker_addr: SocketAddr = tracker_listen
            .parse()
            .map_err(|e| std::io::Error::other(format!("{e}")))?;
        let tracker_proxy = if options.pausable_tracker {
            Some(LineProxy::start(tracker_addr)?)
        } else {
            None
        };
        let source = match &tracker_proxy {
            Some(proxy) => format!("tcp://{}", proxy.addr()),
            None => format!("tcp://{tracker_listen}"),
        };
        let calibration = dir.join("tracker_calibration.toml");
        std::fs::write(&calibration, emulator_calibration_toml())?;
        let tracker = spawn(
            "tracker_agent",
            &[
                "run",
                "--env",
                &env,
                "--source",
                &source,
                "--calibration",
                &calibration.to_string_lossy(),
                // A Zenoh client of the robot's router.
                "--mode",
                "client",
                "--connect",
                &robot_endpoint,
            ],
        )?;
        let robot = spawn(
            "robot_agent",
            &[
                "--env",
                &env,
                "--world",
                options.world(),
                "--watchdog-ms",
                &options.watchdog_ms.to_string(),
                "--estop-latch",
                &dir.join("robot_agent.estop").to_string_lossy(),
                // A Zenoh client of the robot's router.
                "--mode",
                "client",
                "--connect",
                &robot_endpoint,
            ],
        )?;
        Ok(Self {
            endpoint,
            robot_endpoint,
            env: options.env.clone(),
            token,
            dir,
            tracker_proxy,
            controller: Some(controller),
            others: vec![emulator, tracker, robot],
        })
    }

    /// Waits (bounded) until the env is online and the tracker agent reports
    /// tracking, so a first `reset` can navigate.
    pub async fn ready(&self, limit: Duration) -> Result<(), String> {
        let mut config = SessionConfig::connecting(&self.robot_endpoint);
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

    /// Sends a signal (`STOP`, `CONT`, …) to the controller process.
    pub fn signal_controller(&self, signal: &str) {
        if let Some(controller) = &self.controller {
            let pid = controller.0.id().to_string();
            let _ = Command::new("kill")
                .args([format!("-{signal}"), pid])
                .status();
        }
    }

    /// Kills the controller process at once (SIGKILL), like a crash.
    pub fn kill_controller(&mut self) {
        drop(self.controller.take());
    }
}

impl Drop for EmulatedEnclosure {
    fn drop(&mut self) {
        self.controller.take();
        self.others.clear();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
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

fn register_user(db: &str, name: &str) -> std::io::Result<String> {
    let out = Command::new(binary_dir().join("env_controller"))
        .args(["--db", db, "users", "add", name])
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

/// Waits until something accepts TCP connections at `tcp/HOST:PORT`.
fn wait_until_listening(endpoint: &str, limit: Duration) -> std::io::Result<()> {
    let addr: SocketAddr = endpoint
        .trim_start_matches("tcp/")
        .parse()
        .map_err(|e| std::io::Error::other(format!("{endpoint}: {e}")))?;
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

fn free_port() -> std::io::Result<u16> {
    Ok(TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
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
