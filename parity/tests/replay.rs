//! Parity replay on episodes the twin itself recorded: replayed with the
//! profile they were recorded with, the gap is the replay's own error
//! (near zero); with another profile it is the profiles' difference.

use std::path::{Path, PathBuf};

use offworld_env_controller::deployment::{connect, Target};
use offworld_parity::recorded::RecordedEpisode;
use offworld_parity::replay::{replay, EpisodeReplay};
use offworld_parity::report::{markdown, Summary};
use offworld_parity::ParityError;
use offworld_runtime::client::{ClientTimeouts, EnvClient};
use offworld_runtime::msg::{Action, Channels, DepthFormat, ObsOptions, OpenRequest, Seed};
use offworld_sim_twin::TwinProfile;

struct Scratch(PathBuf);

impl Scratch {
    fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!(
            "offworld-parity-{name}-{}",
            offworld_runtime::client::random_id()
        ));
        std::fs::create_dir_all(&dir).expect("scratch dir");
        Self(dir)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Records `episodes` episodes of seeded random discrete actions (at most
/// `steps` each) from an embedded twin with `profile` into `dir`.
async fn record(dir: &Path, profile: TwinProfile, episodes: u64, steps: u32) {
    let connection = connect(
        Target::Embedded {
            task: "MonolithDiscrete".into(),
            resolution: (32, 24),
            count: 1,
            record: Some(dir.to_owned()),
            twin_profile: profile,
        },
        "MonolithDiscrete",
    )
    .await
    .expect("embedded twin recording");
    let request = OpenRequest {
        experiment_name: "parity".into(),
        ..OpenRequest::anonymous(ObsOptions {
            channels: Channels::Rgbd,
            height: 24,
            width: 32,
            depth_format: DepthFormat::Meters,
        })
    };
    let mut client = EnvClient::open(
        &connection.session,
        &connection.envs[0],
        request,
        ClientTimeouts::default(),
    )
    .await
    .expect("open");
    let mut state = 0x2545_f491_4f6c_dd1d_u64;
    for episode in 0..episodes {
        client
            .reset(Seed::Fixed(100 + episode))
            .await
            .expect("reset");
        for _ in 0..steps {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let reply = client
                .step(Action::Discrete((state % 4) as i64))
                .await
                .expect("step");
            if reply.terminated || reply.truncated {
                break;
            }
        }
    }
    client.close().await.expect("close");
}

fn replay_all(dir: &Path, profile: &TwinProfile) -> Vec<EpisodeReplay> {
    offworld_recorder::read::episode_files(dir)
        .expect("files")
        .iter()
        .map(|f| {
            let episode = RecordedEpisode::read(f).expect("episode");
            replay(&episode, profile).expect("replay")
        })
        .collect()
}

fn slippery() -> TwinProfile {
    let mut profile = TwinProfile::default();
    profile.motion.linear_gain = 0.7;
    profile.motion.angular_gain = 0.8;
    profile
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replay_with_the_recording_profile_is_near_exact_and_another_profile_shows_the_gap() {
    let nominal_runs = Scratch::new("nominal");
    let slippery_runs = Scratch::new("slippery");
    record(&nominal_runs.0, TwinProfile::default(), 4, 15).await;
    record(&slippery_runs.0, slippery(), 4, 15).await;

    let nominal = TwinProfile::default();
    let matched = [
        Summary::of(&replay_all(&nominal_runs.0, &nominal)),
        Summary::of(&replay_all(&slippery_runs.0, &slippery())),
    ];
    let mismatched = Summary::of(&replay_all(&slippery_runs.0, &nominal));
    for s in &matched {
        assert_eq!(s.episodes, 4);
        assert!(s.steps >= 4, "{s:?}");
        // The twin replaying its own episodes: only the re-settling of a
        // teleport differs (the robot settles on its springs again).
        assert!(s.one_step_position_m.mean < 0.01, "{s:?}");
        assert!(s.one_step_yaw_rad.mean < 0.01, "{s:?}");
        assert!(s.depth_mae_m.mean < 0.02, "{s:?}");
        assert!(
            s.reward_agreement >= 0.95 && s.termination_agreement >= 0.95,
            "{s:?}"
        );
    }
    // Slip the nominal twin does not have: each step falls short and
    // turns too far (deterministic: seeded resets and actions, lockstep).
    assert!(
        mismatched.one_step_position_m.mean > 2.0 * matched[1].one_step_position_m.mean
            && mismatched.one_step_position_m.mean > 0.015,
        "{mismatched:?} vs {:?}",
        matched[1]
    );
    assert!(
        mismatched.one_step_yaw_rad.mean > 10.0 * matched[1].one_step_yaw_rad.mean,
        "{mismatched:?} vs {:?}",
        matched[1]
    );
    assert!(mismatched.open_loop_position_m.mean > matched[1].open_loop_position_m.mean);

    let report = markdown(
        &replay_all(&slippery_runs.0, &nominal),
        &nominal,
        "nominal (default)",
    );
    assert!(report.starts_with("# Sim↔real parity\n"), "{report}");
    assert!(report.contains("4 episodes"), "{report}");
    assert!(report.contains("| one-step position, cm |"), "{report}");
    assert!(report.contains("## Worst steps"), "{report}");
}

#[test]
fn unreadable_episodes_are_refused_naming_the_file() {
    let dir = Scratch::new("bad");
    // Not MCAP at all.
    let junk = dir.0.join("ep-000000.mcap");
    std::fs::write(&junk, b"not an episode").expect("write");
    let e = RecordedEpisode::read(&junk).expect_err("junk");
    assert!(e.to_string().contains("ep-000000.mcap"), "{e}");
    // Missing.
    let missing = dir.0.join("ep-000001.mcap");
    let e = RecordedEpisode::read(&missing).expect_err("missing");
    assert!(matches!(e, ParityError::Record(_)), "{e:?}");
    assert!(e.to_string().contains("ep-000001.mcap"), "{e}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_truncated_episode_file_is_refused_naming_it() {
    let runs = Scratch::new("cut");
    record(&runs.0, TwinProfile::default(), 1, 5).await;
    let file = offworld_recorder::read::episode_files(&runs.0).expect("files")[0].clone();
    let bytes = std::fs::read(&file).expect("read");
    let cut = runs.0.join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).expect("write");
    let e = RecordedEpisode::read(&cut).expect_err("a cut file");
    assert!(e.to_string().contains("cut.mcap"), "{e}");
}
