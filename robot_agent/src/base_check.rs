//! The start-up check of a base trusted to stop by itself: without the
//! independent base guard, the only thing that stops a base whose agent
//! died is the base driver's own command timeout (ros2_control's
//! `cmd_vel_timeout`, a twist_mux timeout). Before the first motion the
//! agent verifies it: a short slow turn, then silence — the base must stop
//! within its configured timeout, as its odometry shows. A base that keeps
//! moving is never armed; the operator may skip the check explicitly.
//!
//! Pure state, driven by the agent's clock and odometry, so it is tested
//! without a robot.

use std::time::{Duration, Instant};

use crate::limiter::Velocity;

/// How long the check drives before falling silent.
const DRIVE_FOR: Duration = Duration::from_millis(300);
/// The check's motion: a slow turn in place, rad/s.
const TURN: f64 = 0.3;
/// Slack on the base's timeout for odometry to show it stopped.
const SLACK: Duration = Duration::from_millis(300);

#[derive(Debug, Clone, PartialEq)]
enum Phase {
    /// Waiting for motion to be allowed (controller there, no e-stop).
    Pending,
    Driving {
        until: Instant,
        moved: bool,
    },
    Coasting {
        since: Instant,
    },
    Passed,
    Failed(String),
}

/// What the agent does with the base this tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum CheckStep {
    /// The check is not driving: control as usual.
    Idle,
    /// Drive at this velocity.
    Drive(Velocity),
    /// Send nothing: the base must stop by itself.
    Hold,
    /// Send zero now (the check ended or was interrupted).
    Stop,
}

/// The check's state.
#[derive(Debug, Clone)]
pub struct BaseCheck {
    phase: Phase,
    timeout: Duration,
}

impl BaseCheck {
    /// A check that the base stops within `timeout` of its last command.
    pub fn new(timeout: Duration) -> Self {
        Self {
            phase: Phase::Pending,
            timeout,
        }
    }

    /// No check (a base guard is required, or the operator skipped it).
    pub fn skipped() -> Self {
        Self {
            phase: Phase::Passed,
            timeout: Duration::ZERO,
        }
    }

    /// Why motion is refused because of the check, if it is.
    pub fn refusal(&self) -> Option<String> {
        match &self.phase {
            Phase::Passed => None,
            Phase::Failed(reason) => Some(reason.clone()),
            _ => Some(
                "checking that the base stops by itself (its command timeout) before the first motion"
                    .into(),
            ),
        }
    }

    /// Whether the check is driving or waiting for the base to stop.
    pub fn running(&self) -> bool {
        matches!(self.phase, Phase::Driving { .. } | Phase::Coasting { .. })
    }

    /// Advances the check. `may_move`: no e-stop, the watchdog armed, no
    /// other activity; `base_moving`: what the odometry shows (`None`: no
    /// fresh odometry).
    pub fn step(&mut self, now: Instant, may_move: bool, base_moving: Option<bool>) -> CheckStep {
        match &mut self.phase {
            Phase::Passed | Phase::Failed(_) => CheckStep::Idle,
            Phase::Pending if !may_move => CheckStep::Idle,
            Phase::Pending => {
                tracing::info!(
                    timeout_ms = self.timeout.as_millis() as u64,
                    "checking the base's command timeout: a slow turn, then silence"
                );
                self.phase = Phase::Driving {
                    until: now + DRIVE_FOR,
                    moved: false,
                };
                CheckStep::Drive(check_velocity())
            }
            _ if !may_move => {
                // An e-stop or a watchdog trip: stop now, check again later.
                self.phase = Phase::Pending;
                CheckStep::Stop
            }
            Phase::Driving { until, moved } => {
                *moved |= base_moving == Some(true);
                if now < *until {
                    return CheckStep::Drive(check_velocity());
                }
                if *moved {
                    self.phase = Phase::Coasting { since: now };
                    CheckStep::Hold
                } else {
                    self.fail(match base_moving {
                        None => "no odometry from the base: its command timeout cannot be verified"
                            .into(),
                        Some(_) => "the base did not move on the check's command (its odometry shows no motion): its command timeout cannot be verified".into(),
                    })
                }
            }
            Phase::Coasting { since } => {
                let silent = now.saturating_duration_since(*since);
                if base_moving == Some(false) {
                    tracing::info!(
                        stopped_after_ms = silent.as_millis() as u64,
                        "the base stops by itself: armed"
                    );
                    self.phase = Phase::Passed;
                    CheckStep::Idle
                } else if silent > self.timeout + SLACK {
                    let what = match base_moving {
                        None => "its odometry went silent",
                        Some(_) => "it kept moving",
                    };
                    self.fail(format!(
                        "the base did not stop by itself within {} ms of its last command ({what}): \
                         it has no working command timeout. Run `base_guard` beside the agent and set \
                         require_base_guard = true, or fix the base driver's command timeout \
                         (skip_base_timeout_check = true overrides, on the operator's responsibility)",
                        (self.timeout + SLACK).as_millis()
                    ))
                } else {
                    CheckStep::Hold
                }
            }
        }
    }

    fn fail(&mut self, reason: String) -> CheckStep {
        tracing::error!("base check failed, motion refused: {reason}");
        self.phase = Phase::Failed(reason);
        CheckStep::Stop
    }
}

fn check_velocity() -> Velocity {
    Velocity {
        linear: 0.0,
        angular: TURN,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(t0: Instant, ms: u64) -> Instant {
        t0 + Duration::from_millis(ms)
    }

    #[test]
    fn a_base_that_stops_by_itself_passes() {
        let t0 = Instant::now();
        let mut check = BaseCheck::new(Duration::from_millis(500));
        assert!(check.refusal().is_some());
        assert_eq!(check.step(t0, false, Some(false)), CheckStep::Idle);
        assert_eq!(
            check.step(t0, true, Some(false)),
            CheckStep::Drive(check_velocity())
        );
        assert!(check.running());
        assert_eq!(
            check.step(ms(t0, 100), true, Some(true)),
            CheckStep::Drive(check_velocity())
        );
        assert_eq!(check.step(ms(t0, 300), true, Some(true)), CheckStep::Hold);
        assert_eq!(check.step(ms(t0, 600), true, Some(true)), CheckStep::Hold);
        assert_eq!(check.step(ms(t0, 800), true, Some(false)), CheckStep::Idle);
        assert_eq!(check.refusal(), None);
        assert!(!check.running());
    }

    #[test]
    fn a_base_that_keeps_moving_is_never_armed() {
        let t0 = Instant::now();
        let mut check = BaseCheck::new(Duration::from_millis(500));
        check.step(t0, true, Some(false));
        check.step(ms(t0, 100), true, Some(true));
        assert_eq!(check.step(ms(t0, 300), true, Some(true)), CheckStep::Hold);
        assert_eq!(check.step(ms(t0, 1000), true, Some(true)), CheckStep::Hold);
        assert_eq!(check.step(ms(t0, 1101), true, Some(true)), CheckStep::Stop);
        let reason = check.refusal().expect("refused");
        assert!(reason.contains("kept moving"), "{reason}");
        assert!(reason.contains("within 800 ms"), "{reason}");
        // For good: later ticks change nothing.
        assert_eq!(check.step(ms(t0, 5000), true, Some(false)), CheckStep::Idle);
        assert_eq!(check.refusal(), Some(reason));
    }

    #[test]
    fn no_odometry_or_no_motion_cannot_verify() {
        let t0 = Instant::now();
        let mut check = BaseCheck::new(Duration::from_millis(500));
        check.step(t0, true, None);
        assert_eq!(check.step(ms(t0, 300), true, None), CheckStep::Stop);
        assert!(check.refusal().expect("refused").contains("no odometry"));

        let mut check = BaseCheck::new(Duration::from_millis(500));
        check.step(t0, true, Some(false));
        assert_eq!(check.step(ms(t0, 300), true, Some(false)), CheckStep::Stop);
        assert!(check.refusal().expect("refused").contains("did not move"));
    }

    #[test]
    fn an_estop_interrupts_the_check_which_starts_over() {
        let t0 = Instant::now();
        let mut check = BaseCheck::new(Duration::from_millis(500));
        check.step(t0, true, Some(false));
        assert_eq!(check.step(ms(t0, 100), false, Some(true)), CheckStep::Stop);
        assert!(!check.running());
        assert_eq!(check.step(ms(t0, 200), false, Some(false)), CheckStep::Idle);
        assert_eq!(
            check.step(ms(t0, 300), true, Some(false)),
            CheckStep::Drive(check_velocity())
        );
    }

    #[test]
    fn skipped_never_refuses() {
        let mut check = BaseCheck::skipped();
        assert_eq!(check.refusal(), None);
        assert_eq!(
            check.step(Instant::now(), true, Some(true)),
            CheckStep::Idle
        );
    }
}
