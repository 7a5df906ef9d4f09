//! Travel-time estimate of a planned path, for reporting typical reset
//! times and sizing the caller's timeout. Mirrors the follower's speed
//! profile: turns in place at the start, at sharp corners and at the goal;
//! straight runs at cruise speed braking into each stop.

use super::geometry::{wrap_angle, Point};
use super::plan::Path;
use super::NavConfig;

/// Getting moving from rest (acceleration, command latency), s per start.
const START_OVERHEAD_S: f64 = 0.15;

/// Integration step of the turn-in-place profile, s.
const TURN_STEP_S: f64 = 0.005;

/// Longest turn the estimate integrates, s.
const MAX_TURN_S: f64 = 600.0;

/// Seconds the follower should need to drive `path` with `config`, on a
/// robot that follows its commands closely. Pure; ignores re-planning.
pub fn estimate_travel_time(path: &Path, config: &NavConfig) -> f64 {
    let points = path.waypoints();
    let mut yaw = path.start().yaw;
    let mut total = 0.0;
    let mut first = 1;
    if path.has_escape_leg() && points.len() > 2 {
        // Straight out, forwards or backwards, whichever turns less.
        let heading = points[0].bearing_to(points[1]);
        let forward = wrap_angle(heading - yaw).abs();
        let turn = forward.min(std::f64::consts::PI - forward);
        total += turn_time(turn, config.resume_below, config) + START_OVERHEAD_S;
        total += points[0].distance(points[1]) / config.escape_speed;
        yaw = if forward <= std::f64::consts::FRAC_PI_2 {
            heading
        } else {
            wrap_angle(heading + std::f64::consts::PI)
        };
        first = 2;
    }
    // Runs of segments between sharp corners.
    let mut run_start = first - 1;
    for k in first..points.len() {
        let is_stop = k + 1 == points.len()
            || bend(points[k - 1], points[k], points[k + 1]).abs() > config.sharp_turn;
        if !is_stop {
            continue;
        }
        let run: f64 = points[run_start..=k]
            .windows(2)
            .map(|w| w[0].distance(w[1]))
            .sum();
        if run > 0.0 {
            let heading = points[run_start].bearing_to(points[run_start + 1]);
            let turn = wrap_angle(heading - yaw).abs();
            if turn > config.rotate_above {
                // Turning in place ends near the heading; driving fixes the rest.
                total += turn_time(turn, config.resume_below, config);
            }
            total += START_OVERHEAD_S + drive_time(run, config);
            yaw = points[k - 1].bearing_to(points[k]);
        }
        run_start = k;
    }
    let aim = 0.5 * config.heading_tolerance;
    total + turn_time(wrap_angle(path.goal().yaw - yaw).abs(), aim, config)
}

/// Heading change at `b`, rad (0 for a zero-length segment).
fn bend(a: Point, b: Point, c: Point) -> f64 {
    if a.distance(b) == 0.0 || b.distance(c) == 0.0 {
        return 0.0;
    }
    wrap_angle(b.bearing_to(c) - a.bearing_to(b))
}

/// Straight run of `length` from rest to rest: cruise, then brake along
/// v = √(2·decel·d) (time √(2·d₀/decel) over the last d₀).
fn drive_time(length: f64, config: &NavConfig) -> f64 {
    let v = config.cruise_speed;
    let braking = v * v / (2.0 * config.linear_decel);
    if length >= braking {
        (length - braking) / v + v / config.linear_decel
    } else {
        (2.0 * length / config.linear_decel).sqrt()
    }
}

/// Turning in place through `angle` until `aim` is left, with the
/// follower's rate law, s. Capped at `MAX_TURN_S` (a config whose rates
/// are zero would otherwise never finish).
fn turn_time(angle: f64, aim: f64, config: &NavConfig) -> f64 {
    if angle.is_nan() || angle <= aim {
        return 0.0;
    }
    let mut left = angle;
    let mut t = START_OVERHEAD_S;
    while left > aim && t < MAX_TURN_S {
        let rate = (config.turn_gain * left)
            .min((2.0 * config.angular_decel * left).sqrt())
            .max(config.min_turn_rate)
            .min(config.max_turn_rate);
        left -= rate * TURN_STEP_S;
        t += TURN_STEP_S;
    }
    t
}

#[cfg(test)]
mod tests {
    use super::super::plan::plan;
    use super::super::testkit::{grid, pose};
    use super::*;

    #[test]
    fn estimate_grows_with_distance_and_turning() {
        let grid = grid("monolith");
        let config = grid.config();
        let near = plan(&grid, pose(-1.0, 0.5, 0.0), pose(-0.5, 0.5, 0.0)).expect("path");
        let far = plan(&grid, pose(-1.0, 0.5, 0.0), pose(1.0, 0.5, 0.0)).expect("path");
        let turned = plan(&grid, pose(-1.0, 0.5, 3.0), pose(-0.5, 0.5, 0.0)).expect("path");
        let (t_near, t_far) = (
            estimate_travel_time(&near, config),
            estimate_travel_time(&far, config),
        );
        assert!(t_near > 0.5 / config.cruise_speed, "{t_near}");
        assert!(
            t_far > t_near + 1.5 / config.cruise_speed - 1e-9,
            "{t_far} {t_near}"
        );
        assert!(estimate_travel_time(&turned, config) > t_near + 3.0 / config.max_turn_rate);
        // Staying put and turning half a turn.
        let spin = plan(&grid, pose(0.5, 0.5, 0.0), pose(0.5, 0.5, 3.0)).expect("path");
        let t_spin = estimate_travel_time(&spin, config);
        assert!(
            t_spin > 3.0 / config.max_turn_rate && t_spin < 8.0,
            "{t_spin}"
        );
    }

    #[test]
    fn drive_time_is_continuous_at_the_braking_distance() {
        let config = NavConfig::default();
        let d = config.cruise_speed.powi(2) / (2.0 * config.linear_decel);
        assert!((drive_time(d - 1e-9, &config) - drive_time(d + 1e-9, &config)).abs() < 1e-6);
    }
}
