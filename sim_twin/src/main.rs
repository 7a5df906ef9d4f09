//! `sim_twin`: serve one simulated enclosure over Zenoh.
//!
//! `sim_twin --env sim/monolith-0 --world monolith_obstacle --clock lockstep`
//! connects to tcp/127.0.0.1:7447 unless endpoints are given.

use std::path::PathBuf;

use anyhow::Context;
use clap::{Parser, ValueEnum};
use offworld_runtime::{CommonArgs, EnvId};
use offworld_sim_twin::tracker::TrackerConfig;
use offworld_sim_twin::{
    Clock, PlanarPose, Randomization, SimTwin, TwinConfig, TwinNode, WorldSpec,
};

#[derive(Debug, Clone, Copy, ValueEnum)]
enum ClockArg {
    /// Simulate each command as fast as possible (training).
    Lockstep,
    /// Pace physics by the wall clock (hardware-like).
    Realtime,
}

#[derive(Parser)]
#[command(about = "Serve a simulated OffWorld enclosure over Zenoh")]
struct Args {
    /// Env id to serve (must be under `sim/`).
    #[arg(long, default_value = "sim/monolith-0")]
    env: EnvId,
    /// Built-in world name or path to a world TOML file.
    #[arg(long, default_value = "monolith")]
    world: String,
    /// Clock.
    #[arg(long, value_enum, default_value_t = ClockArg::Lockstep)]
    clock: ClockArg,
    /// Rendered resolution WIDTHxHEIGHT (the native view resampled).
    #[arg(long, default_value = "320x240")]
    resolution: String,
    /// Tracker position noise (std dev), m.
    #[arg(long, default_value_t = 0.0)]
    tracker_noise: f32,
    /// Depth noise (std dev as a fraction of depth).
    #[arg(long, default_value_t = 0.0)]
    depth_noise: f32,
    /// Fraction of depth pixels dropped.
    #[arg(long, default_value_t = 0.0)]
    depth_dropout: f32,
    /// Per-episode light jitter (±fraction).
    #[arg(long, default_value_t = 0.0)]
    light_jitter: f32,
    /// Per-episode albedo jitter (±fraction).
    #[arg(long, default_value_t = 0.0)]
    albedo_jitter: f32,
    /// Per-episode wheel slip up to this fraction (friction proxy).
    #[arg(long, default_value_t = 0.0)]
    max_slip: f32,
    /// Seed of noise and randomisation.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    #[command(flatten)]
    common: CommonArgs,
}

fn parse_resolution(text: &str) -> anyhow::Result<(u32, u32)> {
    let (w, h) = text
        .split_once('x')
        .context("resolution must look like 320x240")?;
    Ok((w.parse()?, h.parse()?))
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    offworld_runtime::session::init_logging();
    let args = Args::parse();
    anyhow::ensure!(
        args.env.realm() == offworld_runtime::Realm::Sim,
        "a sim twin serves only `sim/…` envs, not {}",
        args.env
    );
    let world = if args.world.ends_with(".toml") {
        WorldSpec::load(&PathBuf::from(&args.world))?
    } else {
        WorldSpec::builtin(&args.world)?
    };
    let config = TwinConfig {
        world,
        resolution: Some(parse_resolution(&args.resolution)?),
        tracker: TrackerConfig {
            position_noise_m: args.tracker_noise,
            seed: args.seed,
            ..TrackerConfig::default()
        },
        randomization: Randomization {
            seed: args.seed,
            depth_noise: args.depth_noise,
            depth_dropout: args.depth_dropout,
            light_jitter: args.light_jitter,
            albedo_jitter: args.albedo_jitter,
            max_slip: args.max_slip,
        },
        start: PlanarPose {
            x: -1.0,
            y: 0.5,
            yaw: 0.0,
        },
    };
    let clock = match args.clock {
        ClockArg::Lockstep => Clock::Lockstep,
        ClockArg::Realtime => Clock::RealTime,
    };
    let twin = SimTwin::new(config)?;
    let session = args.common.client_config().open().await?;
    let node = TwinNode::spawn(&session, args.env.clone(), twin, clock)?;
    tracing::info!(env = %node.env(), "ready; Ctrl-C to stop");
    tokio::signal::ctrl_c().await?;
    drop(node);
    Ok(())
}
