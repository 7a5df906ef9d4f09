//! Parity replay on episodes the twin itself recorded: replayed with the
//! profile they were recorded with, the gap is the replay's own error
//! (near zero); with another profile it is the profiles' difference.

use crate::common;

use offworld_runtime::Resolution;
use std::path::Path;

use common::{episodes, record, Recording, Scratch};
use offworld_parity::recorded::RecordedEpisode;
use offworld_parity::replay::{replay, EpisodeReplay};
use offworld_parity::report::{markdown, Summary};
use offworld_parity::ParityError;
use offworld_runtime::msg::Channels;
use offworld_sim_twin::TwinProfile;

/// Four (or `episodes`) episodes of up to 15 steps, RGBD at 32×24.
fn rgbd(episodes: u64, steps: u32) -> Recording<'static> {
    Recording {
        task: "MonolithDiscrete",
        resolution: Resolution::new(32, 24),
        channels: Channels::Rgbd,
        episodes,
        steps,
        seed: 100,
    }
}

fn replay_all(dir: &Path, profile: &TwinProfile) -> Vec<EpisodeReplay> {
    episodes(dir)
        .iter()
        .map(|e| replay(e, profile).expect("replay"))
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
    record(&nominal_runs.0, TwinProfile::default(), &rgbd(4, 15)).await;
    record(&slippery_runs.0, slippery(), &rgbd(4, 15)).await;

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
    record(&runs.0, TwinProfile::default(), &rgbd(1, 5)).await;
    let file = offworld_recorder::read::episode_files(&runs.0).expect("files")[0].clone();
    let bytes = std::fs::read(&file).expect("read");
    let cut = runs.0.join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).expect("write");
    let e = RecordedEpisode::read(&cut).expect_err("a cut file");
    assert!(e.to_string().contains("cut.mcap"), "{e}");
}
