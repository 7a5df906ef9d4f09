//! When the base moves: latency and settle time from the wheel-odometry
//! time series of recorded episodes.
//!
//! Where a step ends says little about latency (a late motion ends in the
//! same place, later) and mixes the settle time with traction. The base's
//! own speeds over time show both: each command (its `/cmd_vel` time,
//! speeds and duration) predicts the twin's servo — the target applies
//! `latency_s` after the command and lasts its duration, the servo ramps
//! toward it within the acceleration limits the settle time gives
//! ([`offworld_sim_twin::physics`]'s model) — and the fit compares that
//! prediction with every odometry sample.
//!
//! What is fitted is what the twin needs: the time from the controller's
//! command to the base's reaction as the controller sees it. On a robot
//! that is the base's own latency plus the robot agent's share (transport,
//! and the wait for its next control tick: half a tick on average). The
//! settle time is the slower of the agent's velocity ramp and the base's
//! servo (the two limit in series; the twin models one).

use offworld_runtime::world::RobotSpec;
use offworld_sim_twin::TwinProfile;

use crate::recorded::RecordedEpisode;

/// Radians per second that weigh as much as one metre per second.
const YAW_RATE_WEIGHT: f64 = 0.3;
/// The servo model's integration step, s (the twin's physics runs at
/// 1/60 s; finer here so the fitted latency is not quantised).
const DT: f64 = 1.0 / 1200.0;
/// Odometry this long after a command's end still shows its ramp down, s.
const TAIL_S: f64 = 1.0;
/// Fewer odometry samples per moving step than this: no time series (a
/// twin in lockstep records one per step); the timing is not fitted.
pub const MIN_SAMPLES_PER_STEP: f64 = 4.0;

/// A command as the base was given it, in seconds from its episode's first.
#[derive(Debug, Clone, Copy)]
struct Command {
    at: f64,
    linear: f64,
    angular: f64,
    duration: f64,
}

/// One sample of the base's speeds, seconds from the episode's first command.
#[derive(Debug, Clone, Copy)]
struct Sample {
    at: f64,
    linear: f64,
    angular: f64,
}

/// An episode's commands and the odometry samples that show their effect.
#[derive(Debug, Clone)]
struct Timeline {
    commands: Vec<Command>,
    samples: Vec<Sample>,
}

/// The timing data of recorded episodes.
#[derive(Debug, Clone)]
pub struct TimingData {
    timelines: Vec<Timeline>,
    /// The world's robot (its nominal acceleration limits and top speed).
    robot: RobotSpec,
    /// Moving steps and samples in all.
    moving_steps: usize,
    samples: usize,
}

impl TimingData {
    /// The commands and odometry of `episodes`; `None` when they hold no
    /// odometry time series (fewer than [`MIN_SAMPLES_PER_STEP`] per moving
    /// step near the commands).
    pub fn from_episodes(episodes: &[RecordedEpisode], robot: &RobotSpec) -> Option<Self> {
        let mut timelines = Vec::new();
        let (mut moving_steps, mut samples) = (0, 0);
        for episode in episodes {
            let mut commands: Vec<(u64, Command)> = episode
                .steps
                .iter()
                .filter_map(|s| {
                    let at = s.commanded_ns?;
                    let step = &s.step;
                    let moving = step.duration_s > 0.0
                        && (step.linear_x != 0.0 || step.angular_z != 0.0)
                        && [step.linear_x, step.angular_z, step.duration_s]
                            .iter()
                            .all(|v| v.is_finite());
                    moving.then_some((
                        at,
                        Command {
                            at: 0.0,
                            linear: step.linear_x,
                            angular: step.angular_z,
                            duration: step.duration_s,
                        },
                    ))
                })
                .collect();
            let Some(&(origin, _)) = commands.first() else {
                continue;
            };
            let seconds = |ns: u64| (ns as f64 - origin as f64) * 1e-9;
            for (at, command) in &mut commands {
                command.at = seconds(*at);
            }
            let commands: Vec<Command> = commands.into_iter().map(|(_, c)| c).collect();
            let end = commands.last().map_or(0.0, |c| c.at + c.duration + TAIL_S);
            // From the first command on: before it the base may still be
            // finishing the reset's drive, which no command explains.
            let timeline_samples: Vec<Sample> = episode
                .odometry
                .iter()
                .map(|o| Sample {
                    at: seconds(o.at_ns),
                    linear: o.linear,
                    angular: o.angular,
                })
                .filter(|s| (0.0..=end).contains(&s.at))
                .collect();
            moving_steps += commands.len();
            samples += timeline_samples.len();
            timelines.push(Timeline {
                commands,
                samples: timeline_samples,
            });
        }
        if moving_steps == 0 || (samples as f64) < MIN_SAMPLES_PER_STEP * moving_steps as f64 {
            return None;
        }
        Some(Self {
            timelines,
            robot: robot.clone(),
            moving_steps,
            samples,
        })
    }

    /// Moving steps with a command time.
    pub fn moving_steps(&self) -> usize {
        self.moving_steps
    }

    /// Odometry samples used.
    pub fn samples(&self) -> usize {
        self.samples
    }

    /// Mean squared speed error (m²/s², yaw rate weighted) of the servo
    /// with `profile`'s latency and settle time against the odometry.
    pub fn cost(&self, profile: &TwinProfile) -> f64 {
        let latency = f64::from(profile.motion.latency_s);
        // The twin's own servo limits for this settle time.
        let (linear_accel, angular_accel) = profile.motion.accel_limits(&self.robot);
        let (linear_accel, angular_accel) = (f64::from(linear_accel), f64::from(angular_accel));
        let (mut sum, mut n) = (0.0, 0usize);
        for timeline in &self.timelines {
            let mut servo = Servo::default();
            for sample in &timeline.samples {
                servo.run_until(
                    sample.at,
                    |t| target(&timeline.commands, latency, t),
                    (linear_accel, angular_accel),
                );
                let dv = servo.linear - sample.linear;
                let dw = (servo.angular - sample.angular) * YAW_RATE_WEIGHT;
                sum += dv * dv + dw * dw;
                n += 1;
            }
        }
        if n == 0 {
            return f64::INFINITY;
        }
        sum / n as f64
    }
}

/// The speeds the base is told at `t`: a command's, from its time plus the
/// latency for its duration; zero between commands.
fn target(commands: &[Command], latency: f64, t: f64) -> (f64, f64) {
    // Commands are in time order and never overlap (a step waits for the
    // one before it): the last one begun is the only candidate.
    let begun = commands.partition_point(|c| c.at + latency <= t);
    match begun.checked_sub(1).map(|i| &commands[i]) {
        Some(c) if t < c.at + latency + c.duration => (c.linear, c.angular),
        _ => (0.0, 0.0),
    }
}

/// The twin's velocity servo: each speed ramps toward its target within
/// its acceleration limit.
#[derive(Debug, Default)]
struct Servo {
    time: f64,
    linear: f64,
    angular: f64,
}

impl Servo {
    fn run_until(&mut self, until: f64, target: impl Fn(f64) -> (f64, f64), accel: (f64, f64)) {
        let ramp = |current: f64, target: f64, max_delta: f64| {
            current + (target - current).clamp(-max_delta, max_delta)
        };
        while self.time + DT <= until {
            let (linear, angular) = target(self.time);
            self.linear = ramp(self.linear, linear, accel.0 * DT);
            self.angular = ramp(self.angular, angular, accel.1 * DT);
            self.time += DT;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn data(commands: Vec<Command>, samples: Vec<Sample>) -> TimingData {
        TimingData {
            moving_steps: commands.len(),
            samples: samples.len(),
            timelines: vec![Timeline { commands, samples }],
            robot: offworld_runtime::world::WorldSpec::builtin("monolith")
                .expect("world")
                .robot,
        }
    }

    fn profile(latency: f32, settle: f32) -> TwinProfile {
        let mut p = TwinProfile::default();
        p.motion.latency_s = latency;
        p.motion.settle_time_s = Some(settle);
        p
    }

    #[test]
    fn the_servo_model_predicts_a_delayed_ramp_exactly() {
        // 0.35 m/s for 1 s, 0.15 s late, settle 0.7 s: 1 m/s² ramp.
        let command = Command {
            at: 0.0,
            linear: 0.35,
            angular: 0.0,
            duration: 1.0,
        };
        let expected = |t: f64| {
            let up = (t - 0.15).clamp(0.0, 0.35);
            let down = (t - 1.15).max(0.0);
            (up - down).max(0.0)
        };
        let samples: Vec<Sample> = (0..60)
            .map(|i| {
                let at = f64::from(i) / 30.0;
                Sample {
                    at,
                    linear: expected(at),
                    angular: 0.0,
                }
            })
            .collect();
        let data = data(vec![command], samples);
        assert!(data.cost(&profile(0.15, 0.7)) < 1e-5);
        // Any other latency or settle time predicts worse.
        for other in [profile(0.10, 0.7), profile(0.2, 0.7), profile(0.15, 0.5)] {
            assert!(data.cost(&other) > 100.0 * data.cost(&profile(0.15, 0.7)));
        }
    }

    #[test]
    fn targets_apply_after_the_latency_for_the_duration() {
        let commands = [
            Command {
                at: 0.0,
                linear: 0.3,
                angular: 0.0,
                duration: 0.5,
            },
            Command {
                at: 2.0,
                linear: 0.0,
                angular: 1.0,
                duration: 0.25,
            },
        ];
        assert_eq!(target(&commands, 0.1, 0.05), (0.0, 0.0));
        assert_eq!(target(&commands, 0.1, 0.1), (0.3, 0.0));
        assert_eq!(target(&commands, 0.1, 0.59), (0.3, 0.0));
        assert_eq!(target(&commands, 0.1, 0.6), (0.0, 0.0));
        assert_eq!(target(&commands, 0.1, 2.2), (0.0, 1.0));
        assert_eq!(target(&commands, 0.1, 2.35), (0.0, 0.0));
    }
}
