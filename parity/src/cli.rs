//! `parity`: how far the twin is from the robot, measured on recorded
//! episodes.
//!
//! ```text
//! parity replay runs/real/monolith-0/               # every episode under it, nominal twin
//! parity replay runs/ --profile robot-a.toml --out parity.md
//! parity replay runs/ --out report/parity.md --plots report/plots   # with PNG figures
//! parity identify runs/real/monolith-0/ --out robot-a.toml
//! ```

use std::path::PathBuf;
use std::process::ExitCode;

use crate::identify::{identify, IdentifyOptions};
use crate::plots::{self, WorstDepth};
use crate::recorded::RecordedEpisode;
use crate::replay::replay_with;
use crate::report;
use crate::rrd::SideBySide;
use anyhow::Context;
use clap::{Parser, Subcommand};
use offworld_sim_twin::TwinProfile;

/// Replays recorded episodes (MCAP, from `env_controller serve --record`,
/// `record=` or `recorder record`) in the sim twin and reports the gap
/// between the twin and what was recorded: pose, depth, colour, reward and
/// termination, per step.
#[derive(Debug, Parser)]
#[command(name = "parity", version)]
pub struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Replays each episode in the twin from its first recorded pose with
    /// its recorded commands, and writes a Markdown report.
    Replay {
        /// Episode files or directories of them.
        #[arg(required = true)]
        paths: Vec<PathBuf>,
        /// The twin profile to replay with (see `docs/twin-profile.md`;
        /// default: the nominal twin).
        #[arg(long, value_name = "FILE")]
        profile: Option<PathBuf>,
        /// Where to write the report (default: standard output).
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
        /// Also write a rerun recording (`.rrd`): robot and twin side by
        /// side, step by step (open it with `rerun FILE`).
        #[arg(long, value_name = "FILE")]
        rrd: Option<PathBuf>,
        /// Also write PNG figures into this directory (created if
        /// missing), linked from the report: trajectories over the
        /// enclosure map, errors over the steps, depth images of the
        /// worst steps.
        #[arg(long, value_name = "DIR")]
        plots: Option<PathBuf>,
    },
    /// Fits a twin profile to episodes of one robot in one world (at
    /// least 3 episodes, 20 moving steps): motion gains, camera mount,
    /// depth noise and dropout. Writes the profile for `sim_twin
    /// --profile`, `twin_profile=` and the sim farm.
    Identify {
        /// Episode files or directories of them.
        #[arg(required = true)]
        paths: Vec<PathBuf>,
        /// Where to write the fitted profile.
        #[arg(long, value_name = "FILE")]
        out: PathBuf,
        /// The profile to start from (default: the nominal twin); latency
        /// and settle time are kept from it.
        #[arg(long, value_name = "FILE")]
        start: Option<PathBuf>,
        /// Optimiser iterations per fit, at most.
        #[arg(long, default_value_t = IdentifyOptions::default().max_iters)]
        max_iters: u64,
        /// Depth images the camera fit renders (spread over the episodes).
        #[arg(long, default_value_t = IdentifyOptions::default().camera_steps)]
        camera_steps: usize,
    },
}

/// The episodes for identification, without their colour images (the fit
/// does not use them: an hour of 640×480 colour would be gigabytes).
fn read_all(files: &[PathBuf]) -> anyhow::Result<Vec<RecordedEpisode>> {
    files
        .iter()
        .map(|f| {
            let mut episode = RecordedEpisode::read(f)?;
            for step in &mut episode.steps {
                step.color = None;
            }
            Ok(episode)
        })
        .collect()
}

fn episode_files(paths: &[PathBuf]) -> anyhow::Result<Vec<PathBuf>> {
    let mut files = Vec::new();
    for path in paths {
        let found = offworld_recorder::read::episode_files(path)?;
        anyhow::ensure!(
            !found.is_empty(),
            "{}: no episode files (*.mcap)",
            path.display()
        );
        files.extend(found);
    }
    Ok(files)
}

fn run_command(args: Args) -> anyhow::Result<()> {
    match args.command {
        Command::Replay {
            paths,
            profile,
            out,
            rrd,
            plots,
        } => {
            let (twin_profile, profile_name) = match &profile {
                Some(path) => (TwinProfile::load(path)?, path.display().to_string()),
                None => (TwinProfile::default(), "nominal (default)".to_owned()),
            };
            let files = episode_files(&paths)?;
            let side_by_side = rrd.as_deref().map(SideBySide::create).transpose()?;
            let mut worst_depth = WorstDepth::default();
            let mut replays = Vec::with_capacity(files.len());
            for (i, file) in files.iter().enumerate() {
                let episode = RecordedEpisode::read(file)?;
                let name = format!("episode-{i:03}");
                let mut logged = Ok(());
                let replayed = replay_with(&episode, &twin_profile, |recorded, frame, gap| {
                    if let (Some(out), Ok(())) = (&side_by_side, &logged) {
                        logged = out.step(&name, recorded, frame, gap);
                    }
                    if plots.is_some() {
                        worst_depth.visit(i, file, recorded, frame, gap);
                    }
                })?;
                logged?;
                if let Some(out) = &side_by_side {
                    out.trajectories(&name, &replayed)?;
                }
                let summary = report::Summary::of(std::slice::from_ref(&replayed));
                eprintln!(
                    "[{}/{}] {}: {} steps, open-loop end {:.1} cm, one-step mean {:.1} cm",
                    i + 1,
                    files.len(),
                    file.display(),
                    summary.steps,
                    summary.final_position_m.mean * 100.0,
                    summary.one_step_position_m.mean * 100.0,
                );
                replays.push(replayed);
            }
            if let (Some(out), Some(path)) = (side_by_side, &rrd) {
                out.finish()?;
                eprintln!("rerun recording: {}", path.display());
            }
            let figures = match &plots {
                Some(dir) => {
                    std::fs::create_dir_all(dir)
                        .with_context(|| format!("creating {}", dir.display()))?;
                    let base = plots::link_base(out.as_deref(), dir);
                    let figures = plots::write(dir, &base, &replays, &worst_depth)?;
                    eprintln!("figures: {}", dir.display());
                    Some(figures)
                }
                None => None,
            };
            let text = report::markdown_with_figures(
                &replays,
                &twin_profile,
                &profile_name,
                figures.as_ref(),
            );
            match out {
                Some(path) => {
                    std::fs::write(&path, text)
                        .with_context(|| format!("writing {}", path.display()))?;
                    eprintln!("report: {}", path.display());
                }
                None => print!("{text}"),
            }
            Ok(())
        }
        Command::Identify {
            paths,
            out,
            start,
            max_iters,
            camera_steps,
        } => {
            let start = match &start {
                Some(path) => TwinProfile::load(path)?,
                None => TwinProfile::default(),
            };
            let files = episode_files(&paths)?;
            eprintln!("reading {} episodes …", files.len());
            let episodes = read_all(&files)?;
            let options = IdentifyOptions {
                max_iters,
                camera_steps,
            };
            let found = identify(&episodes, &start, &options, &mut |line| eprintln!("{line}"))?;
            found.profile.save(&out)?;
            println!(
                "{}: one-step position error {:.2} cm → {:.2} cm, depth cost {:.2} cm → {:.2} cm \
                 ({} moving steps, {} iterations)",
                out.display(),
                found.position_error_before_m * 100.0,
                found.position_error_after_m * 100.0,
                found.depth_cost_before_m * 100.0,
                found.depth_cost_after_m * 100.0,
                found.steps,
                found.iterations
            );
            Ok(())
        }
    }
}

/// Runs `parity` (also `offworld parity`) with these arguments.
pub fn run(args: Args) -> ExitCode {
    match run_command(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("parity: {e:#}");
            ExitCode::FAILURE
        }
    }
}
