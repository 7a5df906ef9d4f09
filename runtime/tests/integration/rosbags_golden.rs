//! Golden bytes: our CDR must equal what the independent Python codec
//! `rosbags` (ROS 2 Jazzy type store) produces, byte for byte, and our
//! decoder must read rosbags' bytes back. Needs `python3` with `rosbags`
//! (installed by `.ci/setup`); `OFFWORLD_PYTHON` overrides the interpreter.

use crate::common;

use std::io::Write;
use std::process::{Command, Stdio};

use offworld_runtime::codec::{decode, encode};
use offworld_runtime::msg::*;
use serde::{de::DeserializeOwned, Serialize};

fn rosbags_encode(requests: &[(String, serde_json::Value)]) -> Vec<Vec<u8>> {
    let python = std::env::var("OFFWORLD_PYTHON").unwrap_or_else(|_| "python3".into());
    let script = offworld_test_support::package_dir().join("../tests/python/ros_golden.py");
    let mut child = Command::new(&python)
        .arg(script)
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| {
            panic!("cannot run {python}: {e} (install python3 + rosbags: .ci/setup)")
        });
    let mut stdin = child.stdin.take().expect("stdin");
    for (ty, msg) in requests {
        let line = serde_json::json!({ "type": ty, "msg": msg });
        writeln!(stdin, "{line}").expect("write");
    }
    drop(stdin);
    let out = child.wait_with_output().expect("rosbags helper");
    assert!(
        out.status.success(),
        "rosbags helper failed (is `pip install rosbags` done?):\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout)
        .expect("utf8")
        .lines()
        .map(|hex| {
            (0..hex.len())
                .step_by(2)
                .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).expect("hex"))
                .collect()
        })
        .collect()
}

fn check<T: Serialize + DeserializeOwned + PartialEq + std::fmt::Debug>(ty: &str, msgs: &[T]) {
    let requests: Vec<_> = msgs
        .iter()
        .map(|m| (ty.to_owned(), serde_json::to_value(m).expect("json")))
        .collect();
    let golden = rosbags_encode(&requests);
    assert_eq!(
        golden.len(),
        msgs.len(),
        "{ty}: helper answered every message"
    );
    for (msg, theirs) in msgs.iter().zip(golden) {
        let ours = encode(msg).expect("encode");
        assert_eq!(ours, theirs, "{ty}: our bytes differ from rosbags");
        assert_eq!(
            &decode::<T>(&theirs).expect("decode rosbags bytes"),
            msg,
            "{ty}"
        );
    }
}

#[test]
fn twist_matches_rosbags() {
    check(
        "geometry_msgs/msg/Twist",
        &[common::twist(), Twist::default(), Twist::planar(-0.7, 2.5)],
    );
}

#[test]
fn pose_stamped_matches_rosbags() {
    let mut empty_frame = common::pose_stamped();
    empty_frame.header.frame_id.clear();
    check(
        "geometry_msgs/msg/PoseStamped",
        &[common::pose_stamped(), empty_frame],
    );
}

#[test]
fn odometry_matches_rosbags() {
    check(
        "nav_msgs/msg/Odometry",
        &[common::odometry(), Odometry::default()],
    );
}

#[test]
fn image_matches_rosbags() {
    let mut odd = common::image_rgb();
    odd.header.frame_id = "cam".into(); // other alignment offsets
    let big = Image::packed(
        Header::new(Time { sec: 1, nanosec: 2 }, "camera"),
        32,
        24,
        PixelEncoding::Rgb8,
        (0..32 * 24 * 3).map(|i| (i % 251) as u8).collect(),
    );
    // NaN depths are compared bytewise: image data is opaque bytes.
    check(
        "sensor_msgs/msg/Image",
        &[
            common::image_rgb(),
            odd,
            common::image_depth(),
            common::image_depth_mm(),
            big,
        ],
    );
}
