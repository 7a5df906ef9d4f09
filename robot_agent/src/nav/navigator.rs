//! One reset drive: plans from the current pose to the goal, follows the
//! path, and re-plans from wherever the robot is when it strays off the
//! path (slip, bumps, tracker jumps). The caller owns the clock: it calls
//! [`Navigator::step`] at ~20 Hz with the latest tracker pose, sends the
//! velocity, stops on `Arrived` or on an error, and enforces the overall
//! timeout (size it from [`estimate_travel_time`]).

use offworld_runtime::msg::Pose2D;

use super::estimate::estimate_travel_time;
use super::follow::{NavCommand, PathFollower};
use super::grid::OccupancyGrid;
use super::plan::{plan, Path};
use super::{NavConfig, NavError};

/// Drives to one goal pose. Holds no reference to the map: pass the same
/// grid to every call (the agent keeps the grid and the navigation side by
/// side).
#[derive(Debug, Clone)]
pub struct Navigator {
    goal: Pose2D,
    follower: PathFollower,
    replans: u32,
}

impl Navigator {
    /// Plans from `start` (the current tracker pose) to `goal` with the
    /// grid's configuration. Fails with the planner's typed errors, so an
    /// impossible goal is refused before the robot moves.
    pub fn new(grid: &OccupancyGrid, start: Pose2D, goal: Pose2D) -> Result<Self, NavError> {
        let path = plan(grid, start, goal)?;
        Ok(Self {
            goal,
            follower: PathFollower::new(path, goal.yaw, grid.config()),
            replans: 0,
        })
    }

    /// The command for the robot at `pose`. Re-plans on `grid` first when
    /// the robot is off the path; a failed re-plan is returned as the error
    /// (stop the robot). Non-finite poses give [`NavCommand::STOP`].
    pub fn step(&mut self, grid: &OccupancyGrid, pose: Pose2D) -> Result<NavCommand, NavError> {
        if self.follower.off_path(pose) {
            let path = plan(grid, pose, self.goal)?;
            tracing::debug!(
                x = pose.x,
                y = pose.y,
                replans = self.replans + 1,
                "off the reset path; re-planned"
            );
            self.follower = PathFollower::new(path, self.goal.yaw, grid.config());
            self.replans += 1;
        }
        Ok(self.follower.step(pose))
    }

    /// The path being followed (the latest plan).
    pub fn path(&self) -> &Path {
        self.follower.path()
    }

    /// Re-plans so far.
    pub fn replans(&self) -> u32 {
        self.replans
    }

    /// Estimated seconds to drive the current path from its start with
    /// `config` (the grid's).
    pub fn estimated_time(&self, config: &NavConfig) -> f64 {
        estimate_travel_time(self.follower.path(), config)
    }
}

#[cfg(test)]
mod tests {
    use super::super::geometry::{MapGeometry, Point};
    use super::super::testkit::{
        footprint_separation, grid, pose, spawn_poses, world, Lcg, Unicycle,
    };
    use super::*;

    /// Control period and simulation step, s.
    const DT: f64 = 0.05;
    /// Give up after this much simulated time, s.
    const SIM_LIMIT_S: f64 = 180.0;
    /// ROSbot footprint, m.
    const FOOTPRINT: [f64; 2] = [0.200, 0.235];

    /// How one simulated reset went.
    #[derive(Debug)]
    struct Outcome {
        /// Simulated seconds until `Arrived`.
        time: f64,
        /// Settled pose after the final stop.
        end: Pose2D,
        /// Smallest footprint separation from walls and obstacles, m.
        min_separation: f64,
        replans: u32,
        estimate: f64,
    }

    /// What the navigator sees of the robot.
    #[derive(Debug, Clone, Copy)]
    struct Tracker {
        /// Uniform noise on each pose coordinate, ± m (and ± rad on yaw).
        noise: f64,
        /// Poses reach the navigator this many control periods late.
        latency_ticks: usize,
        seed: u64,
    }

    impl Tracker {
        fn perfect() -> Self {
            Self {
                noise: 0.0,
                latency_ticks: 0,
                seed: 0,
            }
        }
    }

    /// Drives the unicycle from `start` to `goal` at 20 Hz.
    fn simulate(
        grid: &OccupancyGrid,
        map: &MapGeometry,
        start: Pose2D,
        goal: Pose2D,
        tracker: Tracker,
    ) -> Outcome {
        let mut nav = Navigator::new(grid, start, goal).expect("plan");
        let estimate = nav.estimated_time(grid.config());
        let mut robot = Unicycle::new(start);
        let mut rng = Lcg::new(tracker.seed);
        let mut history = std::collections::VecDeque::new();
        let mut min_separation = footprint_separation(map, start, FOOTPRINT);
        let mut time = 0.0;
        loop {
            assert!(
                time < SIM_LIMIT_S,
                "no arrival from {start:?} to {goal:?} at {:?}",
                robot.pose
            );
            history.push_back(robot.pose);
            if history.len() > tracker.latency_ticks + 1 {
                history.pop_front();
            }
            let mut seen = history.front().copied().unwrap_or(robot.pose);
            let noise = tracker.noise;
            seen.x += rng.range(-noise, noise);
            seen.y += rng.range(-noise, noise);
            seen.yaw += rng.range(-noise, noise);
            match nav.step(grid, seen).expect("step") {
                NavCommand::Arrived => break,
                NavCommand::Drive { linear, angular } => robot.step(linear, angular, DT),
            }
            time += DT;
            min_separation = min_separation.min(footprint_separation(map, robot.pose, FOOTPRINT));
        }
        // The caller stops the robot: let it coast to rest.
        for _ in 0..20 {
            robot.step(0.0, 0.0, DT);
            min_separation = min_separation.min(footprint_separation(map, robot.pose, FOOTPRINT));
        }
        Outcome {
            time,
            end: robot.pose,
            min_separation,
            replans: nav.replans(),
            estimate,
        }
    }

    fn assert_within_tolerance(grid: &OccupancyGrid, outcome: &Outcome, goal: Pose2D) {
        let c = grid.config();
        let distance =
            Point::new(outcome.end.x, outcome.end.y).distance(Point::new(goal.x, goal.y));
        let heading = super::super::geometry::wrap_angle(outcome.end.yaw - goal.yaw).abs();
        assert!(distance <= c.position_tolerance, "{outcome:?} vs {goal:?}");
        assert!(heading <= c.heading_tolerance, "{outcome:?} vs {goal:?}");
    }

    fn median(values: &mut [f64]) -> f64 {
        values.sort_by(f64::total_cmp);
        let n = values.len();
        if n % 2 == 1 {
            values[n / 2]
        } else {
            0.5 * (values[n / 2 - 1] + values[n / 2])
        }
    }

    #[test]
    fn closed_loop_reaches_100_random_spawn_pairs_without_collision() {
        let world = world("monolith_obstacle");
        let grid = grid("monolith_obstacle");
        let map = MapGeometry::from_world(&world).expect("map");
        let spawns = spawn_poses(&world, 200, 2024);
        let mut times = Vec::new();
        let mut ratios = Vec::new();
        let mut worst_separation = f64::INFINITY;
        for pair in spawns.chunks(2) {
            let outcome = simulate(&grid, &map, pair[0], pair[1], Tracker::perfect());
            assert_within_tolerance(&grid, &outcome, pair[1]);
            assert!(
                outcome.min_separation > 0.0,
                "collision: {outcome:?} {pair:?}"
            );
            assert_eq!(outcome.replans, 0, "{pair:?}");
            worst_separation = worst_separation.min(outcome.min_separation);
            ratios.push(outcome.estimate / outcome.time.max(DT));
            times.push(outcome.time);
        }
        let max = times.iter().copied().fold(0.0, f64::max);
        let median_time = median(&mut times);
        let (lo, hi) = (
            ratios.iter().copied().fold(f64::INFINITY, f64::min),
            ratios.iter().copied().fold(0.0, f64::max),
        );
        let median_ratio = median(&mut ratios);
        println!(
            "simulated reset time over 100 spawn pairs: median {median_time:.1} s, max {max:.1} s; \
             closest footprint approach {worst_separation:.3} m; \
             estimate/actual median {median_ratio:.2}, range {lo:.2}–{hi:.2}"
        );
        // The estimate is good enough to report and to size timeouts with.
        assert!(lo > 0.7 && hi < 1.3, "estimate/actual {lo}–{hi}");
    }

    #[test]
    fn closed_loop_tolerates_tracker_noise_and_latency() {
        // ±1 cm / ±0.01 rad noise, poses 100 ms late.
        let world = world("monolith_obstacle");
        let grid = grid("monolith_obstacle");
        let map = MapGeometry::from_world(&world).expect("map");
        let spawns = spawn_poses(&world, 60, 99);
        for (i, pair) in spawns.chunks(2).enumerate() {
            let tracker = Tracker {
                noise: 0.01,
                latency_ticks: 2,
                seed: i as u64,
            };
            let outcome = simulate(&grid, &map, pair[0], pair[1], tracker);
            assert_within_tolerance(&grid, &outcome, pair[1]);
            assert!(
                outcome.min_separation > 0.0,
                "collision: {outcome:?} {pair:?}"
            );
        }
    }

    #[test]
    fn closed_loop_leaves_the_tight_pocket_between_boulders() {
        // The spawn pocket south of the boulder at (0.029, −0.903), walled
        // in by boulders and the south wall: its exits are 0.29–0.35 m wide.
        let world = world("monolith_obstacle");
        let grid = grid("monolith_obstacle");
        let map = MapGeometry::from_world(&world).expect("map");
        let pocket = pose(0.006, -1.335, 0.7);
        for goal in [
            pose(-1.2, 0.4, 0.0),
            pose(1.5, 0.8, 2.0),
            pose(0.9, -1.35, 3.0),
        ] {
            for (from, to) in [(pocket, goal), (goal, pocket)] {
                let outcome = simulate(&grid, &map, from, to, Tracker::perfect());
                assert_within_tolerance(&grid, &outcome, to);
                assert!(
                    outcome.min_separation > 0.0,
                    "collision: {outcome:?} {from:?} {to:?}"
                );
            }
        }
    }

    #[test]
    fn closed_loop_backs_out_of_a_boulder_and_arrives() {
        let world = world("monolith_obstacle");
        let grid = grid("monolith_obstacle");
        let map = MapGeometry::from_world(&world).expect("map");
        // Nose 1 cm from the boulder at (0.762, −0.241), facing it.
        let start = pose(0.762 + 0.13 + 0.11, -0.241, std::f64::consts::PI);
        assert!(footprint_separation(&map, start, FOOTPRINT) > 0.0);
        let goal = pose(-0.9, 0.3, 1.0);
        let outcome = simulate(&grid, &map, start, goal, Tracker::perfect());
        assert_within_tolerance(&grid, &outcome, goal);
        assert!(outcome.min_separation > 0.0, "collision: {outcome:?}");
    }

    #[test]
    fn impossible_goals_are_refused_before_moving() {
        let grid = grid("monolith_obstacle");
        let start = pose(-0.3, 0.2, 0.0);
        assert!(matches!(
            Navigator::new(&grid, start, pose(0.762, -0.241, 0.0)),
            Err(NavError::GoalBlocked { .. })
        ));
        assert!(matches!(
            Navigator::new(&grid, start, pose(9.0, 0.0, 0.0)),
            Err(NavError::GoalOutsideEnclosure { .. })
        ));
    }

    #[test]
    fn a_kidnapped_robot_is_replanned() {
        let grid = grid("monolith_obstacle");
        let goal = pose(1.3, 0.0, 0.0);
        let mut nav = Navigator::new(&grid, pose(-1.2, 0.3, 0.0), goal).expect("plan");
        assert!(nav.step(&grid, pose(-1.2, 0.3, 0.0)).is_ok());
        let elsewhere = pose(-0.3, -1.0, 0.0);
        assert!(nav.step(&grid, elsewhere).is_ok());
        assert_eq!(nav.replans(), 1);
        assert_eq!(nav.path().waypoints()[0], Point::new(-0.3, -1.0));
        // Same goal (position and heading).
        assert_eq!(nav.path().goal(), goal);
    }
}
