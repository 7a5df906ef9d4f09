//! `sim_twin`: serve one simulated enclosure over Zenoh.
//!
//! `sim_twin --env sim/monolith-0 --world monolith_obstacle --clock lockstep`
//! connects to tcp/127.0.0.1:7447 unless endpoints are given.
//!
//! `sim_twin --emulate-hardware --tracker-listen 127.0.0.1:7600` instead
//! behaves like the physical enclosure: the robot's ROS 2 topics and a raw
//! tracker stream, for robot_agent + tracker_agent to drive.
//!
//! `--profile FILE` makes either behave like one physical robot (a twin
//! profile, docs/twin-profile.md): the served twin, or the emulated
//! "physical" robot.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::tracker::TrackerConfig;
use crate::{
    Clock, EmulatedEnclosure, EnclosureConfig, PlanarPose, Randomization, SimTwin, TwinConfig,
    TwinNode, TwinProfile, WorldSpec,
};
use anyhow::Context;
use clap::{Parser, ValueEnum};
use offworld_runtime::ros2::{KeyStyle, RosGraph};
use offworld_runtime::shutdown::ShutdownSignals;
use offworld_runtime::{CommonArgs, EnvId};

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
    /// Behave like the hardware (ROS 2 topics + tracker line stream) instead
    /// of serving `--env`.
    #[arg(long)]
    emulate_hardware: bool,
    /// Emulated robot's ROS 2 domain id (rmw_zenoh keys).
    #[arg(long, default_value_t = 0)]
    ros_domain: u32,
    /// Emulated robot's ROS 2 namespace.
    #[arg(long, default_value = "")]
    ros_namespace: String,
    /// Stream the emulated site's overhead camera under this env
    /// (`offworld/@v1/<env>/overhead/top`).
    #[arg(long)]
    overhead_env: Option<EnvId>,
    /// Emulated camera frame rate, Hz (an Astra runs at 30).
    #[arg(long, default_value_t = 30.0)]
    camera_hz: f64,
    /// Emulated camera resolution WIDTHxHEIGHT (default: the world camera's
    /// own). A smaller camera keeps a pitched profile's per-pixel renderer
    /// affordable in real time.
    #[arg(long, value_name = "WxH", requires = "emulate_hardware")]
    camera_resolution: Option<String>,
    /// The emulated base stops when no velocity command came for this long,
    /// ms (a base with ros2_control's `cmd_vel_timeout`); 0 holds the last
    /// velocity forever (the worst case, the default).
    #[arg(long, default_value_t = 0)]
    base_cmd_timeout_ms: u64,
    /// Where the emulated tracker streams its line protocol (TCP server).
    #[arg(long, default_value = "127.0.0.1:7600")]
    tracker_listen: std::net::SocketAddr,
    #[command(flatten)]
    common: CommonArgs,
}

fn parse_resolution(text: &str) -> anyhow::Result<(u32, u32)> {
    let (w, h) = text
        .split_once('x')
        .context("resolution must look like 320x240")?;
    Ok((w.parse()?, h.parse()?))
}

/// Runs `sim_twin` (also `offworld twin`) with these arguments.
pub fn run(args: Args) -> ExitCode {
    offworld_runtime::session::run_program(main_async(args))
}

async fn main_async(args: Args) -> anyhow::Result<()> {
    let mut signals = ShutdownSignals::install()?;
    anyhow::ensure!(
        args.emulate_hardware || args.env.realm() == offworld_runtime::Realm::Sim,
        "a sim twin serves only `sim/…` envs, not {}",
        args.env
    );
    let world = if args.world.ends_with(".toml") {
        WorldSpec::load(&PathBuf::from(&args.world))?
    } else {
        WorldSpec::builtin(&args.world)?
    };
    let profile = match &args.profile {
        Some(path) => TwinProfile::load(path)?,
        None => TwinProfile::default(),
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
        profile,
    };
    if args.emulate_hardware {
        let resolution = match &args.camera_resolution {
            Some(text) => Some(parse_resolution(text)?),
            None => None,
        };
        let twin = SimTwin::new(TwinConfig {
            resolution,
            ..config
        })?;
        let mut enclosure = EnclosureConfig::rosbot(args.tracker_listen)?;
        enclosure.ros = RosGraph::new(
            KeyStyle::RmwZenoh {
                domain_id: args.ros_domain,
            },
            &args.ros_namespace,
        )?;
        enclosure.camera_hz = args.camera_hz;
        enclosure.overhead_key = match &args.overhead_env {
            Some(env) => Some(env.overhead_key(crate::node::OVERHEAD_CAMERA)?),
            None => None,
        };
        enclosure.cmd_timeout = (args.base_cmd_timeout_ms > 0)
            .then(|| std::time::Duration::from_millis(args.base_cmd_timeout_ms));
        let session = args.common.client_config().open().await?;
        let emulator = EmulatedEnclosure::spawn(&session, twin, enclosure)?;
        tracing::info!(tracker = %emulator.tracker_addr(), "emulating the enclosure hardware; Ctrl-C, SIGTERM or SIGHUP to stop");
        signals.recv().await;
        drop(emulator);
        return Ok(());
    }
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
