//! Twin identification on episodes a perturbed twin recorded: the fit must
//! recover the perturbation (which only the recording twin was given) and
//! shrink the replay error.

use crate::common;

use offworld_runtime::Resolution;

use common::{episodes, record, Recording, Scratch};
use offworld_parity::identify::{identify, IdentifyOptions};
use offworld_parity::recorded::RecordedEpisode;
use offworld_parity::ParityError;
use offworld_runtime::msg::Channels;
use offworld_sim_twin::TwinProfile;

/// `episodes` episodes of up to `steps` steps of `task`, depth at 48×36.
fn depth(task: &'static str, episodes: u64, steps: u32) -> Recording<'static> {
    Recording {
        task,
        resolution: Resolution::new(48, 36),
        channels: Channels::DepthOnly,
        episodes,
        steps,
        seed: 200,
    }
}

/// The robot: slipping, turning further, its camera 2 cm higher, pitched
/// 2° down and turned 1.5°, a noisy depth sensor.
fn perturbed() -> TwinProfile {
    let mut p = TwinProfile::default();
    p.motion.linear_gain = 0.85;
    p.motion.angular_gain = 1.12;
    p.camera.height_offset_m = 0.02;
    p.camera.pitch_deg = 2.0;
    p.camera.yaw_deg = 1.5;
    p.depth.noise = 0.01;
    p.depth.dropout = 0.03;
    p
}

fn within(found: f32, truth: f32, share: f32) -> bool {
    (found - truth).abs() <= share * truth.abs()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn identification_recovers_a_perturbed_twin_and_shrinks_the_replay_error() {
    let runs = Scratch::new("perturbed");
    let truth = perturbed();
    record(&runs.0, truth, &depth("MonolithDiscrete", 10, 12)).await;
    let recorded = episodes(&runs.0);
    assert_eq!(recorded.len(), 10);
    let mut log = Vec::new();
    let found = identify(
        &recorded,
        &TwinProfile::default(),
        &IdentifyOptions::default(),
        &mut |line| log.push(line.to_owned()),
    )
    .expect("identified");
    let p = found.profile;
    eprintln!("{}", log.join("\n"));
    assert!(within(p.motion.linear_gain, 0.85, 0.05), "{p:?}");
    assert!(within(p.motion.angular_gain, 1.12, 0.05), "{p:?}");
    assert!(within(p.camera.height_offset_m, 0.02, 0.05), "{p:?}");
    assert!((p.camera.pitch_deg - 2.0).abs() <= 0.5, "{p:?}");
    assert!((p.camera.yaw_deg - 1.5).abs() <= 0.5, "{p:?}");
    assert!(within(p.depth.noise, 0.01, 0.05), "{p:?}");
    assert!(within(p.depth.dropout, 0.03, 0.05), "{p:?}");
    assert!(
        found.position_error_after_m <= 0.25 * found.position_error_before_m,
        "{found:?}"
    );
    assert!(
        found.depth_cost_after_m < found.depth_cost_before_m,
        "{found:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn too_few_episodes_or_mixed_worlds_are_refused_naming_the_reason() {
    let open = Scratch::new("open");
    let obstacle = Scratch::new("obstacle");
    record(
        &open.0,
        TwinProfile::default(),
        &depth("MonolithDiscrete", 3, 8),
    )
    .await;
    record(
        &obstacle.0,
        TwinProfile::default(),
        &depth("MonolithObstacleDiscrete", 1, 3),
    )
    .await;
    let mut two = episodes(&open.0);
    two.truncate(2);
    let e = identify(
        &two,
        &TwinProfile::default(),
        &IdentifyOptions::default(),
        &mut |_| {},
    )
    .expect_err("two episodes");
    assert!(matches!(e, ParityError::TooFew { .. }), "{e:?}");
    assert!(e.to_string().contains("at least 3"), "{e}");

    // A step the twin cannot replay (a 20 s command) is named, not fitted
    // around.
    let mut bad = episodes(&open.0);
    bad[1].steps[2].step.duration_s = 20.0;
    let bad_path = bad[1].path.clone();
    let e = identify(
        &bad,
        &TwinProfile::default(),
        &IdentifyOptions::default(),
        &mut |_| {},
    )
    .expect_err("an unreplayable step");
    let text = e.to_string();
    assert!(
        text.contains(&bad_path.display().to_string()) && text.contains("step 2"),
        "{text}"
    );

    let mut mixed = episodes(&open.0);
    let other = episodes(&obstacle.0).remove(0);
    let other_path = other.path.clone();
    mixed.push(other);
    let e = identify(
        &mixed,
        &TwinProfile::default(),
        &IdentifyOptions::default(),
        &mut |_| {},
    )
    .expect_err("another world");
    let text = e.to_string();
    assert!(text.contains(&other_path.display().to_string()), "{text}");
    assert!(text.contains("monolith_obstacle"), "{text}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_parity_command_replays_identifies_and_explains_what_is_wrong() {
    let runs = Scratch::new("cli");
    record(&runs.0, perturbed(), &depth("MonolithDiscrete", 3, 10)).await;
    let parity = env!("CARGO_BIN_EXE_parity");
    let report = runs.0.join("parity.md");
    let rrd = runs.0.join("parity.rrd");
    let replayed = std::process::Command::new(parity)
        .args(["replay", "--out"])
        .arg(&report)
        .arg("--rrd")
        .arg(&rrd)
        .arg(&runs.0)
        .output()
        .expect("parity replay");
    assert!(replayed.status.success(), "{replayed:?}");
    let text = std::fs::read_to_string(&report).expect("report");
    assert!(
        text.starts_with("# Sim↔real parity\n") && text.contains("3 episodes"),
        "{text}"
    );
    // The side-by-side recording, read back by the rerun SDK itself.
    let checked = std::process::Command::new("python3")
        .arg(offworld_test_support::package_dir().join("../monitor/tests/check_rrd.py"))
        .arg(&rrd)
        .output()
        .expect("python3 (needs rerun-sdk==0.36.3)");
    assert!(checked.status.success(), "{checked:?}");
    let summary: serde_json::Value = serde_json::from_slice(&checked.stdout).expect("json");
    assert_eq!(summary["verify"]["ok"], true, "{summary}");
    let first = offworld_recorder::read::episode_files(&runs.0).expect("files")[0].clone();
    let steps = RecordedEpisode::read(&first).expect("episode").steps.len() - 1;
    for entity in [
        "/episode-000/recorded/depth",
        "/episode-000/twin/depth",
        "/episode-000/error/depth",
        "/episode-000/error/one_step_position_m",
    ] {
        assert_eq!(
            summary["entities"][entity]["rows"], steps,
            "{entity}: {summary}"
        );
    }
    for who in ["recorded", "twin"] {
        let entity = format!("/episode-000/{who}/trajectory");
        assert_eq!(
            summary["entities"][&entity]["static_rows"], 1,
            "{entity}: {summary}"
        );
    }

    let profile = runs.0.join("robot.toml");
    let identified = std::process::Command::new(parity)
        .args(["identify", "--out"])
        .arg(&profile)
        .arg(&runs.0)
        .output()
        .expect("parity identify");
    assert!(identified.status.success(), "{identified:?}");
    let fitted = TwinProfile::load(&profile).expect("a profile the twin loads");
    assert!(
        (fitted.motion.linear_gain - 0.85).abs() < 0.05,
        "{fitted:?}"
    );
    let stderr = String::from_utf8_lossy(&identified.stderr);
    assert!(
        stderr.contains("motion:") && stderr.contains("camera:"),
        "{stderr}"
    );

    let empty = runs.0.join("empty");
    std::fs::create_dir_all(&empty).expect("dir");
    let refused = std::process::Command::new(parity)
        .args(["identify", "--out"])
        .arg(runs.0.join("never.toml"))
        .arg(&empty)
        .output()
        .expect("parity identify");
    assert_eq!(refused.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert!(
        stderr.contains("no episode files") && stderr.contains("empty"),
        "{stderr}"
    );
    assert!(!runs.0.join("never.toml").exists());
}
