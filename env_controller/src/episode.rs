//! Episode rules: reward and termination from the robot's pose, and the
//! seeded spawn sampler. Pure functions of data; no I/O.

use offworld_runtime::msg::{Pose2D, StepInfo};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::task::Task;

/// Why an episode ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum EndReason {
    /// Within the success radius of the monolith.
    Success,
    /// Left the boundary.
    OutOfBounds,
    /// Reached the step limit.
    StepLimit,
    /// Stopped by something outside the task (disconnect, tracking loss…).
    Aborted(String),
}

impl EndReason {
    /// Stable text stored with the episode.
    pub fn as_str(&self) -> &str {
        match self {
            EndReason::Success => "success",
            EndReason::OutOfBounds => "out_of_bounds",
            EndReason::StepLimit => "step_limit",
            EndReason::Aborted(why) => why,
        }
    }
}

/// The result of one step.
#[derive(Debug, Clone, PartialEq)]
pub struct Outcome {
    /// +1 on success, else 0 (no shaping).
    pub reward: f64,
    /// Ended by the task.
    pub terminated: bool,
    /// Cut at the step limit.
    pub truncated: bool,
    /// Set when the episode is over.
    pub end: Option<EndReason>,
}

/// Planar distance from (`x`, `y`) to the monolith's centre, m.
pub fn distance_to_goal(task: &Task, x: f64, y: f64) -> f64 {
    let m = task.world.monolith.center;
    ((x - f64::from(m[0])).powi(2) + (y - f64::from(m[1])).powi(2)).sqrt()
}

/// The `info` of step `step` of episode `episode_id`, reached at `pose`
/// with `outcome` (none for the reset); the ground truth only if
/// `share_pose`.
pub fn step_info(
    task: &Task,
    episode_id: u64,
    step: u32,
    pose: &Pose2D,
    outcome: Option<&Outcome>,
    share_pose: bool,
) -> StepInfo {
    let end = outcome.and_then(|o| o.end.as_ref());
    let mut info = StepInfo {
        episode_id,
        step,
        is_success: end == Some(&EndReason::Success),
        end_reason: end.map(|e| e.as_str().to_owned()).unwrap_or_default(),
        ..StepInfo::default()
    };
    if share_pose {
        info.pose_shared = true;
        info.x = pose.x;
        info.y = pose.y;
        info.yaw = pose.yaw;
        info.distance_to_goal = distance_to_goal(task, pose.x, pose.y);
    }
    info
}

/// Judges the pose reached after step number `step` (1-based).
pub fn judge(task: &Task, x: f64, y: f64, step: u32) -> Outcome {
    let t = &task.world.task;
    if distance_to_goal(task, x, y) <= f64::from(t.success_radius) {
        return Outcome {
            reward: 1.0,
            terminated: true,
            truncated: false,
            end: Some(EndReason::Success),
        };
    }
    // Bounds are f32 data: compare in f32 so a pose exactly on the line is inside.
    let inside = |v: f64, r: [f32; 2]| (v as f32) >= r[0] && (v as f32) <= r[1];
    if !(inside(x, t.boundary_x) && inside(y, t.boundary_y)) {
        return Outcome {
            reward: 0.0,
            terminated: true,
            truncated: false,
            end: Some(EndReason::OutOfBounds),
        };
    }
    if step >= task.episode.max_steps {
        return Outcome {
            reward: 0.0,
            terminated: false,
            truncated: true,
            end: Some(EndReason::StepLimit),
        };
    }
    Outcome {
        reward: 0.0,
        terminated: false,
        truncated: false,
        end: None,
    }
}

/// Samples spawn poses with the episode's RNG.
#[derive(Debug, Clone)]
pub struct SpawnSampler {
    rng: ChaCha8Rng,
}

/// Rejection-sampling budget; the spawn region is mostly free, so this is
/// only reached by an impossible world file.
const MAX_TRIES: usize = 100_000;

impl SpawnSampler {
    /// A sampler seeded with `seed`.
    pub fn new(seed: u64) -> Self {
        Self {
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }

    /// Restarts the stream from `seed` (gymnasium's `reset(seed=…)`).
    pub fn reseed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    /// A uniform position in the spawn region at least the configured
    /// distances from the monolith centre and from every boulder's
    /// footprint, with a uniform heading in [0, 2π).
    pub fn sample(&mut self, task: &Task) -> Option<Pose2D> {
        let t = &task.world.task;
        let m = task.world.monolith.center;
        for _ in 0..MAX_TRIES {
            let x = self.rng.random_range(t.spawn_x[0]..=t.spawn_x[1]);
            let y = self.rng.random_range(t.spawn_y[0]..=t.spawn_y[1]);
            let yaw = self.rng.random_range(0.0..std::f64::consts::TAU);
            if ((x - m[0]).powi(2) + (y - m[1]).powi(2)).sqrt() < t.spawn_min_monolith_distance {
                continue;
            }
            let clear = task.world.boulders.iter().all(|b| {
                let dx = ((x - b.center[0]).abs() - b.size[0] * 0.5).max(0.0);
                let dy = ((y - b.center[1]).abs() - b.size[1] * 0.5).max(0.0);
                (dx * dx + dy * dy).sqrt() >= t.spawn_min_boulder_distance
            });
            if clear {
                return Some(Pose2D {
                    x: f64::from(x),
                    y: f64::from(y),
                    yaw,
                });
            }
        }
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn task(name: &str) -> Task {
        Task::by_name(name).expect("task")
    }

    #[test]
    fn reward_and_termination_table() {
        let t = task("MonolithDiscrete");
        let (mx, my) = (0.0109, -0.2034);
        // (x, y, step) → (reward, terminated, truncated, end)
        let cases = [
            (mx + 0.39, my, 5, 1.0, true, false, Some(EndReason::Success)),
            (mx, my + 0.40, 5, 1.0, true, false, Some(EndReason::Success)),
            (mx + 0.41, my, 5, 0.0, false, false, None),
            // Success wins on the last step.
            (
                mx + 0.2,
                my,
                100,
                1.0,
                true,
                false,
                Some(EndReason::Success),
            ),
            (1.81, 0.0, 5, 0.0, true, false, Some(EndReason::OutOfBounds)),
            (
                -1.61,
                0.0,
                5,
                0.0,
                true,
                false,
                Some(EndReason::OutOfBounds),
            ),
            (0.0, 1.01, 5, 0.0, true, false, Some(EndReason::OutOfBounds)),
            (
                0.0,
                -1.46,
                5,
                0.0,
                true,
                false,
                Some(EndReason::OutOfBounds),
            ),
            (1.80, 1.00, 5, 0.0, false, false, None),
            (1.0, 0.5, 99, 0.0, false, false, None),
            (1.0, 0.5, 100, 0.0, false, true, Some(EndReason::StepLimit)),
            // Out of bounds on the last step is a termination, not a truncation.
            (
                1.9,
                0.5,
                100,
                0.0,
                true,
                false,
                Some(EndReason::OutOfBounds),
            ),
        ];
        for (x, y, step, reward, terminated, truncated, end) in cases {
            let o = judge(&t, x, y, step);
            assert_eq!(
                (o.reward, o.terminated, o.truncated, o.end.clone()),
                (reward, terminated, truncated, end),
                "at ({x}, {y}) step {step}"
            );
        }
    }

    #[test]
    fn spawns_respect_bounds_and_clearances_and_are_deterministic() {
        for name in ["MonolithDiscrete", "MonolithObstacleDiscrete"] {
            let t = task(name);
            let mut sampler = SpawnSampler::new(42);
            let poses: Vec<Pose2D> = (0..2000)
                .map(|_| sampler.sample(&t).expect("spawn"))
                .collect();
            let m = t.world.monolith.center;
            for p in &poses {
                assert!(
                    (-1.52..=1.72).contains(&p.x) && (-1.37..=0.92).contains(&p.y),
                    "{p:?}"
                );
                assert!((0.0..std::f64::consts::TAU).contains(&p.yaw));
                let d = ((p.x - f64::from(m[0])).powi(2) + (p.y - f64::from(m[1])).powi(2)).sqrt();
                assert!(d >= 0.5, "{p:?} too close to the monolith");
                for b in &t.world.boulders {
                    let dx = ((p.x - f64::from(b.center[0])).abs() - f64::from(b.size[0]) * 0.5)
                        .max(0.0);
                    let dy = ((p.y - f64::from(b.center[1])).abs() - f64::from(b.size[1]) * 0.5)
                        .max(0.0);
                    assert!(
                        (dx * dx + dy * dy).sqrt() >= 0.299,
                        "{p:?} too close to a boulder"
                    );
                }
            }
            // Uniform heading: each quarter turn gets about a quarter of spawns.
            for q in 0..4 {
                let lo = q as f64 * std::f64::consts::FRAC_PI_2;
                let n = poses
                    .iter()
                    .filter(|p| p.yaw >= lo && p.yaw < lo + std::f64::consts::FRAC_PI_2)
                    .count();
                assert!((400..600).contains(&n), "quarter {q}: {n}");
            }
            let mut again = SpawnSampler::new(42);
            assert_eq!(again.sample(&t), Some(poses[0]));
            again.reseed(42);
            assert_eq!(again.sample(&t), Some(poses[0]));
            assert_ne!(SpawnSampler::new(43).sample(&t), Some(poses[0]));
        }
    }
}
