//! The operator's e-stops over real Zenoh: pressed and released from the
//! library and from the `env_controller estop` CLI, heard by a robot's
//! subscription byte for byte; a press with no robot or twin present is a
//! typed error.

use std::time::Duration;

use offworld_env_controller::operator::{press_estop, EStopScope};
use offworld_env_controller::ControllerError;
use offworld_runtime::keys::{global_estop_key, Component, EnvId, Topic};
use offworld_runtime::msg::EStop;
use offworld_runtime::session::{loopback_endpoint, loopback_pair, SessionConfig};
use offworld_runtime::zenoh::handlers::FifoChannelHandler;
use offworld_runtime::zenoh::liveliness::LivelinessToken;
use offworld_runtime::zenoh::pubsub::Subscriber;
use offworld_runtime::zenoh::sample::Sample;
use offworld_runtime::zenoh::Session;
use offworld_runtime::{codec, wire};

const HEARD_WITHIN: Duration = Duration::from_secs(10);

async fn next_estop(robot: &Subscriber<FifoChannelHandler<Sample>>) -> EStop {
    let sample = tokio::time::timeout(HEARD_WITHIN, robot.recv_async())
        .await
        .expect("an e-stop within the bound")
        .expect("subscriber open");
    assert_eq!(sample.priority(), wire::CONTROL_PRIORITY);
    codec::decode_payload(sample.payload()).expect("an EStop")
}

/// What an e-stop reaches and waits for: a robot agent or twin's
/// subscription to the env's e-stop and, declared after it as the agents
/// do, its liveliness token.
async fn embodiment(
    session: &Session,
    env: &EnvId,
    component: Component,
) -> (LivelinessToken, Subscriber<FifoChannelHandler<Sample>>) {
    let estop = session
        .declare_subscriber(env.key(Topic::EStop))
        .await
        .expect("subscriber");
    let token = session
        .liveliness()
        .declare_token(env.alive_key(component))
        .await
        .expect("token");
    (token, estop)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_env_and_the_site_estop_reach_the_robot_and_an_unheard_press_is_an_error() {
    let (robot_side, operator) = loopback_pair().await.expect("sessions");
    let env = EnvId::real("estop-0").expect("env");
    let site = robot_side
        .declare_subscriber(global_estop_key())
        .await
        .expect("subscriber");
    let (_alive, robot) = embodiment(&robot_side, &env, Component::RobotAgent).await;
    let wait = HEARD_WITHIN;
    let press = EStop {
        engaged: true,
        reason: "person in the enclosure".into(),
    };
    press_estop(&operator, &EStopScope::Env(env.clone()), &press, wait)
        .await
        .expect("pressed");
    assert_eq!(next_estop(&robot).await, press);
    let release = EStop {
        engaged: false,
        reason: "clear".into(),
    };
    press_estop(&operator, &EStopScope::Env(env.clone()), &release, wait)
        .await
        .expect("released");
    assert_eq!(next_estop(&robot).await, release);
    press_estop(&operator, &EStopScope::Site, &press, wait)
        .await
        .expect("site pressed");
    assert_eq!(next_estop(&site).await, press);

    // No robot or twin for this env (a subscriber alone is no robot): a
    // typed error naming the key.
    let _bystander = robot_side
        .declare_subscriber(
            EnvId::real("estop-unwatched")
                .expect("env")
                .key(Topic::EStop),
        )
        .await
        .expect("subscriber");
    let nobody = EnvId::real("estop-unwatched").expect("env");
    let error = press_estop(
        &operator,
        &EStopScope::Env(nobody.clone()),
        &press,
        Duration::from_millis(300),
    )
    .await
    .expect_err("nobody heard it");
    match error {
        ControllerError::NotFound(message) => {
            assert!(message.contains(&nobody.key(Topic::EStop)), "{message}")
        }
        other => panic!("expected NotFound, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_cli_presses_and_releases_an_env_estop() {
    let endpoint = loopback_endpoint().expect("endpoint");
    let robot_side = SessionConfig::listening(&endpoint)
        .open()
        .await
        .expect("session");
    let env = EnvId::real("estop-cli").expect("env");
    let (_alive, robot) = embodiment(&robot_side, &env, Component::SimTwin).await;
    for (extra, engaged) in [(None, true), (Some("--release"), false)] {
        let mut cli = std::process::Command::new(env!("CARGO_BIN_EXE_env_controller"));
        cli.args(["estop", "--env", &env.to_string(), "--reason", "drill"])
            .args(["--connect", &endpoint, "--wait-s", "5"])
            .args(extra);
        // The CLI's own waits are bounded (--wait-s); so is this one.
        let out = tokio::time::timeout(
            HEARD_WITHIN,
            tokio::task::spawn_blocking(move || cli.output()),
        )
        .await
        .expect("the CLI exits within the bound")
        .expect("join")
        .expect("the CLI runs");
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let verb = if engaged { "engaged" } else { "released" };
        assert_eq!(
            String::from_utf8_lossy(&out.stdout).trim(),
            format!("e-stop {verb} on {}", env.key(Topic::EStop))
        );
        let heard = next_estop(&robot).await;
        assert_eq!(
            heard,
            EStop {
                engaged,
                reason: "drill".into()
            }
        );
    }
}
