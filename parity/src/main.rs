//! `parity`: how far the twin is from the robot, measured on recorded
//! episodes.
//!
//! ```text
//! parity replay runs/real/monolith-0/               # every episode under it, nominal twin
//! parity replay runs/ --profile robot-a.toml --out parity.md
//! ```

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;
use clap::{Parser, Subcommand};
use offworld_parity::recorded::RecordedEpisode;
use offworld_parity::replay::replay;
use offworld_parity::report;
use offworld_sim_twin::TwinProfile;

/// Replays recorded episodes (MCAP, from `env_controller serve --record`,
/// `record=` or `recorder record`) in the sim twin and reports the gap
/// between the twin and what was recorded: pose, depth, colour, reward and
/// termination, per step.
#[derive(Debug, Parser)]
#[command(name = "parity", version)]
struct Args {
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
    },
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

fn run(args: Args) -> anyhow::Result<()> {
    match args.command {
        Command::Replay {
            paths,
            profile,
            out,
        } => {
            let (twin_profile, name) = match &profile {
                Some(path) => (TwinProfile::load(path)?, path.display().to_string()),
                None => (TwinProfile::default(), "nominal (default)".to_owned()),
            };
            let files = episode_files(&paths)?;
            let mut replays = Vec::with_capacity(files.len());
            for (i, file) in files.iter().enumerate() {
                let episode = RecordedEpisode::read(file)?;
                let replayed = replay(&episode, &twin_profile)?;
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
            let text = report::markdown(&replays, &twin_profile, &name);
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
    }
}

fn main() -> ExitCode {
    match run(Args::parse()) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("parity: {e:#}");
            ExitCode::FAILURE
        }
    }
}
