//! `offworld emulate-hardware`: a sim twin behaving like the physical
//! enclosure — the robot's ROS 2 topics and a raw tracker line stream —
//! for `robot_agent` and `tracker_agent` to drive.
//!
//! ```text
//! offworld emulate-hardware --tracker-listen 127.0.0.1:7600 [--profile robot-a.toml]
//! ```

use std::process::ExitCode;

use offworld_program::CommonArgs;
use offworld_runtime::ros2::{KeyStyle, RosGraph};
use offworld_runtime::shutdown::ShutdownSignals;
use offworld_runtime::{EnvId, Resolution};
use offworld_sim_twin::cli::TwinArgs;
use offworld_sim_twin::node::OVERHEAD_CAMERA;
use offworld_sim_twin::SimTwin;

use crate::hardware::{EmulatedHardware, HardwareConfig};

/// Emulate the enclosure's hardware with a sim twin.
#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    twin: TwinArgs,
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
    #[arg(long, value_name = "WxH")]
    camera_resolution: Option<Resolution>,
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

/// Runs `offworld emulate-hardware` with these arguments.
pub fn run(args: Args) -> ExitCode {
    offworld_program::run(emulate(args))
}

async fn emulate(args: Args) -> anyhow::Result<()> {
    let mut signals = ShutdownSignals::install()?;
    let twin = SimTwin::new(args.twin.config(args.camera_resolution)?)?;
    let mut hardware = HardwareConfig::rosbot(args.tracker_listen)?;
    hardware.ros = RosGraph::new(
        KeyStyle::RmwZenoh {
            domain_id: args.ros_domain,
        },
        &args.ros_namespace,
    )?;
    hardware.camera_hz = args.camera_hz;
    hardware.overhead_key = match &args.overhead_env {
        Some(env) => Some(env.overhead_key(OVERHEAD_CAMERA)?),
        None => None,
    };
    hardware.cmd_timeout = (args.base_cmd_timeout_ms > 0)
        .then(|| std::time::Duration::from_millis(args.base_cmd_timeout_ms));
    let session = args.common.client_config().open().await?;
    let emulator = EmulatedHardware::spawn(&session, twin, hardware)?;
    tracing::info!(tracker = %emulator.tracker_addr(), "emulating the enclosure hardware; Ctrl-C, SIGTERM or SIGHUP to stop");
    signals.recv().await;
    drop(emulator);
    Ok(())
}
