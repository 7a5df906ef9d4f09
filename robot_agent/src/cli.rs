//! `robot_agent`: serve a real enclosure's robot.
//!
//! `robot_agent --env real/monolith-0 --robot-config robot.toml` connects to
//! tcp/127.0.0.1:7447 unless endpoints are given; without `--robot-config` it
//! drives a ROSbot on rmw_zenoh domain 0 in the root namespace.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::{AgentConfig, Ros2Robot};
use clap::Parser;
use offworld_program::state_dir;
use offworld_program::CommonArgs;
use offworld_program::SealArgs;
use offworld_runtime::shutdown::ShutdownSignals;
use offworld_runtime::{EnvId, Realm};

/// Run the OffWorld robot agent (ROS 2 robot over Zenoh).
#[derive(Parser)]
#[command(version)]
pub struct Args {
    /// Env id served (under `real/`).
    #[arg(long, default_value = "real/monolith-0")]
    env: EnvId,
    /// Agent configuration (TOML, see robot.example.toml); defaults fit a
    /// ROSbot on rmw_zenoh. The Zenoh configuration is `--zenoh-config`.
    #[arg(long, value_name = "TOML")]
    robot_config: Option<PathBuf>,
    /// Enclosure layout for reset navigation (overrides the config).
    #[arg(long)]
    world: Option<String>,
    /// Watchdog window, ms (overrides the config).
    #[arg(long)]
    watchdog_ms: Option<u64>,
    /// File that remembers an engaged e-stop across restarts (overrides
    /// the config; default `offworld/robot_agent/<env>.estop` in
    /// `$XDG_STATE_HOME`, else `~/.local/state`, else, without `HOME`,
    /// `/var/lib`). The agent refuses to start if it cannot write it.
    #[arg(long)]
    estop_latch: Option<PathBuf>,
    /// The site's keys (override the config's `command_key`, `tracker_key`).
    #[command(flatten)]
    seals: SealArgs,
    #[command(flatten)]
    common: CommonArgs,
}

/// Runs `robot_agent` (also `offworld robot`) with these arguments.
pub fn run(args: Args) -> ExitCode {
    offworld_program::run(main_async(args))
}

async fn main_async(args: Args) -> anyhow::Result<()> {
    // Installed first: a SIGTERM during start-up must still zero the base.
    let mut signals = ShutdownSignals::install()?;
    anyhow::ensure!(
        args.env.realm() == Realm::Real,
        "the robot agent serves `real/…` envs, not {}",
        args.env
    );
    let mut config = AgentConfig::load_or_default(args.robot_config.as_deref())?;
    if let Some(world) = args.world {
        config.world = world;
    }
    if let Some(ms) = args.watchdog_ms {
        config.watchdog_ms = ms;
    }
    if args.estop_latch.is_some() {
        config.estop_latch = args.estop_latch;
    }
    if args.seals.command_key.is_some() {
        config.command_key = args.seals.command_key;
    }
    if args.seals.tracker_key.is_some() {
        config.tracker_key = args.seals.tracker_key;
    }
    if config.estop_latch.is_none() {
        // Never none: an agent without a latch would forget an e-stop on restart.
        let file = format!("{}.estop", args.env.to_string().replace('/', "+"));
        config.estop_latch = Some(state_dir::state_file("robot_agent", &file));
    }
    if let Some(path) = &config.estop_latch {
        tracing::info!(path = %path.display(), "e-stop latch");
    }
    config.validate()?;
    let session = args.common.robot_side_config().open().await?;
    let robot = Ros2Robot::connect(&session, &config.graph()?, &config.topics).await?;
    let agent = crate::spawn(&session, args.env.clone(), config, robot).await?;
    tracing::info!(env = %args.env, "robot agent ready; Ctrl-C, SIGTERM or SIGHUP to stop");
    let signal = signals.recv().await;
    tracing::info!(%signal, "stopping the robot and exiting");
    agent.shutdown().await;
    Ok(())
}
