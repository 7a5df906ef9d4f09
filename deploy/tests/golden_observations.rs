//! Golden observations: what a researcher receives for a seed, at the two
//! resolutions the benchmarks measure (320×240 RGBD, 84×84 depth), through
//! the whole embedded stack (client → controller → twin → reply), must not
//! change unless the change is meant. Each observation is pinned by the
//! SHA-256 of its bytes, beside the step's reward, end flags and pose, so a
//! speed-up of the renderer, the physics or the image path that alters a
//! single pixel fails here.
//!
//! After a deliberate change (say why in the commit and in
//! `docs/performance.md`), regenerate with
//! `UPDATE_GOLDEN=1 cargo test --release --test golden_observations`.

use std::fmt::Write as _;
use std::time::Duration;

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::embedded::{Embedded, SimEnv, Stepping, TwinProfile};
use offworld_env_controller::Store;
use offworld_runtime::msg::{
    Action, Channels, DepthFormat, ObsArray, ObsOptions, OpenRequest, Seed, StepInfo,
};
use offworld_runtime::{EnvId, Resolution, SessionConfig};
use sha2::{Digest, Sha256};

/// A fixed walk: turns both ways, forward, back, then forward towards the
/// monolith side.
const ACTIONS: [i64; 10] = [2, 0, 2, 2, 1, 1, 3, 2, 0, 2];
const SEED: u64 = 11;

fn digest(obs: &ObsArray) -> String {
    format!(
        "{}x{}x{} {:?} sha256:{:x}",
        obs.width,
        obs.height,
        obs.channels,
        obs.dtype,
        Sha256::digest(&obs.data)
    )
}

/// The pose to the millimetre and milliradian: enough to say which way a
/// changed frame went, without pinning float noise twice.
fn pose(info: &StepInfo) -> String {
    format!("x={:.3} y={:.3} yaw={:.3}", info.x, info.y, info.yaw)
}

/// One line per observation (reset, then each step) of one episode.
async fn walk(task: &str, world_env: &str, options: ObsOptions) -> String {
    let session = SessionConfig::isolated().open().await.expect("session");
    let env = EnvId::sim(world_env).expect("env id");
    let sim = SimEnv {
        env: env.clone(),
        task: task.into(),
        resolution: Some(Resolution::new(options.width, options.height)),
        seed: 0,
        profile: TwinProfile::default(),
        render_threads: 2,
        stepping: Stepping::OwnThread,
    };
    let embedded = Embedded::start(&session, &[sim], Store::in_memory().expect("store"))
        .await
        .expect("embedded env");
    let mut gym = EnvClient::open_when_ready(
        &session,
        &env,
        OpenRequest::anonymous(options),
        ClientTimeouts::default(),
        Duration::from_secs(10),
    )
    .await
    .expect("open");
    let mut lines = String::new();
    let reset = gym.reset(Seed::Fixed(SEED)).await.expect("reset");
    writeln!(
        lines,
        "{task} {options_name} reset seed={SEED} {} {}",
        pose(&reset.info),
        digest(&reset.observation),
        options_name = name(&options),
    )
    .expect("a String takes any text");
    for (i, action) in ACTIONS.into_iter().enumerate() {
        let step = gym.step(Action::Discrete(action)).await.expect("step");
        writeln!(
            lines,
            "{task} {} step={} action={action} reward={} terminated={} truncated={} {} {}",
            name(&options),
            i + 1,
            step.reward,
            step.terminated,
            step.truncated,
            pose(&step.info),
            digest(&step.observation),
        )
        .expect("a String takes any text");
        if step.terminated || step.truncated {
            break;
        }
    }
    gym.close().await.expect("close");
    embedded.shutdown("test over").await;
    lines
}

fn name(options: &ObsOptions) -> String {
    format!(
        "{}x{}-{:?}-{:?}",
        options.width, options.height, options.channels, options.depth_format
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn observations_for_a_seed_match_the_golden_digests() {
    let cases = [
        (
            "MonolithObstacleDiscrete",
            "golden-rgbd-320",
            ObsOptions {
                channels: Channels::Rgbd,
                width: 320,
                height: 240,
                depth_format: DepthFormat::Uint8,
            },
        ),
        (
            "MonolithDiscrete",
            "golden-depth-84",
            ObsOptions {
                channels: Channels::DepthOnly,
                width: 84,
                height: 84,
                depth_format: DepthFormat::Uint8,
            },
        ),
        (
            "MonolithDiscrete",
            "golden-meters-84",
            ObsOptions {
                channels: Channels::DepthOnly,
                width: 84,
                height: 84,
                depth_format: DepthFormat::Meters,
            },
        ),
    ];
    let mut got = String::new();
    for (task, env, options) in cases {
        got.push_str(&walk(task, env, options).await);
    }
    // The same seed twice in one process gives the same bytes (no state
    // leaks from one episode into the next).
    let again = walk(cases[1].0, "golden-depth-84-again", cases[1].2).await;
    let first_84: String = got
        .lines()
        .filter(|l| l.contains(&name(&cases[1].2)))
        .map(|l| format!("{l}\n"))
        .collect();
    assert_eq!(again, first_84, "a second env with the same seed differs");

    let path = offworld_test_support::package_dir().join("tests/golden/observations.txt");
    if std::env::var_os("UPDATE_GOLDEN").is_some() {
        std::fs::create_dir_all(path.with_file_name("")).expect("golden directory");
        std::fs::write(&path, &got).expect("write golden");
        return;
    }
    let want = std::fs::read_to_string(&path)
        .expect("tests/golden/observations.txt (UPDATE_GOLDEN=1 to create it)");
    for (line, (g, w)) in got.lines().zip(want.lines()).enumerate() {
        assert_eq!(g, w, "line {} of the golden observations", line + 1);
    }
    assert_eq!(
        got.lines().count(),
        want.lines().count(),
        "number of observations"
    );
}
