//! The tracker agent over real Zenoh sessions on loopback, fed by real
//! sources (a TCP line server, a UDP socket, a replay file), and the
//! `tracker_agent` binary.

use std::io::Write;
use std::net::{SocketAddr, TcpListener};
use std::path::PathBuf;
use std::process::Command;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use offworld_runtime::codec;
use offworld_runtime::msg::{PoseStamped, Time, TrackingStatus};
use offworld_runtime::session::{loopback_endpoint, loopback_pair, SessionConfig};
use offworld_runtime::{Component, EnvId, Topic};
use offworld_tracker_agent::calibration::{rosbot_mount, ReferenceFile, ReferencePoint};
use offworld_tracker_agent::source::{Backoff, LineSource, TcpLineSource, UdpLineSource};
use offworld_tracker_agent::{
    AgentConfig, AgentStats, Calibration, PoseSource, ProtocolErrorKind, SourceError, SourceSpec,
    TrackerAgent, TrackerSample,
};
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;
use zenoh::Session;

const DEVICE: &str = "LHR-0A1B2C3D";

/// A tilted lighthouse frame and the ROSbot mount.
fn calibration() -> Calibration {
    Calibration {
        world_from_tracking: Isometry3::from_parts(
            Translation3::new(1.2, -0.7, 2.4),
            UnitQuaternion::from_euler_angles(0.35, -0.2, 2.1),
        ),
        tracker_in_base_link: rosbot_mount(),
    }
}

fn base_link(x: f64, y: f64, yaw: f64) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(x, y, 0.0),
        UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
    )
}

/// The protocol line a tracker on a robot at `base` would stream.
fn line(device: &str, t: f64, base: &Isometry3<f64>) -> String {
    let cal = calibration();
    let device_pose = cal.world_from_tracking.inverse() * base * cal.tracker_in_base_link;
    let sample = TrackerSample {
        device: Some(device.to_owned()),
        timestamp_s: t,
        pose: device_pose,
    };
    format!("{}\n", sample.to_line())
}

fn temp_path(name: &str) -> PathBuf {
    std::env::temp_dir().join(format!("tracker_agent_test_{}_{name}", std::process::id()))
}

/// A TCP server streaming whatever the test sends it; `None` closes the
/// current connection and accepts the next one.
struct LineServer {
    addr: SocketAddr,
    tx: mpsc::Sender<Option<String>>,
}

impl LineServer {
    fn start() -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
        let addr = listener.local_addr().expect("addr");
        let (tx, rx) = mpsc::channel::<Option<String>>();
        std::thread::spawn(move || {
            'connections: while let Ok((mut stream, _)) = listener.accept() {
                loop {
                    match rx.recv() {
                        Ok(Some(text)) => {
                            if stream.write_all(text.as_bytes()).is_err() {
                                continue 'connections;
                            }
                        }
                        Ok(None) => continue 'connections,
                        Err(_) => return,
                    }
                }
            }
        });
        Self { addr, tx }
    }

    fn send(&self, text: &str) {
        self.tx.send(Some(text.to_owned())).expect("server alive");
    }

    fn reconnect(&self) {
        self.tx.send(None).expect("server alive");
    }
}

type Sub = Subscriber<FifoChannelHandler<Sample>>;

async fn next<T: serde::de::DeserializeOwned>(sub: &Sub, within: Duration) -> Option<T> {
    let sample = tokio::time::timeout(within, sub.recv_async())
        .await
        .ok()?
        .ok()?;
    Some(codec::decode_payload(sample.payload()).expect("decodes"))
}

/// Waits for a status matching `pred`, skipping others.
async fn status_where(
    sub: &Sub,
    within: Duration,
    pred: impl Fn(&TrackingStatus) -> bool,
) -> TrackingStatus {
    let deadline = Instant::now() + within;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let status: TrackingStatus = next(sub, left)
            .await
            .expect("the expected tracking status in time");
        if pred(&status) {
            return status;
        }
    }
}

/// Returns once a put on `from` reaches `to` (declarations made on `to`
/// before this call are then known to `from`).
async fn wait_routed(from: &Session, to: &Session) {
    let probe = to
        .declare_subscriber("offworld/test/probe")
        .await
        .expect("probe subscriber");
    for _ in 0..250 {
        from.put("offworld/test/probe", "ping").await.expect("put");
        if let Ok(Ok(_)) = tokio::time::timeout(Duration::from_millis(20), probe.recv_async()).await
        {
            return;
        }
    }
    panic!("sessions never connected");
}

fn assert_pose_eq(got: &PoseStamped, want: &Isometry3<f64>) {
    let p = &got.pose.position;
    let q = &got.pose.orientation;
    let t = want.translation.vector;
    assert!(
        (p.x - t.x).abs() < 1e-9 && (p.y - t.y).abs() < 1e-9 && (p.z - t.z).abs() < 1e-9,
        "position {p:?} != {t:?}"
    );
    let w = want.rotation.quaternion();
    // q and −q are the same rotation.
    let dot = q.x * w.i + q.y * w.j + q.z * w.k + q.w * w.w;
    assert!((dot.abs() - 1.0).abs() < 1e-9, "orientation {q:?} != {w:?}");
    assert_eq!(got.header.frame_id, "world");
    let age = Time::now().as_secs_f64() - got.header.stamp.as_secs_f64();
    assert!((0.0..5.0).contains(&age), "stamp is the receipt clock");
}

/// An agent's session and a client watching one env's `pose` and
/// `tracking`, routed to each other.
struct Observed {
    agent_session: Session,
    client: Session,
    env: EnvId,
    poses: Subscriber<FifoChannelHandler<Sample>>,
    /// The poses' viewers' copy (`preview_pose`).
    copies: Subscriber<FifoChannelHandler<Sample>>,
    tracking: Subscriber<FifoChannelHandler<Sample>>,
}

async fn observe(env: &str) -> Observed {
    let (agent_session, client) = loopback_pair().await.expect("sessions");
    let env: EnvId = env.parse().expect("env");
    let poses = client
        .declare_subscriber(env.key(Topic::Pose))
        .await
        .expect("pose subscriber");
    let copies = client
        .declare_subscriber(env.key(Topic::PreviewPose))
        .await
        .expect("copy subscriber");
    let tracking = client
        .declare_subscriber(env.key(Topic::Tracking))
        .await
        .expect("tracking subscriber");
    wait_routed(&agent_session, &client).await;
    Observed {
        agent_session,
        client,
        env,
        poses,
        copies,
        tracking,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn agent_publishes_world_poses_skips_bad_lines_and_reports_tracking_loss() {
    tokio::time::timeout(Duration::from_secs(30), async {
        let Observed {
            agent_session,
            client,
            env,
            poses,
            copies,
            tracking,
        } = observe("real/enclosure-t").await;

        let server = LineServer::start();
        let source = TcpLineSource::new(
            server.addr.to_string(),
            Backoff {
                initial: Duration::from_millis(10),
                max: Duration::from_millis(100),
            },
        );
        let config = AgentConfig {
            lost_after: Duration::from_millis(150),
            status_period: Duration::from_millis(200),
            device: Some(DEVICE.to_owned()),
            ..AgentConfig::default()
        };
        let agent = TrackerAgent::spawn(
            &agent_session,
            env.clone(),
            calibration(),
            Box::new(source),
            config,
        )
        .await
        .expect("agent");

        // Before any pose: not tracking, "no pose yet"; the token is up.
        let first = status_where(&tracking, Duration::from_secs(2), |_| true).await;
        assert_eq!(
            (first.tracking, first.reason.as_str()),
            (false, "no pose yet")
        );
        let alive = client
            .liveliness()
            .get(env.alive_key(Component::TrackerAgent))
            .await
            .expect("liveliness get");
        assert!(alive.recv_async().await.is_ok(), "tracker token visible");

        // 10 poses at 100 Hz (0.5 m/s), with a malformed line, another
        // device's pose and a 1 m jump in between.
        let truth: Vec<Isometry3<f64>> = (0..10)
            .map(|i| base_link(0.5 + 0.005 * i as f64, 0.8, 0.3 + 0.01 * i as f64))
            .collect();
        let mut text = String::new();
        for (i, base) in truth.iter().enumerate() {
            text.push_str(&line(DEVICE, 100.0 + 0.01 * i as f64, base));
            if i == 4 {
                text.push_str(&format!("{DEVICE} 100.045 1 2 nope 0 0 0 1\n"));
                text.push_str(&line("LHR-FFFFFFFF", 100.046, &base_link(0.0, 0.0, 0.0)));
                text.push_str(&line(DEVICE, 100.047, &base_link(1.5, 0.8, 0.3)));
            }
        }
        server.send(&text);
        let mut published = Vec::new();
        for (i, want) in truth.iter().enumerate() {
            let got: PoseStamped = next(&poses, Duration::from_secs(3))
                .await
                .unwrap_or_else(|| panic!("pose {i}"));
            assert_pose_eq(&got, want);
            published.push(got);
        }
        let status = status_where(&tracking, Duration::from_secs(2), |s| s.tracking).await;
        assert_eq!(status.reason, "tracking");
        let last_pose_at = Instant::now();

        // Silence: tracking is lost after `lost_after`.
        let lost = status_where(&tracking, Duration::from_secs(2), |s| !s.tracking).await;
        assert!(lost.reason.starts_with("no pose for"), "{}", lost.reason);
        assert!(lost.last_pose_age_s >= 0.15, "{lost:?}");
        assert!(last_pose_at.elapsed() >= Duration::from_millis(100));
        assert!(next::<PoseStamped>(&poses, Duration::from_millis(50))
            .await
            .is_none());

        // Viewers read the same poses from their copy (queued meanwhile), in
        // order; a copy may be dropped (`Latest`: a congested link drops it
        // rather than wait, as a loaded CI host's once did), never altered.
        let mut copied = Vec::new();
        let mut wait = Duration::from_secs(3);
        while let Some(copy) = next::<PoseStamped>(&copies, wait).await {
            copied.push(copy);
            wait = Duration::from_millis(300);
        }
        assert!(!copied.is_empty(), "no copy of the poses");
        let mut rest = published.iter();
        for copy in &copied {
            assert!(
                rest.any(|pose| pose == copy),
                "{copy:?} is not among the poses published, in order"
            );
        }

        // Poses resume (the robot moved 0.2 m during the 1 s gap).
        let resumed: Vec<Isometry3<f64>> = (0..5)
            .map(|i| base_link(0.7 + 0.005 * i as f64, 0.8, 0.4))
            .collect();
        let text: String = resumed
            .iter()
            .enumerate()
            .map(|(i, base)| line(DEVICE, 101.0 + 0.01 * i as f64, base))
            .collect();
        server.send(&text);
        for want in &resumed {
            let got: PoseStamped = next(&poses, Duration::from_secs(3)).await.expect("pose");
            assert_pose_eq(&got, want);
        }
        let back = status_where(&tracking, Duration::from_secs(2), |s| s.tracking).await;
        assert_eq!(back.reason, "tracking");

        let stats = agent.stop().await.expect("clean stop");
        assert_eq!(
            stats,
            AgentStats {
                received: 17,
                published: 15,
                malformed: 1,
                rejected: 1,
                relocks: 0,
                other_device: 1,
                // The silence, and the stop.
                losses: 2,
            }
        );
        let last = status_where(&tracking, Duration::from_secs(2), |s| !s.tracking).await;
        assert_eq!(last.reason, "tracker agent stopped");
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replayed_file_keeps_its_timing_then_tracking_ends() {
    tokio::time::timeout(Duration::from_secs(30), async {
        let Observed {
            agent_session,
            client: _client,
            env,
            poses,
            tracking,
            ..
        } = observe("real/replay-t").await;

        // 6 poses 40 ms apart (unix-time stamps), replayed twice as fast.
        let truth: Vec<Isometry3<f64>> = (0..6)
            .map(|i| base_link(1.0 + 0.01 * i as f64, 0.5, -1.0))
            .collect();
        let mut text = String::from("# recorded by a test\n\n");
        for (i, base) in truth.iter().enumerate() {
            text.push_str(&line(DEVICE, 1_718_000_000.0 + 0.04 * i as f64, base));
            if i == 2 {
                text.push_str("not a pose\n");
            }
        }
        let path = temp_path("replay.txt");
        std::fs::write(&path, text).expect("write replay");
        let spec: SourceSpec = format!("replay:{}?rate=2", path.display())
            .parse()
            .expect("spec");
        let source = spec.open().await.expect("replay opens");
        let started = Instant::now();
        let agent = TrackerAgent::spawn(
            &agent_session,
            env,
            calibration(),
            source,
            AgentConfig::default(),
        )
        .await
        .expect("agent");
        let mut first_at = None;
        for want in &truth {
            let got: PoseStamped = next(&poses, Duration::from_secs(3)).await.expect("pose");
            first_at.get_or_insert_with(Instant::now);
            assert_pose_eq(&got, want);
        }
        let span = first_at.expect("poses").elapsed();
        // 5 gaps of 40 ms at rate 2 = 100 ms.
        assert!(span >= Duration::from_millis(80), "{span:?}");
        assert!(
            started.elapsed() < Duration::from_secs(3),
            "{:?}",
            started.elapsed()
        );
        let ended = status_where(&tracking, Duration::from_secs(2), |s| {
            !s.tracking && s.reason != "no pose yet"
        })
        .await;
        assert_eq!(ended.reason, "pose source ended");
        let stats = agent.join().await.expect("ends by itself");
        assert_eq!((stats.published, stats.malformed), (6, 1));
        let _ = std::fs::remove_file(&path);
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn outliers_lose_tracking_until_the_relock_and_dropping_the_agent_reports_it() {
    tokio::time::timeout(Duration::from_secs(30), async {
        let Observed {
            agent_session,
            client,
            env,
            poses,
            tracking,
            ..
        } = observe("real/relock-t").await;
        let server = LineServer::start();
        let config = AgentConfig {
            lost_after: Duration::from_millis(100),
            ..AgentConfig::default()
        };
        let agent = TrackerAgent::spawn(
            &agent_session,
            env.clone(),
            calibration(),
            Box::new(TcpLineSource::new(
                server.addr.to_string(),
                Backoff::default(),
            )),
            config,
        )
        .await
        .expect("agent");
        let start = base_link(0.5, 0.5, 0.0);
        server.send(&line(DEVICE, 10.0, &start));
        let got: PoseStamped = next(&poses, Duration::from_secs(3)).await.expect("pose");
        assert_pose_eq(&got, &start);
        status_where(&tracking, Duration::from_secs(2), |s| s.tracking).await;

        // Carried 2 m away: every pose is an outlier, streamed in real
        // time at 33 Hz, until 0.5 s of source time has passed.
        let carried = base_link(2.5, 0.5, 0.0);
        for i in 1..=20 {
            server.send(&line(DEVICE, 10.0 + 0.03 * i as f64, &carried));
            tokio::time::sleep(Duration::from_millis(30)).await;
        }
        let lost = status_where(&tracking, Duration::from_secs(2), |s| !s.tracking).await;
        assert!(
            lost.reason
                .starts_with("poses rejected as outliers (implied speed"),
            "{}",
            lost.reason
        );
        // Re-locked at t = 10.54 (first rejection at 10.03, then > 0.5 s).
        let got: PoseStamped = next(&poses, Duration::from_secs(3)).await.expect("relock");
        assert_pose_eq(&got, &carried);
        let back = status_where(&tracking, Duration::from_secs(2), |s| s.tracking).await;
        assert_eq!(back.reason, "tracking");
        let stats = agent.stats();
        assert_eq!((stats.relocks, stats.rejected), (1, 17));

        // Dropping a running agent withdraws its token and says so.
        drop(agent);
        let last = status_where(&tracking, Duration::from_secs(2), |s| !s.tracking).await;
        assert_eq!(last.reason, "tracker agent stopped");
        tokio::time::sleep(Duration::from_millis(200)).await;
        let alive = client
            .liveliness()
            .get(env.alive_key(Component::TrackerAgent))
            .timeout(Duration::from_millis(500))
            .await
            .expect("liveliness get");
        assert!(alive.recv_async().await.is_err(), "token withdrawn");
    })
    .await
    .expect("test finished in time");
}

async fn collect(source: &mut dyn PoseSource, n: usize) -> Vec<Result<f64, SourceError>> {
    let mut out = Vec::new();
    while out.len() < n {
        match tokio::time::timeout(Duration::from_secs(5), source.next()).await {
            Ok(Ok(Some(sample))) => out.push(Ok(sample.timestamp_s)),
            Ok(Ok(None)) => break,
            Ok(Err(e)) => out.push(Err(e)),
            Err(_) => panic!("source stalled after {out:?}"),
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tcp_source_reconnects_after_the_server_drops_it() {
    let server = LineServer::start();
    let mut source = TcpLineSource::new(
        server.addr.to_string(),
        Backoff {
            initial: Duration::from_millis(10),
            max: Duration::from_millis(50),
        },
    );
    assert_eq!(source.describe(), format!("tcp://{}", server.addr));
    // A partial line cut by the disconnect is dropped, not misparsed.
    server.send("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n3 0 0");
    server.reconnect();
    server.send("4 0 0 0 0 0 0 1\n5 0 0 0 0 0 0 1\n");
    let got: Vec<f64> = collect(&mut source, 4)
        .await
        .into_iter()
        .map(|r| r.expect("well-formed"))
        .collect();
    assert_eq!(got, vec![1.0, 2.0, 4.0, 5.0]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn udp_source_reads_lines_from_datagrams() {
    let mut source = UdpLineSource::bind("127.0.0.1:0").await.expect("bind");
    let addr = source.local_addr().expect("bound");
    let sender = std::net::UdpSocket::bind("127.0.0.1:0").expect("sender");
    // The last line of a datagram needs no newline.
    sender
        .send_to(b"1 0 0 0 0 0 0 1\nLHR-1 2 0 0 0 0 0 0 1", addr)
        .expect("send");
    sender
        .send_to(b"oops\n3 0 0 0 0 0 0 1\n", addr)
        .expect("send");
    let got = collect(&mut source, 4).await;
    assert_eq!(got.len(), 4);
    assert_eq!(got[0].as_ref().ok(), Some(&1.0));
    assert_eq!(got[1].as_ref().ok(), Some(&2.0));
    match &got[2] {
        Err(SourceError::Malformed(e)) => {
            assert_eq!(e.line, 3);
            assert_eq!(e.kind, ProtocolErrorKind::TokenCount { found: 1 });
        }
        other => panic!("expected a malformed line, got {other:?}"),
    }
    assert_eq!(got[3].as_ref().ok(), Some(&3.0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn line_source_ends_at_end_of_stream() {
    let mut source = LineSource::new(&b"1 0 0 0 0 0 0 1\n# c\n2 0 0 0 0 0 0 1"[..], "memory");
    let got: Vec<f64> = collect(&mut source, 10)
        .await
        .into_iter()
        .map(|r| r.expect("well-formed"))
        .collect();
    assert_eq!(got, vec![1.0, 2.0]);
    assert!(matches!(source.next().await, Ok(None)));
    // A missing replay file is a fatal, typed error.
    let missing = "replay:/nonexistent/recording.txt"
        .parse::<SourceSpec>()
        .expect("spec")
        .open()
        .await;
    assert!(matches!(missing, Err(SourceError::Io { .. })));
}

fn samples_file(points: usize) -> ReferenceFile {
    let cal = calibration();
    let marks = [
        (0.0, 0.0, 0.0),
        (2.5, 0.0, 1.0),
        (2.5, 2.0, 2.0),
        (0.0, 2.0, -1.5),
    ];
    ReferenceFile {
        point: marks[..points]
            .iter()
            .map(|&(x, y, yaw)| {
                let device = cal.world_from_tracking.inverse()
                    * base_link(x, y, yaw)
                    * cal.tracker_in_base_link;
                let t = device.translation.vector;
                let q = device.rotation.quaternion();
                ReferencePoint {
                    name: None,
                    world: [x, y, 0.0],
                    device_translation: Some([t.x, t.y, t.z]),
                    device_rotation: Some([q.i, q.j, q.k, q.w]),
                }
            })
            .collect(),
    }
}

#[test]
fn calibrate_command_writes_the_solved_config() {
    let samples = temp_path("samples.toml");
    let out = temp_path("calibration.toml");
    samples_file(4).save(&samples).expect("write samples");
    let run = Command::new(env!("CARGO_BIN_EXE_tracker_agent"))
        .args(["calibrate", "--samples"])
        .arg(&samples)
        .arg("--out")
        .arg(&out)
        .arg("--mount=-0.03,0,0.14")
        .output()
        .expect("runs");
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(stderr.contains("RMS residual 0.0 mm"), "{stderr}");
    let written = Calibration::load(&out).expect("valid config");
    let truth = calibration();
    let error = written.world_from_tracking.inverse() * truth.world_from_tracking;
    assert!(error.translation.vector.norm() < 1e-9);
    assert!(error.rotation.angle() < 1e-9);
    assert_eq!(written.tracker_in_base_link, rosbot_mount());

    // Two points: a typed error, reported, and no file written.
    let _ = std::fs::remove_file(&out);
    samples_file(2).save(&samples).expect("write samples");
    let run = Command::new(env!("CARGO_BIN_EXE_tracker_agent"))
        .args(["calibrate", "--samples"])
        .arg(&samples)
        .arg("--out")
        .arg(&out)
        .output()
        .expect("runs");
    assert!(!run.status.success());
    assert!(
        String::from_utf8_lossy(&run.stderr).contains("at least 3 reference points"),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    assert!(!out.exists());
    let _ = std::fs::remove_file(&samples);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn run_command_publishes_a_replay_and_exits() {
    let endpoint = loopback_endpoint().expect("port");
    let client = SessionConfig::listening(&endpoint)
        .open()
        .await
        .expect("session");
    let env: EnvId = "real/cli-t".parse().expect("env");
    let poses = client
        .declare_subscriber(env.key(Topic::Pose))
        .await
        .expect("pose subscriber");

    let calibration_path = temp_path("cli_calibration.toml");
    calibration()
        .save(&calibration_path, "test")
        .expect("write calibration");
    // 1.5 s of poses at 20 Hz: the binary connects within the first ones.
    let replay = temp_path("cli_replay.txt");
    let text: String = (0..30)
        .map(|i| {
            line(
                DEVICE,
                0.05 * i as f64,
                &base_link(0.01 * i as f64, 0.0, 0.0),
            )
        })
        .collect();
    std::fs::write(&replay, text).expect("write replay");
    let mut child = Command::new(env!("CARGO_BIN_EXE_tracker_agent"))
        .args(["run", "--env", "real/cli-t", "--source"])
        .arg(format!("replay:{}", replay.display()))
        .arg("--calibration")
        .arg(&calibration_path)
        .args(["--connect", &endpoint])
        .stdout(std::process::Stdio::null())
        .spawn()
        .expect("spawns");
    let deadline = Instant::now() + Duration::from_secs(20);
    let status = loop {
        if let Some(status) = child.try_wait().expect("child status") {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("tracker_agent run did not exit when the replay ended");
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert!(status.success());
    let mut received = 0;
    while let Ok(Some(sample)) = poses.try_recv() {
        let pose: PoseStamped = codec::decode_payload(sample.payload()).expect("pose");
        assert_eq!(pose.header.frame_id, "world");
        received += 1;
    }
    assert!((5..=30).contains(&received), "{received} poses");
    let _ = std::fs::remove_file(&replay);
    let _ = std::fs::remove_file(&calibration_path);
}

/// A stand-in for libsurvive's `pysurvive` module with the same surface
/// the adapter uses (SimpleContext, Running, NextUpdated, Name, Pose,
/// simple_object_get_type, simple_serial_number).
const FAKE_PYSURVIVE: &str = r#"
import sys
SurviveSimpleObject_LIGHTHOUSE = 1
SurviveSimpleObject_OBJECT = 2

class _Pose:
    def __init__(self, pos, rot):
        self.Pos = pos
        self.Rot = rot  # w, x, y, z like libsurvive

class _Obj:
    def __init__(self, ptr, name, serial, kind):
        self.ptr, self.name, self.serial, self.kind = ptr, name, serial, kind
        self.current = (_Pose([0, 0, 0], [1, 0, 0, 0]), 0.0)
    def Name(self):
        return self.name.encode()
    def Pose(self):
        return self.current

_objs = [_Obj(0, "LH0", "LHB-00000001", 1), _Obj(1, "T20", "LHR-1A2B3C4D", 2), _Obj(2, "T21", "", 2)]

def simple_object_get_type(ptr):
    return _objs[ptr].kind

def simple_serial_number(ptr):
    return _objs[ptr].serial.encode()

class SimpleContext:
    def __init__(self, args):
        if any(a.startswith("--only") or a == "--unix-time" for a in args):
            raise SystemExit("adapter options leaked to libsurvive: %r" % args)
        lh, t20, t21 = _objs
        self.updates = [
            (lh, _Pose([0.1, 2.0, 0.3], [1, 0, 0, 0]), 1.0),
            (t20, _Pose([9, 9, 9], [1, 0, 0, 0]), 0.0),
            (t20, _Pose([1.25, -0.5, 0.75], [0.9238795, 0, 0, 0.3826834]), 1.5),
            (t20, _Pose([1.25, -0.5, 0.75], [0.9238795, 0, 0, 0.3826834]), 1.5),
            None,
            (t20, _Pose([1.26, -0.5, 0.75], [0.9238795, 0, 0, 0.3826834]), 1.51),
            (t21, _Pose([0.0, 1.0, 2.0], [0.0, 1.0, 0.0, 0.0]), 2.0),
        ]
    def Running(self):
        return bool(self.updates)
    def NextUpdated(self):
        update = self.updates.pop(0)
        if update is None:
            return None
        obj, pose, t = update
        obj.current = (pose, t)
        return obj
"#;

fn run_adapter(extra: &[&str]) -> Vec<TrackerSample> {
    let dir = temp_path("fake_pysurvive");
    std::fs::create_dir_all(&dir).expect("temp dir");
    std::fs::write(dir.join("pysurvive.py"), FAKE_PYSURVIVE).expect("fake module");
    let script = offworld_test_support::package_dir().join("scripts/pysurvive_source.py");
    let out = Command::new("python3")
        .arg(script)
        .args(extra)
        .env("PYTHONPATH", &dir)
        .output()
        .expect("python3 runs (install python3)");
    let _ = std::fs::remove_dir_all(&dir);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout)
        .expect("UTF-8")
        .lines()
        .enumerate()
        .map(|(i, l)| {
            offworld_tracker_agent::parse_line(l, i as u64 + 1)
                .expect("a protocol line")
                .expect("not blank")
        })
        .collect()
}

#[test]
fn pysurvive_adapter_prints_protocol_lines() {
    let samples = run_adapter(&["--v", "10"]);
    let summary: Vec<(Option<&str>, f64, [f64; 3])> = samples
        .iter()
        .map(|s| {
            let t = s.pose.translation.vector;
            (s.device.as_deref(), s.timestamp_s, [t.x, t.y, t.z])
        })
        .collect();
    // Lighthouse, no-pose-yet and repeated updates are skipped; a device
    // without a serial number is named.
    assert_eq!(
        summary,
        vec![
            (Some("LHR-1A2B3C4D"), 1.5, [1.25, -0.5, 0.75]),
            (Some("LHR-1A2B3C4D"), 1.51, [1.26, -0.5, 0.75]),
            (Some("T21"), 2.0, [0.0, 1.0, 2.0]),
        ]
    );
    // libsurvive's (w, x, y, z) becomes the protocol's x y z w.
    let q = samples[0].pose.rotation.quaternion();
    assert!((q.w - 0.9238795).abs() < 1e-6 && (q.k - 0.3826834).abs() < 1e-6);
    let q = samples[2].pose.rotation.quaternion();
    assert!((q.i - 1.0).abs() < 1e-9 && q.w.abs() < 1e-9);

    let only = run_adapter(&["--only", "T21"]);
    assert_eq!(only.len(), 1);
    assert_eq!(only[0].device.as_deref(), Some("T21"));
}

#[test]
fn live_calibration_prompts_averages_and_writes_the_config() {
    let reference = temp_path("live_reference.toml");
    let out = temp_path("live_calibration.toml");
    let measured = temp_path("live_samples.toml");
    let marks = samples_file(4);
    let plain = ReferenceFile {
        point: marks
            .point
            .iter()
            .map(|p| ReferencePoint {
                device_translation: None,
                device_rotation: None,
                ..p.clone()
            })
            .collect(),
    };
    plain.save(&reference).expect("write reference");

    // The tracker streams the device pose of whichever mark the robot is
    // at, 100 Hz.
    let server = LineServer::start();
    let at_mark = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(usize::MAX));
    let streaming = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    {
        let (at_mark, streaming) = (at_mark.clone(), streaming.clone());
        let tx = server.tx.clone();
        let points = marks.point.clone();
        std::thread::spawn(move || {
            let mut t = 0.0;
            while streaming.load(std::sync::atomic::Ordering::SeqCst) {
                let i = at_mark.load(std::sync::atomic::Ordering::SeqCst);
                if let Some(p) = points.get(i) {
                    let (Some(tr), Some(q)) = (p.device_translation, p.device_rotation) else {
                        return;
                    };
                    let sample = TrackerSample::new(
                        Some(DEVICE),
                        t,
                        tr,
                        UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
                            q[3], q[0], q[1], q[2],
                        )),
                    );
                    if tx.send(Some(format!("{}\n", sample.to_line()))).is_err() {
                        return;
                    }
                }
                t += 0.01;
                std::thread::sleep(Duration::from_millis(10));
            }
        });
    }

    let mut child = Command::new(env!("CARGO_BIN_EXE_tracker_agent"))
        .args(["calibrate", "--reference"])
        .arg(&reference)
        .arg("--source")
        .arg(format!("tcp://{}", server.addr))
        .arg("--out")
        .arg(&out)
        .arg("--save-samples")
        .arg(&measured)
        .args(["--average", "0.2"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("spawns");
    let mut stdin = child.stdin.take().expect("stdin");
    let stderr = child.stderr.take().expect("stderr");
    let (line_tx, lines) = mpsc::channel::<String>();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            if line_tx.send(line).is_err() {
                return;
            }
        }
    });
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut transcript = Vec::new();
    let mut prompts = 0;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match lines.recv_timeout(left) {
            Ok(line) => {
                if let Some(rest) = line.strip_prefix("place the robot at point ") {
                    let n: usize = rest
                        .split_whitespace()
                        .next()
                        .and_then(|n| n.parse().ok())
                        .expect("point number");
                    at_mark.store(n - 1, std::sync::atomic::Ordering::SeqCst);
                    // Let the previous mark's poses drain, then press Enter.
                    std::thread::sleep(Duration::from_millis(100));
                    stdin.write_all(b"\n").expect("enter");
                    prompts += 1;
                }
                transcript.push(line);
            }
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
            Err(mpsc::RecvTimeoutError::Timeout) => {
                let _ = child.kill();
                panic!("calibrate stalled:\n{}", transcript.join("\n"));
            }
        }
    }
    streaming.store(false, std::sync::atomic::Ordering::SeqCst);
    let status = child.wait().expect("exit status");
    assert!(status.success(), "{}", transcript.join("\n"));
    assert_eq!(prompts, 4, "{}", transcript.join("\n"));

    let written = Calibration::load(&out).expect("valid config");
    let error = written.world_from_tracking.inverse() * calibration().world_from_tracking;
    assert!(error.translation.vector.norm() < 1e-9, "{error:?}");
    assert!(error.rotation.angle() < 1e-9);
    // The measured poses were saved for an offline re-run.
    let saved = ReferenceFile::load(&measured).expect("samples file");
    assert_eq!(saved.point.len(), 4);
    for (got, want) in saved.point.iter().zip(&marks.point) {
        let (Some(a), Some(b)) = (got.device_translation, want.device_translation) else {
            panic!("device poses saved");
        };
        assert!(a.iter().zip(b).all(|(x, y)| (x - y).abs() < 1e-9));
    }
    for path in [&reference, &out, &measured] {
        let _ = std::fs::remove_file(path);
    }
}
