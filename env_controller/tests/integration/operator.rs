//! The operator's e-stops over real Zenoh, against real sim twins: pressed
//! and released from the library and from the `env_controller estop` CLI,
//! acknowledged by every twin under the scope with the latches now in
//! force; a component present but silent (a frozen agent, an ACL that
//! drops the press) fails the press naming it; a press nobody can hear is
//! a typed error.

use offworld_runtime::Resolution;
use std::time::Duration;

use offworld_client::operator::{press_estop, EStopScope, PressError};
use offworld_runtime::keys::{Component, EnvId, Topic};
use offworld_runtime::session::{loopback_endpoint, loopback_pair, SessionConfig};
use offworld_sim_twin::{Clock, SimTwin, TwinConfig, TwinNode};
use zenoh::Session;

const PRESENCE: Duration = Duration::from_secs(10);
/// Generous on a loaded machine; the CLI's default is 1 s.
const ACK: Duration = Duration::from_secs(5);

fn twin(session: &Session, name: &str) -> TwinNode {
    let mut config = TwinConfig::builtin("monolith").expect("world");
    config.resolution = Some(Resolution::new(8, 6));
    TwinNode::spawn(
        session,
        EnvId::sim(name).expect("env"),
        SimTwin::new(config).expect("twin"),
        Clock::Lockstep,
    )
    .expect("twin node")
}

/// Waits (bounded) until `observer` sees the liveliness token `key`.
async fn until_visible(observer: &Session, key: &str) {
    for _ in 0..100 {
        let replies = observer
            .liveliness()
            .get(key)
            .timeout(Duration::from_millis(500))
            .await
            .expect("liveliness get");
        if replies.recv_async().await.is_ok_and(|r| r.result().is_ok()) {
            return;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("{key} never became visible");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_twin_under_the_scope_acknowledges_and_latches_stay_independent() {
    let (robot_side, operator) = loopback_pair().await.expect("sessions");
    let _a = twin(&robot_side, "estop-a");
    let _b = twin(&robot_side, "estop-b");
    let a = EnvId::sim("estop-a").expect("env");
    let b = EnvId::sim("estop-b").expect("env");
    for env in [&a, &b] {
        until_visible(&operator, &env.alive_key(Component::SimTwin)).await;
    }

    let report = press_estop(
        &operator,
        &EStopScope::Site,
        true,
        "fire alarm",
        PRESENCE,
        ACK,
    )
    .await
    .expect("both twins acknowledge the site e-stop");
    let mut who: Vec<(String, String)> = report
        .acknowledged
        .iter()
        .map(|a| (a.env.clone(), a.component.clone()))
        .collect();
    who.sort();
    assert_eq!(
        who,
        [
            ("sim/estop-a".to_owned(), "sim_twin".to_owned()),
            ("sim/estop-b".to_owned(), "sim_twin".to_owned())
        ]
    );
    assert!(report
        .acknowledged
        .iter()
        .all(|a| a.state.summary() == "site"));
    assert!(report.silent.is_empty());

    let env_scope = EStopScope::Env(a.clone());
    let report = press_estop(&operator, &env_scope, true, "person inside", PRESENCE, ACK)
        .await
        .expect("env press");
    assert_eq!(report.acknowledged.len(), 1, "only the env's twin answers");
    assert_eq!(report.acknowledged[0].state.summary(), "site+env");
    // Releasing the env leaves the site latch engaged.
    let report = press_estop(&operator, &env_scope, false, "person out", PRESENCE, ACK)
        .await
        .expect("env release");
    assert_eq!(report.acknowledged[0].state.summary(), "site");
    assert_eq!(report.acknowledged[0].state.site.reason, "fire alarm");
    let report = press_estop(
        &operator,
        &EStopScope::Site,
        false,
        "all clear",
        PRESENCE,
        ACK,
    )
    .await
    .expect("site release");
    assert!(report
        .acknowledged
        .iter()
        .all(|a| a.state.summary() == "none"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_component_fails_the_press_and_an_unheard_press_is_an_error() {
    let (robot_side, operator) = loopback_pair().await.expect("sessions");
    let _a = twin(&robot_side, "estop-c");
    // A robot agent that declares itself but never acknowledges (frozen,
    // or its router drops the press).
    let frozen = EnvId::real("estop-frozen").expect("env");
    let _token = robot_side
        .liveliness()
        .declare_token(frozen.alive_key(Component::RobotAgent))
        .await
        .expect("token");
    until_visible(&operator, &frozen.alive_key(Component::RobotAgent)).await;
    until_visible(
        &operator,
        &EnvId::sim("estop-c")
            .expect("env")
            .alive_key(Component::SimTwin),
    )
    .await;
    let error = press_estop(
        &operator,
        &EStopScope::Site,
        true,
        "drill",
        PRESENCE,
        Duration::from_millis(1500),
    )
    .await
    .expect_err("the frozen agent did not acknowledge");
    match error {
        PressError::Unacknowledged { message, report } => {
            assert_eq!(
                report.silent,
                [("real/estop-frozen".to_owned(), "robot_agent".to_owned())]
            );
            // Once, though the press was repeated for the frozen agent
            // and the twin acknowledged each repetition.
            assert_eq!(report.acknowledged.len(), 1, "the twin did");
            assert!(
                message.contains("robot_agent of real/estop-frozen"),
                "{message}"
            );
        }
        other => panic!("expected Unacknowledged, got {other:?}"),
    }

    // No robot or twin for this env (a subscriber alone is no robot): a
    // typed error naming the key.
    let nobody = EnvId::real("estop-unwatched").expect("env");
    let _bystander = robot_side
        .declare_subscriber(nobody.key(Topic::EStop))
        .await
        .expect("subscriber");
    let error = press_estop(
        &operator,
        &EStopScope::Env(nobody.clone()),
        true,
        "drill",
        Duration::from_millis(300),
        ACK,
    )
    .await
    .expect_err("nobody heard it");
    match error {
        PressError::NotFound(message) => {
            assert!(message.contains(&nobody.key(Topic::EStop)), "{message}")
        }
        other => panic!("expected NotFound, got {other:?}"),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_cli_prints_who_acknowledged_and_fails_when_someone_did_not() {
    let endpoint = loopback_endpoint().expect("endpoint");
    let robot_side = SessionConfig::listening(&endpoint)
        .open()
        .await
        .expect("session");
    let _twin = twin(&robot_side, "estop-cli");
    let env = EnvId::sim("estop-cli").expect("env");
    let cli = |args: Vec<String>| async move {
        let mut cli = std::process::Command::new(env!("CARGO_BIN_EXE_env_controller"));
        cli.args(args);
        // The CLI's own waits are bounded (--wait-s, --ack-ms); so is this one.
        tokio::time::timeout(
            Duration::from_secs(30),
            tokio::task::spawn_blocking(move || cli.output()),
        )
        .await
        .expect("the CLI exits within the bound")
        .expect("join")
        .expect("the CLI runs")
    };
    let base = |extra: &[&str]| {
        let mut args: Vec<String> = ["estop", "--env", &env.to_string(), "--reason", "drill"]
            .iter()
            .map(|s| s.to_string())
            .collect();
        args.extend(
            ["--connect", &endpoint, "--wait-s", "5", "--ack-ms", "5000"].map(String::from),
        );
        args.extend(extra.iter().map(|s| s.to_string()));
        args
    };
    for (extra, verb, now) in [
        (&[][..], "engaged", "env"),
        (&["--release"][..], "released", "none"),
    ] {
        let out = cli(base(extra)).await;
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(
            out.status.success(),
            "{stdout}{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let lines: Vec<&str> = stdout.lines().collect();
        assert_eq!(
            lines[0],
            format!("e-stop {verb} on {}", env.key(Topic::EStop))
        );
        // Its log (stderr, a pipe here) is plain text: no colour codes.
        let log = String::from_utf8_lossy(&out.stderr);
        assert!(log.contains("e-stop published"), "{log}");
        assert!(
            !log.contains('\u{1b}'),
            "colour codes in a piped log: {log:?}"
        );
        assert!(
            lines[1].starts_with("  acknowledged by sim_twin of sim/estop-cli in ")
                && lines[1].ends_with(&format!(" ms (e-stops now engaged: {now})")),
            "{stdout}"
        );
        assert_eq!(lines.len(), 2, "{stdout}");
    }

    // A second, frozen component under the env: the CLI names it and
    // exits non-zero.
    let _token = robot_side
        .liveliness()
        .declare_token(env.alive_key(Component::RobotAgent))
        .await
        .expect("token");
    let watcher = SessionConfig::connecting(&endpoint)
        .open()
        .await
        .expect("session");
    until_visible(&watcher, &env.alive_key(Component::RobotAgent)).await;
    let mut args = base(&[]);
    let ack = args.iter().position(|a| a == "5000").expect("--ack-ms");
    args[ack] = "1000".into();
    let out = cli(args).await;
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(!out.status.success(), "{stdout}");
    assert!(
        stdout.contains("  NOT acknowledged by robot_agent of sim/estop-cli"),
        "{stdout}"
    );
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("was not acknowledged within 1000 ms"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// A copy of a press arriving again (a press repeated while another
/// obeyer was silent, a duplicated delivery) is acknowledged but never
/// re-applied, and a release applies only when pressed after the latch's
/// last change: a late copy does not undo a press made in between by
/// someone else.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_repeated_release_never_undoes_a_later_engage() {
    use offworld_runtime::msg::{EStop, EStopAck};
    use offworld_runtime::{codec, wire};

    let (robot_side, operator) = loopback_pair().await.expect("sessions");
    let _twin = twin(&robot_side, "estop-repeat");
    let env = EnvId::sim("estop-repeat").expect("env");
    until_visible(&operator, &env.alive_key(Component::SimTwin)).await;
    let (tx, mut acks) = tokio::sync::mpsc::unbounded_channel();
    let _acks = operator
        .declare_subscriber(env.key(Topic::EStopAck))
        .callback(move |s| {
            if let Ok(ack) = codec::decode_payload::<EStopAck>(s.payload()) {
                let _ = tx.send(ack);
            }
        })
        .await
        .expect("ack subscriber");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let press = |engaged: bool, press_id: u64| {
        let stop = EStop {
            engaged,
            reason: format!("press {press_id}"),
            press_id,
        };
        let operator = operator.clone();
        let key = env.key(Topic::EStop);
        async move {
            wire::put_control(&operator, &key, &stop)
                .await
                .expect("published");
        }
    };
    let mut ack_of = async |press_id: u64| loop {
        let ack = tokio::time::timeout(ACK, acks.recv())
            .await
            .expect("acknowledged in time")
            .expect("subscriber open");
        if ack.press_id == press_id {
            return ack;
        }
    };
    // Alice releases (press 11), Bob engages (press 12), then a copy of
    // Alice's release arrives late.
    press(false, 11).await;
    assert_eq!(ack_of(11).await.state.summary(), "none");
    press(true, 12).await;
    assert_eq!(ack_of(12).await.state.summary(), "env");
    press(false, 11).await;
    let late = ack_of(11).await;
    assert_eq!(late.state.summary(), "env", "Bob's engage stands: {late:?}");
    assert_eq!(late.state.env.reason, "press 12");
    // A release pressed before Bob's engage whose first copy arrives after
    // it (its earlier copies lost) is refused too: outdated.
    press(false, 10).await;
    let outdated = ack_of(10).await;
    assert_eq!(outdated.state.env.reason, "press 12", "{outdated:?}");

    // A release pressed now applies: pressed after everything above.
    let scope = EStopScope::Env(env.clone());
    let released = press_estop(&operator, &scope, false, "all clear", PRESENCE, ACK)
        .await
        .expect("released");
    assert_eq!(released.acknowledged[0].state.summary(), "none");
}

/// An obeyer that acknowledges a press while holding its latch the other
/// way (a release pressed before someone's engage reached it first, an
/// engage released by a later press) fails the press, `Overtaken`, naming
/// who holds what: the operator is never told a latch is in a state it is
/// not. Scripted obeyers answer as a robot agent whose latch was overtaken.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_press_acknowledged_with_the_latch_the_other_way_is_overtaken() {
    use offworld_runtime::msg::{EStop, EStopAck, EStopState, LatchState, Time};
    use offworld_runtime::{codec, wire};

    let (robot_side, operator) = loopback_pair().await.expect("sessions");
    let env = EnvId::real("estop-overtaken").expect("env");
    let _token = robot_side
        .liveliness()
        .declare_token(env.alive_key(Component::RobotAgent))
        .await
        .expect("token");
    // It acknowledges every press with the latch the other way.
    let (answering, answering_env) = (robot_side.clone(), env.clone());
    let _obeyer = robot_side
        .declare_subscriber(env.key(Topic::EStop))
        .callback(move |s| {
            let stop: EStop = codec::decode_payload(s.payload()).expect("an e-stop");
            let ack = EStopAck {
                press_id: stop.press_id,
                component: "robot_agent".into(),
                env: answering_env.to_string(),
                state: EStopState {
                    env: LatchState {
                        engaged: !stop.engaged,
                        reason: "bob's press".into(),
                        changed: Time::now(),
                    },
                    ..EStopState::default()
                },
            };
            let (session, key) = (answering.clone(), answering_env.key(Topic::EStopAck));
            tokio::spawn(async move { wire::put_control(&session, &key, &ack).await });
        })
        .await
        .expect("obeyer");
    until_visible(&operator, &env.alive_key(Component::RobotAgent)).await;
    let scope = EStopScope::Env(env.clone());
    for (engage, said) in [
        (
            false,
            "the release on offworld/@v1/real/estop-overtaken/estop was refused: the env latch \
             was engaged again after it was pressed, and holds at robot_agent of \
             real/estop-overtaken (bob's press)",
        ),
        (
            true,
            "the e-stop on offworld/@v1/real/estop-overtaken/estop is not in force at \
             robot_agent of real/estop-overtaken (bob's press): a later press released the env \
             latch",
        ),
    ] {
        match press_estop(&operator, &scope, engage, "alice", PRESENCE, ACK).await {
            Err(PressError::Overtaken { message, report }) => {
                assert_eq!(message, said);
                assert_eq!(report.acknowledged.len(), 1, "{report:?}");
                assert!(report.silent.is_empty());
            }
            other => panic!("expected Overtaken, got {other:?}"),
        }
    }
}
