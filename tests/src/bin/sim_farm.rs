//! `sim_farm`: a sim farm behind the real `zenohd` router, built from the
//! repository's deployment files (TLS, mutual TLS, passwords, ACL): N
//! `sim_twin` processes and one `env_controller`, each a separate process
//! in its role.
//!
//! ```text
//! sim_farm --twins 2                                  # prints the trainer's environment, serves until stdin closes
//! sim_farm --twins 4 -- python3 py_client/examples/random_agent.py
//! sim_farm --twins 2 --twin-profile robot-a.toml      # twins that behave like one robot (docs/twin-profile.md)
//! ```
//! A command after `--` runs with the trainer's environment
//! (`OFFWORLD_ZENOH_CONFIG`, `OFFWORLD_ZENOH_CFG`, `OFFWORLD_GYM_CONNECT`,
//! `OFFWORLD_GYM_ACCESS_TOKEN`); the farm stops when it exits. Without a
//! command the environment is printed as `KEY=VALUE` lines on stdout, then
//! `ready`, and the farm runs until stdin closes.

use std::io::{BufRead, Write};
use std::process::Command;

use anyhow::Context;
use clap::Parser;
use offworld_sim_twin::TwinProfile;
use offworld_tests::site::{RouterSite, SimFarm};

#[derive(Parser)]
#[command(about = "Run a sim farm behind the zenohd router")]
struct Args {
    /// Number of sim twins (envs `sim/farm-0` …).
    #[arg(long, default_value_t = 2)]
    twins: usize,
    /// Task served.
    #[arg(long, default_value = "MonolithDiscrete")]
    task: String,
    /// Every twin behaves like this physical robot (a twin profile,
    /// docs/twin-profile.md; passed to each `sim_twin --profile`).
    #[arg(long, value_name = "FILE", alias = "profile")]
    twin_profile: Option<std::path::PathBuf>,
    /// Command to run against the farm (after `--`).
    #[arg(last = true)]
    command: Vec<String>,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    offworld_program::init_logging();
    let args = Args::parse();
    let profile = match &args.twin_profile {
        Some(path) => {
            // Here, not in each twin's log: a bad file names itself and its field.
            TwinProfile::load(path)?;
            // The twins may run elsewhere in the tree: an absolute path.
            Some(std::fs::canonicalize(path)?)
        }
        None => None,
    };
    let farm = SimFarm::start_profiled(
        RouterSite::start("farm")?,
        "farm",
        args.twins,
        &args.task,
        profile.as_deref(),
    )
    .context("starting the farm")?;
    farm.ready(std::time::Duration::from_secs(60)).await?;
    let envs: Vec<String> = farm.envs.iter().map(ToString::to_string).collect();
    eprintln!("sim farm serving {} ({})", envs.join(", "), args.task);
    let Some((program, rest)) = args.command.split_first() else {
        let mut out = std::io::stdout().lock();
        for (key, value) in farm.trainer_env() {
            writeln!(out, "{key}={value}")?;
        }
        writeln!(out, "OFFWORLD_FARM_ENVS={}", envs.join(","))?;
        writeln!(out, "ready")?;
        out.flush()?;
        drop(out);
        // Until stdin closes (the parent is done), then stop everything.
        let _ = tokio::task::spawn_blocking(|| {
            for line in std::io::stdin().lock().lines() {
                if line.is_err() {
                    break;
                }
            }
        })
        .await;
        return Ok(());
    };
    let status = Command::new(program)
        .args(rest)
        .envs(farm.trainer_env())
        .status()
        .with_context(|| format!("running {program}"))?;
    drop(farm);
    anyhow::ensure!(status.success(), "{program} failed: {status}");
    Ok(())
}
