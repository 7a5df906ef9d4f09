//! `sim_twin`: serve one simulated enclosure over Zenoh.
//!
//! `sim_twin --env sim/monolith-0 --world monolith_obstacle --clock lockstep`
//! connects to tcp/127.0.0.1:7447 unless endpoints are given.
//!
//! `--profile FILE` makes it behave like one physical robot (a twin
//! profile, docs/twin-profile.md). The same twin flags ([`TwinArgs`])
//! shape the emulated hardware of `offworld emulate-hardware`
//! (`offworld_deploy`).

use std::path::PathBuf;
use std::process::ExitCode;

use crate::tracker::TrackerConfig;
use crate::{
    Clock, PlanarPose, Randomization, SimTwin, TwinConfig, TwinNode, TwinProfile, WorldSpec,
    RENDER_THREADS_LIMIT,
};
use clap::{Parser, ValueEnum};
use offworld_program::CommonArgs;
use offworld_runtime::shutdown::ShutdownSignals;
use offworld_runtime::{EnvId, Resolution};

#[derive(Debug, Clone, Copy, ValueEnum)]
enum ClockArg {
    /// Simulate each command as fast as possible (training).
    Lockstep,
    /// Pace physics by the wall clock (hardware-like).
    Realtime,
}

/// Serve a simulated OffWorld enclosure over Zenoh.
#[derive(Parser)]
#[command(version)]
pub struct Args {
    /// Env id to serve (must be under `sim/`).
    #[arg(long, default_value = "sim/monolith-0")]
    env: EnvId,
    /// Clock.
    #[arg(long, value_enum, default_value_t = ClockArg::Lockstep)]
    clock: ClockArg,
    /// Rendered resolution WIDTHxHEIGHT (the native view resampled).
    #[arg(long, default_value = "320x240")]
    resolution: Resolution,
    #[command(flatten)]
    twin: TwinArgs,
    #[command(flatten)]
    common: CommonArgs,
}

/// What the twin simulates: its world, noise, randomisation and profile.
#[derive(clap::Args)]
pub struct TwinArgs {
    /// Built-in world name or path to a world TOML file.
    #[arg(long, default_value = "monolith")]
    world: String,
    /// Tracker position noise (std dev), m.
    #[arg(long, default_value_t = 0.0)]
    tracker_noise: f32,
    /// Depth noise (std dev as a fraction of depth); with `--profile`, the
    /// profile's `[depth]` says it instead.
    #[arg(long, default_value_t = 0.0, conflicts_with = "profile")]
    depth_noise: f32,
    /// Fraction of depth pixels dropped; with `--profile`, the profile's
    /// `[depth]` says it instead.
    #[arg(long, default_value_t = 0.0, conflicts_with = "profile")]
    depth_dropout: f32,
    /// Twin profile (TOML, docs/twin-profile.md): the physical robot this
    /// twin (or the emulated hardware) behaves like. Default: the nominal twin.
    #[arg(long, value_name = "FILE")]
    profile: Option<PathBuf>,
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
    /// Threads each frame is rendered on: more pays while cores idle
    /// (one twin on the machine); keep 1 where every core steps a twin.
    #[arg(long, default_value_t = 1,
          value_parser = clap::value_parser!(u16).range(1..=i64::from(RENDER_THREADS_LIMIT)))]
    render_threads: u16,
}

impl TwinArgs {
    /// The twin these flags describe, rendering at `resolution` (`None`:
    /// the world camera's own); reads the world and profile files.
    pub fn config(&self, resolution: Option<Resolution>) -> anyhow::Result<TwinConfig> {
        let world = if self.world.ends_with(".toml") {
            WorldSpec::load(&PathBuf::from(&self.world))?
        } else {
            WorldSpec::builtin(&self.world)?
        };
        let profile = match &self.profile {
            Some(path) => TwinProfile::load(path)?,
            None => TwinProfile::default(),
        };
        Ok(TwinConfig {
            world,
            resolution,
            tracker: TrackerConfig {
                position_noise_m: self.tracker_noise,
                seed: self.seed,
                ..TrackerConfig::default()
            },
            randomization: Randomization {
                seed: self.seed,
                depth_noise: self.depth_noise,
                depth_dropout: self.depth_dropout,
                light_jitter: self.light_jitter,
                albedo_jitter: self.albedo_jitter,
                max_slip: self.max_slip,
            },
            start: PlanarPose {
                x: -1.0,
                y: 0.5,
                yaw: 0.0,
            },
            profile,
            render_threads: self.render_threads.into(),
        })
    }
}

/// Runs `sim_twin` (also `offworld twin`) with these arguments.
pub fn run(args: Args) -> ExitCode {
    offworld_program::run(main_async(args))
}

async fn main_async(args: Args) -> anyhow::Result<()> {
    let mut signals = ShutdownSignals::install()?;
    anyhow::ensure!(
        args.env.realm() == offworld_runtime::Realm::Sim,
        "a sim twin serves only `sim/…` envs, not {} (the real stack drives \
         emulated hardware: `offworld emulate-hardware`)",
        args.env
    );
    let config = args.twin.config(Some(args.resolution))?;
    let clock = match args.clock {
        ClockArg::Lockstep => Clock::Lockstep,
        ClockArg::Realtime => Clock::RealTime,
    };
    let twin = SimTwin::new(config)?;
    let session = args.common.client_config().open().await?;
    let node = TwinNode::spawn(&session, args.env.clone(), twin, clock)?;
    tracing::info!(env = %node.env(), "ready; Ctrl-C, SIGTERM or SIGHUP to stop");
    tokio::select! {
        _ = signals.recv() => {}
        () = until_stuck(&node) => {
            // The stuck thread cannot be stopped: exit (the node has
            // withdrawn the twin) so that a supervisor starts a fresh one.
            tracing::error!(env = %node.env(), "exiting with status {STUCK_EXIT}: restart this twin");
            std::process::exit(STUCK_EXIT);
        }
    }
    drop(node);
    Ok(())
}

/// Exit status of a twin whose simulation thread got stuck (`EX_SOFTWARE`).
const STUCK_EXIT: i32 = 70;

/// Returns once `node`'s simulation thread is stuck ([`TwinNode::stuck`]).
async fn until_stuck(node: &TwinNode) {
    while !node.stuck() {
        tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    }
}
