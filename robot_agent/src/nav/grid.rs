//! The occupancy grid: the enclosure interior cut into square cells, each
//! free or blocked by the inflated walls, monolith and boulders, with the
//! clearance of its centre (for the planner's comfort cost) and the label
//! of the connected free region it belongs to (so that unreachable goals
//! are known without searching).
//!
//! A cell is blocked when *any* part of it is closer than the inflation
//! radius to a wall or footprint. That is conservative by up to a cell
//! diagonal, but it makes the guarantee exact: every point of a free cell,
//! and so every point of a segment that only crosses free cells, has at
//! least the inflation radius of clearance.

use std::collections::VecDeque;

use offworld_runtime::WorldSpec;

use super::geometry::{MapGeometry, Point, Rect};
use super::{NavConfig, NavError};

/// Largest grid accepted, cells (a 4 × 3 m enclosure at 5 mm is 480 000).
const MAX_CELLS: usize = 4_000_000;

/// Tolerance, in cell units, for a segment touching a cell edge or corner:
/// such cells count as crossed, so grazing a blocked cell is never missed.
const EDGE_EPSILON: f64 = 1e-9;

/// Region label of blocked cells.
const NO_REGION: u32 = u32::MAX;

/// The eight moves, in a fixed order (determinism of the planner's
/// tie-breaking depends on it): straight ones first.
const MOVES: [(isize, isize); 8] = [
    (1, 0),
    (0, 1),
    (-1, 0),
    (0, -1),
    (1, 1),
    (-1, 1),
    (-1, -1),
    (1, -1),
];

/// The map as the planner sees it. Built once per world and reused for
/// every reset.
#[derive(Debug, Clone)]
pub struct OccupancyGrid {
    config: NavConfig,
    map: MapGeometry,
    /// World position of the low corner of cell (0, 0).
    origin: Point,
    cols: usize,
    rows: usize,
    /// Row-major, index = row · cols + col.
    free: Vec<bool>,
    /// Clearance of each cell centre, m.
    centre_clearance: Vec<f64>,
    /// Connected free region of each cell (8-connected, no corner cutting,
    /// exactly the planner's moves); `NO_REGION` when blocked.
    region: Vec<u32>,
}

impl OccupancyGrid {
    /// Rasterises the enclosure interior of `world` at `config.resolution`
    /// with walls, monolith and boulders inflated by
    /// `config.inflation_radius`.
    pub fn from_world(world: &WorldSpec, config: &NavConfig) -> Result<Self, NavError> {
        config.validate()?;
        let map = MapGeometry::from_world(world)?;
        let res = config.resolution;
        let origin = map.interior.min;
        let cols = ((map.interior.max.x - origin.x) / res).ceil() as usize;
        let rows = ((map.interior.max.y - origin.y) / res).ceil() as usize;
        if cols.checked_mul(rows).is_none_or(|n| n > MAX_CELLS) {
            return Err(NavError::InvalidConfig(
                "resolution too fine for the enclosure (grid too large)",
            ));
        }
        let mut free = Vec::with_capacity(cols * rows);
        let mut centre_clearance = Vec::with_capacity(cols * rows);
        for row in 0..rows {
            for col in 0..cols {
                let low = Point::new(origin.x + col as f64 * res, origin.y + row as f64 * res);
                let cell = Rect {
                    min: low,
                    max: Point::new(low.x + res, low.y + res),
                };
                free.push(map.rect_clearance(&cell) >= config.inflation_radius);
                let centre = Point::new(low.x + 0.5 * res, low.y + 0.5 * res);
                centre_clearance.push(map.clearance(centre));
            }
        }
        let mut grid = Self {
            config: config.clone(),
            map,
            origin,
            cols,
            rows,
            free,
            centre_clearance,
            region: Vec::new(),
        };
        grid.region = grid.label_regions();
        Ok(grid)
    }

    /// The configuration the grid was built with (the planner and the
    /// navigator use it too).
    pub fn config(&self) -> &NavConfig {
        &self.config
    }

    /// Columns (along x) and rows (along y).
    pub fn size(&self) -> (usize, usize) {
        (self.cols, self.rows)
    }

    /// The cell containing `p` exists and is free: the robot centre may be
    /// anywhere in it.
    pub fn is_free_at(&self, p: Point) -> bool {
        self.cell_at(p).is_some_and(|cell| self.free[cell])
    }

    /// Exact distance from `p` to the nearest wall face or obstacle
    /// footprint, m; 0 or less when outside the interior or inside a
    /// footprint.
    pub fn clearance_at(&self, p: Point) -> f64 {
        self.map.clearance(p)
    }

    /// The exact map geometry behind the grid.
    pub(crate) fn map(&self) -> &MapGeometry {
        &self.map
    }

    /// Index of the cell containing `p`, `None` outside the grid.
    pub(crate) fn cell_at(&self, p: Point) -> Option<usize> {
        let u = (p.x - self.origin.x) / self.config.resolution;
        let v = (p.y - self.origin.y) / self.config.resolution;
        // The negated comparison also rejects NaN.
        if !(u >= 0.0 && v >= 0.0 && u < self.cols as f64 && v < self.rows as f64) {
            return None;
        }
        Some(v as usize * self.cols + u as usize)
    }

    /// Centre of cell `cell`.
    pub(crate) fn cell_centre(&self, cell: usize) -> Point {
        let (col, row) = (cell % self.cols, cell / self.cols);
        Point::new(
            self.origin.x + (col as f64 + 0.5) * self.config.resolution,
            self.origin.y + (row as f64 + 0.5) * self.config.resolution,
        )
    }

    /// Column and row of `cell`.
    pub(crate) fn col_row(&self, cell: usize) -> (usize, usize) {
        (cell % self.cols, cell / self.cols)
    }

    /// Number of cells.
    pub(crate) fn len(&self) -> usize {
        self.free.len()
    }

    /// Cell `cell` is free.
    pub(crate) fn is_free(&self, cell: usize) -> bool {
        self.free[cell]
    }

    /// Clearance of the centre of `cell`, m.
    pub(crate) fn centre_clearance(&self, cell: usize) -> f64 {
        self.centre_clearance[cell]
    }

    /// Connected free region of `cell`, `None` when blocked.
    pub(crate) fn region(&self, cell: usize) -> Option<u32> {
        Some(self.region[cell]).filter(|&r| r != NO_REGION)
    }

    /// The free cells one planner move away from free cell `cell`, with the
    /// move length in cells (1 or √2). Diagonal moves need both cells they
    /// pass between to be free (no corner cutting), so the straight segment
    /// between the centres only crosses free cells.
    pub(crate) fn moves(&self, cell: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        let (col, row) = self.col_row(cell);
        MOVES.iter().filter_map(move |&(dc, dr)| {
            let to = self.offset(col, row, dc, dr)?;
            if !self.free[to] {
                return None;
            }
            if dc != 0 && dr != 0 {
                let side_a = self.offset(col, row, dc, 0)?;
                let side_b = self.offset(col, row, 0, dr)?;
                if !(self.free[side_a] && self.free[side_b]) {
                    return None;
                }
                return Some((to, std::f64::consts::SQRT_2));
            }
            Some((to, 1.0))
        })
    }

    fn offset(&self, col: usize, row: usize, dc: isize, dr: isize) -> Option<usize> {
        let c = col.checked_add_signed(dc).filter(|&c| c < self.cols)?;
        let r = row.checked_add_signed(dr).filter(|&r| r < self.rows)?;
        Some(r * self.cols + c)
    }

    /// Calls `visit` with every cell the segment `a`–`b` crosses or touches
    /// (supercover), stopping early when `visit` returns false. Returns
    /// false when stopped or when the segment leaves the grid.
    pub(crate) fn for_cells_on_segment(
        &self,
        a: Point,
        b: Point,
        mut visit: impl FnMut(usize) -> bool,
    ) -> bool {
        let res = self.config.resolution;
        let (ua, va) = ((a.x - self.origin.x) / res, (a.y - self.origin.y) / res);
        let (ub, vb) = ((b.x - self.origin.x) / res, (b.y - self.origin.y) / res);
        if !(ua.is_finite() && va.is_finite() && ub.is_finite() && vb.is_finite()) {
            return false;
        }
        let (u_lo, u_hi) = (ua.min(ub), ua.max(ub));
        let col_first = (u_lo - EDGE_EPSILON).floor();
        let col_last = (u_hi + EDGE_EPSILON).floor();
        if col_first < 0.0 || col_last >= self.cols as f64 {
            return false;
        }
        let du = ub - ua;
        let slope = if du.abs() > 1e-12 {
            Some((vb - va) / du)
        } else {
            None
        };
        for col in col_first as usize..=col_last as usize {
            // The part of the segment within this column.
            let (v_lo, v_hi) = match slope {
                Some(slope) => {
                    let from = u_lo.max(col as f64);
                    let to = u_hi.min(col as f64 + 1.0);
                    let (v_from, v_to) = (va + (from - ua) * slope, va + (to - ua) * slope);
                    (v_from.min(v_to), v_from.max(v_to))
                }
                None => (va.min(vb), va.max(vb)),
            };
            let row_first = (v_lo - EDGE_EPSILON).floor();
            let row_last = (v_hi + EDGE_EPSILON).floor();
            if row_first < 0.0 || row_last >= self.rows as f64 {
                return false;
            }
            for row in row_first as usize..=row_last as usize {
                if !visit(row * self.cols + col) {
                    return false;
                }
            }
        }
        true
    }

    /// The segment `a`–`b` only crosses free cells; then the smallest
    /// centre clearance of those cells, m.
    pub(crate) fn segment_clearance(&self, a: Point, b: Point) -> Option<f64> {
        let mut lowest = f64::INFINITY;
        let clear = self.for_cells_on_segment(a, b, |cell| {
            lowest = lowest.min(self.centre_clearance[cell]);
            self.free[cell]
        });
        clear.then_some(lowest)
    }

    /// Labels the connected free regions by flood fill over planner moves.
    fn label_regions(&self) -> Vec<u32> {
        let mut region = vec![NO_REGION; self.len()];
        let mut next = 0u32;
        let mut queue = VecDeque::new();
        for seed in 0..self.len() {
            if !self.free[seed] || region[seed] != NO_REGION {
                continue;
            }
            region[seed] = next;
            queue.push_back(seed);
            while let Some(cell) = queue.pop_front() {
                for (to, _) in self.moves(cell) {
                    if region[to] == NO_REGION {
                        region[to] = next;
                        queue.push_back(to);
                    }
                }
            }
            next += 1;
        }
        region
    }
}

#[cfg(test)]
mod tests {
    use super::super::testkit::{spawn_poses, world};
    use super::*;

    #[test]
    fn inflated_obstacles_and_walls_are_blocked_and_open_centre_is_free() {
        let config = NavConfig::default();
        let grid = OccupancyGrid::from_world(&world("monolith_obstacle"), &config).expect("grid");
        let r = config.inflation_radius;
        // Boulder 14 at (0.029, −0.903), 0.26 × 0.20: its centre, just
        // inside the inflation beside each face, and just outside it.
        let (bx, by) = (0.029, -0.903);
        assert!(!grid.is_free_at(Point::new(bx, by)));
        for p in [
            Point::new(bx + 0.13 + r - 0.01, by),
            Point::new(bx - 0.13 - r + 0.01, by),
            Point::new(bx, by + 0.10 + r - 0.01),
            Point::new(bx, by - 0.10 - r + 0.01),
        ] {
            assert!(!grid.is_free_at(p), "{p:?} should be inflated");
        }
        // Free once a whole cell diagonal further out.
        let beyond = r + config.resolution * std::f64::consts::SQRT_2 + 0.001;
        assert!(grid.is_free_at(Point::new(bx + 0.13 + beyond, by)));
        // Monolith at (0.0109, −0.2034), 0.0254 × 0.2159.
        assert!(!grid.is_free_at(Point::new(0.0109, -0.2034)));
        assert!(!grid.is_free_at(Point::new(0.0109 + 0.0127 + r - 0.01, -0.2034)));
        // Walls.
        assert!(!grid.is_free_at(Point::new(-1.913 + r - 0.01, 0.3)));
        assert!(!grid.is_free_at(Point::new(2.06 - r + 0.01, 0.3)));
        assert!(!grid.is_free_at(Point::new(0.3, -1.761 + r - 0.01)));
        assert!(!grid.is_free_at(Point::new(0.3, 1.235 - r + 0.01)));
        assert!(!grid.is_free_at(Point::new(3.0, 0.0)));
        // Open space: the enclosure centre region west of the monolith and
        // the open world's centre beside the monolith.
        assert!(grid.is_free_at(Point::new(-0.3, 0.2)));
        let open = OccupancyGrid::from_world(&world("monolith"), &config).expect("grid");
        assert!(open.is_free_at(Point::new(0.4, -0.2)));
        assert!(
            open.is_free_at(Point::new(-0.677, -0.187)),
            "no boulders there"
        );
    }

    #[test]
    fn free_cells_keep_the_inflation_radius_everywhere() {
        let config = NavConfig::default();
        let grid = OccupancyGrid::from_world(&world("monolith_obstacle"), &config).expect("grid");
        let res = config.resolution;
        for cell in (0..grid.len()).filter(|&c| grid.is_free(c)) {
            let c = grid.cell_centre(cell);
            for (dx, dy) in [
                (-0.5, -0.5),
                (0.5, -0.5),
                (-0.5, 0.5),
                (0.5, 0.5),
                (0.0, 0.0),
            ] {
                let p = Point::new(c.x + dx * res, c.y + dy * res);
                assert!(grid.clearance_at(p) >= config.inflation_radius - 1e-9);
            }
        }
    }

    #[test]
    fn every_valid_spawn_is_free_in_both_worlds() {
        let config = NavConfig::default();
        for name in ["monolith", "monolith_obstacle"] {
            let world = world(name);
            let grid = OccupancyGrid::from_world(&world, &config).expect("grid");
            let spawns = spawn_poses(&world, 500, 7);
            assert_eq!(spawns.len(), 500);
            for pose in &spawns {
                assert!(
                    grid.is_free_at(Point::new(pose.x, pose.y)),
                    "{name}: spawn {pose:?} is blocked"
                );
            }
            // One connected region holds them all (the planner's moves).
            let regions: Vec<_> = spawns
                .iter()
                .map(|p| {
                    grid.cell_at(Point::new(p.x, p.y))
                        .and_then(|c| grid.region(c))
                })
                .collect();
            assert!(
                regions.iter().all(|r| r.is_some() && *r == regions[0]),
                "{name}"
            );
        }
    }

    #[test]
    fn supercover_sees_every_crossed_or_touched_cell() {
        let config = NavConfig::default();
        let grid = OccupancyGrid::from_world(&world("monolith"), &config).expect("grid");
        let res = config.resolution;
        let c0 = grid.cell_centre(grid.cell_at(Point::new(0.5, 0.5)).expect("cell"));
        // Diagonal through a shared corner touches all four cells.
        let mut seen = Vec::new();
        let done = grid.for_cells_on_segment(c0, Point::new(c0.x + res, c0.y + res), |c| {
            seen.push(c);
            true
        });
        assert!(done);
        seen.sort_unstable();
        assert_eq!(seen.len(), 4);
        // A shallow segment over three columns crosses a row boundary once.
        let mut seen = Vec::new();
        grid.for_cells_on_segment(c0, Point::new(c0.x + 2.0 * res, c0.y + res), |c| {
            seen.push(grid.col_row(c));
            true
        });
        let (col, row) = grid.col_row(grid.cell_at(c0).expect("cell"));
        assert_eq!(
            seen,
            vec![
                (col, row),
                (col + 1, row),
                (col + 1, row + 1),
                (col + 2, row + 1)
            ]
        );
        // Leaving the grid is never clear.
        assert!(!grid.for_cells_on_segment(c0, Point::new(5.0, 0.0), |_| true));
        assert!(!grid.for_cells_on_segment(c0, Point::new(f64::NAN, 0.0), |_| true));
    }

    #[test]
    fn bad_config_and_map_are_typed_errors() {
        let bad = NavConfig {
            resolution: -1.0,
            ..NavConfig::default()
        };
        assert!(matches!(
            OccupancyGrid::from_world(&world("monolith"), &bad),
            Err(NavError::InvalidConfig(_))
        ));
        let mut broken = world("monolith");
        broken.enclosure.x_max = broken.enclosure.x_min;
        assert!(matches!(
            OccupancyGrid::from_world(&broken, &NavConfig::default()),
            Err(NavError::InvalidMap(_))
        ));
        let mut broken = world("monolith_obstacle");
        broken.boulders[0].center[0] = f32::NAN;
        assert!(matches!(
            OccupancyGrid::from_world(&broken, &NavConfig::default()),
            Err(NavError::InvalidMap(_))
        ));
    }
}
