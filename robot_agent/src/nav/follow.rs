//! The path follower: turns each tracker pose into a velocity command.
//! Turn in place while the lookahead point is far off the nose, otherwise
//! pure pursuit (steering proportional to the lateral offset of the
//! lookahead point); stop–turn–go at sharp path corners; slow down to stop
//! on the goal position, then turn in place to the goal heading. Forward
//! only, except along an escape leg, which may be driven backwards
//! (backing out of an obstacle the robot was pushed against).
//!
//! The follower does not re-plan: [`PathFollower::off_path`] tells the
//! caller when to (the [`Navigator`](super::Navigator) does it).

use std::f64::consts::{FRAC_PI_2, PI};

use offworld_runtime::msg::Pose2D;

use super::geometry::{wrap_angle, Point};
use super::plan::Path;
use super::NavConfig;

/// The follower aims for this fraction of the position and heading
/// tolerances, so that coasting after the final stop command (the robot
/// decelerates within its acceleration limits) stays within them.
const AIM_FRACTION: f64 = 0.5;

/// Consecutive calm commands (slow enough to stop within the tolerances)
/// needed before arrival is declared, so that a robot still spinning from
/// an earlier turn is first stopped rather than declared arrived mid-turn.
const ARRIVAL_CALM_TICKS: u32 = 2;

/// What to send to the robot this tick.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NavCommand {
    /// Drive at these velocities until the next tick.
    Drive {
        /// Forward speed, m/s (negative only on an escape leg).
        linear: f64,
        /// Yaw rate, rad/s, positive = left (counter-clockwise).
        angular: f64,
    },
    /// At the goal within tolerances: stop. Latched: every later step
    /// answers `Arrived` too.
    Arrived,
}

impl NavCommand {
    /// Zero velocity.
    pub const STOP: NavCommand = NavCommand::Drive {
        linear: 0.0,
        angular: 0.0,
    };
}

/// Follows one [`Path`] to its goal pose. Stateful (progress along the
/// path, turn-in-place and final-alignment latches): feed it every pose, in
/// order, at a steady rate (~20 Hz).
#[derive(Debug, Clone)]
pub struct PathFollower {
    config: NavConfig,
    path: Path,
    /// Heading to end with, rad.
    goal_yaw: f64,
    /// Arc length at each waypoint, m.
    arc: Vec<f64>,
    /// Waypoint k (interior only) bends the path by more than
    /// `sharp_turn`: stop there and turn in place.
    sharp: Vec<bool>,
    /// Still on the escape leg.
    escaping: bool,
    /// Segment of the last projection onto the path.
    segment: usize,
    /// Arc length of the last projection, m; never decreases.
    progress: f64,
    /// Turning in place towards the target (hysteresis latch).
    turning: bool,
    /// Stopped on the goal, turning to the goal heading.
    aligning: bool,
    /// Consecutive commands so far that were calm (see
    /// [`ARRIVAL_CALM_TICKS`]).
    calm_ticks: u32,
    arrived: bool,
}

impl PathFollower {
    /// A follower at the start of `path` that ends turned to `goal_yaw`
    /// (normally `path.goal().yaw`; a non-finite value falls back to it),
    /// with `config`'s speeds, tolerances and lookahead.
    pub fn new(path: Path, goal_yaw: f64, config: &NavConfig) -> Self {
        let points = path.waypoints();
        let mut arc = Vec::with_capacity(points.len());
        let mut total = 0.0;
        for (i, p) in points.iter().enumerate() {
            if i > 0 {
                total += points[i - 1].distance(*p);
            }
            arc.push(total);
        }
        let sharp = (0..points.len())
            .map(|k| {
                k > 0
                    && k + 1 < points.len()
                    && turn_angle(points[k - 1], points[k], points[k + 1]).abs() > config.sharp_turn
            })
            .collect();
        let goal_yaw = if goal_yaw.is_finite() {
            goal_yaw
        } else {
            path.goal().yaw
        };
        Self {
            config: config.clone(),
            goal_yaw,
            escaping: path.has_escape_leg() && points.len() > 2,
            path,
            arc,
            sharp,
            segment: 0,
            progress: 0.0,
            turning: false,
            aligning: false,
            calm_ticks: 0,
            arrived: false,
        }
    }

    /// The path being followed.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Path length not yet covered, m.
    pub fn remaining(&self) -> f64 {
        (self.total() - self.progress).max(0.0)
    }

    /// The command for the robot at `pose` (latest tracker pose). A
    /// non-finite pose gives [`NavCommand::STOP`]: wait for a good one.
    pub fn step(&mut self, pose: Pose2D) -> NavCommand {
        let command = self.command(pose);
        if let NavCommand::Drive { linear, angular } = command {
            let calm = linear.abs() <= self.config.min_speed
                && angular.abs() <= self.turn_rate(self.config.heading_tolerance);
            self.calm_ticks = if calm {
                self.calm_ticks.saturating_add(1)
            } else {
                0
            };
        }
        command
    }

    fn command(&mut self, pose: Pose2D) -> NavCommand {
        if self.arrived {
            return NavCommand::Arrived;
        }
        if !(pose.x.is_finite() && pose.y.is_finite() && pose.yaw.is_finite()) {
            return NavCommand::STOP;
        }
        let here = Point::new(pose.x, pose.y);
        if self.escaping {
            if let Some(command) = self.escape(here, pose.yaw) {
                return command;
            }
        }
        self.advance(here);
        let goal = self.goal_point();
        let to_goal = here.distance(goal);
        let tolerance = self.config.position_tolerance;
        if self.aligning && to_goal > tolerance {
            // Pushed off the goal while turning: drive back.
            self.aligning = false;
            self.turning = false;
        }
        // On the spot, or within tolerance but with the goal point off to
        // the side or behind (turning to face it from so close would only
        // spin the robot): stop and turn to the goal heading.
        let off_nose =
            wrap_angle(here.bearing_to(goal) - pose.yaw).abs() > self.config.rotate_above;
        let end_reached = self.segment + 2 >= self.path.waypoints().len();
        if !self.aligning
            && (to_goal <= AIM_FRACTION * tolerance
                || (end_reached && to_goal <= tolerance && off_nose))
        {
            self.aligning = true;
        }
        if self.aligning {
            return self.align(pose.yaw);
        }

        let (target, stop_point) = self.target(here);
        let heading_error = wrap_angle(here.bearing_to(target) - pose.yaw);
        if let Some(command) = self.turn_in_place_if_needed(heading_error) {
            return command;
        }
        self.pursue(here, target, heading_error, here.distance(stop_point))
    }

    /// The robot at `pose` is farther than `replan_distance` from the rest
    /// of the path: re-plan from `pose` and start a new follower. False
    /// once arrived and for a non-finite pose.
    pub fn off_path(&self, pose: Pose2D) -> bool {
        if self.arrived || !(pose.x.is_finite() && pose.y.is_finite()) {
            return false;
        }
        let here = Point::new(pose.x, pose.y);
        let points = self.path.waypoints();
        let distance = (self.segment..points.len().saturating_sub(1))
            .map(|k| project(here, points[k], points[k + 1]).1)
            .fold(f64::INFINITY, f64::min);
        distance.is_finite() && distance > self.config.replan_distance
    }

    fn total(&self) -> f64 {
        self.arc.last().copied().unwrap_or(0.0)
    }

    fn goal_point(&self) -> Point {
        let points = self.path.waypoints();
        points.last().copied().unwrap_or(Point::new(0.0, 0.0))
    }

    /// Command along the escape leg (straight to its end, forwards or
    /// backwards, whichever needs less turning); `None` once it is done.
    fn escape(&mut self, here: Point, yaw: f64) -> Option<NavCommand> {
        let points = self.path.waypoints();
        let (from, exit) = (points[0], points[1]);
        let (along, _) = project(here, from, exit);
        let remaining = here.distance(exit);
        if remaining <= AIM_FRACTION * self.config.position_tolerance || along >= 1.0 {
            self.escaping = false;
            self.turning = false;
            self.segment = 1;
            self.progress = self.arc[1];
            return None;
        }
        let forward_error = wrap_angle(here.bearing_to(exit) - yaw);
        let (direction, error) = if forward_error.abs() <= FRAC_PI_2 {
            (1.0, forward_error)
        } else {
            // Backing up: the tail points at the exit. The yaw rate that
            // reduces the error has the same sign either way.
            (-1.0, wrap_angle(forward_error - PI))
        };
        if let Some(command) = self.turn_in_place_if_needed(error) {
            return Some(command);
        }
        let c = &self.config;
        let speed = c
            .escape_speed
            .min((2.0 * c.linear_decel * remaining).sqrt())
            .max(c.min_speed)
            .min(c.escape_speed);
        // max/min rather than clamp: no panic on an unvalidated config.
        let angular = (c.turn_gain * error)
            .max(-c.max_turn_rate)
            .min(c.max_turn_rate);
        Some(NavCommand::Drive {
            linear: direction * speed,
            angular,
        })
    }

    /// Moves the progress to the nearest point of the path within reach
    /// ahead (never backwards, and never jumping to a later part of the
    /// path that merely passes nearby).
    fn advance(&mut self, here: Point) {
        let points = self.path.waypoints();
        let reach = self.progress + self.config.lookahead + self.config.replan_distance;
        let mut best: Option<(f64, usize, f64)> = None;
        for k in self.segment..points.len().saturating_sub(1) {
            if self.arc[k] > reach {
                break;
            }
            let (t, distance) = project(here, points[k], points[k + 1]);
            if best.is_none_or(|(d, _, _)| distance < d) {
                let at = self.arc[k] + t * (self.arc[k + 1] - self.arc[k]);
                best = Some((distance, k, at));
            }
        }
        if let Some((_, k, at)) = best {
            if at >= self.progress {
                self.segment = k;
                self.progress = at;
            }
        }
    }

    /// The pure-pursuit target (lookahead point, held at the next sharp
    /// corner until the robot is on it) and the point to be stopped at
    /// (that corner, else the goal).
    fn target(&self, here: Point) -> (Point, Point) {
        let release = AIM_FRACTION * self.config.position_tolerance;
        let points = self.path.waypoints();
        let stop = (self.segment + 1..points.len().saturating_sub(1))
            .find(|&k| self.sharp[k] && self.arc[k] > self.progress + release);
        let stop_arc = stop.map_or(self.total(), |k| self.arc[k]);
        let stop_point = stop.map_or(self.goal_point(), |k| points[k]);
        let look_arc = (self.progress + self.config.lookahead).min(stop_arc);
        let target = if look_arc >= stop_arc || here.distance(stop_point) <= self.config.lookahead {
            stop_point
        } else {
            self.point_at(look_arc)
        };
        (target, stop_point)
    }

    /// The path point at arc length `s`.
    fn point_at(&self, s: f64) -> Point {
        let points = self.path.waypoints();
        for k in self.segment..points.len().saturating_sub(1) {
            if s <= self.arc[k + 1] {
                let length = self.arc[k + 1] - self.arc[k];
                let t = if length > 0.0 {
                    (s - self.arc[k]) / length
                } else {
                    1.0
                };
                return points[k].lerp(points[k + 1], t.clamp(0.0, 1.0));
            }
        }
        self.goal_point()
    }

    /// Turn in place while the heading error is large (with hysteresis so
    /// that it does not chatter at the threshold).
    fn turn_in_place_if_needed(&mut self, heading_error: f64) -> Option<NavCommand> {
        let magnitude = heading_error.abs();
        if self.turning && magnitude < self.config.resume_below {
            self.turning = false;
        } else if !self.turning && magnitude > self.config.rotate_above {
            self.turning = true;
        }
        self.turning.then(|| NavCommand::Drive {
            linear: 0.0,
            angular: self.turn_rate(heading_error),
        })
    }

    /// Pure pursuit towards `target`: the arc through it tangent to the
    /// heading, at cruise speed reduced for misalignment and to stop on
    /// `stop_distance`, the yaw rate capped (keeping the arc) at the limit.
    fn pursue(
        &self,
        here: Point,
        target: Point,
        heading_error: f64,
        stop_distance: f64,
    ) -> NavCommand {
        let c = &self.config;
        let release = AIM_FRACTION * c.position_tolerance;
        let braking = (2.0 * c.linear_decel * (stop_distance - release).max(0.0)).sqrt();
        let mut linear = (c.cruise_speed.min(braking) * heading_error.cos().max(0.0))
            .max(c.min_speed)
            .min(c.cruise_speed);
        let curvature = 2.0 * heading_error.sin() / here.distance(target).max(1e-3);
        let mut angular = linear * curvature;
        if angular.abs() > c.max_turn_rate {
            angular = c.max_turn_rate.copysign(angular);
            linear = c.max_turn_rate / curvature.abs();
        }
        NavCommand::Drive { linear, angular }
    }

    /// Turning in place to the goal heading; arrived once within the aim
    /// with the robot calm (else stop first and look again).
    fn align(&mut self, yaw: f64) -> NavCommand {
        let error = wrap_angle(self.goal_yaw - yaw);
        if error.abs() <= AIM_FRACTION * self.config.heading_tolerance {
            if self.calm_ticks < ARRIVAL_CALM_TICKS {
                return NavCommand::STOP;
            }
            self.arrived = true;
            return NavCommand::Arrived;
        }
        NavCommand::Drive {
            linear: 0.0,
            angular: self.turn_rate(error),
        }
    }

    /// Yaw rate for turning in place through `error`: proportional, capped
    /// so that the planned deceleration stops it on target, floored so it
    /// does not stall, within the turn-rate limit.
    fn turn_rate(&self, error: f64) -> f64 {
        let c = &self.config;
        let magnitude = error.abs();
        let rate = (c.turn_gain * magnitude)
            .min((2.0 * c.angular_decel * magnitude).sqrt())
            .max(c.min_turn_rate)
            .min(c.max_turn_rate);
        rate.copysign(error)
    }
}

/// Projection of `p` on segment `a`–`b`: the parameter in [0, 1] and the
/// distance.
fn project(p: Point, a: Point, b: Point) -> (f64, f64) {
    let (dx, dy) = (b.x - a.x, b.y - a.y);
    let length2 = dx * dx + dy * dy;
    let t = if length2 > 0.0 {
        (((p.x - a.x) * dx + (p.y - a.y) * dy) / length2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (t, p.distance(a.lerp(b, t)))
}

/// Signed heading change at `b` of the polyline `a`–`b`–`c`, rad (0 when a
/// segment has no length).
fn turn_angle(a: Point, b: Point, c: Point) -> f64 {
    if a.distance(b) == 0.0 || b.distance(c) == 0.0 {
        return 0.0;
    }
    wrap_angle(b.bearing_to(c) - a.bearing_to(b))
}

#[cfg(test)]
mod tests {
    use super::super::plan::plan;
    use super::super::testkit::{grid, pose, Lcg};
    use super::*;

    fn follower(start: Pose2D, goal: Pose2D) -> PathFollower {
        let grid = grid("monolith");
        let path = plan(&grid, start, goal).expect("path");
        PathFollower::new(path, goal.yaw, grid.config())
    }

    fn drive(command: NavCommand) -> (f64, f64) {
        match command {
            NavCommand::Drive { linear, angular } => (linear, angular),
            NavCommand::Arrived => panic!("unexpected arrival"),
        }
    }

    #[test]
    fn turns_in_place_when_the_path_is_behind() {
        let start = pose(-1.0, 0.4, PI);
        let mut f = follower(start, pose(-0.2, 0.4, 0.0));
        let (linear, angular) = drive(f.step(start));
        assert_eq!(linear, 0.0);
        assert!(angular.abs() > 0.5);
        // Facing it: drives forward, no turn needed.
        let mut f = follower(pose(-1.0, 0.4, 0.0), pose(-0.2, 0.4, 0.0));
        let (linear, angular) = drive(f.step(pose(-1.0, 0.4, 0.0)));
        assert!(linear > 0.1 && angular.abs() < 1e-6, "{linear} {angular}");
    }

    #[test]
    fn steers_towards_the_path_and_slows_near_the_goal() {
        let goal = pose(0.6, 0.5, 0.0);
        let mut f = follower(pose(-1.0, 0.5, 0.0), goal);
        // Right of the path, heading along it: steer left (positive).
        let (_, angular) = drive(f.step(pose(-0.8, 0.45, 0.0)));
        assert!(angular > 0.0);
        let (cruising, _) = drive(f.step(pose(-0.5, 0.5, 0.0)));
        let (near, _) = drive(f.step(pose(0.55, 0.5, 0.0)));
        assert!(near < cruising, "{near} < {cruising}");
    }

    #[test]
    fn outputs_respect_the_limits() {
        let config = NavConfig::default();
        let mut rng = Lcg::new(5);
        let mut f = follower(pose(-1.2, -0.9, 0.0), pose(1.4, 0.6, 1.0));
        for _ in 0..5000 {
            let p = pose(
                rng.range(-1.5, 1.7),
                rng.range(-1.3, 0.9),
                rng.range(-10.0, 10.0),
            );
            match f.step(p) {
                NavCommand::Drive { linear, angular } => {
                    assert!((0.0..=config.cruise_speed).contains(&linear), "{linear}");
                    assert!(angular.abs() <= config.max_turn_rate + 1e-12, "{angular}");
                }
                NavCommand::Arrived => break,
            }
        }
        assert_eq!(f.step(pose(f64::NAN, 0.0, 0.0)), NavCommand::STOP);
    }

    #[test]
    fn arrives_only_within_the_tolerances() {
        let goal = pose(0.6, 0.5, 1.0);
        let mut f = follower(pose(0.0, 0.5, 0.0), goal);
        // On the spot but facing the wrong way: turns, no arrival.
        let (linear, angular) = drive(f.step(pose(0.6, 0.5, 0.0)));
        assert_eq!(linear, 0.0);
        assert!(angular > 0.0, "turn left towards yaw 1.0");
        // Within half the tolerances but just turning fast: stop first,
        // then arrived once calm, and it stays so.
        let there = pose(0.61, 0.5, 1.02);
        assert_eq!(f.step(there), NavCommand::STOP);
        let calm_steps = (0..5)
            .take_while(|_| f.step(there) != NavCommand::Arrived)
            .count();
        assert!(calm_steps < 5);
        assert_eq!(f.step(pose(5.0, 5.0, 0.0)), NavCommand::Arrived);
        // Close in position, wrong heading ⇒ not arrived.
        let mut f = follower(pose(0.0, 0.5, 0.0), goal);
        assert_ne!(f.step(pose(0.6, 0.5, 1.3)), NavCommand::Arrived);
    }

    #[test]
    fn off_path_flags_large_deviations_only() {
        let f = follower(pose(-1.0, 0.5, 0.0), pose(0.6, 0.5, 0.0));
        assert!(!f.off_path(pose(-0.5, 0.55, 0.0)));
        assert!(!f.off_path(pose(-0.5, 0.5 + 0.19, 0.0)));
        assert!(f.off_path(pose(-0.5, 0.5 + 0.21, 0.0)));
        assert!(!f.off_path(pose(f64::NAN, 0.0, 0.0)));
    }

    #[test]
    fn escape_leg_backs_out_of_a_boulder() {
        let grid = grid("monolith_obstacle");
        // Nose against the right face of the boulder at (0.762, −0.241),
        // facing it (west): the way out (east) is behind.
        let start = pose(0.762 + 0.13 + 0.105, -0.241, PI);
        let path = plan(&grid, start, pose(1.3, 0.0, 0.0)).expect("path");
        assert!(path.has_escape_leg());
        let mut f = PathFollower::new(path, 0.0, grid.config());
        let (linear, _) = drive(f.step(start));
        assert!(linear < 0.0, "reverses out: {linear}");
    }

    #[test]
    fn turn_angle_is_signed() {
        let (a, b) = (Point::new(0.0, 0.0), Point::new(1.0, 0.0));
        assert!((turn_angle(a, b, Point::new(1.0, 1.0)) - FRAC_PI_2).abs() < 1e-12);
        assert!((turn_angle(a, b, Point::new(1.0, -1.0)) + FRAC_PI_2).abs() < 1e-12);
        assert_eq!(turn_angle(a, a, b), 0.0);
    }
}
