//! Renders frames in a loop (for profilers): `render_loop [WIDTH HEIGHT FRAMES]`.

use offworld_runtime::Resolution;
use offworld_sim_twin::{SimTwin, TwinConfig};

fn main() -> anyhow::Result<()> {
    let args: Vec<u32> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let (w, h, n) = match args[..] {
        [w, h, n] => (w, h, n),
        _ => (320, 240, 500),
    };
    let mut config = TwinConfig::builtin("monolith_obstacle")?;
    config.resolution = Some(Resolution::new(w, h));
    let mut twin = SimTwin::new(config)?;
    let mut checksum = 0.0f64;
    for i in 0..n {
        if i.is_multiple_of(50) {
            twin.execute(0.07, 1.25, 1.2)?;
        }
        checksum += f64::from(twin.render().depth[(w * h / 2) as usize]);
    }
    println!("rendered {n} frames of {w}x{h} (checksum {checksum:.3})");
    Ok(())
}
