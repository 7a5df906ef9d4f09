//! `recorder`: records episodes from outside the controller, inspects
//! recorded episodes and recovers crashed ones.
//!
//! ```text
//! recorder record --env sim/monolith-0 --out runs -e tcp/127.0.0.1:7447
//! recorder record --all runs --duration 3600        # every env, for an hour
//! recorder info runs/                               # every episode under runs/
//! recorder recover runs/sim/monolith-0/exp-000001/ep-000007.mcap.partial
//! ```

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use crate::follow::{FinishedEpisode, FollowConfig, FollowScope, Follower};
use crate::read::{self, EpisodeSummary};
use clap::{ArgGroup, Parser, Subcommand};
use offworld_program::CommonArgs;
use offworld_runtime::EnvId;

/// Records OffWorld Gym episodes from outside the controller, inspects
/// recorded episodes (MCAP, ROS 2 profile) and recovers the ones a crash
/// left as `.partial`.
#[derive(Debug, Parser)]
#[command(name = "recorder", version)]
pub struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Joins a deployment as a subscriber (like the monitor) and writes one
    /// episode file per episode, as `env_controller serve --record` does
    /// (`DIR/<realm>/<env>/exp-N/ep-N.mcap`), until Ctrl-C or `--duration`.
    /// What a subscriber cannot know (seed, learning type, algorithm mode,
    /// requested start, action index) is left empty and named in each
    /// file's metadata (`unknown`).
    Record(RecordArgs),
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

/// `recorder record (--env ENV… | --all) (--out DIR | DIR)`
#[derive(Debug, clap::Args)]
#[command(group(ArgGroup::new("scope").required(true).args(["env", "all"])))]
#[command(group(ArgGroup::new("dir").required(true).args(["out", "path"])))]
struct RecordArgs {
    /// Record this env, e.g. `sim/monolith-0` or `real/monolith-0`
    /// (repeat for several).
    #[arg(long)]
    env: Vec<EnvId>,
    /// Record every env whose controller is alive, as they appear.
    #[arg(long)]
    all: bool,
    /// The recordings directory (created; checked writable at start).
    #[arg(long, value_name = "DIR")]
    out: Option<PathBuf>,
    /// The recordings directory (same as `--out`).
    #[arg(value_name = "DIR")]
    path: Option<PathBuf>,
    /// Stop after this many seconds (default: run until Ctrl-C); open
    /// episodes are finished either way.
    #[arg(long, value_name = "SECS")]
    duration: Option<f64>,
    /// How long a step waits for its camera frame after its event before
    /// it is skipped, ms.
    #[arg(long, value_name = "MS", default_value_t = 500)]
    frame_wait_ms: u64,
    #[command(flatten)]
    common: CommonArgs,
}

/// Runs `recorder` (also `offworld recorder`) with these arguments.
pub fn run(args: Args) -> ExitCode {
    offworld_program::init_logging();
    match run_command(args.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("recorder: {e}");
            ExitCode::FAILURE
        }
    }
}

/// One line on stderr per finished episode.
fn report(done: &FinishedEpisode) {
    let skipped = if done.skipped > 0 {
        format!(" ({} skipped)", done.skipped)
    } else {
        String::new()
    };
    eprintln!(
        "recorder: {} experiment {} episode {}: {} steps recorded{skipped}, {} → {}",
        done.env,
        done.experiment_id,
        done.episode_id,
        done.recorded,
        done.end_reason,
        done.path.display()
    );
}

async fn record(args: RecordArgs) -> anyhow::Result<()> {
    let dir = args.out.or(args.path).unwrap_or_default();
    let duration = match args.duration {
        Some(secs) if !(secs.is_finite() && secs >= 0.0) => {
            anyhow::bail!("--duration {secs}: expected a number of seconds ≥ 0")
        }
        secs => secs.map(Duration::from_secs_f64),
    };
    // An unwritable directory is reported before anything is joined.
    crate::RecordTo::check(&dir)?;
    // Installed first: a Ctrl-C at any time finishes the files.
    let mut signals = offworld_runtime::shutdown::ShutdownSignals::install()?;
    let scope = if args.all {
        FollowScope::All
    } else {
        FollowScope::Envs(args.env)
    };
    let config = FollowConfig {
        frame_wait: Duration::from_millis(args.frame_wait_ms),
        on_finished: Some(Arc::new(report)),
        ..FollowConfig::new(&dir)
    };
    let session = args
        .common
        .client_config()
        .open()
        .await
        .map_err(|e| anyhow::anyhow!("cannot open the Zenoh session: {e}"))?;
    let follower = Follower::start(&session, scope, config).await?;
    eprintln!("recorder: recording into {}", dir.display());
    let elapsed = async {
        match duration {
            Some(d) => tokio::time::sleep(d).await,
            None => std::future::pending().await,
        }
    };
    tokio::select! {
        () = elapsed => tracing::info!("--duration elapsed"),
        signal = signals.recv() => tracing::info!(%signal, "stop requested"),
    }
    let stats = follower.stop().await;
    eprintln!(
        "recorder: {} envs, {} episodes ({} finished), {} steps recorded, {} skipped (no frame in time), \
         {} never seen, {} malformed samples, {} events dropped",
        stats.envs,
        stats.episodes,
        stats.finished,
        stats.steps,
        stats.skipped_steps,
        stats.missed_events,
        stats.malformed,
        stats.dropped_events
    );
    let _ = session.close().await;
    Ok(())
}

fn run_command(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Record(args) => tokio::runtime::Builder::new_multi_thread()
            .enable_all()
            .build()?
            .block_on(record(args)),
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
