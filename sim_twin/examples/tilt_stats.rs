//! Prints how much the chassis tilts on the terrain over random poses: the
//! figure behind the level-camera approximation.

use offworld_sim_twin::{PlanarPose, SimTwin, TwinConfig};
use rand::{Rng, SeedableRng};

fn main() -> anyhow::Result<()> {
    let mut twin = SimTwin::new(TwinConfig::builtin("monolith")?)?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    let mut tilts: Vec<f32> = Vec::new();
    for _ in 0..300 {
        let pose = PlanarPose {
            x: rng.random_range(-1.5..1.7),
            y: rng.random_range(-1.3..0.9),
            yaw: rng.random_range(0.0..std::f32::consts::TAU),
        };
        twin.teleport(pose)?;
        let p = twin.ground_truth();
        tilts.push(p.pitch.abs().max(p.roll.abs()).to_degrees());
    }
    tilts.sort_by(f32::total_cmp);
    let pct = |q: f32| tilts[((tilts.len() - 1) as f32 * q) as usize];
    println!(
        "chassis tilt (max of |pitch|, |roll|) over 300 spawns: median {:.1}°, p90 {:.1}°, max {:.1}°",
        pct(0.5),
        pct(0.9),
        pct(1.0)
    );
    Ok(())
}
