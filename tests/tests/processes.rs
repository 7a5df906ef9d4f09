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
