//! The planner: A* over the occupancy grid (8-connected, octile heuristic,
//! no corner cutting, a soft cost for cells closer to obstacles than the
//! comfort radius), then line-of-sight shortcutting. A start inside
//! inflated space (robot pushed against an obstacle) first leaves it along
//! a straight escape leg to the nearest free cell connected to the goal.

use std::cmp::{Ordering, Reverse};
use std::collections::BinaryHeap;
use std::f64::consts::PI;

use offworld_runtime::msg::Pose2D;

use super::geometry::{wrap_angle, Point};
use super::grid::OccupancyGrid;
use super::NavError;

/// Sampling step when checking that an escape leg stays out of obstacle
/// footprints, m (footprints are ≥ 2 cm thick, so nothing slips between).
const ESCAPE_CHECK_STEP: f64 = 0.005;

/// Escape-leg choice: metres of extra leg worth one radian less turning on
/// the spot (turning in place is what scrapes when close to something).
const ESCAPE_TURN_COST: f64 = 0.15;

/// A route from the start pose to the goal pose: a polyline whose segments
/// keep at least the inflation radius of clearance (except an escape leg),
/// plus the start and goal poses it was planned for.
#[derive(Debug, Clone, PartialEq)]
pub struct Path {
    waypoints: Vec<Point>,
    start: Pose2D,
    goal: Pose2D,
    escape_leg: bool,
}

impl Path {
    /// Points to drive through, world frame: the start position first, the
    /// goal position last, at least two (equal when start = goal).
    pub fn waypoints(&self) -> &[Point] {
        &self.waypoints
    }

    /// The pose planned from.
    pub fn start(&self) -> Pose2D {
        self.start
    }

    /// The pose to end at (position and heading).
    pub fn goal(&self) -> Pose2D {
        self.goal
    }

    /// The first segment leaves inflated space (the start was too close to
    /// an obstacle or wall); it has less clearance than the rest and the
    /// follower may drive it backwards.
    pub fn has_escape_leg(&self) -> bool {
        self.escape_leg
    }

    /// Length of the polyline, m.
    pub fn length(&self) -> f64 {
        self.waypoints.windows(2).map(|w| w[0].distance(w[1])).sum()
    }
}

/// Plans from `start` to `goal` on `grid`. Deterministic: the same inputs
/// give the same path.
///
/// Errors: non-finite poses; a goal outside the walls, or inside an
/// obstacle or its inflation; a start outside the walls or inside a
/// footprint; a start boxed in by inflated space; a goal not connected to
/// the start.
pub fn plan(grid: &OccupancyGrid, start: Pose2D, goal: Pose2D) -> Result<Path, NavError> {
    if !(start.x.is_finite() && start.y.is_finite() && start.yaw.is_finite()) {
        return Err(NavError::NonFinite { what: "start" });
    }
    if !(goal.x.is_finite() && goal.y.is_finite() && goal.yaw.is_finite()) {
        return Err(NavError::NonFinite { what: "goal" });
    }
    let map = grid.map();
    let (start_pt, goal_pt) = (Point::new(start.x, start.y), Point::new(goal.x, goal.y));
    if !map.inside_enclosure(goal_pt) {
        return Err(NavError::GoalOutsideEnclosure {
            x: goal.x,
            y: goal.y,
        });
    }
    let blocked = NavError::GoalBlocked {
        x: goal.x,
        y: goal.y,
    };
    let goal_cell = grid.cell_at(goal_pt).ok_or(blocked.clone())?;
    let goal_region = grid.region(goal_cell).ok_or(blocked)?;
    let outside = NavError::StartOutsideEnclosure {
        x: start.x,
        y: start.y,
    };
    if !map.inside_enclosure(start_pt) {
        return Err(outside);
    }
    if map.inside_obstacle(start_pt) {
        return Err(NavError::StartInsideObstacle {
            x: start.x,
            y: start.y,
        });
    }
    let start_cell = grid.cell_at(start_pt).ok_or(outside)?;

    // Too close to something to turn in place safely: first drive straight
    // (forwards or backwards) to comfortable clearance if there is some
    // nearby. Outside the goal's free region: to any free cell of it.
    let config = grid.config();
    let in_goal_region = grid.region(start_cell) == Some(goal_region);
    let comfortable = if map.clearance(start_pt) < config.comfort_radius {
        escape_cell(grid, start, goal_region, config.comfort_radius)
    } else {
        None
    };
    let (first_cell, escape_leg) = match (comfortable, in_goal_region) {
        (Some(cell), _) => (cell, true),
        (None, true) => (start_cell, false),
        (None, false) => match escape_cell(grid, start, goal_region, f64::NEG_INFINITY) {
            Some(cell) => (cell, true),
            None if grid.is_free(start_cell) => return Err(NavError::Unreachable),
            None => {
                return Err(NavError::StartBlocked {
                    x: start.x,
                    y: start.y,
                });
            }
        },
    };
    // Same region, so the search succeeds; `None` would be a grid bug.
    let cells = astar(grid, first_cell, goal_cell).ok_or(NavError::Unreachable)?;

    // Raw polyline: the exact start and goal positions replace their cells'
    // centres. From any point of a cell to a neighbour's centre the segment
    // stays within the cells of that move, all free.
    let mut raw: Vec<Point> = cells.iter().map(|&c| grid.cell_centre(c)).collect();
    let mut raw_clearance: Vec<f64> = cells.iter().map(|&c| grid.centre_clearance(c)).collect();
    if let Some(last) = raw.last_mut() {
        *last = goal_pt;
    }
    if raw.len() == 1 {
        // Start (or escape) cell is the goal cell.
        raw.push(goal_pt);
        raw_clearance.push(grid.centre_clearance(goal_cell));
    }
    let mut waypoints = Vec::with_capacity(raw.len() + 1);
    if escape_leg {
        waypoints.push(start_pt);
    } else {
        raw[0] = start_pt;
    }
    waypoints.extend(shortcut(grid, &raw, &raw_clearance));
    Ok(Path {
        waypoints,
        start,
        goal,
        escape_leg,
    })
}

/// Where an escape leg from `start` ends: a free cell of `region` whose
/// centre has at least `min_clearance`, within the escape distance, reached
/// in a straight line that does not enter an obstacle footprint. Preferred:
/// near, and needing little turning first (the leg may be driven
/// backwards, so straight back out is as good as straight ahead). Ties go
/// to the lower cell index.
fn escape_cell(
    grid: &OccupancyGrid,
    start: Pose2D,
    region: u32,
    min_clearance: f64,
) -> Option<usize> {
    let config = grid.config();
    let from = Point::new(start.x, start.y);
    let reach = config.max_escape_distance;
    let (cols, rows) = grid.size();
    let (col, row) = grid.col_row(grid.cell_at(from)?);
    let span = (reach / config.resolution).ceil() as usize + 1;
    let mut candidates: Vec<(f64, usize)> = Vec::new();
    for r in row.saturating_sub(span)..(row + span + 1).min(rows) {
        for c in col.saturating_sub(span)..(col + span + 1).min(cols) {
            let cell = r * cols + c;
            let to = grid.cell_centre(cell);
            let distance = from.distance(to);
            if grid.region(cell) != Some(region)
                || distance > reach
                || grid.centre_clearance(cell) < min_clearance
            {
                continue;
            }
            let off_axis = wrap_angle(from.bearing_to(to) - start.yaw).abs();
            let turn = off_axis.min(PI - off_axis);
            candidates.push((distance + ESCAPE_TURN_COST * turn, cell));
        }
    }
    candidates.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    candidates.into_iter().map(|(_, cell)| cell).find(|&cell| {
        let to = grid.cell_centre(cell);
        let steps = (from.distance(to) / ESCAPE_CHECK_STEP).ceil().max(1.0) as usize;
        (0..=steps).all(|i| {
            !grid
                .map()
                .inside_obstacle(from.lerp(to, i as f64 / steps as f64))
        })
    })
}

/// An open-list entry, ordered by f, then h (closer to the goal first),
/// then cell index: a total order, so the search is deterministic.
#[derive(Debug, Clone, Copy)]
struct Open {
    f: f64,
    h: f64,
    cell: usize,
}

impl Ord for Open {
    fn cmp(&self, other: &Self) -> Ordering {
        self.f
            .total_cmp(&other.f)
            .then(self.h.total_cmp(&other.h))
            .then(self.cell.cmp(&other.cell))
    }
}

impl PartialOrd for Open {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

impl PartialEq for Open {
    fn eq(&self, other: &Self) -> bool {
        self.cmp(other) == Ordering::Equal
    }
}

impl Eq for Open {}

/// Cheapest cell sequence from `from` to `to` (both free), inclusive.
/// Costs are in cells: move length × (1 + comfort penalty of the cell
/// entered), so the octile distance is an admissible heuristic.
fn astar(grid: &OccupancyGrid, from: usize, to: usize) -> Option<Vec<usize>> {
    let config = grid.config();
    let band = config.comfort_radius - config.inflation_radius;
    let penalty = |cell: usize| {
        if band <= 0.0 {
            return 0.0;
        }
        let shortfall = (config.comfort_radius - grid.centre_clearance(cell)) / band;
        config.comfort_weight * shortfall.clamp(0.0, 1.0)
    };
    let (goal_col, goal_row) = grid.col_row(to);
    let heuristic = |cell: usize| {
        let (col, row) = grid.col_row(cell);
        let dx = col.abs_diff(goal_col) as f64;
        let dy = row.abs_diff(goal_row) as f64;
        dx.max(dy) + (std::f64::consts::SQRT_2 - 1.0) * dx.min(dy)
    };

    let mut cost = vec![f64::INFINITY; grid.len()];
    let mut parent = vec![usize::MAX; grid.len()];
    let mut closed = vec![false; grid.len()];
    let mut open = BinaryHeap::new();
    cost[from] = 0.0;
    let h = heuristic(from);
    open.push(Reverse(Open {
        f: h,
        h,
        cell: from,
    }));
    while let Some(Reverse(Open { cell, .. })) = open.pop() {
        if closed[cell] {
            continue;
        }
        if cell == to {
            let mut cells = vec![to];
            let mut at = to;
            while at != from {
                at = parent[at];
                cells.push(at);
            }
            cells.reverse();
            return Some(cells);
        }
        closed[cell] = true;
        for (next, step) in grid.moves(cell) {
            if closed[next] {
                continue;
            }
            let g = cost[cell] + step * (1.0 + penalty(next));
            if g < cost[next] {
                cost[next] = g;
                parent[next] = cell;
                let h = heuristic(next);
                open.push(Reverse(Open {
                    f: g + h,
                    h,
                    cell: next,
                }));
            }
        }
    }
    None
}

/// Greedy line-of-sight shortcutting of `raw` (whose consecutive points
/// are always connectable): from each kept point, jump to the farthest
/// later point whose straight segment crosses only free cells and comes no
/// closer to obstacles than the raw path it replaces did (capped at the
/// comfort radius, half a cell of slack). Without that second condition
/// shortcuts would hug the inflation boundary at every corner, where the
/// robot could not turn in place.
fn shortcut(grid: &OccupancyGrid, raw: &[Point], raw_clearance: &[f64]) -> Vec<Point> {
    let config = grid.config();
    let slack = 0.5 * config.resolution;
    let Some(&first) = raw.first() else {
        return Vec::new();
    };
    let mut kept = vec![first];
    let mut i = 0;
    while i + 1 < raw.len() {
        // Lowest raw clearance from i to each later point.
        let mut lowest = Vec::with_capacity(raw.len() - i);
        let mut running = f64::INFINITY;
        for &c in &raw_clearance[i..] {
            running = running.min(c);
            lowest.push(running);
        }
        let next = (i + 2..raw.len())
            .rev()
            .find(|&j| {
                let needed = lowest[j - i].min(config.comfort_radius) - slack;
                grid.segment_clearance(raw[i], raw[j])
                    .is_some_and(|clearance| clearance >= needed)
            })
            .unwrap_or(i + 1);
        kept.push(raw[next]);
        i = next;
    }
    kept
}

#[cfg(test)]
mod tests {
    use super::super::testkit::{grid, pose, spawn_poses, world};
    use super::super::NavConfig;
    use super::*;

    /// Every point of every segment, sampled at 1 cm, keeps the inflation
    /// radius of exact clearance (the escape leg excepted).
    fn assert_clear(grid: &OccupancyGrid, path: &Path) {
        let r = grid.config().inflation_radius;
        let skip = usize::from(path.has_escape_leg());
        for w in path.waypoints().windows(2).skip(skip) {
            let steps = (w[0].distance(w[1]) / 0.01).ceil().max(1.0) as usize;
            for i in 0..=steps {
                let p = w[0].lerp(w[1], i as f64 / steps as f64);
                assert!(
                    grid.clearance_at(p) >= r - 1e-9,
                    "{p:?} has clearance {} < {r}",
                    grid.clearance_at(p)
                );
            }
        }
    }

    #[test]
    fn path_around_a_boulder_keeps_inflation_clearance() {
        let grid = grid("monolith_obstacle");
        // Either side of the boulder at (0.762, −0.241), 0.26 × 0.20.
        let start = pose(0.35, -0.24, 0.0);
        let goal = pose(1.18, -0.24, 0.0);
        let path = plan(&grid, start, goal).expect("path");
        assert!(!path.has_escape_leg());
        assert_eq!(path.waypoints().first(), Some(&Point::new(0.35, -0.24)));
        assert_eq!(path.waypoints().last(), Some(&Point::new(1.18, -0.24)));
        assert!(path.waypoints().len() >= 3, "must bend around the boulder");
        assert!(path.length() > 0.83 + 0.05);
        assert_clear(&grid, &path);
    }

    #[test]
    fn paths_between_spawns_keep_inflation_clearance() {
        let world = world("monolith_obstacle");
        let grid = grid("monolith_obstacle");
        let spawns = spawn_poses(&world, 60, 11);
        for pair in spawns.windows(2) {
            let path = plan(&grid, pair[0], pair[1]).expect("path");
            assert!(!path.has_escape_leg());
            assert_clear(&grid, &path);
            // Shortcutting leaves few corners.
            assert!(path.waypoints().len() <= 12, "{}", path.waypoints().len());
        }
    }

    #[test]
    fn every_spawn_is_reachable_from_every_other() {
        // Reachability is symmetric and transitive on the grid, so paths
        // from one spawn to all others (and back) cover every pair.
        for name in ["monolith", "monolith_obstacle"] {
            let world = world(name);
            let grid = grid(name);
            let spawns = spawn_poses(&world, 500, 3);
            for other in &spawns[1..] {
                assert!(plan(&grid, spawns[0], *other).is_ok(), "{name}: {other:?}");
                assert!(plan(&grid, *other, spawns[0]).is_ok(), "{name}: {other:?}");
            }
        }
    }

    #[test]
    fn goal_inside_a_boulder_or_its_inflation_is_goal_blocked() {
        let grid = grid("monolith_obstacle");
        let start = pose(-0.3, 0.2, 0.0);
        for goal in [
            pose(0.762, -0.241, 0.0),
            pose(0.762 + 0.13 + 0.05, -0.241, 1.0),
        ] {
            assert!(matches!(
                plan(&grid, start, goal),
                Err(NavError::GoalBlocked { .. })
            ));
        }
        // The monolith too.
        assert!(matches!(
            plan(&grid, start, pose(0.0109, -0.2034, 0.0)),
            Err(NavError::GoalBlocked { .. })
        ));
    }

    #[test]
    fn goal_outside_the_enclosure_is_a_typed_error() {
        let grid = grid("monolith");
        let start = pose(-0.3, 0.2, 0.0);
        for goal in [
            pose(2.5, 0.0, 0.0),
            pose(0.0, -1.8, 0.0),
            pose(-1e9, 0.0, 0.0),
        ] {
            assert!(matches!(
                plan(&grid, start, goal),
                Err(NavError::GoalOutsideEnclosure { .. })
            ));
        }
        assert!(matches!(
            plan(&grid, pose(5.0, 0.0, 0.0), start),
            Err(NavError::StartOutsideEnclosure { .. })
        ));
    }

    #[test]
    fn enclosed_goal_is_unreachable() {
        // A ring of thin walls (as boulders) around a free 0.8 m square.
        let mut world = world("monolith");
        let (cx, cy, half, t) = (1.2_f32, 0.3_f32, 0.45_f32, 0.05_f32);
        let template = world.monolith.clone();
        for (x, y, sx, sy) in [
            (cx, cy + half, 2.0 * half + t, t),
            (cx, cy - half, 2.0 * half + t, t),
            (cx + half, cy, t, 2.0 * half + t),
            (cx - half, cy, t, 2.0 * half + t),
        ] {
            world.boulders.push(offworld_runtime::world::BoulderSpec {
                center: [x, y],
                size: [sx, sy, 0.2],
                albedo: template.albedo,
            });
        }
        let grid = OccupancyGrid::from_world(&world, &NavConfig::default()).expect("grid");
        let inside = pose(f64::from(cx), f64::from(cy), 0.0);
        assert!(grid.is_free_at(Point::new(inside.x, inside.y)));
        let outside = pose(-0.5, 0.5, 0.0);
        assert_eq!(plan(&grid, outside, inside), Err(NavError::Unreachable));
        assert_eq!(plan(&grid, inside, outside), Err(NavError::Unreachable));
    }

    #[test]
    fn non_finite_inputs_are_typed_errors() {
        let grid = grid("monolith");
        let ok = pose(-0.3, 0.2, 0.0);
        assert_eq!(
            plan(&grid, pose(f64::NAN, 0.0, 0.0), ok),
            Err(NavError::NonFinite { what: "start" })
        );
        assert_eq!(
            plan(&grid, ok, pose(0.5, 0.5, f64::INFINITY)),
            Err(NavError::NonFinite { what: "goal" })
        );
    }

    #[test]
    fn same_inputs_give_identical_paths() {
        let a = grid("monolith_obstacle");
        let b = grid("monolith_obstacle");
        let start = pose(-1.3, -0.5, 0.3);
        let goal = pose(1.4, 0.1, -2.0);
        let first = plan(&a, start, goal).expect("path");
        for _ in 0..3 {
            assert_eq!(plan(&a, start, goal).expect("path"), first);
            assert_eq!(plan(&b, start, goal).expect("path"), first);
        }
    }

    #[test]
    fn start_inside_inflation_escapes_to_free_space() {
        let grid = grid("monolith_obstacle");
        // Nose against the right face of the boulder at (0.762, −0.241):
        // the robot centre 0.105 m from the face.
        let start = pose(0.762 + 0.13 + 0.105, -0.241, std::f64::consts::PI);
        assert!(!grid.is_free_at(Point::new(start.x, start.y)));
        let goal = pose(1.3, 0.0, 0.0);
        let path = plan(&grid, start, goal).expect("path");
        assert!(path.has_escape_leg());
        let w = path.waypoints();
        assert!(grid.is_free_at(w[1]), "escape leg ends in free space");
        assert!(w[0].distance(w[1]) <= grid.config().max_escape_distance);
        // It leaves away from the boulder (east).
        assert!(w[1].x > w[0].x);
        assert_clear(&grid, &path);
        // Inside a footprint is a map/tracker disagreement.
        assert!(matches!(
            plan(&grid, pose(0.762, -0.241, 0.0), goal),
            Err(NavError::StartInsideObstacle { .. })
        ));
    }

    #[test]
    fn start_at_goal_is_a_two_point_path() {
        let grid = grid("monolith");
        let here = pose(-0.5, 0.4, 0.2);
        let path = plan(&grid, here, pose(-0.5, 0.4, 2.0)).expect("path");
        assert_eq!(path.waypoints().len(), 2);
        assert_eq!(path.length(), 0.0);
    }
}
