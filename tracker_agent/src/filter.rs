//! Outlier rejection: a pose implying the robot moved or turned faster than
//! it can is a tracking glitch (reflection, occlusion, a bad solve).
//!
//! Each candidate is compared with the last *accepted* pose using source
//! timestamps for `dt`: a speed above `max_speed_mps` or a yaw rate above
//! `max_yaw_rate_rps` rejects it, and so does `dt ≤ 0` (out of order or
//! repeated). When poses keep being rejected for longer than
//! `relock_after_s` (source time, from the first rejection of the streak),
//! the newest one is accepted as a re-lock: the robot was probably carried,
//! or the tracker's clock restarted.

use std::fmt;

use nalgebra::Isometry3;

/// Limits of the filter.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FilterConfig {
    /// Fastest plausible base_link speed, m/s.
    pub max_speed_mps: f64,
    /// Fastest plausible yaw rate, rad/s.
    pub max_yaw_rate_rps: f64,
    /// Accept the newest pose after rejecting for this long, s.
    pub relock_after_s: f64,
}

impl Default for FilterConfig {
    fn default() -> Self {
        Self {
            max_speed_mps: 2.0,
            max_yaw_rate_rps: 10.0,
            relock_after_s: 0.5,
        }
    }
}

/// Why a pose was rejected.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Rejection {
    /// Implied speed above the limit.
    TooFast {
        /// m/s.
        speed_mps: f64,
    },
    /// Implied yaw rate above the limit.
    TurnsTooFast {
        /// rad/s.
        yaw_rate_rps: f64,
    },
    /// Not newer than the last accepted pose.
    OutOfOrder {
        /// Timestamp difference, s (≤ 0).
        dt_s: f64,
    },
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Rejection::TooFast { speed_mps } => write!(f, "implied speed {speed_mps:.2} m/s"),
            Rejection::TurnsTooFast { yaw_rate_rps } => {
                write!(f, "implied yaw rate {yaw_rate_rps:.2} rad/s")
            }
            Rejection::OutOfOrder { dt_s } => write!(f, "out of order (dt {dt_s} s)"),
        }
    }
}

/// The filter's decision on one pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Verdict {
    /// Plausible (or the first pose).
    Accepted,
    /// Implausible, but rejections lasted longer than `relock_after_s`:
    /// accepted as the new reference.
    Relocked {
        /// How long poses had been rejected, s (source time).
        rejected_for_s: f64,
    },
    /// Dropped.
    Rejected(Rejection),
}

impl Verdict {
    /// Whether the pose is to be used.
    pub fn is_accepted(&self) -> bool {
        !matches!(self, Verdict::Rejected(_))
    }
}

/// The filter's state: the last accepted pose and the current rejection
/// streak.
#[derive(Debug, Clone)]
pub struct OutlierFilter {
    config: FilterConfig,
    last: Option<(f64, Isometry3<f64>)>,
    /// Source time of the first rejection of the current streak.
    rejecting_since: Option<f64>,
    rejected_in_streak: u64,
}

impl OutlierFilter {
    /// A filter that accepts its first pose.
    pub fn new(config: FilterConfig) -> Self {
        Self {
            config,
            last: None,
            rejecting_since: None,
            rejected_in_streak: 0,
        }
    }

    /// The limits.
    pub fn config(&self) -> &FilterConfig {
        &self.config
    }

    /// Whether the latest pose was rejected (a streak is running).
    pub fn is_rejecting(&self) -> bool {
        self.rejecting_since.is_some()
    }

    /// Poses rejected since the last accepted one.
    pub fn rejected_in_streak(&self) -> u64 {
        self.rejected_in_streak
    }

    /// Judges the pose `pose` stamped `t` (source clock, s); an accepted pose
    /// becomes the reference for the next.
    pub fn check(&mut self, t: f64, pose: &Isometry3<f64>) -> Verdict {
        let Some((t_last, last)) = &self.last else {
            self.accept(t, pose);
            return Verdict::Accepted;
        };
        let dt = t - t_last;
        let rejection = if dt <= 0.0 || !dt.is_finite() {
            Some(Rejection::OutOfOrder { dt_s: dt })
        } else {
            let speed_mps = (pose.translation.vector - last.translation.vector).norm() / dt;
            let yaw_rate_rps = wrap_angle(yaw(pose) - yaw(last)).abs() / dt;
            if speed_mps > self.config.max_speed_mps {
                Some(Rejection::TooFast { speed_mps })
            } else if yaw_rate_rps > self.config.max_yaw_rate_rps {
                Some(Rejection::TurnsTooFast { yaw_rate_rps })
            } else {
                None
            }
        };
        let Some(rejection) = rejection else {
            self.accept(t, pose);
            return Verdict::Accepted;
        };
        let since = *self.rejecting_since.get_or_insert(t);
        let rejected_for_s = t - since;
        if rejected_for_s > self.config.relock_after_s {
            self.accept(t, pose);
            return Verdict::Relocked { rejected_for_s };
        }
        self.rejected_in_streak += 1;
        Verdict::Rejected(rejection)
    }

    fn accept(&mut self, t: f64, pose: &Isometry3<f64>) {
        self.last = Some((t, *pose));
        self.rejecting_since = None;
        self.rejected_in_streak = 0;
    }
}

/// Heading (rotation about world +z) of a pose, rad.
pub fn yaw(pose: &Isometry3<f64>) -> f64 {
    let q = pose.rotation.quaternion();
    let siny_cosp = 2.0 * (q.w * q.k + q.i * q.j);
    let cosy_cosp = 1.0 - 2.0 * (q.j * q.j + q.k * q.k);
    siny_cosp.atan2(cosy_cosp)
}

/// An angle wrapped into (−π, π].
pub fn wrap_angle(a: f64) -> f64 {
    let wrapped = a.rem_euclid(std::f64::consts::TAU);
    if wrapped > std::f64::consts::PI {
        wrapped - std::f64::consts::TAU
    } else {
        wrapped
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    fn at(x: f64, yaw: f64) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(x, 0.5, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        )
    }

    #[test]
    fn plausible_motion_is_accepted() {
        let mut f = OutlierFilter::new(FilterConfig::default());
        // 1 m/s and 3 rad/s at 100 Hz.
        for i in 0..100 {
            let t = i as f64 * 0.01;
            assert_eq!(f.check(t, &at(t, 3.0 * t)), Verdict::Accepted, "t = {t}");
        }
        // Yaw wraps from +π to −π without looking like a spin.
        let mut f = OutlierFilter::new(FilterConfig::default());
        assert_eq!(f.check(0.0, &at(0.0, 3.13)), Verdict::Accepted);
        assert_eq!(f.check(0.01, &at(0.0, -3.13)), Verdict::Accepted);
    }

    #[test]
    fn a_jump_is_rejected_and_the_reference_stays() {
        let mut f = OutlierFilter::new(FilterConfig::default());
        assert_eq!(f.check(0.0, &at(0.0, 0.0)), Verdict::Accepted);
        // 0.5 m in 10 ms = 50 m/s.
        match f.check(0.01, &at(0.5, 0.0)) {
            Verdict::Rejected(Rejection::TooFast { speed_mps }) => {
                assert!((speed_mps - 50.0).abs() < 1e-9)
            }
            other => panic!("{other:?}"),
        }
        assert!(f.is_rejecting());
        // The next good pose is judged against the last accepted one.
        assert_eq!(f.check(0.02, &at(0.01, 0.0)), Verdict::Accepted);
        assert!(!f.is_rejecting());
        // A 1 rad flip in 10 ms = 100 rad/s.
        match f.check(0.03, &at(0.01, 1.0)) {
            Verdict::Rejected(Rejection::TurnsTooFast { yaw_rate_rps }) => {
                assert!((yaw_rate_rps - 100.0).abs() < 1e-6)
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn out_of_order_and_repeated_timestamps_are_rejected() {
        let mut f = OutlierFilter::new(FilterConfig::default());
        assert_eq!(f.check(1.0, &at(0.0, 0.0)), Verdict::Accepted);
        assert_eq!(
            f.check(1.0, &at(0.0, 0.0)),
            Verdict::Rejected(Rejection::OutOfOrder { dt_s: 0.0 })
        );
        assert_eq!(
            f.check(0.5, &at(0.0, 0.0)),
            Verdict::Rejected(Rejection::OutOfOrder { dt_s: -0.5 })
        );
        assert_eq!(f.check(1.01, &at(0.0, 0.0)), Verdict::Accepted);
    }

    #[test]
    fn sustained_rejection_relocks_on_the_newest_pose() {
        let mut f = OutlierFilter::new(FilterConfig::default());
        assert_eq!(f.check(0.0, &at(0.0, 0.0)), Verdict::Accepted);
        // Carried 3 m away: rejected until more than 0.5 s of rejections.
        let mut verdicts = Vec::new();
        for i in 1..=70 {
            let t = i as f64 * 0.01;
            verdicts.push((i, f.check(t, &at(3.0, 0.0))));
        }
        // The first rejection is at t = 0.01; t − 0.01 > 0.5 first at i = 52.
        for (i, v) in &verdicts {
            match (*i, v) {
                (52, Verdict::Relocked { rejected_for_s }) => {
                    assert!((rejected_for_s - 0.51).abs() < 1e-9)
                }
                (i, Verdict::Rejected(_)) if i < 52 => {}
                (i, Verdict::Accepted) if i > 52 => {}
                other => panic!("unexpected {other:?}"),
            }
        }
        // A restarted source clock (timestamps back near 0) relocks too.
        let mut f = OutlierFilter::new(FilterConfig::default());
        assert_eq!(f.check(1000.0, &at(0.0, 0.0)), Verdict::Accepted);
        let relocked = (0..100)
            .map(|i| f.check(i as f64 * 0.01, &at(0.0, 0.0)))
            .position(|v| matches!(v, Verdict::Relocked { .. }));
        assert_eq!(relocked, Some(51));
        assert_eq!(f.check(1.0, &at(0.0, 0.0)), Verdict::Accepted);
    }

    #[test]
    fn angles_wrap_into_minus_pi_pi() {
        use std::f64::consts::PI;
        assert!((wrap_angle(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(-0.25) + 0.25).abs() < 1e-12);
        assert!((wrap_angle(2.0 * PI + 0.1) - 0.1).abs() < 1e-12);
        assert!((yaw(&at(0.0, -2.0)) + 2.0).abs() < 1e-12);
    }
}
