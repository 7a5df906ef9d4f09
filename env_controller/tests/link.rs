//! The controller's link to the robot over real Zenoh, with the test
//! playing the robot: a command the robot reports it cannot answer fails
//! with the robot's reason (Unavailable), not with the answer timeout;
//! faults of other commands and malformed faults are ignored.

use std::time::Duration;

use offworld_env_controller::link::{LinkTimeouts, RobotLink};
use offworld_runtime::keys::{EnvId, Topic};
use offworld_runtime::msg::{MotionCommand, MotionFault};
use offworld_runtime::session::loopback_pair;
use offworld_runtime::zenoh::sample::Sample;
use offworld_runtime::zenoh::Wait;
use offworld_runtime::{codec, ErrorCode};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reported_fault_fails_the_command_with_its_reason() {
    let (controller, robot) = loopback_pair().await.expect("loopback sessions");
    let env = EnvId::real("fault-link").expect("env id");
    // Far beyond the test: a timeout would be its own error code.
    let timeouts = LinkTimeouts {
        answer_margin: Duration::from_secs(60),
        ..LinkTimeouts::default()
    };
    let link = RobotLink::connect(&controller, &env, timeouts)
        .await
        .expect("link");

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

    // The subscriptions may still be propagating: a command sent before
    // the robot hears it goes unanswered, so each attempt is bounded (an
    // answer timeout is impossible within 60 s).
    let command = |seq| MotionCommand {
        seq,
        linear_x: 0.1,
        angular_z: 0.0,
        duration_s: 0.5,
    };
    let mut answered = None;
    for seq in 1..=5u64 {
        let cmd = command(seq);
        let attempt = link.execute(&cmd);
        if let Ok(result) = tokio::time::timeout(Duration::from_secs(3), attempt).await {
            answered = Some((seq, result));
            break;
        }
    }
    let (seq, result) = answered.expect("a command reached the robot");
    let Err(err) = result else {
        panic!("command {seq} was answered")
    };
    assert_eq!(err.code, ErrorCode::Unavailable, "{err}");
    assert_eq!(
        err.message,
        format!("the robot cannot answer command {seq}: fault of {seq}")
    );

    // The link keeps serving: the next command fails with its own fault.
    let Err(err) = link.execute(&command(50)).await else {
        panic!("command 50 was answered")
    };
    assert_eq!(err.code, ErrorCode::Unavailable);
    assert_eq!(
        err.message,
        "the robot cannot answer command 50: fault of 50"
    );
}
