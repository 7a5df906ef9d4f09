//! The distributed path: `env_controller serve` and `sim_twin` as separate
//! processes, a client in this one, all meeting over TCP on loopback.

use std::time::Duration;

use offworld_runtime::client::{self, ClientTimeouts, EnvClient};
use offworld_runtime::msg::*;
use offworld_runtime::session::loopback_endpoint;
use offworld_runtime::{EnvId, ErrorCode, SessionConfig};
use offworld_tests::Process;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn controller_and_twin_processes_serve_a_full_episode() {
    let scratch = std::env::temp_dir().join(format!("offworld-processes-{}", client::random_id()));
    std::fs::create_dir_all(&scratch).expect("scratch");
    let db = scratch.join("gym.db");
    let endpoint = loopback_endpoint().expect("port");
    let env = EnvId::sim("proc-0").expect("env");
    let env_arg = format!("{env}=MonolithObstacleContinuous");
    let _controller = Process::spawn(
        "env_controller",
        &[
            "--db",
            db.to_str().expect("utf8"),
            "serve",
            "--env",
            &env_arg,
            "--listen",
            &endpoint,
        ],
    )
    .expect("controller");
    let _twin = Process::spawn(
        "sim_twin",
        &[
            "--env",
            &env.to_string(),
            "--world",
            "monolith_obstacle",
            "--resolution",
            "64x48",
            "--connect",
            &endpoint,
        ],
    )
    .expect("twin");

    let session = SessionConfig::connecting(&endpoint)
        .open()
        .await
        .expect("client session");
    // Bounded wait: the controller answers `spec`, then the twin comes online.
    let mut opened = None;
    for _ in 0..200 {
        if client::spec(&session, &env, Duration::from_secs(1))
            .await
            .is_ok()
        {
            let request = OpenRequest {
                token: String::new(),
                client_id: String::new(),
                experiment_name: "distributed".into(),
                resume_experiment: false,
                learning_type: LearningType::EndToEnd,
                algorithm_mode: AlgorithmMode::Train,
                obs: ObsOptions {
                    channels: Channels::Rgbd,
                    height: 48,
                    width: 64,
                    depth_format: DepthFormat::Meters,
                },
            };
            match EnvClient::open(&session, &env, request, ClientTimeouts::default()).await {
                Ok(c) => {
                    opened = Some(c);
                    break;
                }
                Err(e) if e.code == ErrorCode::Unavailable => {} // twin not yet online
                Err(e) => panic!("open failed: {e}"),
            }
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let mut gym = opened.expect("the deployment came up");
    assert_eq!(gym.spec().task, "MonolithObstacleContinuous");
    let reset = gym.reset(Seed::Fixed(4)).await.expect("reset");
    assert_eq!(
        (
            reset.observation.height,
            reset.observation.width,
            reset.observation.channels
        ),
        (48, 64, 4)
    );
    assert_eq!(reset.observation.dtype, DType::F32);
    let mut steps = 0;
    loop {
        let r = gym
            .step(Action::Continuous(vec![0.3, 0.1]))
            .await
            .expect("step");
        steps += 1;
        assert_eq!(r.info.step, steps);
        if r.terminated || r.truncated {
            break;
        }
        assert!(steps < 100);
    }
    gym.close().await.expect("close");
    drop(session);
    let _ = std::fs::remove_dir_all(&scratch);
}

/// Every long-running binary treats SIGTERM, SIGINT and SIGHUP as "stop
/// cleanly": it exits by itself with status 0 (its liveliness tokens are
/// undeclared and its records closed on the way), not by the signal's
/// default action.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_service_exits_cleanly_on_sigterm_sigint_and_sighup() {
    let scratch = std::env::temp_dir().join(format!("offworld-signals-{}", client::random_id()));
    std::fs::create_dir_all(&scratch).expect("scratch");
    let endpoint = loopback_endpoint().expect("port");
    let db = scratch.join("gym.db");
    let rrd = scratch.join("monitor.rrd");
    let calibration = scratch.join("calibration.toml");
    std::fs::write(
        &calibration,
        offworld_tests::emulated::emulator_calibration_toml(),
    )
    .expect("calibration");
    let latch = scratch.join("robot.estop");
    let (db, rrd, calibration, latch) = (
        db.to_string_lossy().into_owned(),
        rrd.to_string_lossy().into_owned(),
        calibration.to_string_lossy().into_owned(),
        latch.to_string_lossy().into_owned(),
    );
    let connect = ["--connect", endpoint.as_str()];
    let services: Vec<(&str, Vec<&str>)> = vec![
        (
            "sim_twin",
            [&["--env", "sim/signals-0"][..], &connect].concat(),
        ),
        (
            "robot_agent",
            [
                &["--env", "real/signals-0", "--estop-latch", &latch][..],
                &connect,
            ]
            .concat(),
        ),
        (
            "base_guard",
            [&["--env", "real/signals-0"][..], &connect].concat(),
        ),
        (
            "tracker_agent",
            [
                &[
                    "run",
                    "--env",
                    "real/signals-0",
                    "--source",
                    "udp://127.0.0.1:0",
                ][..],
                &["--calibration", &calibration],
                &connect,
            ]
            .concat(),
        ),
        (
            "monitor",
            [&["--all", "--save", &rrd][..], &connect].concat(),
        ),
    ];
    for signal in ["TERM", "INT", "HUP"] {
        // The controller serves and listens: the others connect to it.
        let controller = Process::spawn(
            "env_controller",
            &[
                "--db",
                &db,
                "serve",
                "--env",
                "sim/signals-0=MonolithDiscrete",
                "--listen",
                &endpoint,
            ],
        )
        .expect("controller");
        let mut running = Vec::new();
        for (binary, args) in &services {
            running.push((*binary, Process::spawn(binary, args).expect(binary)));
        }
        // Up and past start-up (sessions open, handlers installed).
        tokio::time::sleep(Duration::from_secs(3)).await;
        for (binary, mut process) in running.into_iter().chain([("env_controller", controller)]) {
            assert!(
                process.0.try_wait().expect("wait").is_none(),
                "{binary} died before the signal"
            );
            process.signal(signal);
            let deadline = std::time::Instant::now() + Duration::from_secs(15);
            let status = loop {
                if let Some(status) = process.0.try_wait().expect("wait") {
                    break status;
                }
                assert!(
                    std::time::Instant::now() < deadline,
                    "{binary} did not exit on SIG{signal}"
                );
                tokio::time::sleep(Duration::from_millis(20)).await;
            };
            assert!(status.success(), "{binary} on SIG{signal}: {status}");
        }
    }
    let _ = std::fs::remove_dir_all(&scratch);
}
