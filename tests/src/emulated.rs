//! The emulated enclosure with faults around it: the deployment of
//! [`offworld_deploy::enclosure`] (what `offworld emulate-enclosure` runs),
//! plus what only tests do to it — the robot computer isolated behind a
//! link a test can cut, delay or make lossy, and a tracker stream it can
//! pause. Used by the end-to-end tests and the fault matrix.

use std::io::{BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::ops::{Deref, DerefMut};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

pub use offworld_deploy::enclosure::{
    emulator_calibration_toml, Enclosure, Part, SiteRouter, COMMAND_KEY, TRACKER_KEY,
};
use offworld_deploy::process::{endpoint_addr, wait_until_listening};
use offworld_runtime::session::loopback_endpoint;

use crate::link::ImpairedLink;
use crate::netns::RobotNamespace;
use crate::{Process, Spawn};

/// What to start: the deployment's options (through `Deref`) and the
/// faults a test may inject.
#[derive(Debug, Clone)]
pub struct Options {
    /// The deployment itself.
    pub deployment: offworld_deploy::enclosure::Options,
    /// Route the tracker stream through a [`LineProxy`] the caller can pause
    /// (tracker silence).
    pub pausable_tracker: bool,
    /// Run the robot computer (its router, the hardware, robot agent, base
    /// guard and tracker agent) in a network namespace of its own, which
    /// the controller reaches only through [`EmulatedEnclosure::robot_link`]:
    /// a link a test can cut, delay or make lossy. Needs CAP_NET_ADMIN.
    pub isolated_robot: bool,
}

impl Options {
    /// `task` on `real/<world>-0`, no faults.
    pub fn new(task: &str) -> anyhow::Result<Self> {
        Ok(Self {
            deployment: offworld_deploy::enclosure::Options::new(task)?,
            pausable_tracker: false,
            isolated_robot: false,
        })
    }
}

impl Deref for Options {
    type Target = offworld_deploy::enclosure::Options;
    fn deref(&self) -> &Self::Target {
        &self.deployment
    }
}

impl DerefMut for Options {
    fn deref_mut(&mut self) -> &mut Self::Target {
        &mut self.deployment
    }
}

/// A running emulated enclosure (its fields and methods through `Deref`)
/// and the fault injectors around it; everything stops when dropped.
pub struct EmulatedEnclosure {
    /// Declared first: the deployment's processes stop before the link,
    /// the site router and the namespace go.
    enclosure: Enclosure,
    /// The tracker stream proxy, when requested.
    pub tracker_proxy: Option<LineProxy>,
    /// The link between the site's router and the robot's, with
    /// [`Options::isolated_robot`].
    pub robot_link: Option<ImpairedLink>,
    /// The site's router, with [`Options::isolated_robot`]: held to run
    /// until the deployment drops.
    _site_router: Option<Process>,
    /// Declared last: the namespace is removed after the processes stopped.
    _robot_netns: Option<RobotNamespace>,
}

impl EmulatedEnclosure {
    /// Starts the deployment with the faults asked for.
    pub fn start(options: &Options) -> std::io::Result<Self> {
        if options.isolated_robot && options.pausable_tracker {
            return Err(std::io::Error::other(
                "a pausable tracker needs the tracker stream on this host: not with an isolated robot",
            ));
        }
        let mut deployment = options.deployment.clone();
        let robot_netns = if options.isolated_robot {
            Some(RobotNamespace::create().map_err(|e| {
                std::io::Error::other(format!("the robot's network namespace: {e:#}"))
            })?)
        } else {
            None
        };
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
                wait_until_listening(None, &endpoint, Duration::from_secs(20))?;
                let host_ip = ns.host_ip.parse().map_err(std::io::Error::other)?;
                let upstream = endpoint_addr(&endpoint)?;
                let seed = std::process::id().into();
                let link = ImpairedLink::start(host_ip, upstream, seed)?;
                deployment.robot_netns = Some(ns.name.clone());
                deployment.site_router = Some(SiteRouter {
                    endpoint,
                    robot_uplink: link.endpoint(),
                });
                (Some(router), Some(link))
            }
            None => (None, None),
        };
        let mut tracker_proxy = None;
        let enclosure = Enclosure::start_with(&deployment, |enclosure, part| {
            if part == Part::Hardware && options.pausable_tracker {
                let addr: SocketAddr = enclosure
                    .tracker_listen
                    .parse()
                    .map_err(|e| std::io::Error::other(format!("{e}")))?;
                let proxy = LineProxy::start(addr)?;
                enclosure.tracker_source = Some(format!("tcp://{}", proxy.addr()));
                tracker_proxy = Some(proxy);
            }
            Ok(())
        })?;
        Ok(Self {
            enclosure,
            tracker_proxy,
            robot_link,
            _site_router: site_router,
            _robot_netns: robot_netns,
        })
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

impl Deref for EmulatedEnclosure {
    type Target = Enclosure;
    fn deref(&self) -> &Enclosure {
        &self.enclosure
    }
}

impl DerefMut for EmulatedEnclosure {
    fn deref_mut(&mut self) -> &mut Enclosure {
        &mut self.enclosure
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
