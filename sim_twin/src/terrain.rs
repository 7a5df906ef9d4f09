//! The lunar terrain: a seeded height grid over the enclosure floor. One
//! grid feeds physics (wheel suspension rays), the fast renderer and the
//! exact parry heightfield, all with parry's triangle split.

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use crate::world::{EnclosureSpec, TerrainSpec};

/// A regular height grid in the world frame. Vertex `(ix, iy)` sits at
/// `(x0 + ix·dx, y0 + iy·dy)`. Each cell splits along its main diagonal
/// (from `(ix, iy)` to `(ix+1, iy+1)`) exactly as parry splits the
/// equivalent heightfield (see [`Terrain::to_parry`]).
#[derive(Debug, Clone, PartialEq)]
pub struct Terrain {
    /// World x of column 0.
    pub x0: f32,
    /// World y of row 0.
    pub y0: f32,
    /// Cell size along x.
    pub dx: f32,
    /// Cell size along y.
    pub dy: f32,
    /// Cells along x.
    pub nx: usize,
    /// Cells along y.
    pub ny: usize,
    /// `(nx + 1) × (ny + 1)` heights, row-major by y.
    heights: Vec<f32>,
    /// Highest vertex.
    pub max_height: f32,
    /// The two triangle planes of every cell, `(iy·nx + ix)·2 + upper`.
    planes: Vec<TerrainPlane>,
    /// Highest corner of every cell, `iy·nx + ix` (lets rays skip cells).
    cell_max: Vec<f32>,
}

impl Terrain {
    /// Generates the relief of `spec` over the enclosure floor.
    pub fn generate(spec: &TerrainSpec, enclosure: &EnclosureSpec) -> Self {
        let (nx, ny) = (spec.cells_x, spec.cells_y);
        let size_x = enclosure.x_max - enclosure.x_min;
        let size_y = enclosure.y_max - enclosure.y_min;
        let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
        let octaves: Vec<ValueNoise> = spec
            .wavelengths
            .iter()
            .map(|w| ValueNoise::new(&mut rng, size_x, size_y, *w))
            .collect();
        let mut raw = Vec::with_capacity((nx + 1) * (ny + 1));
        for iy in 0..=ny {
            for ix in 0..=nx {
                let x = ix as f32 / nx as f32 * size_x;
                let y = iy as f32 / ny as f32 * size_y;
                let h: f32 = octaves
                    .iter()
                    .zip(&spec.weights)
                    .map(|(o, w)| w * o.sample(x, y))
                    .sum();
                raw.push(h);
            }
        }
        let heights = shape_heights(&raw, spec.max_height, spec.mean_height);
        Self::from_heights(enclosure, nx, ny, heights)
    }

    fn from_heights(enclosure: &EnclosureSpec, nx: usize, ny: usize, heights: Vec<f32>) -> Self {
        let max_height = heights.iter().copied().fold(0.0, f32::max);
        let mut terrain = Self {
            x0: enclosure.x_min,
            y0: enclosure.y_min,
            dx: (enclosure.x_max - enclosure.x_min) / nx as f32,
            dy: (enclosure.y_max - enclosure.y_min) / ny as f32,
            nx,
            ny,
            heights,
            max_height,
            planes: Vec::new(),
            cell_max: Vec::new(),
        };
        terrain.cell_max = (0..ny)
            .flat_map(|iy| (0..nx).map(move |ix| (ix, iy)))
            .map(|(ix, iy)| {
                let t = &terrain;
                t.vertex(ix, iy)
                    .max(t.vertex(ix + 1, iy))
                    .max(t.vertex(ix, iy + 1))
                    .max(t.vertex(ix + 1, iy + 1))
            })
            .collect();
        terrain.planes = (0..ny)
            .flat_map(|iy| (0..nx).map(move |ix| (ix, iy)))
            .flat_map(|(ix, iy)| [false, true].map(|upper| (ix, iy, upper)))
            .map(|(ix, iy, upper)| terrain.compute_plane(ix, iy, upper))
            .collect();
        terrain
    }

    /// A flat terrain at height `h` (tests and calibration).
    pub fn flat(enclosure: &EnclosureSpec, nx: usize, ny: usize, h: f32) -> Self {
        Self::from_heights(enclosure, nx, ny, vec![h; (nx + 1) * (ny + 1)])
    }

    /// Vertex height.
    #[inline]
    pub fn vertex(&self, ix: usize, iy: usize) -> f32 {
        self.heights[iy * (self.nx + 1) + ix]
    }

    /// All vertex heights, row-major by y.
    pub fn heights(&self) -> &[f32] {
        &self.heights
    }

    /// The plane `h = a + gx·x + gy·y` (world x, y) of the triangle under
    /// `(x, y)`; points outside the grid use the nearest border cell.
    #[inline]
    pub fn plane_at(&self, x: f32, y: f32) -> TerrainPlane {
        let u = ((x - self.x0) / self.dx).clamp(0.0, self.nx as f32);
        let v = ((y - self.y0) / self.dy).clamp(0.0, self.ny as f32);
        let ix = (u as usize).min(self.nx - 1);
        let iy = (v as usize).min(self.ny - 1);
        self.cell_plane(ix, iy, u - ix as f32 <= v - iy as f32)
    }

    /// The plane of one triangle: `upper` is the half with x-frac ≤ y-frac.
    #[inline]
    pub fn cell_plane(&self, ix: usize, iy: usize, upper: bool) -> TerrainPlane {
        self.planes[self.plane_index(ix, iy, upper)]
    }

    /// Every triangle's plane, at [`Terrain::plane_index`].
    pub fn planes(&self) -> &[TerrainPlane] {
        &self.planes
    }

    /// Where [`Terrain::planes`] holds the triangle of [`Terrain::cell_plane`].
    #[inline]
    pub fn plane_index(&self, ix: usize, iy: usize, upper: bool) -> usize {
        (iy * self.nx + ix) * 2 + upper as usize
    }

    /// Highest corner of a cell.
    #[inline]
    pub fn cell_max(&self, ix: usize, iy: usize) -> f32 {
        self.cell_max[iy * self.nx + ix]
    }

    fn compute_plane(&self, ix: usize, iy: usize, upper: bool) -> TerrainPlane {
        let h00 = self.vertex(ix, iy);
        let h10 = self.vertex(ix + 1, iy);
        let h01 = self.vertex(ix, iy + 1);
        let h11 = self.vertex(ix + 1, iy + 1);
        // Slopes per unit cell fraction.
        let (sx, sy) = if upper {
            (h11 - h01, h01 - h00)
        } else {
            (h10 - h00, h11 - h10)
        };
        let gx = sx / self.dx;
        let gy = sy / self.dy;
        let cx = self.x0 + ix as f32 * self.dx;
        let cy = self.y0 + iy as f32 * self.dy;
        TerrainPlane {
            a: h00 - gx * cx - gy * cy,
            gx,
            gy,
        }
    }

    /// Height under `(x, y)`.
    #[inline]
    pub fn height_at(&self, x: f32, y: f32) -> f32 {
        self.plane_at(x, y).height(x, y)
    }

    /// The same surface as a parry heightfield shape plus the pose that puts
    /// it in the world (parry's heightfield is y-up with rows along local z).
    pub fn to_parry(&self) -> (parry3d::shape::HeightField, parry3d::math::Pose) {
        use parry3d::math::{Pose, Rot3, Vec3};
        let (nrows, ncols) = (self.ny + 1, self.nx + 1);
        // Local z = −(world y − centre): parry row i is our row ny − i.
        let mut data = vec![0.0; nrows * ncols];
        for i in 0..nrows {
            for j in 0..ncols {
                // Array2 is column-major.
                data[i + j * nrows] = self.vertex(j, self.ny - i);
            }
        }
        let heights = parry3d::utils::Array2::new(nrows, ncols, data);
        let size_x = self.dx * self.nx as f32;
        let size_y = self.dy * self.ny as f32;
        let shape = parry3d::shape::HeightField::with_flags(
            heights,
            Vec3::new(size_x, 1.0, size_y),
            parry3d::shape::HeightFieldFlags::FIX_INTERNAL_EDGES,
        );
        let centre = Vec3::new(self.x0 + size_x * 0.5, self.y0 + size_y * 0.5, 0.0);
        // +90° about x maps local y (up) to world z and local z to world −y.
        let pose = Pose::from_parts(centre, Rot3::from_rotation_x(std::f32::consts::FRAC_PI_2));
        (shape, pose)
    }

    /// Mean vertex height.
    pub fn mean_height(&self) -> f32 {
        self.heights.iter().sum::<f32>() / self.heights.len() as f32
    }
}

/// A terrain triangle's plane `h = a + gx·x + gy·y`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TerrainPlane {
    /// Height at the world origin.
    pub a: f32,
    /// ∂h/∂x.
    pub gx: f32,
    /// ∂h/∂y.
    pub gy: f32,
}

impl TerrainPlane {
    /// Height at `(x, y)`.
    #[inline]
    pub fn height(&self, x: f32, y: f32) -> f32 {
        self.a + self.gx * x + self.gy * y
    }

    /// Unit upward normal.
    #[inline]
    pub fn normal(&self) -> [f32; 3] {
        let inv = 1.0 / (self.gx * self.gx + self.gy * self.gy + 1.0).sqrt();
        [-self.gx * inv, -self.gy * inv, inv]
    }
}

/// Smooth value noise on a lattice of the given wavelength.
struct ValueNoise {
    cols: usize,
    rows: usize,
    inv_wavelength: f32,
    values: Vec<f32>,
}

impl ValueNoise {
    fn new(rng: &mut ChaCha8Rng, size_x: f32, size_y: f32, wavelength: f32) -> Self {
        let wavelength = wavelength.max(1e-3);
        let cols = (size_x / wavelength).ceil() as usize + 2;
        let rows = (size_y / wavelength).ceil() as usize + 2;
        let values = (0..cols * rows).map(|_| rng.random::<f32>()).collect();
        Self {
            cols,
            rows,
            inv_wavelength: 1.0 / wavelength,
            values,
        }
    }

    fn sample(&self, x: f32, y: f32) -> f32 {
        let (u, v) = (x * self.inv_wavelength, y * self.inv_wavelength);
        let (i, j) = (u as usize, v as usize);
        let (i, j) = (i.min(self.cols - 2), j.min(self.rows - 2));
        let smooth = |t: f32| t * t * (3.0 - 2.0 * t);
        let (fu, fv) = (smooth(u - i as f32), smooth(v - j as f32));
        let at = |a: usize, b: usize| self.values[b * self.cols + a];
        let top = at(i, j) + (at(i + 1, j) - at(i, j)) * fu;
        let bottom = at(i, j + 1) + (at(i + 1, j + 1) - at(i, j + 1)) * fu;
        top + (bottom - top) * fv
    }
}

/// Maps raw noise onto `[0, max]` with the requested mean (a power curve
/// found by bisection), so the relief has the reference's statistics.
fn shape_heights(raw: &[f32], max: f32, mean: f32) -> Vec<f32> {
    let lo = raw.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = raw.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let span = (hi - lo).max(1e-6);
    let unit: Vec<f32> = raw.iter().map(|r| (r - lo) / span).collect();
    let target = if max > 0.0 { mean / max } else { 0.0 };
    let mean_for = |gamma: f32| unit.iter().map(|u| u.powf(gamma)).sum::<f32>() / unit.len() as f32;
    // mean_for decreases with gamma; bisect log(gamma) in [-4, 4].
    let (mut a, mut b) = (-4.0f32, 4.0f32);
    for _ in 0..40 {
        let mid = 0.5 * (a + b);
        if mean_for(mid.exp()) > target {
            a = mid;
        } else {
            b = mid;
        }
    }
    let gamma = (0.5 * (a + b)).exp();
    unit.iter().map(|u| max * u.powf(gamma)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::WorldSpec;

    fn terrain() -> Terrain {
        let world = WorldSpec::builtin("monolith").expect("world");
        Terrain::generate(&world.terrain, &world.enclosure)
    }

    #[test]
    fn relief_has_the_reference_statistics() {
        let t = terrain();
        let lo = t.heights().iter().copied().fold(f32::INFINITY, f32::min);
        assert!((0.0..0.005).contains(&lo), "min {lo}");
        assert!((t.max_height - 0.16).abs() < 1e-4, "max {}", t.max_height);
        assert!(
            (t.mean_height() - 0.085).abs() < 0.002,
            "mean {}",
            t.mean_height()
        );
        // Gentle enough for an 8 cm wheel: no slope steeper than 30°.
        for iy in 0..t.ny {
            for ix in 0..t.nx {
                for upper in [true, false] {
                    let p = t.cell_plane(ix, iy, upper);
                    assert!(p.normal()[2] > 0.866, "steep cell {ix},{iy}");
                }
            }
        }
    }

    #[test]
    fn same_seed_same_terrain_other_seed_other_terrain() {
        let world = WorldSpec::builtin("monolith").expect("world");
        let a = Terrain::generate(&world.terrain, &world.enclosure);
        let b = Terrain::generate(&world.terrain, &world.enclosure);
        assert_eq!(a, b);
        let mut other = world.terrain.clone();
        other.seed += 1;
        assert_ne!(a, Terrain::generate(&other, &world.enclosure));
    }

    #[test]
    fn heights_interpolate_vertices_and_match_parry_triangles() {
        use parry3d::math::Vec3;
        use parry3d::query::{Ray, RayCast};
        let t = terrain();
        let at_vertex = t.height_at(t.x0 + 3.0 * t.dx, t.y0 + 5.0 * t.dy);
        assert!((at_vertex - t.vertex(3, 5)).abs() < 1e-5);
        let (shape, pose) = t.to_parry();
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for _ in 0..500 {
            let x = rng.random_range(t.x0 + 0.01..t.x0 + t.dx * t.nx as f32 - 0.01);
            let y = rng.random_range(t.y0 + 0.01..t.y0 + t.dy * t.ny as f32 - 0.01);
            let ray = Ray::new(Vec3::new(x, y, 1.0), Vec3::new(0.0, 0.0, -1.0));
            let toi = shape
                .cast_ray(&pose, &ray, 2.0, true)
                .expect("ray hits the terrain");
            let parry_h = 1.0 - toi;
            assert!((parry_h - t.height_at(x, y)).abs() < 1e-4, "at {x},{y}");
        }
    }
}
