//! `emulated_enclosure`: the whole real-side deployment on one machine —
//! env_controller, robot_agent and tracker_agent as separate processes
//! under `real/<world>-0`, driving `offworld emulate-hardware` as if it
//! were the robot and the lighthouse tracker.
//!
//! ```text
//! emulated_enclosure --task MonolithDiscrete              # serve until Ctrl-C
//! emulated_enclosure -- python3 py_client/examples/random_agent.py --env OffWorldMonolithDiscreteReal-v0
//! ```
//! A command after `--` runs with `OFFWORLD_GYM_CONNECT`,
//! `OFFWORLD_GYM_ACCESS_TOKEN` (a researcher's) and
//! `OFFWORLD_OPERATOR_TOKEN` (an operator's) set; the deployment stops
//! when it exits.

use std::process::Command;

use anyhow::Context;
use clap::Parser;
use offworld_tests::emulated::{EmulatedEnclosure, Options};

#[derive(Parser)]
#[command(about = "Run the real stack against an emulated enclosure")]
struct Args {
    /// Task served (MonolithDiscrete, MonolithContinuous, MonolithObstacleDiscrete, …).
    #[arg(long, default_value = "MonolithDiscrete")]
    task: String,
    /// Robot agent watchdog window, ms (a real robot: 200).
    #[arg(long, default_value_t = 200)]
    watchdog_ms: u64,
    /// Command to run against the deployment (after `--`).
    #[arg(last = true)]
    command: Vec<String>,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut options = Options::new(&args.task)?;
    options.watchdog_ms = args.watchdog_ms;
    let deployment = EmulatedEnclosure::start(&options).context("starting the deployment")?;
    deployment
        .ready(std::time::Duration::from_secs(60))
        .await
        .map_err(anyhow::Error::msg)?;
    eprintln!(
        "emulated enclosure {} serving {}",
        deployment.env, args.task
    );
    eprintln!("  OFFWORLD_GYM_CONNECT={}", deployment.endpoint);
    eprintln!("  OFFWORLD_GYM_ACCESS_TOKEN={}", deployment.token);
    eprintln!("  OFFWORLD_OPERATOR_TOKEN={}", deployment.operator_token);
    let Some((program, rest)) = args.command.split_first() else {
        eprintln!("Ctrl-C to stop");
        offworld_runtime::shutdown::signalled().await?;
        return Ok(());
    };
    let status = Command::new(program)
        .args(rest)
        .env("OFFWORLD_GYM_CONNECT", &deployment.endpoint)
        .env("OFFWORLD_GYM_ACCESS_TOKEN", &deployment.token)
        .env("OFFWORLD_OPERATOR_TOKEN", &deployment.operator_token)
        .status()
        .with_context(|| format!("running {program}"))?;
    drop(deployment);
    anyhow::ensure!(status.success(), "{program} failed: {status}");
    Ok(())
}
