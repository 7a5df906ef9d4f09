//! Renders one RGBD frame of a world from a robot pose and writes
//! `rgb.png` and `depth.png`, for a person to look at.
//!
//! `cargo run --release --example render_frame -- --x -1 --y 0.3 --yaw -0.3 --out out`

use offworld_runtime::Resolution;
use std::path::PathBuf;

use clap::Parser;
use offworld_sim_twin::camera::{write_depth_png, write_rgb_png, ExactRenderer};
use offworld_sim_twin::{PlanarPose, SimTwin, TwinConfig};

#[derive(Parser)]
struct Args {
    /// Built-in world name.
    #[arg(long, default_value = "monolith_obstacle")]
    world: String,
    /// Robot x, m.
    #[arg(long, default_value_t = -1.2, allow_negative_numbers = true)]
    x: f32,
    /// Robot y, m.
    #[arg(long, default_value_t = 0.2, allow_negative_numbers = true)]
    y: f32,
    /// Robot heading, rad.
    #[arg(long, default_value_t = -0.3, allow_negative_numbers = true)]
    yaw: f32,
    /// Image width.
    #[arg(long, default_value_t = 320)]
    width: u32,
    /// Image height.
    #[arg(long, default_value_t = 240)]
    height: u32,
    /// Also render with the exact per-pixel reference renderer.
    #[arg(long)]
    exact: bool,
    /// Output folder.
    #[arg(long, default_value = "out")]
    out: PathBuf,
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut config = TwinConfig::builtin(&args.world)?;
    config.resolution = Some(Resolution::new(args.width, args.height));
    config.start = PlanarPose {
        x: args.x,
        y: args.y,
        yaw: args.yaw,
    };
    let mut twin = SimTwin::new(config)?;
    std::fs::create_dir_all(&args.out)?;
    let frame = twin.render().clone();
    write_rgb_png(&frame, &args.out.join("rgb.png"))?;
    write_depth_png(&frame, &args.out.join("depth.png"), 5.0)?;
    let pose = twin.camera_pose();
    println!(
        "camera at {:?}, yaw {:.3}, pitch {:.3}, roll {:.3}",
        pose.position, pose.yaw, pose.pitch, pose.roll
    );
    println!(
        "centre depth {:.3} m",
        frame.depth_at(args.width / 2, args.height / 2)
    );
    if args.exact {
        let exact = ExactRenderer::new(*twin.intrinsics(), &twin.scene().world.light, twin.scene());
        let reference = exact.render(&pose);
        write_rgb_png(&reference, &args.out.join("rgb_exact.png"))?;
        write_depth_png(&reference, &args.out.join("depth_exact.png"), 5.0)?;
    }
    println!("wrote {}", args.out.display());
    Ok(())
}
