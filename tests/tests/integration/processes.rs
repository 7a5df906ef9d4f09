//! The distributed path: `env_controller serve` and `sim_twin` as separate
//! processes, a client in this one, all meeting over TCP on loopback.

use std::time::Duration;

use offworld_client::{self as client, ClientTimeouts, EnvClient};
use offworld_runtime::msg::*;
use offworld_runtime::session::loopback_endpoint;
use offworld_runtime::{EnvId, ErrorCode, SessionConfig};
use offworld_tests::{Process, Spawn};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn controller_and_twin_processes_serve_a_full_episode() {
    let scratch = std::env::temp_dir().join(format!(
        "offworld-processes-{}",
        offworld_runtime::keys::random_id()
    ));
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
    let scratch = std::env::temp_dir().join(format!(
        "offworld-signals-{}",
        offworld_runtime::keys::random_id()
    ));
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

/// Durability: the controller is killed (`kill -9`) at random points while
/// a client runs episode after episode, and restarted. Every episode the
/// client saw end is in the store as it ended (steps, end reason); every
/// episode started is on record, the ones cut by a kill as aborted; the
/// experiment resumes with all of them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_completed_episode_survives_kill_9_at_random_points() {
    use offworld_env_controller::store::IN_PROGRESS;
    use offworld_env_controller::Store;
    use rand::{Rng, SeedableRng};

    let scratch = std::env::temp_dir().join(format!(
        "offworld-durable-{}",
        offworld_runtime::keys::random_id()
    ));
    std::fs::create_dir_all(&scratch).expect("scratch");
    let db = scratch.join("gym.db");
    let endpoint = loopback_endpoint().expect("port");
    let env = EnvId::sim("durable-0").expect("env");
    let env_arg = format!("{env}=MonolithDiscrete");
    let serve = [
        "--db",
        db.to_str().expect("utf8"),
        "serve",
        "--env",
        &env_arg,
        "--embedded-twins",
        "--listen",
        &endpoint,
    ];
    let session = SessionConfig::connecting(&endpoint)
        .open()
        .await
        .expect("client session");
    let request = |resume: bool| OpenRequest {
        token: String::new(),
        client_id: String::new(),
        experiment_name: "durable".into(),
        resume_experiment: resume,
        learning_type: LearningType::EndToEnd,
        algorithm_mode: AlgorithmMode::Train,
        obs: ObsOptions {
            channels: Channels::DepthOnly,
            height: 24,
            width: 32,
            depth_format: DepthFormat::Uint8,
        },
    };
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(21);
    // (episode index, steps) of every episode the client saw end.
    let mut completed: Vec<(u64, u32)> = Vec::new();
    let mut started = 0u64;
    const KILLS: usize = 4;
    for round in 0..=KILLS {
        let controller = Process::spawn("offworld", &serve).expect("controller");
        let deadline = std::time::Instant::now() + Duration::from_secs(30);
        let mut gym = loop {
            match EnvClient::open(
                &session,
                &env,
                request(round > 0),
                ClientTimeouts::default(),
            )
            .await
            {
                Ok(gym) => break gym,
                Err(e) if std::time::Instant::now() < deadline => {
                    let _ = e;
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
                Err(e) => panic!("round {round}: no controller: {e}"),
            }
        };
        // Every episode started is on record; one more when the kill fell
        // between a reset's record and its reply.
        let recorded = gym.opened().experiment.episodes;
        assert!(
            (started..=started + 1).contains(&recorded),
            "round {round}: resumed with {recorded} episodes, {started} started"
        );
        started = recorded;
        if round == KILLS {
            gym.close().await.expect("close");
            drop(controller);
            break;
        }
        // Kill somewhere in the next 0.3–2 s, wherever the client is.
        let kill_at =
            tokio::time::Instant::now() + Duration::from_millis(rng.random_range(300..2_000));
        let killer = tokio::spawn(async move {
            tokio::time::sleep_until(kill_at).await;
            drop(controller);
        });
        'episodes: loop {
            let Ok(reset) = gym.reset(Seed::Fixed(rng.random())).await else {
                break;
            };
            started += 1;
            let index = reset.info.episode_id;
            loop {
                match gym.step(Action::Discrete(rng.random_range(0..4))).await {
                    Ok(r) if r.terminated || r.truncated => {
                        completed.push((index, r.info.step));
                        break;
                    }
                    Ok(_) => {}
                    Err(_) => break 'episodes,
                }
            }
        }
        killer.await.expect("killer");
    }
    assert!(
        completed.len() >= 2,
        "episodes completed between kills: {completed:?}"
    );
    assert!(
        started > completed.len() as u64,
        "some episode was cut by a kill"
    );

    let store = Store::open(&db).expect("store");
    let experiment = store
        .experiments()
        .expect("experiments")
        .into_iter()
        .find(|e| e.name == "durable")
        .expect("the experiment");
    assert_eq!(
        experiment.episodes, started,
        "every episode started is on record"
    );
    let episodes = store.episodes(experiment.id).expect("episodes");
    assert_eq!(episodes.len() as u64, started);
    for (index, steps) in &completed {
        let e = episodes
            .iter()
            .find(|e| e.index == *index)
            .unwrap_or_else(|| panic!("completed episode {index} lost"));
        assert_eq!(
            e.steps, *steps,
            "episode {index}: steps as the client saw them"
        );
        assert!(
            ["success", "out_of_bounds", "step_limit"].contains(&e.end_reason.as_str()),
            "episode {index} ended {:?}",
            e.end_reason
        );
    }
    // The others were cut by a kill (aborted), or ended just before one
    // with the reply lost: none is left in progress.
    for e in &episodes {
        assert_ne!(
            e.end_reason, IN_PROGRESS,
            "episode {} left in progress",
            e.index
        );
    }
    let aborted = episodes
        .iter()
        .filter(|e| e.end_reason.starts_with("aborted"))
        .count();
    assert!(aborted >= 1, "the cut episodes are recorded as aborted");
    drop(session);
    let _ = std::fs::remove_dir_all(&scratch);
}

/// Every program that joins a deployment takes the shared Zenoh settings
/// from the same environment variables as the Python client (one shared
/// clap group, `offworld_program::CommonArgs`), and says so in `--help`.
#[test]
fn every_program_reads_the_shared_zenoh_settings_from_the_same_variables() {
    let dir = offworld_tests::binary_dir();
    let programs: [(&str, &[&str]); 7] = [
        ("env_controller", &["serve"]),
        ("sim_twin", &[]),
        ("robot_agent", &[]),
        ("base_guard", &[]),
        ("tracker_agent", &["run"]),
        ("monitor", &[]),
        ("recorder", &["record"]),
    ];
    for (program, subcommand) in programs {
        let help = std::process::Command::new(dir.join(program))
            .args(subcommand)
            .arg("--help")
            .output()
            .expect(program);
        assert!(help.status.success(), "{program} --help: {help:?}");
        let text = String::from_utf8_lossy(&help.stdout);
        for variable in [
            "OFFWORLD_ZENOH_CONFIG",
            "OFFWORLD_ZENOH_MODE",
            "OFFWORLD_ZENOH_CONNECT",
            "OFFWORLD_ZENOH_LISTEN",
        ] {
            assert!(
                text.contains(&format!("env: {variable}")),
                "{program} --help does not name {variable}:\n{text}"
            );
        }
        // Read, not only shown: a bad mode in the variable is refused.
        let refused = std::process::Command::new(dir.join(program))
            .args(subcommand)
            .env("OFFWORLD_ZENOH_MODE", "bogus")
            .output()
            .expect(program);
        assert_eq!(refused.status.code(), Some(2), "{program}: {refused:?}");
        let stderr = String::from_utf8_lossy(&refused.stderr);
        assert!(
            stderr.contains("bogus") && stderr.contains("--mode"),
            "{program}: {stderr}"
        );
    }
}
