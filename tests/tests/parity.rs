//! Issue 24's acceptance: the emulated enclosure's "physical" robot runs
//! with hardware parameters perturbed away from the twin's (the values go
//! to the emulator only, never to the calibrator); ten recorded episodes of
//! random actions; `parity identify` recovers the parameters, and the
//! fitted twin replays the episodes far closer than the nominal one.

use std::path::PathBuf;
use std::time::Duration;

use offworld_parity::identify::{identify, IdentifyOptions};
use offworld_parity::recorded::RecordedEpisode;
use offworld_parity::replay::replay;
use offworld_parity::report::Summary;
use offworld_runtime::client::{ClientTimeouts, EnvClient};
use offworld_runtime::msg::{
    Action, AlgorithmMode, Channels, DepthFormat, ObsOptions, OpenRequest, Seed,
};
use offworld_runtime::session::SessionConfig;
use offworld_runtime::ErrorCode;
use offworld_sim_twin::{CameraProfile, DepthProfile, MotionProfile, TwinProfile};
use offworld_tests::emulated::{EmulatedEnclosure, Options};
use rand::{Rng, SeedableRng};

const EPISODES: u64 = 10;
const STEPS: u32 = 6;

/// The robot the emulator plays: slipping, late, slow to settle, its
/// camera mounted a little high, tilted and turned, its depth noisy.
fn hardware() -> TwinProfile {
    TwinProfile {
        motion: MotionProfile {
            linear_gain: 0.85,
            angular_gain: 1.12,
            // A whole number of the emulator's 1/60 s physics steps.
            latency_s: 0.15,
            settle_time_s: Some(0.8),
        },
        camera: CameraProfile {
            height_offset_m: 0.02,
            pitch_deg: 2.0,
            yaw_deg: 1.5,
        },
        depth: DepthProfile {
            noise: 0.01,
            dropout: 0.03,
        },
    }
}

struct Scratch(PathBuf);

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn within(name: &str, fitted: f64, truth: f64, tolerance: f64) {
    assert!(
        (fitted - truth).abs() <= tolerance,
        "{name}: fitted {fitted}, hardware {truth} (tolerance {tolerance})"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn identification_recovers_the_emulated_hardware_and_closes_the_replay_gap() {
    let scratch = Scratch(std::env::temp_dir().join(format!(
        "offworld-parity-emulated-{}",
        offworld_runtime::client::random_id()
    )));
    std::fs::create_dir_all(&scratch.0).expect("scratch");
    let hardware_file = scratch.0.join("hardware.toml");
    hardware().save(&hardware_file).expect("hardware profile");
    let runs = scratch.0.join("runs");
    let mut options = Options::new("MonolithContinuous").expect("options");
    options.record = Some(runs.clone());
    options.hardware_profile = Some(hardware_file);
    // A small camera: the tilted mount renders per pixel, in real time.
    options.hardware_camera = Some((64, 48));
    let deployment = EmulatedEnclosure::start(&options).expect("deployment");
    deployment
        .ready(Duration::from_secs(60))
        .await
        .expect("deployment ready");

    let session = SessionConfig::connecting(&deployment.endpoint)
        .open()
        .await
        .expect("client session");
    let request = OpenRequest {
        token: deployment.token.clone(),
        experiment_name: "parity-acceptance".into(),
        algorithm_mode: AlgorithmMode::Test,
        ..OpenRequest::anonymous(ObsOptions {
            channels: Channels::DepthOnly,
            height: 48,
            width: 64,
            depth_format: DepthFormat::Meters,
        })
    };
    let mut gym = EnvClient::open_when_ready(
        &session,
        &deployment.env,
        request,
        ClientTimeouts::default(),
        Duration::from_secs(30),
    )
    .await
    .expect("the emulated deployment came up");
    // Random actions, gentle enough to stay inside the enclosure for a few
    // steps: up to 0.21 m/s and 1.5 rad/s, held 1 s.
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(24);
    for episode in 0..EPISODES {
        let mut reset = None;
        for _ in 0..50 {
            match gym.reset(Seed::Fixed(100 + episode)).await {
                Ok(r) => {
                    reset = Some(r);
                    break;
                }
                // The tracker's first poses may still be arriving.
                Err(e) if matches!(e.code, ErrorCode::Unavailable | ErrorCode::Timeout) => {
                    tokio::time::sleep(Duration::from_millis(200)).await;
                }
                Err(e) => panic!("reset failed: {e}"),
            }
        }
        reset.expect("reset");
        for _ in 0..STEPS {
            let action = vec![rng.random_range(-0.3..=0.3), rng.random_range(-0.6..=0.6)];
            let reply = gym.step(Action::Continuous(action)).await.expect("step");
            if reply.terminated || reply.truncated {
                break;
            }
        }
    }
    gym.close().await.expect("close");
    drop(session);
    drop(deployment);

    let files = offworld_recorder::read::episode_files(&runs).expect("recorded files");
    let episodes: Vec<RecordedEpisode> = files
        .iter()
        .map(|f| RecordedEpisode::read(f).expect("a recorded episode"))
        .collect();
    assert_eq!(episodes.len() as u64, EPISODES, "{files:?}");
    assert!(
        episodes.iter().all(|e| e.info.embodiment == "robot"),
        "recorded from the robot side"
    );

    let nominal = TwinProfile::default();
    let mut log = Vec::new();
    let fitted = identify(
        &episodes,
        &nominal,
        &IdentifyOptions::default(),
        &mut |line| log.push(line.to_owned()),
    )
    .unwrap_or_else(|e| panic!("identification failed: {e}"));
    let p = fitted.profile;
    let truth = hardware();
    eprintln!("{}\nfitted: {p:?}", log.join("\n"));
    let timing = fitted.timing.expect("the odometry time series was fitted");
    assert!(timing.speed_error_after < 0.5 * timing.speed_error_before);
    let five_percent = |v: f32| f64::from(v.abs()) * 0.05;
    within(
        "linear gain",
        f64::from(p.motion.linear_gain),
        f64::from(truth.motion.linear_gain),
        five_percent(truth.motion.linear_gain),
    );
    within(
        "angular gain",
        f64::from(p.motion.angular_gain),
        f64::from(truth.motion.angular_gain),
        five_percent(truth.motion.angular_gain),
    );
    let settle = truth.motion.settle_time_s.expect("settle");
    within(
        "settle time",
        f64::from(p.motion.settle_time_s.expect("fitted settle")),
        f64::from(settle),
        five_percent(settle),
    );
    within(
        "latency",
        f64::from(p.motion.latency_s),
        f64::from(truth.motion.latency_s),
        five_percent(truth.motion.latency_s),
    );
    within(
        "camera height",
        f64::from(p.camera.height_offset_m),
        f64::from(truth.camera.height_offset_m),
        five_percent(truth.camera.height_offset_m),
    );
    within(
        "camera pitch",
        f64::from(p.camera.pitch_deg),
        f64::from(truth.camera.pitch_deg),
        0.5,
    );
    within(
        "camera yaw",
        f64::from(p.camera.yaw_deg),
        f64::from(truth.camera.yaw_deg),
        0.5,
    );

    // The replay gap: the fitted twin within a quarter of the nominal one's.
    let one_step = |profile: &TwinProfile| {
        let replays: Vec<_> = episodes
            .iter()
            .map(|e| replay(e, profile).expect("replay"))
            .collect();
        Summary::of(&replays).one_step_position_m.mean
    };
    let (before, after) = (one_step(&nominal), one_step(&p));
    eprintln!(
        "mean one-step position error: nominal {:.2} cm, fitted {:.2} cm",
        before * 100.0,
        after * 100.0
    );
    assert!(
        after <= 0.25 * before,
        "nominal {before} m, fitted {after} m"
    );
}
