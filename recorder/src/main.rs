//! `recorder`: inspects recorded episodes and recovers crashed ones.
//!
//! ```text
//! recorder info runs/                               # every episode under runs/
//! recorder recover runs/sim/monolith-0/exp-000001/ep-000007.mcap.partial
//! ```

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};
use offworld_recorder::read::{self, EpisodeSummary};

/// Inspects recorded OffWorld Gym episodes (MCAP, ROS 2 profile) and
/// recovers the ones a crash left as `.partial`.
#[derive(Debug, Parser)]
#[command(name = "recorder", version)]
struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// One line per episode file under each path: env, experiment, episode,
    /// steps, return, how it ended, messages per topic.
    Info {
        /// Episode files or directories of them.
        #[arg(required = true)]
        paths: Vec<PathBuf>,
    },
    /// Writes the complete steps of a crashed episode's `.partial` file as
    /// a complete MCAP file (next to it, without `.partial`).
    Recover {
        /// The `.partial` file.
        partial: PathBuf,
        /// Where to write (default: the name without `.partial`).
        #[arg(long, value_name = "FILE")]
        out: Option<PathBuf>,
    },
}

fn main() -> ExitCode {
    offworld_runtime::session::init_logging();
    let args = Args::parse();
    match run(args.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("recorder: {e}");
            ExitCode::FAILURE
        }
    }
}

fn run(command: Command) -> Result<(), offworld_recorder::RecordError> {
    match command {
        Command::Info { paths } => {
            let mut files = 0;
            for path in &paths {
                for file in read::episode_files(path)? {
                    files += 1;
                    match read::summarize(&file) {
                        Ok(summary) => println!("{}", describe(&summary)),
                        Err(e) => println!("{}: unreadable: {e}", file.display()),
                    }
                }
            }
            if files == 0 {
                eprintln!("recorder: no episode files (*.mcap, *.mcap.partial) found");
            }
            Ok(())
        }
        Command::Recover { partial, out } => {
            let (path, kept) = read::recover(&partial, out.as_deref())?;
            println!("{}: {kept} messages recovered", path.display());
            Ok(())
        }
    }
}

fn describe(s: &EpisodeSummary) -> String {
    let get = |k: &str| s.metadata.get(k).map_or("?", String::as_str);
    let (steps, ret) = s
        .last_step
        .as_ref()
        .map_or((0, 0.0), |st| (st.step, st.episode_return));
    let ended = match (&s.end, s.complete) {
        (Some(end), _) => end.end_reason.clone(),
        (None, true) => "no end recorded".to_owned(),
        (None, false) => "crashed (.partial: `recorder recover` it)".to_owned(),
    };
    let topics: Vec<String> = s
        .messages
        .iter()
        .map(|(topic, n)| format!("{topic}={n}"))
        .collect();
    format!(
        "{}: {} experiment {} ({}, {}) episode {}: {steps} steps, return {ret:.3}, {ended}; {}",
        s.path.display(),
        get("env_id"),
        get("experiment_id"),
        get("experiment"),
        get("learning_type"),
        get("episode_id"),
        topics.join(" ")
    )
}
