//! `offworld farm`: a sim farm behind the real `zenohd` router with the
//! deployment's own files (TLS, mutual TLS, passwords, access control):
//! `--twins` sim twin processes and one gym server, each a separate
//! process in its role. Needs `zenohd` on `PATH` and `openssl`.
//!
//! ```text
//! offworld farm --twins 2                                   # serve until Ctrl-C, printing how to connect
//! offworld farm --twins 4 -- python3 py_client/examples/random_agent.py --env-id sim/farm-0
//! ```

use std::io::Write;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use offworld_runtime::shutdown::ShutdownSignals;
use offworld_sim_twin::TwinProfile;

use crate::farm::SimFarm;
use crate::site::{Link, RouterSite};

/// How long the farm may take to come up (router, twins, gym server).
const READY_LIMIT: Duration = Duration::from_secs(60);

/// The farm's envs are `sim/farm-<i>`.
const FARM_NAME: &str = "farm";

const EXAMPLES: &str = "\
Examples:
  offworld farm --twins 2                     # serve sim/farm-0 and sim/farm-1 until Ctrl-C
  offworld farm --twins 2 --twin-profile robot-a.toml
  offworld farm --twins 4 -- python3 py_client/examples/random_agent.py --env-id sim/farm-0

How to connect is printed as KEY=VALUE lines on standard output:
OFFWORLD_ZENOH_CONFIG (the trainer's role file), OFFWORLD_ZENOH_CFG (its
certificate and password), OFFWORLD_GYM_CONNECT, OFFWORLD_GYM_ACCESS_TOKEN
and OFFWORLD_FARM_ENVS (comma-separated). A command after `--` runs with
them set; the farm stops when it exits, with its exit status.";

/// Run a sim farm behind the zenohd router.
#[derive(clap::Args)]
#[command(after_help = EXAMPLES)]
pub struct Args {
    /// Number of sim twins (envs `sim/farm-0` …).
    #[arg(long, default_value_t = 2, value_parser = clap::value_parser!(u16).range(1..=64))]
    twins: u16,
    /// Task served (a task of tasks.toml).
    #[arg(long, default_value = "MonolithDiscrete")]
    task: String,
    /// Every twin behaves like this physical robot (a twin profile,
    /// docs/twin-profile.md).
    #[arg(long, value_name = "FILE")]
    twin_profile: Option<std::path::PathBuf>,
    /// Command to run against the farm (after `--`).
    #[arg(last = true, value_name = "COMMAND")]
    command: Vec<String>,
}

/// Runs `offworld farm` with these arguments.
pub fn run(args: Args) -> ExitCode {
    offworld_program::run(farm(args))
}

async fn farm(args: Args) -> anyhow::Result<ExitCode> {
    // Refused before anything starts, naming the known tasks.
    offworld_env_controller::Task::by_name(&args.task)
        .with_context(|| format!("--task {}: not a task of tasks.toml", args.task))?;
    let profile = match &args.twin_profile {
        Some(path) => {
            // Here, not in each twin's log: a bad file names itself and its field.
            TwinProfile::load(path)?;
            // The twins run elsewhere in the tree: an absolute path.
            Some(
                std::fs::canonicalize(path)
                    .with_context(|| format!("--twin-profile {}", path.display()))?,
            )
        }
        None => None,
    };
    // Before anything starts: a stop during the start is answered.
    let mut signals = ShutdownSignals::install()?;
    eprintln!(
        "starting a sim farm of {} twins ({})…",
        args.twins, args.task
    );
    let start = async {
        let site = RouterSite::start(FARM_NAME)
            .context("starting the router (is `zenohd` on PATH? `.ci/setup` installs it)")?;
        let farm = SimFarm::start_profiled(
            site,
            FARM_NAME,
            usize::from(args.twins),
            &args.task,
            profile.as_deref(),
            Link::LocalSocket,
        )
        .context("starting the farm")?;
        farm.ready(READY_LIMIT)
            .await
            .context("the farm did not come up")?;
        Ok(farm)
    };
    let farm = match super::started_unless_stopped(&mut signals, start).await? {
        Ok(farm) => farm,
        Err(stopped) => return Ok(stopped),
    };
    let envs: Vec<String> = farm.envs.iter().map(ToString::to_string).collect();
    let mut environment = farm.trainer_env();
    environment.push(("OFFWORLD_FARM_ENVS".to_owned(), envs.join(",")));
    eprintln!("sim farm serving {} ({})", envs.join(", "), args.task);
    eprintln!("  trainers: {}", farm.site.trainer_endpoint);
    eprintln!("  site:     {} (mutual TLS)", farm.site.site_endpoint);
    eprintln!(
        "  farm:     {} (this host's twins and gym server)",
        farm.site.local_endpoint()
    );
    if args.command.is_empty() {
        let mut out = std::io::stdout().lock();
        for (key, value) in &environment {
            writeln!(out, "{key}={value}")?;
        }
        out.flush()?;
        drop(out);
    }
    super::serve_or_run(&mut signals, &args.command, environment).await
}
