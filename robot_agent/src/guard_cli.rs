//! The command line of `base_guard` (also `offworld guard`): the robot's
//! independent safety process. Runs beside the robot agent on the robot's
//! computer (its own systemd unit, restarted on failure) as a client of
//! the robot's Zenoh router, and zeroes the base when the agent dies,
//! freezes or goes silent mid-motion; see [`crate::guard`].
//!
//! ```text
//! base_guard --env real/monolith-0 --robot-config robot.toml --mode client --connect tcp/127.0.0.1:7447
//! ```

use std::path::PathBuf;
use std::process::ExitCode;

use crate::{guard, AgentConfig};
use clap::Parser;
use offworld_program::CommonArgs;
use offworld_runtime::shutdown::ShutdownSignals;
use offworld_runtime::{EnvId, Realm};

/// Zero the robot's base when the robot agent dies, freezes or goes silent.
#[derive(Parser)]
#[command(version)]
pub struct Args {
    /// Env id whose robot is guarded (under `real/…`).
    #[arg(long, default_value = "real/monolith-0")]
    env: EnvId,
    /// The robot agent's configuration (TOML): the ROS graph, topics and
    /// the `[guard]` timings are read from it.
    #[arg(long)]
    robot_config: Option<PathBuf>,
    /// Stop a moving base after this long without a velocity command, ms
    /// (overrides the config).
    #[arg(long)]
    stale_ms: Option<u64>,
    #[command(flatten)]
    common: CommonArgs,
}

/// Runs `base_guard` (also `offworld guard`) with these arguments, on one
/// runtime thread: it stays small beside the agent.
pub fn run(args: Args) -> ExitCode {
    offworld_program::run_on(Some(1), guard_base(args))
}

async fn guard_base(args: Args) -> anyhow::Result<()> {
    let mut signals = ShutdownSignals::install()?;
    anyhow::ensure!(
        args.env.realm() == Realm::Real,
        "the base guard guards `real/…` envs, not {}",
        args.env
    );
    let mut config = AgentConfig::load_or_default(args.robot_config.as_deref())?;
    if let Some(ms) = args.stale_ms {
        config.guard.stale_ms = ms;
    }
    config.validate()?;
    let session = args.common.robot_side_config().open().await?;
    let guard = guard::spawn(
        &session,
        &args.env,
        &config.graph()?,
        &config.topics,
        config.guard,
    )
    .await?;
    tracing::info!(env = %args.env, stale_ms = config.guard.stale_ms, "base guard ready");
    let signal = signals.recv().await;
    tracing::info!(%signal, "base guard exiting");
    guard.shutdown().await;
    Ok(())
}
