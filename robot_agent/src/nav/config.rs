//! Tuning of the reset navigation: map inflation, planner costs, follower
//! speeds and tolerances. The defaults are for the ROSbot (0.200 × 0.235 m
//! footprint: half-width 0.1175 m, circumradius 0.154 m) in the Monolith
//! enclosures.

use serde::{Deserialize, Serialize};

use super::NavError;

/// Navigation parameters. `Default` gives the tuned values (a TOML table
/// may override any subset); every field is checked by
/// [`NavConfig::validate`] before a grid is built from it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NavConfig {
    /// Grid cell edge, m. Default 0.025: at 0.05 the tightest spawn pocket
    /// of `monolith_obstacle` (around (0.0, −1.33), exit between two
    /// boulders 0.351 m apart) only stays connected with an inflation of
    /// at most 0.122 m, barely above the robot's half-width; at 0.025 the
    /// limit is 0.147 m.
    pub resolution: f64,
    /// Hard clearance, m: a cell is blocked when any part of it is closer
    /// than this to a wall or obstacle footprint, so every point of every
    /// planned segment keeps at least this clearance. Default 0.14: the
    /// robot's half-width (0.1175, what a robot driving through a gap
    /// needs) plus 0.0225 margin. The circumradius (0.154) cannot be used:
    /// it disconnects a valid spawn pocket of `monolith_obstacle`.
    pub inflation_radius: f64,
    /// Comfortable clearance, m, where the robot may turn in place in any
    /// orientation: the circumradius 0.154 plus 0.046 margin. Cells with
    /// less clearance cost more to the planner, and path shortcuts may not
    /// come closer to obstacles than the planner's own path (or this).
    pub comfort_radius: f64,
    /// Extra cost factor of a step at the inflation radius (it falls
    /// linearly to 0 at the comfort radius): how far the planner detours to
    /// keep comfortable clearance.
    pub comfort_weight: f64,
    /// Farthest the start may be from free space that it leaves along a
    /// straight escape leg, m (robot pushed against an obstacle).
    pub max_escape_distance: f64,
    /// Forward speed on open stretches, m/s.
    pub cruise_speed: f64,
    /// Slowest forward command while driving (overcomes wheel stiction), m/s.
    pub min_speed: f64,
    /// Speed along the escape leg, forwards or backwards, m/s.
    pub escape_speed: f64,
    /// Deceleration the follower plans with when slowing for a stop, m/s²
    /// (below the robot's real limit so that stops do not overshoot).
    pub linear_decel: f64,
    /// Fastest yaw-rate command, rad/s.
    pub max_turn_rate: f64,
    /// Slowest yaw-rate command when turning in place, rad/s.
    pub min_turn_rate: f64,
    /// Angular deceleration the follower plans with when a turn in place
    /// ends, rad/s².
    pub angular_decel: f64,
    /// Yaw rate per radian of heading error when turning in place, 1/s.
    pub turn_gain: f64,
    /// Pure-pursuit lookahead along the path, m.
    pub lookahead: f64,
    /// Heading error to the lookahead point above which the robot stops and
    /// turns in place, rad.
    pub rotate_above: f64,
    /// Heading error below which a turn in place ends and driving resumes,
    /// rad.
    pub resume_below: f64,
    /// Path vertices bending more than this are driven as stop–turn–go
    /// (no corner cutting), rad; gentler ones are rounded by pure pursuit.
    pub sharp_turn: f64,
    /// Arrival: distance to the goal position, m.
    pub position_tolerance: f64,
    /// Arrival: heading error to the goal yaw, rad.
    pub heading_tolerance: f64,
    /// Distance from the remaining path beyond which the robot counts as
    /// off the path and the plan is redone, m.
    pub replan_distance: f64,
}

impl Default for NavConfig {
    fn default() -> Self {
        Self {
            resolution: 0.025,
            inflation_radius: 0.14,
            comfort_radius: 0.20,
            comfort_weight: 3.0,
            max_escape_distance: 0.30,
            cruise_speed: 0.25,
            min_speed: 0.04,
            escape_speed: 0.08,
            linear_decel: 0.4,
            max_turn_rate: 1.0,
            min_turn_rate: 0.15,
            angular_decel: 2.0,
            turn_gain: 2.5,
            lookahead: 0.25,
            rotate_above: 0.6,
            resume_below: 0.15,
            sharp_turn: 0.6,
            position_tolerance: 0.05,
            heading_tolerance: 0.08,
            replan_distance: 0.20,
        }
    }
}

impl NavConfig {
    /// Checks ranges: everything finite and positive, the resolution
    /// 0.005–1 m, comfort ≥ inflation, resume below rotate, minimum and
    /// escape speeds not above the maximum ones.
    pub fn validate(&self) -> Result<(), NavError> {
        let positive = [
            (self.resolution, "resolution must be positive"),
            (self.inflation_radius, "inflation_radius must be positive"),
            (self.comfort_radius, "comfort_radius must be positive"),
            (
                self.max_escape_distance,
                "max_escape_distance must be positive",
            ),
            (self.cruise_speed, "cruise_speed must be positive"),
            (self.min_speed, "min_speed must be positive"),
            (self.escape_speed, "escape_speed must be positive"),
            (self.linear_decel, "linear_decel must be positive"),
            (self.max_turn_rate, "max_turn_rate must be positive"),
            (self.min_turn_rate, "min_turn_rate must be positive"),
            (self.angular_decel, "angular_decel must be positive"),
            (self.turn_gain, "turn_gain must be positive"),
            (self.lookahead, "lookahead must be positive"),
            (self.rotate_above, "rotate_above must be positive"),
            (self.resume_below, "resume_below must be positive"),
            (self.sharp_turn, "sharp_turn must be positive"),
            (
                self.position_tolerance,
                "position_tolerance must be positive",
            ),
            (self.heading_tolerance, "heading_tolerance must be positive"),
            (self.replan_distance, "replan_distance must be positive"),
        ];
        for (value, complaint) in positive {
            // `!(v > 0)` also rejects NaN.
            if !(value > 0.0 && value.is_finite()) {
                return Err(NavError::InvalidConfig(complaint));
            }
        }
        if !(self.comfort_weight >= 0.0 && self.comfort_weight.is_finite()) {
            return Err(NavError::InvalidConfig("comfort_weight must be ≥ 0"));
        }
        if !(0.005..=1.0).contains(&self.resolution) {
            return Err(NavError::InvalidConfig("resolution must be 0.005–1 m"));
        }
        if self.comfort_radius < self.inflation_radius {
            return Err(NavError::InvalidConfig(
                "comfort_radius must be at least inflation_radius",
            ));
        }
        if self.resume_below >= self.rotate_above {
            return Err(NavError::InvalidConfig(
                "resume_below must be below rotate_above",
            ));
        }
        if self.min_speed > self.cruise_speed
            || self.escape_speed > self.cruise_speed
            || self.min_turn_rate > self.max_turn_rate
        {
            return Err(NavError::InvalidConfig(
                "minimum speeds must not exceed the maximum ones",
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_within_the_brief_limits() {
        let c = NavConfig::default();
        assert_eq!(c.validate(), Ok(()));
        assert!(c.cruise_speed <= 0.3 && c.max_turn_rate <= 1.2);
        // Hard clearance covers the half-width; comfort covers the
        // circumradius of the 0.200 × 0.235 m footprint.
        assert!(c.inflation_radius > 0.1175);
        assert!(c.comfort_radius > 0.1f64.hypot(0.1175));
    }

    #[test]
    fn out_of_range_values_are_typed_errors() {
        let bad = [
            NavConfig {
                resolution: 0.0,
                ..NavConfig::default()
            },
            NavConfig {
                lookahead: f64::NAN,
                ..NavConfig::default()
            },
            NavConfig {
                comfort_radius: 0.1,
                ..NavConfig::default()
            },
            NavConfig {
                resume_below: 1.0,
                ..NavConfig::default()
            },
            NavConfig {
                resolution: 5.0,
                ..NavConfig::default()
            },
        ];
        for config in bad {
            assert!(matches!(config.validate(), Err(NavError::InvalidConfig(_))));
        }
    }
}
