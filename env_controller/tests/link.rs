//! The controller's link to the robot over real Zenoh, with the test
//! playing the robot: a command the robot reports it cannot answer fails
//! with the robot's reason (Unavailable), not with the answer timeout;
//! faults of other commands and malformed faults are ignored; the
//! observation is built from the command's own frame, never a stale one.

use std::time::Duration;

use offworld_env_controller::link::{Answer, LinkTimeouts, ObservationRequest, RobotLink};
use offworld_runtime::keys::{EnvId, Topic};
use offworld_runtime::msg::{
    CameraFrame, Channels, DepthFormat, Header, Image, MotionCommand, MotionFault, ObsOptions,
    PixelEncoding, PoseStamped, SeqTag,
};
use offworld_runtime::session::loopback_pair;
use offworld_runtime::wire::{self, Delivery};
use offworld_runtime::zenoh::sample::Sample;
use offworld_runtime::zenoh::{Session, Wait};
use offworld_runtime::{codec, ErrorCode, WireError};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reported_fault_fails_the_command_with_its_reason() {
    let (link, robot, env) = connect("fault-link").await;

    // The robot: every command gets a malformed fault, a fault of another
    // command, then its own.
    let (fault_session, fault_key) = (robot.clone(), env.key(Topic::Fault));
    let _robot_cmd = robot
        .declare_subscriber(env.key(Topic::Cmd))
        .callback(move |sample: Sample| {
            let Ok(cmd) = codec::decode_payload::<MotionCommand>(sample.payload()) else {
                return;
            };
            let put = |bytes: Vec<u8>| fault_session.put(&fault_key, bytes).wait();
            let fault = |seq| {
                codec::encode(&MotionFault {
                    seq,
                    reason: format!("fault of {seq}"),
                })
                .expect("encode")
            };
            let _ = put(vec![0xde, 0xad]);
            let _ = put(fault(cmd.seq + 1000));
            let _ = put(fault(cmd.seq));
        })
        .await
        .expect("robot's cmd subscriber");

    let (seq, result) = first_heard(&link, 1, 0.1, 0.5).await;
    let Err(err) = result else {
        panic!("command {seq} was answered")
    };
    assert_eq!(err.code, ErrorCode::Unavailable, "{err}");
    assert_eq!(
        err.message,
        format!("the robot cannot answer command {seq}: fault of {seq}")
    );

    // The link keeps serving: the next command fails with its own fault.
    let Err(err) = link.execute(&command(50, 0.1, 0.5), rgbd(2, 2)).await else {
        panic!("command 50 was answered")
    };
    assert_eq!(err.code, ErrorCode::Unavailable);
    assert_eq!(
        err.message,
        "the robot cannot answer command 50: fault of 50"
    );
}

/// A 2×2 frame answering `seq`: every colour byte is `seq`, depth 1 m
/// except one pixel with no return (NaN).
fn frame(seq: u64) -> CameraFrame {
    let depth = [1.0f32, 1.0, f32::NAN, 1.0]
        .iter()
        .flat_map(|d| d.to_le_bytes())
        .collect();
    CameraFrame {
        seq,
        color: Image::packed(
            Header::default(),
            2,
            2,
            PixelEncoding::Rgb8,
            vec![seq as u8; 12],
        ),
        depth: Image::packed(Header::default(), 2, 2, PixelEncoding::Depth32FC1, depth),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_observation_is_built_from_the_commands_own_frame() {
    let (link, robot, env) = connect("obs-link").await;

    // The robot: every command gets a malformed frame, a stale frame (of
    // the command before), then its pose and its own frame.
    let obs = wire::publisher(&robot, env.key(Topic::Obs), Delivery::Every)
        .await
        .expect("obs publisher");
    let pose = wire::publisher(&robot, env.key(Topic::Pose), Delivery::Every)
        .await
        .expect("pose publisher");
    let _robot_cmd = robot
        .declare_subscriber(env.key(Topic::Cmd))
        .callback(move |sample: Sample| {
            let Ok(cmd) = codec::decode_payload::<MotionCommand>(sample.payload()) else {
                return;
            };
            let _ = obs.put(vec![0xde, 0xad]).wait();
            let _ = wire::publish(&obs, &frame(cmd.seq - 1));
            let tag = SeqTag { seq: cmd.seq };
            let _ = wire::publish_tagged(&pose, &PoseStamped::default(), tag);
            let _ = wire::publish(&obs, &frame(cmd.seq));
        })
        .await
        .expect("robot's cmd subscriber");

    let (seq, answer) = first_heard(&link, 10, 0.0, 0.0).await;
    let answer = answer.expect("answered");
    assert_eq!(answer.frame.seq(), seq);
    assert_eq!(answer.pose.seq, Some(seq));
    let c = seq as u8;
    // 1 m of 0–5 m is level 51; no return is 0.
    assert_eq!(
        answer.observation().await.expect("observation").to_bytes(),
        [c, c, c, 51, c, c, c, 51, c, c, c, 0, c, c, c, 51].as_slice()
    );

    // The next command, with other options, gets its own.
    let mut depth_only = rgbd(1, 1);
    depth_only.options.channels = Channels::DepthOnly;
    let answer = link
        .execute(&command(seq + 1, 0.0, 0.0), depth_only)
        .await
        .expect("answered");
    assert_eq!(answer.frame.seq(), seq + 1);
    // Sampled at the source pixel nearest the centre: (1, 1).
    let observation = answer.observation().await.expect("observation");
    assert_eq!(observation.to_bytes(), [51].as_slice());
}

/// A link to env `name` and the session that plays its robot. The answer
/// margin is far beyond the tests: a timeout would be its own error code.
async fn connect(name: &str) -> (RobotLink, Session, EnvId) {
    let (controller, robot) = loopback_pair().await.expect("loopback sessions");
    let env = EnvId::real(name).expect("env id");
    let timeouts = LinkTimeouts {
        answer_margin: Duration::from_secs(60),
        ..LinkTimeouts::default()
    };
    let link = RobotLink::connect(&controller, &env, timeouts)
        .await
        .expect("link");
    (link, robot, env)
}

/// Command `seq`: straight ahead at `linear_x` for `duration_s`.
fn command(seq: u64, linear_x: f64, duration_s: f64) -> MotionCommand {
    MotionCommand {
        seq,
        linear_x,
        angular_z: 0.0,
        duration_s,
    }
}

/// Drives at `linear_x` for `duration_s` as command `first`, `first + 1`,
/// … until the robot hears one: the subscriptions may still be
/// propagating, and a command sent before that goes unanswered, so each
/// attempt is bounded.
async fn first_heard(
    link: &RobotLink,
    first: u64,
    linear_x: f64,
    duration_s: f64,
) -> (u64, Result<Answer, WireError>) {
    for seq in first..first + 5 {
        let cmd = command(seq, linear_x, duration_s);
        let attempt = link.execute(&cmd, rgbd(2, 2));
        if let Ok(result) = tokio::time::timeout(Duration::from_secs(3), attempt).await {
            return (seq, result);
        }
    }
    panic!("no command reached the robot");
}

/// RGBD uint8 observations of `width × height`, depth 0–5 m.
fn rgbd(width: u32, height: u32) -> ObservationRequest {
    ObservationRequest {
        options: ObsOptions {
            channels: Channels::Rgbd,
            height,
            width,
            depth_format: DepthFormat::Uint8,
        },
        depth_max_m: 5.0,
    }
}
