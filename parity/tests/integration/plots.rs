//! `parity replay --plots`: the PNG figures of a replay of episodes a twin
//! recorded (a slippery twin, replayed with the nominal profile, so there
//! is a gap to draw), their sizes, that they are drawn (not blank), that
//! the report links them, that the same replay gives the same bytes, and
//! that an empty replay or NaN errors do not break them.

use crate::common;

use offworld_runtime::Resolution;
use std::path::{Path, PathBuf};

use common::{episodes, record, Recording, Scratch};
use offworld_parity::plots::{self, Figures, WorstDepth, WORST_DEPTH_STEPS};
use offworld_parity::recorded::ResetRecord;
use offworld_parity::replay::{replay_with, EpisodeReplay, StepGap};
use offworld_parity::report::markdown_with_figures;
use offworld_runtime::msg::{Channels, Pose2D};
use offworld_sim_twin::TwinProfile;

fn slippery() -> TwinProfile {
    let mut profile = TwinProfile::default();
    profile.motion.linear_gain = 0.7;
    profile.motion.angular_gain = 0.8;
    profile
}

/// Three episodes of up to 12 steps in the obstacle world, RGBD 48×36.
fn recording() -> Recording<'static> {
    Recording {
        task: "MonolithObstacleDiscrete",
        resolution: Resolution::new(48, 36),
        channels: Channels::Rgbd,
        episodes: 3,
        steps: 12,
        seed: 7,
    }
}

/// Replays every episode under `runs` with the nominal profile, keeping
/// the worst depth steps, and writes the figures into `dir`.
fn replay_and_plot(runs: &Path, dir: &Path) -> (Vec<EpisodeReplay>, Figures) {
    let mut worst = WorstDepth::default();
    let replays: Vec<EpisodeReplay> = episodes(runs)
        .iter()
        .enumerate()
        .map(|(i, episode)| {
            replay_with(episode, &TwinProfile::default(), |recorded, frame, gap| {
                worst.visit(i, &episode.path, recorded, frame, gap);
            })
            .expect("replay")
        })
        .collect();
    let figures = plots::write(dir, "plots", &replays, &worst).expect("figures");
    (replays, figures)
}

/// Decodes a PNG: (width, height, RGB or RGBA bytes, channels).
fn decode(path: &Path) -> (u32, u32, Vec<u8>, usize) {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
    let mut reader = decoder
        .read_info()
        .unwrap_or_else(|e| panic!("{}: not a PNG: {e}", path.display()));
    let mut buf = vec![0; reader.output_buffer_size().expect("buffer size")];
    let info = reader.next_frame(&mut buf).expect("frame");
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf, info.color_type.samples())
}

/// Asserts `path` is a `size` PNG with something drawn on it: many
/// distinct colours and a spread of grey levels (not a blank canvas).
fn assert_drawn(path: &Path, size: (u32, u32)) {
    let (w, h, pixels, channels) = decode(path);
    assert_eq!((w, h), size, "{}", path.display());
    assert!(channels >= 3, "{}: {channels} channels", path.display());
    let grey: Vec<f64> = pixels
        .chunks_exact(channels)
        .map(|p| (f64::from(p[0]) + f64::from(p[1]) + f64::from(p[2])) / 3.0)
        .collect();
    let mean = grey.iter().sum::<f64>() / grey.len() as f64;
    let variance = grey.iter().map(|g| (g - mean).powi(2)).sum::<f64>() / grey.len() as f64;
    assert!(
        variance > 100.0,
        "{}: grey variance {variance}",
        path.display()
    );
    let mut colours: Vec<[u8; 3]> = pixels
        .chunks_exact(channels)
        .map(|p| [p[0], p[1], p[2]])
        .collect();
    colours.sort_unstable();
    colours.dedup();
    assert!(
        colours.len() > 20,
        "{}: {} colours",
        path.display(),
        colours.len()
    );
    // Not the white canvas alone: a fair share of the pixels is drawn.
    let drawn = grey.iter().filter(|g| **g < 250.0).count();
    assert!(
        drawn * 50 > grey.len(),
        "{}: {drawn} of {} pixels drawn",
        path.display(),
        grey.len()
    );
}

fn all_files(figures: &Figures) -> Vec<PathBuf> {
    figures
        .trajectories
        .iter()
        .chain(&figures.episode_trajectories)
        .chain(&figures.errors)
        .chain(figures.depth.iter().map(|d| &d.figure))
        .map(|f| f.path.clone())
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_replay_writes_its_figures_and_the_report_links_them() {
    let runs = Scratch::new("plots-runs");
    record(&runs.0, slippery(), &recording()).await;
    let out = Scratch::new("plots-out");
    let dir = out.0.join("plots");
    let (replays, figures) = replay_and_plot(&runs.0, &dir);
    assert_eq!(replays.len(), 3);

    // The files, their sizes, and something drawn on each.
    let names: Vec<String> = all_files(&figures)
        .iter()
        .map(|p| p.file_name().expect("name").to_string_lossy().into_owned())
        .collect();
    assert_eq!(
        names[..5],
        [
            "trajectories.png",
            "trajectory-000.png",
            "trajectory-001.png",
            "trajectory-002.png",
            "pose-error.png"
        ],
        "{names:?}"
    );
    assert_eq!(figures.depth.len(), WORST_DEPTH_STEPS, "{names:?}");
    for (k, d) in figures.depth.iter().enumerate() {
        assert!(d
            .figure
            .path
            .ends_with(format!("depth-error-{}.png", k + 1)));
    }
    // Worst first.
    let maes: Vec<f64> = figures.depth.iter().map(|d| d.gap.depth_mae_m).collect();
    assert!(maes.windows(2).all(|w| w[0] >= w[1]), "{maes:?}");
    let measured = replays
        .iter()
        .flat_map(|r| &r.steps)
        .map(|s| s.depth_mae_m)
        .filter(|m| m.is_finite())
        .fold(0.0, f64::max);
    assert_eq!(maes[0], measured);
    for f in figures
        .trajectories
        .iter()
        .chain(&figures.episode_trajectories)
    {
        assert_drawn(&f.path, plots::MAP_SIZE);
    }
    assert_drawn(
        &figures.errors.as_ref().expect("errors figure").path,
        plots::ERROR_SIZE,
    );
    for d in &figures.depth {
        assert_drawn(&d.figure.path, plots::DEPTH_SIZE);
    }
    let written: Vec<_> = std::fs::read_dir(&dir)
        .expect("plots dir")
        .map(|e| e.expect("entry").file_name())
        .collect();
    assert_eq!(written.len(), names.len(), "{written:?}");

    // The report links each figure, relative to itself, in its section.
    let report =
        markdown_with_figures(&replays, &TwinProfile::default(), "nominal", Some(&figures));
    std::fs::write(out.0.join("parity.md"), &report).expect("report");
    for name in &names {
        let link = format!("](plots/{name})");
        assert!(report.contains(&link), "{link} missing from\n{report}");
        assert!(out.0.join("plots").join(name).is_file());
    }
    let episodes_at = report.find("## Episodes").expect("episodes section");
    let depth_at = report
        .find("## Depth error, worst steps")
        .expect("depth section");
    assert!(report[..episodes_at].contains("](plots/trajectories.png)"));
    assert!(report[..episodes_at].contains("](plots/pose-error.png)"));
    assert!(report[episodes_at..depth_at].contains("[map](plots/trajectory-002.png)"));
    assert!(report[depth_at..].contains("](plots/depth-error-5.png)"));

    // Deterministic: the same replay draws the same bytes.
    let again = Scratch::new("plots-again");
    let (_, figures_again) = replay_and_plot(&runs.0, &again.0);
    for (a, b) in all_files(&figures).iter().zip(all_files(&figures_again)) {
        assert_eq!(
            std::fs::read(a).expect("first"),
            std::fs::read(&b).expect("second"),
            "{} differs from {}",
            a.display(),
            b.display()
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_parity_binary_writes_figures_beside_its_report() {
    let runs = Scratch::new("plots-cli-runs");
    record(
        &runs.0,
        slippery(),
        &Recording {
            episodes: 1,
            steps: 6,
            ..recording()
        },
    )
    .await;
    let out = Scratch::new("plots-cli-out");
    let report = out.0.join("report").join("parity.md");
    std::fs::create_dir_all(report.parent().expect("parent")).expect("report dir");
    let figures = out.0.join("figures");
    let status = std::process::Command::new(env!("CARGO_BIN_EXE_parity"))
        .arg("replay")
        .arg(&runs.0)
        .arg("--out")
        .arg(&report)
        .arg("--plots")
        .arg(&figures)
        .status()
        .expect("run parity");
    assert!(status.success(), "{status}");
    let text = std::fs::read_to_string(&report).expect("report");
    // The figures' directory is a sibling of the report's: linked via `..`.
    assert!(text.contains("](../figures/trajectories.png)"), "{text}");
    assert!(
        text.contains("[map](../figures/trajectory-000.png)"),
        "{text}"
    );
    assert!(figures.join("pose-error.png").is_file());
    assert!(figures.join("depth-error-1.png").is_file());
}

fn nan_pose() -> Pose2D {
    Pose2D {
        x: f64::NAN,
        y: f64::NAN,
        yaw: f64::NAN,
    }
}

#[test]
fn empty_episodes_and_nan_errors_are_drawn_without_panicking() {
    let dir = Scratch::new("plots-edge");
    let start = Pose2D {
        x: 0.5,
        y: -0.5,
        yaw: 1.0,
    };
    let episode = |steps: Vec<StepGap>| EpisodeReplay {
        path: PathBuf::from("ep-000000.mcap"),
        env_id: "real/enclosure-a".into(),
        task: "MonolithDiscrete".into(),
        world: "monolith".into(),
        embodiment: "robot".into(),
        start,
        reset: ResetRecord {
            requested: start,
            achieved: start,
            duration_s: None,
        },
        steps,
    };
    let nan_step = StepGap {
        step: 1,
        time_s: f64::NAN,
        recorded: nan_pose(),
        open_loop: nan_pose(),
        open_loop_position_m: f64::NAN,
        open_loop_yaw_rad: f64::NAN,
        one_step_position_m: f64::NAN,
        one_step_yaw_rad: f64::NAN,
        depth_mae_m: f64::NAN,
        depth_validity_disagreement: f64::NAN,
        color_mae: f64::NAN,
        reward: (0.0, 0.0),
        terminated: (false, false),
    };
    // No episode at all: nothing to draw, no error.
    let none = plots::write(&dir.0.join("none"), "", &[], &WorstDepth::default()).expect("none");
    assert!(none.trajectories.is_none() && none.errors.is_none());
    assert!(none.episode_trajectories.is_empty() && none.depth.is_empty());
    // An episode without steps, one whose errors are all NaN, and one in a
    // world that is not built in: drawn, whatever is finite.
    let unknown_world = EpisodeReplay {
        world: "elsewhere".into(),
        ..episode(vec![nan_step])
    };
    let replays = [episode(Vec::new()), episode(vec![nan_step]), unknown_world];
    let figures =
        plots::write(&dir.0.join("edge"), "", &replays, &WorstDepth::default()).expect("edge");
    assert_eq!(figures.episode_trajectories.len(), 3);
    for path in all_files(&figures) {
        let (w, h, _, _) = decode(&path);
        assert!(w > 0 && h > 0);
    }
    assert!(figures.depth.is_empty());
    let report =
        markdown_with_figures(&replays, &TwinProfile::default(), "nominal", Some(&figures));
    assert!(
        report.contains("No step has a depth error measured"),
        "{report}"
    );
    assert!(report.contains("[map](trajectory-000.png)"), "{report}");

    // An output directory that cannot be made is an error naming it.
    let blocker = dir.0.join("a-file");
    std::fs::write(&blocker, b"").expect("file");
    let e = plots::write(&blocker.join("plots"), "", &replays, &WorstDepth::default())
        .expect_err("a file in the way");
    assert!(e.to_string().contains("a-file"), "{e}");
}
