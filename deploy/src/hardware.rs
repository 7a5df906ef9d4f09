//! The enclosure's hardware emulated by a sim twin: the twin behaving like
//! the hardware instead of like the twin, so the real stack (robot_agent +
//! tracker_agent + env_controller under a `real/…` namespace) runs against
//! it unchanged. The physics crate knows nothing of it.
//!
//! In real time it:
//! - takes `geometry_msgs/Twist` on the robot's velocity topic and either
//!   holds the last velocity until told otherwise (`cmd_timeout: None`: a
//!   base without its own timeout, the worst case every fault test runs
//!   against) or stops when no command came for `cmd_timeout` (a correctly
//!   configured base: ros2_control's `cmd_vel_timeout`); a twist takes
//!   effect the twin profile's `motion.latency_s` after it arrives (the
//!   physics holds it in its time-ordered target queue,
//!   [`RobotPhysics::set_targets`](offworld_sim_twin::physics::RobotPhysics::set_targets));
//! - publishes colour (`rgb8`), depth (`16UC1` mm, like an Astra driver) and
//!   `nav_msgs/Odometry` on the robot's ROS 2 topics, with rmw_zenoh keys
//!   and attachments;
//! - streams raw tracker poses in the tracker's own frame over the tracker
//!   line protocol (a TCP server), through a calibration the controller
//!   never sees;
//! - optionally streams the site's overhead camera view on an env's
//!   `overhead/<camera>` key (a camera streamer at the site would).
//!
//! It declares nothing under `offworld/…`: only the agents speak there.
//!
//! Like separate device drivers, the emulation loop never waits on Zenoh:
//! it hands encoded messages to an output thread through a short queue and
//! drops a frame when that queue is full (a camera driver whose consumer
//! lags does the same), so a congested link to the robot agent cannot
//! stall physics or the tracker stream.

use std::io::Write;
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Quaternion as NaQuaternion, Translation3, UnitQuaternion};
use offworld_runtime::codec;
use offworld_runtime::msg::{PixelEncoding, Time, Twist};
use offworld_runtime::ros2::{RmwPublisherId, RobotTopics, RosGraph, RosType};
use zenoh::bytes::Encoding;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;
use zenoh::session::SessionPutBuilder;
use zenoh::{Session, Wait};

use offworld_runtime::preview::ViewerCopy;
use offworld_sim_twin::overhead::OverheadStream;
use offworld_sim_twin::physics::DT;
use offworld_sim_twin::{ros_out, SimError, SimTwin};

/// How the emulated hardware presents itself.
#[derive(Debug, Clone)]
pub struct HardwareConfig {
    /// The robot's ROS 2 graph (key style, namespace).
    pub ros: RosGraph,
    /// The robot's topic names.
    pub topics: RobotTopics,
    /// Camera frame rate, Hz.
    pub camera_hz: f64,
    /// Wheel odometry rate, Hz.
    pub odom_hz: f64,
    /// Tracker rate, Hz.
    pub tracker_hz: f64,
    /// Where the tracker line server listens (port 0 = any free port).
    pub tracker_listen: SocketAddr,
    /// Device id at the start of every tracker line.
    pub tracker_device: String,
    /// Maps tracking-frame coordinates into the world: the lighthouse
    /// calibration the tracker agent must know and the controller never does.
    pub world_from_tracking: Isometry3<f64>,
    /// Depth encoding published (`16UC1` like an Astra, or `32FC1`).
    pub depth_encoding: PixelEncoding,
    /// Where the site's overhead camera streams (an env's
    /// `overhead/<camera>` key), if anywhere.
    pub overhead_key: Option<String>,
    /// The base stops when no velocity command came for this long; `None`
    /// holds the last velocity forever (the worst case).
    pub cmd_timeout: Option<Duration>,
}

impl HardwareConfig {
    /// A ROSbot on rmw_zenoh (domain 0, root namespace), 30 Hz camera and
    /// odometry, 60 Hz tracker on `listen`, with the default lighthouse
    /// placement [`default_world_from_tracking`].
    pub fn rosbot(listen: SocketAddr) -> Result<Self, SimError> {
        Ok(Self {
            ros: RosGraph::new(Default::default(), "")
                .map_err(|e| SimError::BadCommand(e.to_string()))?,
            topics: RobotTopics::default(),
            camera_hz: 30.0,
            odom_hz: 30.0,
            tracker_hz: 60.0,
            tracker_listen: listen,
            tracker_device: "LHR-EMULATED".into(),
            world_from_tracking: default_world_from_tracking(),
            depth_encoding: PixelEncoding::Depth16UC1,
            overhead_key: None,
            cmd_timeout: None,
        })
    }
}

/// A lighthouse frame the way SteamVR leaves it: origin 2.3 m up in a
/// corner, y up, turned about the vertical — nothing like the world frame.
pub fn default_world_from_tracking() -> Isometry3<f64> {
    let y_up_to_z_up = UnitQuaternion::from_euler_angles(std::f64::consts::FRAC_PI_2, 0.0, 0.0);
    let turned = UnitQuaternion::from_euler_angles(0.0, 0.0, 0.7);
    Isometry3::from_parts(Translation3::new(1.35, -0.92, 2.31), turned * y_up_to_z_up)
}

enum Event {
    Twist(Twist),
    Shutdown,
}

/// A running emulated enclosure; stops when dropped.
pub struct EmulatedHardware {
    events: SyncSender<Event>,
    thread: Option<JoinHandle<()>>,
    output: Option<JoinHandle<()>>,
    tracker_addr: SocketAddr,
    stop_accepting: Arc<AtomicBool>,
    acceptor: Option<JoinHandle<()>>,
    _cmd_vel: Subscriber<()>,
}

impl EmulatedHardware {
    /// Starts emulating `twin` as hardware on `session`.
    pub fn spawn(
        session: &Session,
        twin: SimTwin,
        config: HardwareConfig,
    ) -> Result<Self, SimError> {
        let key = |topic: &str, ty: RosType, publish: bool| {
            let k = if publish {
                config.ros.publication_key(topic, ty)
            } else {
                config.ros.subscription_key(topic, ty)
            };
            k.map_err(|e| SimError::BadCommand(e.to_string()))
        };
        let keys = RosKeys {
            color: key(&config.topics.color, RosType::Image, true)?,
            depth: key(&config.topics.depth, RosType::Image, true)?,
            odom: key(&config.topics.odom, RosType::Odometry, true)?,
        };
        let (tx, rx) = sync_channel::<Event>(64);
        let twist_tx = tx.clone();
        let cmd_vel = session
            .declare_subscriber(key(&config.topics.cmd_vel, RosType::Twist, false)?)
            .callback(move |sample: Sample| {
                match codec::decode_payload::<Twist>(sample.payload()) {
                    Ok(twist) if twist.linear.x.is_finite() && twist.angular.z.is_finite() => {
                        // Newest wins: when the queue is full, drop.
                        let _ = twist_tx.try_send(Event::Twist(twist));
                    }
                    Ok(_) => tracing::warn!("emulated base: ignored a non-finite twist"),
                    Err(e) => tracing::warn!("emulated base: rejected a malformed twist: {e}"),
                }
            })
            .wait()
            .map_err(|e| SimError::Zenoh(e.to_string()))?;

        let listener =
            TcpListener::bind(config.tracker_listen).map_err(|e| SimError::Io(e.to_string()))?;
        let tracker_addr = listener
            .local_addr()
            .map_err(|e| SimError::Io(e.to_string()))?;
        listener
            .set_nonblocking(true)
            .map_err(|e| SimError::Io(e.to_string()))?;
        let clients = Arc::new(Mutex::new(Vec::<TcpStream>::new()));
        let stop_accepting = Arc::new(AtomicBool::new(false));
        let acceptor = {
            let clients = clients.clone();
            let stop = stop_accepting.clone();
            std::thread::Builder::new()
                .name("enclosure/tracker-accept".into())
                .spawn(move || accept_loop(listener, clients, stop))
                .map_err(|e| SimError::Io(e.to_string()))?
        };
        // The ceiling camera, for spectators only: rendered on the emulation's
        // thread while someone watches, put on the output thread. One that
        // cannot be declared is logged and left out.
        let overhead_copy = config.overhead_key.clone().and_then(|key| {
            ViewerCopy::declare_on(session, key)
                .inspect_err(|e| tracing::warn!("no overhead view: {e}"))
                .ok()
        });
        let overhead = overhead_copy.as_ref().map(|copy| {
            OverheadStream::new(twin.scene(), copy.watch(), OverheadStream::DEFAULT_HZ)
        });
        let (out_tx, out_rx) = sync_channel::<Outgoing>(OUTPUT_QUEUE);
        let out = RosOut {
            session: session.clone(),
            overhead: overhead_copy,
            keys,
            color_id: RmwPublisherId::random(),
            depth_id: RmwPublisherId::random(),
            odom_id: RmwPublisherId::random(),
        };
        let output = std::thread::Builder::new()
            .name("enclosure/output".into())
            .spawn(move || out.run(out_rx))
            .map_err(|e| SimError::Io(e.to_string()))?;
        let hardware = Hardware {
            overhead,
            twin,
            config,
            clients,
            depth_scratch: Vec::new(),
            out: out_tx,
            dropped: 0,
        };
        let thread = std::thread::Builder::new()
            .name("enclosure/hardware".into())
            .spawn(move || hardware.run(rx))
            .map_err(|e| SimError::Io(e.to_string()))?;
        tracing::info!(%tracker_addr, "emulated enclosure running");
        Ok(Self {
            events: tx,
            thread: Some(thread),
            output: Some(output),
            tracker_addr,
            stop_accepting,
            acceptor: Some(acceptor),
            _cmd_vel: cmd_vel,
        })
    }

    /// Where the tracker line server listens.
    pub fn tracker_addr(&self) -> SocketAddr {
        self.tracker_addr
    }
}

impl Drop for EmulatedHardware {
    fn drop(&mut self) {
        let _ = self.events.send(Event::Shutdown);
        self.stop_accepting.store(true, Ordering::SeqCst);
        // The hardware thread first: its end closes the output queue.
        for handle in [self.thread.take(), self.output.take(), self.acceptor.take()]
            .into_iter()
            .flatten()
        {
            let _ = handle.join();
        }
    }
}

fn accept_loop(listener: TcpListener, clients: Arc<Mutex<Vec<TcpStream>>>, stop: Arc<AtomicBool>) {
    while !stop.load(Ordering::SeqCst) {
        match listener.accept() {
            Ok((stream, peer)) => {
                tracing::info!(%peer, "tracker client connected");
                // A stalled reader must not stall the emulator.
                let _ = stream.set_write_timeout(Some(Duration::from_millis(50)));
                let _ = stream.set_nodelay(true);
                if let Ok(mut list) = clients.lock() {
                    list.push(stream);
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(20));
            }
            Err(e) => {
                tracing::warn!("tracker accept failed: {e}");
                std::thread::sleep(Duration::from_millis(100));
            }
        }
    }
}

struct RosKeys {
    color: String,
    depth: String,
    odom: String,
}

/// Encoded messages waiting for the output thread: a camera frame pair
/// and a few odometry messages; more means the link lags and we drop.
const OUTPUT_QUEUE: usize = 8;

/// The emulation thread's state.
struct Hardware {
    twin: SimTwin,
    config: HardwareConfig,
    clients: Arc<Mutex<Vec<TcpStream>>>,
    /// Depth bytes converted from the render's metres (reused).
    depth_scratch: Vec<u8>,
    out: SyncSender<Outgoing>,
    /// Messages dropped because the output queue was full.
    dropped: u64,
    overhead: Option<OverheadStream>,
}

/// Encoded messages for the output thread.
enum Outgoing {
    /// A colour and depth image of one exposure: both or neither (the
    /// robot agent pairs them by stamp).
    Camera {
        color: Vec<u8>,
        depth: Vec<u8>,
    },
    Odom(Vec<u8>),
    Overhead(Vec<u8>),
}

/// The emulated drivers' publishers, on the output thread.
struct RosOut {
    session: Session,
    keys: RosKeys,
    overhead: Option<ViewerCopy>,
    color_id: RmwPublisherId,
    depth_id: RmwPublisherId,
    odom_id: RmwPublisherId,
}

/// A periodic deadline that never bursts to catch up.
struct Every {
    period: f64,
    next: f64,
}

impl Every {
    fn new(hz: f64) -> Self {
        Self {
            period: 1.0 / hz.clamp(0.1, 1000.0),
            next: 0.0,
        }
    }

    fn due(&mut self, now: f64) -> bool {
        if now < self.next {
            return false;
        }
        self.next = (self.next + self.period).max(now);
        true
    }
}

impl Hardware {
    fn run(mut self, events: Receiver<Event>) {
        let start = Instant::now();
        let sim_start = self.twin.physics().time();
        let mut camera = Every::new(self.config.camera_hz);
        let mut odom = Every::new(self.config.odom_hz);
        let mut tracker = Every::new(self.config.tracker_hz);
        let mut last_twist = Instant::now();
        let mut moving = false;
        loop {
            let now = start.elapsed().as_secs_f64();
            let next_step = self.twin.physics().time() - sim_start + f64::from(DT);
            let wake = next_step.min(camera.next).min(odom.next).min(tracker.next);
            let wait = Duration::from_secs_f64((wake - now).max(0.0));
            match events.recv_timeout(wait) {
                Ok(Event::Twist(t)) => {
                    last_twist = Instant::now();
                    moving = t.linear.x != 0.0 || t.angular.z != 0.0;
                    self.twin
                        .physics_mut()
                        .set_targets(t.linear.x as f32, t.angular.z as f32);
                }
                Ok(Event::Shutdown) | Err(RecvTimeoutError::Disconnected) => return,
                Err(RecvTimeoutError::Timeout) => {}
            }
            if let Some(timeout) = self.config.cmd_timeout {
                if moving && last_twist.elapsed() > timeout {
                    tracing::warn!(
                        timeout_ms = timeout.as_millis() as u64,
                        "emulated base: command timeout, stopping"
                    );
                    moving = false;
                    self.twin.physics_mut().set_targets(0.0, 0.0);
                }
            }
            let now = start.elapsed().as_secs_f64();
            while self.twin.physics().time() - sim_start + f64::from(DT) <= now {
                self.twin.physics_mut().substep();
            }
            if camera.due(now) {
                self.publish_camera();
            }
            if odom.due(now) {
                let msg = ros_out::odometry(&self.twin, Time::now());
                if let Some(bytes) = encode(&msg) {
                    self.enqueue(Outgoing::Odom(bytes));
                }
            }
            if tracker.due(now) {
                self.stream_tracker(now);
            }
            if let Some(stream) = self.overhead.as_mut().filter(|s| s.watched()) {
                let pose = self.twin.ground_truth();
                if let Some(bytes) = stream.maybe_encode(self.twin.scene(), &pose) {
                    self.enqueue(Outgoing::Overhead(bytes));
                }
            }
        }
    }

    fn publish_camera(&mut self) {
        let stamp = Time::now();
        let frame = self.twin.render();
        let (color, depth) = ros_out::frame_images(
            frame,
            stamp,
            self.config.depth_encoding,
            &mut self.depth_scratch,
        );
        if let (Some(color), Some(depth)) = (encode(&color), encode(&depth)) {
            self.enqueue(Outgoing::Camera { color, depth });
        }
    }

    fn enqueue(&mut self, outgoing: Outgoing) {
        match self.out.try_send(outgoing) {
            Ok(()) | Err(TrySendError::Disconnected(_)) => {}
            Err(TrySendError::Full(_)) => self.count_dropped(),
        }
    }

    fn count_dropped(&mut self) {
        self.dropped += 1;
        // Log at 1, 2, 4, 8, … drops: visible without flooding.
        if self.dropped.is_power_of_two() {
            tracing::warn!(
                dropped = self.dropped,
                "emulated drivers dropped messages: the link to the robot agent lags"
            );
        }
    }

    /// One raw tracker line: the device's pose in the tracking frame.
    fn stream_tracker(&mut self, now: f64) {
        let reading = self.twin.tracker_reading();
        let [x, y, z] = reading.position.map(f64::from);
        let [qx, qy, qz, qw] = reading.orientation.map(f64::from);
        let world_from_base = Isometry3::from_parts(
            Translation3::new(x, y, z),
            UnitQuaternion::from_quaternion(NaQuaternion::new(qw, qx, qy, qz)),
        );
        let [mx, my, mz] = self.twin.scene().world.robot.tracker_offset.map(f64::from);
        let base_from_device = Isometry3::translation(mx, my, mz);
        let device = self.config.world_from_tracking.inverse() * world_from_base * base_from_device;
        let p = device.translation.vector;
        let q = device.rotation.coords; // (x, y, z, w)
        let line = format!(
            "{} {now:.6} {:.6} {:.6} {:.6} {:.7} {:.7} {:.7} {:.7}\n",
            self.config.tracker_device, p.x, p.y, p.z, q.x, q.y, q.z, q.w
        );
        let Ok(mut clients) = self.clients.lock() else {
            return;
        };
        clients.retain_mut(|c| c.write_all(line.as_bytes()).is_ok());
    }
}

impl RosOut {
    /// Publishes what the emulation queues until it stops.
    fn run(self, queue: Receiver<Outgoing>) {
        for outgoing in queue {
            match outgoing {
                Outgoing::Camera { color, depth } => {
                    self.put_ros(&self.keys.color, color, &self.color_id);
                    self.put_ros(&self.keys.depth, depth, &self.depth_id);
                }
                Outgoing::Odom(bytes) => self.put_ros(&self.keys.odom, bytes, &self.odom_id),
                Outgoing::Overhead(bytes) => {
                    if let Some(copy) = &self.overhead {
                        copy.put(bytes.into(), None);
                    }
                }
            }
        }
    }

    /// A put the way an rmw_zenoh publisher makes it (with its attachment).
    fn put_ros(&self, key: &str, bytes: Vec<u8>, id: &RmwPublisherId) {
        let put = self
            .session
            .put(key, bytes)
            .attachment(id.next_attachment().to_bytes().to_vec());
        self.put(put, key);
    }

    fn put(&self, put: SessionPutBuilder<'_, '_>, key: &str) {
        if let Err(e) = put.encoding(Encoding::APPLICATION_CDR).wait() {
            tracing::warn!("put on {key} failed: {e}");
        }
    }
}

/// `msg` in CDR, or logged.
fn encode<T: serde::Serialize>(msg: &T) -> Option<Vec<u8>> {
    codec::encode(msg)
        .map_err(|e| tracing::error!("emulated driver cannot encode: {e}"))
        .ok()
}
