//! `offworld emulate-enclosure`: the whole real-side deployment on one
//! machine — gym server, robot agent, base guard and tracker agent as
//! separate processes under `real/<world>-0`, driving `offworld
//! emulate-hardware` as if it were the robot and the lighthouse tracker.
//! Needs `zenohd` (the robot computer's router) on `PATH`.
//!
//! ```text
//! offworld emulate-enclosure --task MonolithDiscrete      # serve until Ctrl-C
//! offworld emulate-enclosure -- python3 py_client/examples/random_agent.py --env OffWorldMonolithDiscreteReal-v0
//! ```

use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use offworld_runtime::shutdown::ShutdownSignals;

use crate::enclosure::{Enclosure, Options};

/// How long the deployment may take to come up (processes, tracking, the
/// env online).
const READY_LIMIT: Duration = Duration::from_secs(60);

const EXAMPLES: &str = "\
Examples:
  offworld emulate-enclosure                                  # serve until Ctrl-C, printing how to connect
  offworld emulate-enclosure --task MonolithObstacleContinuous
  offworld emulate-enclosure -- python3 py_client/examples/random_agent.py --env OffWorldMonolithDiscreteReal-v0

A command after `--` runs with OFFWORLD_GYM_CONNECT, OFFWORLD_GYM_ACCESS_TOKEN
(a researcher's) and OFFWORLD_OPERATOR_TOKEN (an operator's) set; the
deployment stops when it exits, with its exit status.";

/// Run the real stack against an emulated enclosure.
#[derive(clap::Args)]
#[command(after_help = EXAMPLES)]
pub struct Args {
    /// Task served (MonolithDiscrete, MonolithContinuous,
    /// MonolithObstacleDiscrete, MonolithObstacleContinuous); the env is
    /// `real/<world>-0`, what the `…Real-v0` ids use by default.
    #[arg(long, default_value = "MonolithDiscrete")]
    task: String,
    /// Robot agent watchdog window, ms (a real robot: 200).
    #[arg(long, default_value_t = 200)]
    watchdog_ms: u64,
    /// Record every episode under this directory (`serve --record`).
    #[arg(long, value_name = "DIR")]
    record: Option<std::path::PathBuf>,
    /// The emulated robot behaves per this twin profile
    /// (docs/twin-profile.md) instead of the nominal twin.
    #[arg(long, value_name = "FILE")]
    hardware_profile: Option<std::path::PathBuf>,
    /// Command to run against the deployment (after `--`).
    #[arg(last = true, value_name = "COMMAND")]
    command: Vec<String>,
}

/// Runs `offworld emulate-enclosure` with these arguments.
pub fn run(args: Args) -> ExitCode {
    offworld_program::run(emulate(args))
}

async fn emulate(args: Args) -> anyhow::Result<ExitCode> {
    let mut options = Options::new(&args.task)
        .with_context(|| format!("--task {}: not a task of tasks.toml", args.task))?;
    options.watchdog_ms = args.watchdog_ms;
    options.record = args.record;
    options.hardware_profile = match args.hardware_profile {
        // The hardware process runs elsewhere in the tree: an absolute path.
        Some(path) => Some(
            std::fs::canonicalize(&path)
                .with_context(|| format!("--hardware-profile {}", path.display()))?,
        ),
        None => None,
    };
    // Before anything starts: a stop during the start is answered.
    let mut signals = ShutdownSignals::install()?;
    eprintln!(
        "starting the emulated enclosure {} ({})…",
        options.env, args.task
    );
    let start = async {
        let deployment = Enclosure::start(&options)
            .context("starting the deployment (is `zenohd` on PATH? `.ci/setup` installs it)")?;
        deployment
            .ready(READY_LIMIT)
            .await
            .map_err(anyhow::Error::msg)
            .context("the deployment did not come up")?;
        Ok(deployment)
    };
    let deployment = match super::started_unless_stopped(&mut signals, start).await? {
        Ok(deployment) => deployment,
        Err(stopped) => return Ok(stopped),
    };
    eprintln!(
        "emulated enclosure {} serving {}",
        deployment.env, args.task
    );
    eprintln!("  gym server:   {}", deployment.endpoint);
    eprintln!("  robot router: {}", deployment.robot_endpoint);
    let environment = [
        ("OFFWORLD_GYM_CONNECT", &deployment.endpoint),
        ("OFFWORLD_GYM_ACCESS_TOKEN", &deployment.token),
        ("OFFWORLD_OPERATOR_TOKEN", &deployment.operator_token),
    ]
    .map(|(key, value)| (key.to_owned(), value.clone()));
    for (key, value) in &environment {
        eprintln!("  {key}={value}");
    }
    super::serve_or_run(&mut signals, &args.command, environment.to_vec()).await
}
