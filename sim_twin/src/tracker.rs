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
