//! The simulated Vive tracker: reports the robot's base_link pose as the
//! real tracker_agent would (after calibration), with optional noise.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::physics::BodyPose;

/// Tracker behaviour.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackerConfig {
    /// Pose rate in real-time mode, Hz.
    pub rate_hz: f32,
    /// Position noise (standard deviation), m. 0 = exact.
    pub position_noise_m: f32,
    /// Heading noise (standard deviation), rad.
    pub yaw_noise_rad: f32,
    /// Noise seed.
    pub seed: u64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        Self {
            rate_hz: 60.0,
            position_noise_m: 0.0,
            yaw_noise_rad: 0.0,
            seed: 0,
        }
    }
}

/// Produces tracker readings from ground truth.
#[derive(Debug, Clone)]
pub struct SimTracker {
    config: TrackerConfig,
    rng: ChaCha8Rng,
}

impl SimTracker {
    /// A tracker.
    pub fn new(config: TrackerConfig) -> Self {
        Self {
            config,
            rng: ChaCha8Rng::seed_from_u64(config.seed),
        }
    }

    /// Restarts the noise for an episode that starts at `start`: the same
    /// start (a seeded reset) gives the same readings, as a seeded
    /// `reset()` promises.
    pub fn restart_noise(&mut self, start: [f32; 3]) {
        let mut seed = self.config.seed;
        for v in start {
            seed = splitmix64(seed ^ u64::from(v.to_bits()));
        }
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// The configuration.
    pub fn config(&self) -> &TrackerConfig {
        &self.config
    }

    /// A reading of `truth` (exact when noise is off).
    pub fn read(&mut self, truth: &BodyPose) -> BodyPose {
        let c = self.config;
        if c.position_noise_m <= 0.0 && c.yaw_noise_rad <= 0.0 {
            return *truth;
        }
        let mut pose = *truth;
        for p in &mut pose.position {
            *p += self.rng.sample::<f32, _>(StandardNormal) * c.position_noise_m;
        }
        let dyaw = self.rng.sample::<f32, _>(StandardNormal) * c.yaw_noise_rad;
        pose.yaw += dyaw;
        // Rotate the quaternion about world z by dyaw.
        let (s, cz) = (0.5 * dyaw).sin_cos();
        let [x, y, z, w] = pose.orientation;
        pose.orientation = [
            cz * x - s * y,
            cz * y + s * x,
            cz * z + s * w,
            cz * w - s * z,
        ];
        pose
    }
}

/// SplitMix64's output function: mixes a word into a well-spread seed.
fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}
