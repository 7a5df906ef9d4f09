//! The fast level-camera renderer: one front-to-back walk per image column.
//!
//! For a level camera, every ray of column `u` lies in the vertical plane
//! through the optical centre along `forward + a_u · right`; with that
//! unnormalised direction the walk parameter `t` *is* the z-depth. Rows are
//! ordered by how steeply they look down (`b_v`), so while walking forward
//! the rows that meet the ground do so in order: each pixel is resolved once,
//! exactly, on the terrain triangle it hits (the profile of a triangulated
//! heightfield along a line is piecewise linear between grid-line and
//! diagonal crossings). Boxes are intersected analytically per column.

use super::{CameraPose, Intrinsics, PixelsMut, RgbdFrame, Shading};
use crate::scene::Scene;
use crate::terrain::Terrain;
use crate::world::LightSpec;

/// Renders level-camera RGBD frames; owns its scratch buffers so a frame
/// costs no allocation.
#[derive(Debug, Clone)]
pub struct ColumnRenderer {
    intrinsics: Intrinsics,
    shading: Shading,
    row_slopes: Vec<f32>,
    inv_row_slopes: Vec<f32>,
    col_depth: Vec<f32>,
    col_grey: Vec<u8>,
}

const T_START: f32 = 1e-3;

impl ColumnRenderer {
    /// A renderer for one image size.
    pub fn new(intrinsics: Intrinsics, light: &LightSpec) -> Self {
        let h = intrinsics.height as usize;
        Self {
            intrinsics,
            shading: Shading::new(light),
            row_slopes: (0..intrinsics.height)
                .map(|v| intrinsics.row_slope(v))
                .collect(),
            inv_row_slopes: (0..intrinsics.height)
                .map(|v| 1.0 / intrinsics.row_slope(v))
                .collect(),
            col_depth: vec![f32::INFINITY; h],
            col_grey: vec![0; h],
        }
    }

    /// The intrinsics rendered with.
    pub fn intrinsics(&self) -> &Intrinsics {
        &self.intrinsics
    }

    /// Renders into `frame` (resized if needed). Pitch and roll of `pose`
    /// are ignored: this is the level-camera fast path.
    pub fn render(&mut self, scene: &Scene, pose: &CameraPose, frame: &mut RgbdFrame) {
        let intr = self.intrinsics;
        if frame.width != intr.width || frame.height != intr.height {
            *frame = RgbdFrame::new(intr.width, intr.height);
        }
        self.render_into(scene, pose, &mut frame.pixels_mut());
    }

    /// Renders into `pixels`, which must have the sizes of the intrinsics
    /// (every pixel is written); returns false, writing nothing, if not.
    pub fn render_into(
        &mut self,
        scene: &Scene,
        pose: &CameraPose,
        pixels: &mut PixelsMut<'_>,
    ) -> bool {
        let intr = self.intrinsics;
        let n = (intr.width * intr.height) as usize;
        if pixels.rgb.len() != n * 3 || pixels.depth.len() != n {
            return false;
        }
        let (sin_y, cos_y) = pose.yaw.sin_cos();
        let forward = [cos_y, sin_y];
        let right = [sin_y, -cos_y];
        for u in 0..intr.width {
            let a = intr.col_slope(u);
            let dir = [forward[0] + a * right[0], forward[1] + a * right[1]];
            self.render_column(scene, pose.position, dir);
            self.write_column(pixels, u);
        }
        true
    }

    fn write_column(&self, frame: &mut PixelsMut<'_>, u: u32) {
        let intr = &self.intrinsics;
        let w = intr.width as usize;
        for (v, (&d, &g)) in self.col_depth.iter().zip(&self.col_grey).enumerate() {
            let i = v * w + u as usize;
            frame.depth[i] = if d >= intr.min_range && d <= intr.max_range {
                d
            } else {
                f32::NAN
            };
            frame.rgb[i * 3..i * 3 + 3].fill(g);
        }
    }

    fn render_column(&mut self, scene: &Scene, c: [f32; 3], dir: [f32; 2]) {
        self.col_depth.fill(f32::INFINITY);
        self.col_grey.fill(0);
        self.boxes(scene, c, dir);
        self.terrain_walk(scene, c, dir);
    }

    /// Intersects every box crossed by this column's plane.
    fn boxes(&mut self, scene: &Scene, c: [f32; 3], dir: [f32; 2]) {
        let intr = self.intrinsics;
        for b in &scene.boxes {
            let Some((te, tx, side_normal)) = slab_2d(c, dir, b.min, b.max) else {
                continue;
            };
            let te = te.max(T_START);
            if tx <= te {
                continue;
            }
            let (zmin, zmax) = (b.min[2], b.max[2]);
            // Rows whose ray can pass through the (t, z) rectangle.
            let b_lo = if c[2] - zmax < 0.0 {
                (c[2] - zmax) / te
            } else {
                (c[2] - zmax) / tx
            };
            let b_hi = if c[2] - zmin > 0.0 {
                (c[2] - zmin) / te
            } else {
                (c[2] - zmin) / tx
            };
            let v_lo = ((b_lo * intr.fy + intr.cy - 0.5).floor().max(0.0)) as usize;
            let v_hi = ((b_hi * intr.fy + intr.cy - 0.5).ceil()).min(intr.height as f32 - 1.0);
            if v_hi < 0.0 {
                continue;
            }
            // Shade each face once per column, not once per pixel.
            let grey_side = self.shading.grey(side_normal, b.albedo);
            let grey_top = self.shading.grey([0.0, 0.0, 1.0], b.albedo);
            let grey_bottom = self.shading.grey([0.0, 0.0, -1.0], b.albedo);
            for v in v_lo..=v_hi as usize {
                let slope = self.row_slopes[v];
                let inv = self.inv_row_slopes[v];
                let (tz_in, tz_out, cap_grey) = if slope > 0.0 {
                    ((c[2] - zmax) * inv, (c[2] - zmin) * inv, grey_top)
                } else if slope < 0.0 {
                    ((c[2] - zmin) * inv, (c[2] - zmax) * inv, grey_bottom)
                } else if c[2] >= zmin && c[2] <= zmax {
                    (f32::NEG_INFINITY, f32::INFINITY, grey_side)
                } else {
                    continue;
                };
                let entry = te.max(tz_in);
                if entry > tx.min(tz_out) || entry >= self.col_depth[v] {
                    continue;
                }
                self.col_depth[v] = entry;
                self.col_grey[v] = if te >= tz_in { grey_side } else { cap_grey };
            }
        }
    }

    /// Walks the terrain profile under this column front to back, cell by
    /// cell (a grid DDA), splitting each cell at its diagonal.
    fn terrain_walk(&mut self, scene: &Scene, c: [f32; 3], dir: [f32; 2]) {
        let terrain = &*scene.terrain;
        let albedo = scene.world.terrain.albedo;
        let shading = self.shading;
        let grid_min = [terrain.x0, terrain.y0, 0.0];
        let grid_max = [
            terrain.x0 + terrain.dx * terrain.nx as f32,
            terrain.y0 + terrain.dy * terrain.ny as f32,
            0.0,
        ];
        let Some((grid_enter, grid_exit, _)) = slab_2d(c, dir, grid_min, grid_max) else {
            return;
        };
        let t_end = grid_exit.min(self.intrinsics.max_range);
        let max_h = terrain.max_height;
        let line = GridLine::new(terrain, c, dir);
        let mut next = self.row_slopes.len() as isize - 1;
        let mut t = T_START.max(grid_enter);
        let mut cell = line.cell_at(t, terrain);
        'walk: while t < t_end {
            // Rows already hit by a box nearer than `t` are final.
            while next >= 0 && self.col_depth[next as usize] <= t {
                next -= 1;
            }
            if next < 0 {
                break;
            }
            // Skip ahead while even the steepest open ray is above every hill.
            let slope = self.row_slopes[next as usize];
            if c[2] - t * slope > max_h {
                if slope <= 0.0 {
                    break;
                }
                let t_clear = (c[2] - max_h) / slope;
                if t_clear >= t_end {
                    break;
                }
                // Only ever forward: rounding can leave the ray "above"
                // max_h at a `t` already past `t_clear`, and going back to
                // `t_clear`'s cell there walked the same cell forever.
                if t_clear > t {
                    t = t_clear;
                    cell = line.cell_at(t, terrain);
                }
            }
            let cell_end = cell.t_next_x.min(cell.t_next_y).min(t_end);
            // The open ray is lowest at the cell's far edge: above the
            // cell's highest corner there, it cannot touch this cell.
            if c[2] - cell_end * slope > terrain.cell_max(cell.ix, cell.iy) {
                t = cell_end;
                if !cell.advance(terrain) {
                    break;
                }
                continue;
            }
            // The cell's diagonal (u − v = ix − iy) may split it in two.
            let k = cell.ix as f32 - cell.iy as f32;
            let t_diag = line.diagonal_t(k);
            let mut segment_start = t;
            for segment_end in [t_diag, cell_end] {
                if segment_end <= segment_start || segment_end > cell_end {
                    continue;
                }
                let mid = 0.5 * (segment_start + segment_end);
                let upper = line.w_at(mid) <= k;
                let plane = terrain.cell_plane(cell.ix, cell.iy, upper);
                let h1 = plane.height(c[0] + segment_end * dir[0], c[1] + segment_end * dir[1]);
                // Along the ray: ground = hc + t·s, ray = c.z − t·b.
                let hc = plane.height(c[0], c[1]);
                let s = plane.gx * dir[0] + plane.gy * dir[1];
                let mut grey = None;
                while next >= 0 {
                    let row = next as usize;
                    let slope = self.row_slopes[row];
                    if c[2] - segment_end * slope > h1 {
                        break; // above ground here, and so is every row above it
                    }
                    let hit = ((c[2] - hc) / (slope + s)).clamp(segment_start, segment_end);
                    if hit < self.col_depth[row] {
                        self.col_depth[row] = hit;
                        self.col_grey[row] =
                            *grey.get_or_insert_with(|| shading.grey(plane.normal(), albedo));
                    }
                    next -= 1;
                }
                if next < 0 {
                    break 'walk;
                }
                segment_start = segment_end;
            }
            t = cell_end;
            if !cell.advance(terrain) {
                break;
            }
        }
    }
}

/// A column's line in grid coordinates: `u = u0 + t·du`, `v = v0 + t·dv`.
struct GridLine {
    u0: f32,
    v0: f32,
    du: f32,
    dv: f32,
    inv_du: f32,
    inv_dv: f32,
    inv_dw: f32,
}

/// The DDA's current cell and the `t` of its next x / y boundary crossings.
struct Cell {
    ix: usize,
    iy: usize,
    step_x: isize,
    step_y: isize,
    t_next_x: f32,
    t_next_y: f32,
    t_delta_x: f32,
    t_delta_y: f32,
}

impl GridLine {
    fn new(terrain: &Terrain, c: [f32; 3], dir: [f32; 2]) -> Self {
        let (du, dv) = (dir[0] / terrain.dx, dir[1] / terrain.dy);
        let inv = |d: f32| {
            if d.abs() > 1e-12 {
                1.0 / d
            } else {
                f32::INFINITY
            }
        };
        Self {
            u0: (c[0] - terrain.x0) / terrain.dx,
            v0: (c[1] - terrain.y0) / terrain.dy,
            du,
            dv,
            inv_du: inv(du),
            inv_dv: inv(dv),
            inv_dw: inv(du - dv),
        }
    }

    #[inline]
    fn w_at(&self, t: f32) -> f32 {
        (self.u0 - self.v0) + t * (self.du - self.dv)
    }

    /// Where `u − v = k` (a cell diagonal), or infinity.
    #[inline]
    fn diagonal_t(&self, k: f32) -> f32 {
        let t = (k - (self.u0 - self.v0)) * self.inv_dw;
        if t.is_finite() {
            t
        } else {
            f32::INFINITY
        }
    }

    /// The cell containing the line at `t` and its next boundary crossings.
    fn cell_at(&self, t: f32, terrain: &Terrain) -> Cell {
        let (u, v) = (self.u0 + t * self.du, self.v0 + t * self.dv);
        let ix = (u.max(0.0) as usize).min(terrain.nx - 1);
        let iy = (v.max(0.0) as usize).min(terrain.ny - 1);
        let axis = |i: usize, d: f32, inv: f32, origin: f32| -> (isize, f32, f32) {
            if d > 1e-12 {
                (1, (i as f32 + 1.0 - origin) * inv, inv)
            } else if d < -1e-12 {
                (-1, (i as f32 - origin) * inv, -inv)
            } else {
                (0, f32::INFINITY, f32::INFINITY)
            }
        };
        let (step_x, t_next_x, t_delta_x) = axis(ix, self.du, self.inv_du, self.u0);
        let (step_y, t_next_y, t_delta_y) = axis(iy, self.dv, self.inv_dv, self.v0);
        Cell {
            ix,
            iy,
            step_x,
            step_y,
            t_next_x: t_next_x.max(t),
            t_next_y: t_next_y.max(t),
            t_delta_x,
            t_delta_y,
        }
    }
}

impl Cell {
    /// Steps to the next cell; false when leaving the grid.
    #[inline]
    fn advance(&mut self, terrain: &Terrain) -> bool {
        if self.t_next_x < self.t_next_y {
            let ix = self.ix as isize + self.step_x;
            if ix < 0 || ix >= terrain.nx as isize {
                return false;
            }
            self.ix = ix as usize;
            self.t_next_x += self.t_delta_x;
        } else {
            let iy = self.iy as isize + self.step_y;
            if iy < 0 || iy >= terrain.ny as isize {
                return false;
            }
            self.iy = iy as usize;
            self.t_next_y += self.t_delta_y;
        }
        true
    }
}

/// Where the 2D line `c + t·dir` crosses the footprint `[min, max]`:
/// `(t_enter, t_exit, outward normal of the entry face)`.
#[inline]
pub(crate) fn slab_2d(
    c: [f32; 3],
    dir: [f32; 2],
    min: [f32; 3],
    max: [f32; 3],
) -> Option<(f32, f32, [f32; 3])> {
    let mut te = f32::NEG_INFINITY;
    let mut tx = f32::INFINITY;
    let mut normal = [0.0, 0.0, 1.0];
    for axis in 0..2 {
        let d = dir[axis];
        if d.abs() < 1e-12 {
            if c[axis] < min[axis] || c[axis] > max[axis] {
                return None;
            }
            continue;
        }
        let (t1, t2) = ((min[axis] - c[axis]) / d, (max[axis] - c[axis]) / d);
        let (near, far) = if t1 < t2 { (t1, t2) } else { (t2, t1) };
        if near > te {
            te = near;
            normal = [0.0; 3];
            normal[axis] = if d > 0.0 { -1.0 } else { 1.0 };
        }
        tx = tx.min(far);
    }
    (te < tx && tx > 0.0).then_some((te, tx, normal))
}
