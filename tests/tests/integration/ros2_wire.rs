//! robot_agent against a ROS 2 robot impersonated by independent code:
//! `tests/python/ros2_robot.py` (Python `eclipse-zenoh` + `rosbags`, nothing
//! of ours) listens on the exact rmw_zenoh key of `/cmd_vel` and publishes
//! the ROSbot's camera and odometry topics. Proves our keys, CDR bytes and
//! rmw_zenoh attachments are what a ROS 2 robot speaks.

use std::io::{BufRead, BufReader};
use std::process::{Command, Stdio};
use std::time::Duration;

use offworld_robot_agent::{AgentConfig, Ros2Robot};
use offworld_runtime::codec;
use offworld_runtime::keys::{Component, EnvId, Topic};
use offworld_runtime::msg::{CameraFrame, Heartbeat, MotionCommand, Time};
use offworld_runtime::session::loopback_endpoint;
use offworld_runtime::{wire, SessionConfig};
use serde_json::Value;

const WIDTH: usize = 8;
const HEIGHT: usize = 6;

fn color_pattern(k: usize) -> Vec<u8> {
    (0..WIDTH * HEIGHT * 3)
        .map(|i| ((i * 7 + k) % 256) as u8)
        .collect()
}

fn depth_pattern(k: usize) -> Vec<u8> {
    (0..WIDTH * HEIGHT)
        .flat_map(|i| ((1000 + k + i) as u16).to_le_bytes())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn robot_agent_speaks_ros2_to_an_independent_rmw_zenoh_robot() {
    let endpoint = loopback_endpoint().expect("port");
    let session = SessionConfig::listening(&endpoint)
        .open()
        .await
        .expect("session");
    let script = offworld_test_support::package_dir().join("python/ros2_robot.py");
    let mut robot_py = Command::new("python3")
        .arg(&script)
        .args(["--connect", &endpoint])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("python3 ros2_robot.py (pip install -r tests/requirements.txt)");
    let mut stderr = BufReader::new(robot_py.stderr.take().expect("stderr"));
    let mut line = String::new();
    stderr.read_line(&mut line).expect("robot ready line");
    assert_eq!(line.trim(), "ready", "python robot failed: {line}");

    // The agent, exactly as the binary runs it (default config: rmw_zenoh,
    // domain 0, root namespace, ROSbot topic names).
    let env = EnvId::real("wire-0").expect("env");
    let config = AgentConfig::default();
    let graph = config.graph().expect("graph");
    // The robot's base guard beside it, as on a robot (the agent refuses
    // to move without one).
    let guard =
        offworld_robot_agent::guard::spawn(&session, &env, &graph, &config.topics, config.guard)
            .await
            .expect("base guard");
    let hardware = Ros2Robot::connect(&session, &graph, &config.topics)
        .await
        .expect("ros2 backend");
    let agent = offworld_robot_agent::spawn(&session, env.clone(), config, hardware)
        .await
        .expect("agent");

    // This test plays the controller: liveliness token + heartbeats.
    let _token = session
        .liveliness()
        .declare_token(env.alive_key(Component::Controller))
        .await
        .expect("token");
    let beat_session = session.clone();
    let beat_key = env.key(Topic::Heartbeat);
    let beats = tokio::spawn(async move {
        for counter in 0.. {
            let beat = Heartbeat {
                stamp: Time::now(),
                counter,
            };
            let _ = wire::put(&beat_session, &beat_key, &beat).await;
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    });
    let frames = session
        .declare_subscriber(env.key(Topic::Obs))
        .await
        .expect("obs subscriber");
    tokio::time::sleep(Duration::from_millis(300)).await;

    let cmd = MotionCommand {
        seq: 7,
        linear_x: 0.2,
        angular_z: -0.5,
        duration_s: 0.3,
    };
    wire::put(&session, &env.key(Topic::Cmd), &cmd)
        .await
        .expect("cmd");
    let sent = std::time::SystemTime::now();
    let frame = tokio::time::timeout(Duration::from_secs(5), async {
        loop {
            let sample = frames.recv_async().await.expect("obs");
            let frame: CameraFrame = codec::decode_payload(sample.payload()).expect("frame");
            if frame.seq == 7 {
                return frame;
            }
        }
    })
    .await
    .expect("the agent answered command 7");

    // The frames are the robot's own bytes, captured after the motion ended.
    let k: usize = frame
        .color
        .header
        .frame_id
        .strip_prefix("frame-")
        .and_then(|k| k.parse().ok())
        .expect("frame id frame-<k>");
    assert_eq!(frame.color.encoding, "rgb8");
    assert_eq!((frame.color.width, frame.color.height), (8, 6));
    assert_eq!(frame.color.data, color_pattern(k));
    assert_eq!(frame.depth.encoding, "16UC1");
    let kd: usize = frame.depth.header.frame_id[6..].parse().expect("depth k");
    assert_eq!(frame.depth.data, depth_pattern(kd));
    let motion_end = sent + Duration::from_millis(300);
    let stamp = Duration::new(
        frame.color.header.stamp.sec as u64,
        frame.color.header.stamp.nanosec,
    );
    assert!(
        std::time::UNIX_EPOCH + stamp >= motion_end,
        "the answer was captured after the motion ended"
    );

    // The guard first: it would rightly zero the base when the agent's
    // token goes, from a publisher of its own, and this test checks the
    // agent's stream alone.
    guard.shutdown().await;
    agent.shutdown().await;
    beats.abort();
    drop(robot_py.stdin.take());
    let out = robot_py.wait_with_output().expect("python robot report");
    let report: Value = serde_json::from_slice(&out.stdout).expect("JSON report");
    assert_eq!(report["bad_twists"], 0, "rosbags decoded every Twist");
    let twists = report["twists"].as_array().expect("twists");
    assert!(!twists.is_empty());
    let gid = twists[0]["gid"].as_str().expect("gid").to_owned();
    let mut last_seq = 0;
    for t in twists {
        assert_eq!(t["bytes"], 52, "Twist is 52 CDR bytes");
        assert_eq!(t["attachment_len"], 33);
        assert_eq!(t["gid_len"], 16);
        assert_eq!(t["gid"], gid.as_str(), "one publisher GID");
        let seq = t["seq"].as_i64().expect("seq");
        assert_eq!(seq, last_seq + 1, "rmw sequence numbers count up");
        last_seq = seq;
        assert_eq!(t["linear"][1], 0.0);
        assert_eq!(t["angular"][0], 0.0);
    }
    let commanded = |t: &Value| (t["linear"][0].as_f64(), t["angular"][2].as_f64());
    assert!(
        twists
            .iter()
            .any(|t| commanded(t) == (Some(0.2), Some(-0.5))),
        "the commanded velocity reached the robot"
    );
    let last = twists.last().expect("last twist");
    assert_eq!(commanded(last), (Some(0.0), Some(0.0)), "ends stopped");
}
