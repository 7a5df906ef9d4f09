//! Velocity and acceleration limits applied to everything sent to the base.

use crate::config::Limits;

/// A planar body velocity.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Velocity {
    /// m/s.
    pub linear: f64,
    /// rad/s.
    pub angular: f64,
}

impl Velocity {
    /// Zero.
    pub const ZERO: Velocity = Velocity {
        linear: 0.0,
        angular: 0.0,
    };

    /// Whether both components are zero.
    pub fn is_zero(&self) -> bool {
        self.linear == 0.0 && self.angular == 0.0
    }
}

/// Clamps targets to the speed limits and ramps the commanded velocity
/// toward them within the acceleration limits.
#[derive(Debug, Clone)]
pub struct VelocityLimiter {
    limits: Limits,
    current: Velocity,
}

impl VelocityLimiter {
    /// At rest.
    pub fn new(limits: Limits) -> Self {
        Self {
            limits,
            current: Velocity::ZERO,
        }
    }

    /// `target` within the speed limits, and whether it had to be clamped
    /// (non-finite values become zero and count as clamped).
    pub fn clamp(&self, target: Velocity) -> (Velocity, bool) {
        let fit = |v: f64, max: f64| {
            if !v.is_finite() {
                (0.0, true)
            } else {
                let c = v.clamp(-max, max);
                (c, c != v)
            }
        };
        let (linear, a) = fit(target.linear, self.limits.max_linear);
        let (angular, b) = fit(target.angular, self.limits.max_angular);
        (Velocity { linear, angular }, a || b)
    }

    /// Moves the commanded velocity toward `target` over `dt` seconds.
    pub fn ramp(&mut self, target: Velocity, dt: f64) -> Velocity {
        let (target, _) = self.clamp(target);
        let step = |from: f64, to: f64, rate: f64| {
            let max = rate * dt.max(0.0);
            from + (to - from).clamp(-max, max)
        };
        self.current = Velocity {
            linear: step(
                self.current.linear,
                target.linear,
                self.limits.max_linear_accel,
            ),
            angular: step(
                self.current.angular,
                target.angular,
                self.limits.max_angular_accel,
            ),
        };
        self.current
    }

    /// Stops at once (safety stops do not ramp: the base brakes).
    pub fn halt(&mut self) {
        self.current = Velocity::ZERO;
    }

    /// The velocity last commanded.
    pub fn current(&self) -> Velocity {
        self.current
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn targets_are_clamped_to_the_limits() {
        let limiter = VelocityLimiter::new(Limits::default());
        let (v, clamped) = limiter.clamp(Velocity {
            linear: 2.0,
            angular: -9.0,
        });
        assert_eq!(
            v,
            Velocity {
                linear: 0.7,
                angular: -2.5
            }
        );
        assert!(clamped);
        let (v, clamped) = limiter.clamp(Velocity {
            linear: f64::NAN,
            angular: 1.0,
        });
        assert_eq!(
            v,
            Velocity {
                linear: 0.0,
                angular: 1.0
            }
        );
        assert!(clamped);
        assert!(
            !limiter
                .clamp(Velocity {
                    linear: 0.1,
                    angular: 1.25
                })
                .1
        );
    }

    #[test]
    fn ramps_within_the_acceleration_limits() {
        let mut limiter = VelocityLimiter::new(Limits::default());
        let target = Velocity {
            linear: 0.7,
            angular: 2.5,
        };
        let v = limiter.ramp(target, 0.1);
        assert!((v.linear - 0.15).abs() < 1e-12);
        assert!((v.angular - 1.2).abs() < 1e-12);
        for _ in 0..10 {
            limiter.ramp(target, 0.1);
        }
        assert_eq!(limiter.current(), target);
        limiter.halt();
        assert!(limiter.current().is_zero());
    }
}
