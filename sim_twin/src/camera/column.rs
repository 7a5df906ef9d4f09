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
use std::sync::Arc;

use crate::terrain::Terrain;
use crate::world::LightSpec;

/// Renders level-camera RGBD frames; owns its scratch buffers so a frame
/// costs no allocation.
#[derive(Debug, Clone)]
pub struct ColumnRenderer {
    intrinsics: Intrinsics,
    shading: Shading,
    rows: Rows,
    /// The frame column by column (`u · height + v`): each column is walked
    /// into contiguous memory, then the frame is written row by row, so
    /// neither pass strides across the row-major image per pixel.
    depth_by_column: Vec<f32>,
    grey_by_column: Vec<u8>,
    /// The scene's boxes shaded, face by face, once per frame.
    box_faces: Vec<FaceGreys>,
    /// The terrain's triangles shaded (at [`Terrain::plane_index`]), with
    /// the terrain and albedo they were shaded for: held, so the terrain
    /// cannot be freed and another built at its address while cached.
    terrain_greys: Option<(Arc<Terrain>, f32, Vec<u8>)>,
    /// Threads that walk columns beside the caller's (none: the caller
    /// walks them all).
    helpers: Option<Arc<rayon::ThreadPool>>,
}

/// The grey level of each face of an upright box.
#[derive(Debug, Clone, Copy)]
struct FaceGreys {
    minus_x: u8,
    plus_x: u8,
    minus_y: u8,
    plus_y: u8,
    top: u8,
    bottom: u8,
}

impl FaceGreys {
    fn new(shading: &Shading, albedo: f32) -> Self {
        let grey = |normal| shading.grey(normal, albedo);
        Self {
            minus_x: grey([-1.0, 0.0, 0.0]),
            plus_x: grey([1.0, 0.0, 0.0]),
            minus_y: grey([0.0, -1.0, 0.0]),
            plus_y: grey([0.0, 1.0, 0.0]),
            top: grey([0.0, 0.0, 1.0]),
            bottom: grey([0.0, 0.0, -1.0]),
        }
    }

    /// The face with outward `normal` (an axis, as [`slab_2d`] gives).
    fn facing(&self, normal: [f32; 3]) -> u8 {
        match normal {
            [x, _, _] if x < 0.0 => self.minus_x,
            [x, _, _] if x > 0.0 => self.plus_x,
            [_, y, _] if y < 0.0 => self.minus_y,
            [_, y, _] if y > 0.0 => self.plus_y,
            [_, _, z] if z < 0.0 => self.bottom,
            _ => self.top,
        }
    }
}

/// The image rows' ray slopes (increasing with `v`: up, level, down).
#[derive(Debug, Clone)]
struct Rows {
    slopes: Vec<f32>,
    inv_slopes: Vec<f32>,
    /// First row that does not look up (slope ≥ 0).
    first_level: usize,
    /// First row that looks down (slope > 0).
    first_down: usize,
}

const T_START: f32 = 1e-3;

/// Columns a thread walks at a time (one band per take).
const BAND: usize = 8;

/// Frame rows a thread writes at a time: one row of 8 × 8 tiles.
const TILE_ROWS: usize = 8;

impl ColumnRenderer {
    /// A renderer for one image size.
    pub fn new(intrinsics: Intrinsics, light: &LightSpec) -> Self {
        let slopes: Vec<f32> = (0..intrinsics.height)
            .map(|v| intrinsics.row_slope(v))
            .collect();
        let pixels = (intrinsics.width * intrinsics.height) as usize;
        Self {
            intrinsics,
            shading: Shading::new(light),
            rows: Rows {
                inv_slopes: slopes.iter().map(|s| 1.0 / s).collect(),
                first_level: slopes.partition_point(|&s| s < 0.0),
                first_down: slopes.partition_point(|&s| s <= 0.0),
                slopes,
            },
            depth_by_column: vec![f32::INFINITY; pixels],
            grey_by_column: vec![0; pixels],
            box_faces: Vec::new(),
            terrain_greys: None,
            helpers: None,
        }
    }

    /// Renders each frame on `threads` threads: the caller's and
    /// `threads − 1` helpers of its own (shared by its clones). Every pixel
    /// is the same whatever the count; it pays where a core idles while
    /// the frame renders (one env on a multi-core machine), not where every
    /// core already steps an env.
    pub fn with_threads(mut self, threads: usize) -> Result<Self, rayon::ThreadPoolBuildError> {
        self.helpers = match threads {
            0 | 1 => None,
            n => Some(Arc::new(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n - 1)
                    .thread_name(|i| format!("render-{i}"))
                    .build()?,
            )),
        };
        Ok(self)
    }

    /// Shades with `light` from the next frame on.
    pub fn set_light(&mut self, light: &LightSpec) {
        self.shading = Shading::new(light);
        self.terrain_greys = None;
    }

    /// Threads a frame is rendered on.
    pub fn threads(&self) -> usize {
        1 + self.helpers.as_ref().map_or(0, |p| p.current_num_threads())
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
        if n == 0 {
            return true;
        }
        let (sin_y, cos_y) = pose.yaw.sin_cos();
        let forward = [cos_y, sin_y];
        let right = [sin_y, -cos_y];
        let h = intr.height as usize;
        self.box_faces.clear();
        let shading = &self.shading;
        let faces = scene
            .boxes
            .iter()
            .map(|b| FaceGreys::new(shading, b.albedo));
        self.box_faces.extend(faces);
        let albedo = scene.world.terrain.albedo;
        let shaded = |(terrain, shaded_albedo, _): &(Arc<Terrain>, f32, Vec<u8>)| {
            Arc::ptr_eq(terrain, &scene.terrain) && *shaded_albedo == albedo
        };
        if !self.terrain_greys.as_ref().is_some_and(shaded) {
            let planes = scene.terrain.planes().iter();
            let greys = planes.map(|p| shading.grey(p.normal(), albedo)).collect();
            self.terrain_greys = Some((scene.terrain.clone(), albedo, greys));
        }
        let terrain_greys = self.terrain_greys.as_ref().map_or(&[][..], |(_, _, g)| g);
        let walk_band = |band: usize, depth: &mut [f32], grey: &mut [u8]| {
            let columns = depth.chunks_exact_mut(h).zip(grey.chunks_exact_mut(h));
            for (k, (depth, grey)) in columns.enumerate() {
                let a = intr.col_slope((band * BAND + k) as u32);
                let dir = [forward[0] + a * right[0], forward[1] + a * right[1]];
                let mut column = Column {
                    intrinsics: &intr,
                    box_faces: &self.box_faces,
                    terrain_greys,
                    rows: &self.rows,
                    depth,
                    grey,
                };
                column.render(scene, pose.position, dir);
            }
        };
        let bands = self
            .depth_by_column
            .chunks_mut(BAND * h)
            .zip(self.grey_by_column.chunks_mut(BAND * h))
            .enumerate();
        on_threads(self.helpers.as_deref(), bands, |(b, (depth, grey))| {
            walk_band(b, depth, grey)
        });
        self.write_rows(pixels);
        true
    }

    /// Writes the column-major scratch into the row-major frame, grey as
    /// RGB, a band of [`TILE_ROWS`] rows at a time (on the helpers too).
    fn write_rows(&self, frame: &mut PixelsMut<'_>) {
        let scratch = Scratch {
            intrinsics: &self.intrinsics,
            depth: &self.depth_by_column,
            grey: &self.grey_by_column,
        };
        let w = self.intrinsics.width as usize;
        let bands = frame
            .depth
            .chunks_mut(TILE_ROWS * w)
            .zip(frame.rgb.chunks_mut(TILE_ROWS * w * 3))
            .enumerate();
        on_threads(self.helpers.as_deref(), bands, |(b, (depth, rgb))| {
            scratch.write_band(b * TILE_ROWS, &mut PixelsMut { rgb, depth });
        });
    }
}

/// Does `work` for every item, on the caller's thread and, if given, up to
/// one per pool thread beside it: each takes the next item until none is
/// left, so the caller never idles while items are left. It still waits at
/// the end for every helper it woke to have run (a queued rayon job cannot
/// be withdrawn): where every core is busy, a frame waits for a helper's
/// turn, hence one render thread per twin where every core steps an env.
fn on_threads<I>(pool: Option<&rayon::ThreadPool>, items: I, work: impl Fn(I::Item) + Sync)
where
    I: ExactSizeIterator + Send,
    I::Item: Send,
{
    // No helper for the caller's own last item.
    let helpers = pool.map_or(0, |p| {
        p.current_num_threads().min(items.len().saturating_sub(1))
    });
    let (Some(pool), 1..) = (pool, helpers) else {
        return items.for_each(work);
    };
    let items = std::sync::Mutex::new(items);
    let next = || items.lock().unwrap_or_else(|e| e.into_inner()).next();
    let drain = || {
        while let Some(item) = next() {
            work(item);
        }
    };
    pool.in_place_scope(|scope| {
        for _ in 0..helpers {
            scope.spawn(|_| drain());
        }
        drain();
    });
}

/// The frame column by column, as [`ColumnRenderer`] walked it.
struct Scratch<'s> {
    /// The frame's size and the depths the camera reports (others are
    /// written NaN).
    intrinsics: &'s Intrinsics,
    depth: &'s [f32],
    grey: &'s [u8],
}

impl Scratch<'_> {
    /// Width, height.
    fn size(&self) -> (usize, usize) {
        (
            self.intrinsics.width as usize,
            self.intrinsics.height as usize,
        )
    }

    /// Writes the frame's rows from `top` on into `band` (those rows of
    /// the frame, at most [`TILE_ROWS`]): whole tiles with AVX2, the rest
    /// one pixel at a time.
    fn write_band(&self, top: usize, band: &mut PixelsMut<'_>) {
        let (w, _) = self.size();
        let tiled = tiles::write_band(self, top, band);
        self.write_pixels(top, tiled..w, band);
    }

    /// Writes `columns` of the rows of `band` (the frame's rows from `top`
    /// on), one pixel at a time.
    fn write_pixels(&self, top: usize, columns: std::ops::Range<usize>, band: &mut PixelsMut<'_>) {
        let (w, h) = self.size();
        for r in 0..band.depth.len() / w {
            for u in columns.clone() {
                let (from, to) = (u * h + top + r, r * w + u);
                band.depth[to] = self.intrinsics.reported_depth(self.depth[from]);
                band.rgb[to * 3..to * 3 + 3].copy_from_slice(&[self.grey[from]; 3]);
            }
        }
    }
}

/// The frame's transposition in 8 × 8 tiles with AVX2: each tile column
/// loaded as one vector, eight shuffled into eight tile rows, each range
/// checked and stored as one; one pixel at a time cost ~13 instructions
/// (a strided load and four stores) and the range check ~4 more.
#[cfg(target_arch = "x86_64")]
mod tiles {
    use super::Scratch;
    use crate::camera::PixelsMut;
    use core::arch::x86_64::{__m128i, __m256, __m256i, _CMP_GE_OQ, _CMP_LE_OQ};
    use pulp::{x86::V3, Simd};

    const TILE: usize = super::TILE_ROWS;

    /// Writes the whole tiles of `band` (the frame's rows from `top` on);
    /// returns the columns they cover (none without AVX2, or for a band of
    /// fewer than a tile's rows).
    pub(super) fn write_band(scratch: &Scratch<'_>, top: usize, band: &mut PixelsMut<'_>) -> usize {
        let Some(simd) = V3::try_new() else {
            return 0;
        };
        let (w, h) = scratch.size();
        if band.depth.len() != TILE * w || top + TILE > h {
            return 0;
        }
        // The trait's entry point (V3's own `vectorize` takes a closure).
        Simd::vectorize(
            simd,
            Tiles {
                simd,
                scratch,
                top,
                band,
            },
        )
    }

    struct Tiles<'a, 's, 'f, 'p> {
        simd: V3,
        scratch: &'a Scratch<'s>,
        top: usize,
        band: &'f mut PixelsMut<'p>,
    }

    impl pulp::WithSimd for Tiles<'_, '_, '_, '_> {
        type Output = usize;

        // Inlined into pulp's AVX2 entry point, so the intrinsics are too.
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _: S) -> usize {
            let Self {
                simd,
                scratch,
                top,
                band,
            } = self;
            let (w, h) = scratch.size();
            let tiled = w - w % TILE;
            // Per 128-bit half: the grey byte of each of 4 pixels three times.
            let grey_to_rgb: __m256i = pulp::cast(GREY_TO_RGB);
            let avx = simd.avx;
            let (min_range, max_range) =
                (scratch.intrinsics.min_range, scratch.intrinsics.max_range);
            let (min_range, max_range) =
                (avx._mm256_set1_ps(min_range), avx._mm256_set1_ps(max_range));
            let nan = avx._mm256_set1_ps(f32::NAN);
            for g in 0..tiled / TILE {
                // The tile's columns, one vector each (`top` is a multiple
                // of TILE: the column's `top / TILE`-th chunk).
                let column = |k: usize| (g * TILE + k) * h..(g * TILE + k + 1) * h;
                let depth = std::array::from_fn(|k| {
                    pulp::cast(scratch.depth[column(k)].as_chunks::<TILE>().0[top / TILE])
                });
                let grey = std::array::from_fn(|k| {
                    let column = scratch.grey[column(k)].as_chunks::<TILE>().0[top / TILE];
                    let bytes: [u8; 16] = pulp::cast([column, [0; TILE]]);
                    let widened = simd
                        .avx2
                        ._mm256_cvtepu8_epi32(pulp::cast::<_, __m128i>(bytes));
                    simd.avx._mm256_castsi256_ps(widened)
                });
                let rows = transpose(simd, depth)
                    .into_iter()
                    .zip(transpose(simd, grey));
                for (r, (depth, grey)) in rows.enumerate() {
                    let start = r * w + g * TILE;
                    // Out of range or NaN → NaN, as `depth >= min && depth <= max` decides.
                    let in_range = avx._mm256_and_ps(
                        avx._mm256_cmp_ps::<_CMP_GE_OQ>(depth, min_range),
                        avx._mm256_cmp_ps::<_CMP_LE_OQ>(depth, max_range),
                    );
                    let depth = avx._mm256_blendv_ps(nan, depth, in_range);
                    let depth: [f32; TILE] = pulp::cast(depth);
                    band.depth[start..start + TILE].copy_from_slice(&depth);
                    let rgb = simd
                        .avx2
                        ._mm256_shuffle_epi8(simd.avx._mm256_castps_si256(grey), grey_to_rgb);
                    let rgb: [[u8; 16]; 2] = pulp::cast(rgb);
                    let out = &mut band.rgb[start * 3..(start + TILE) * 3];
                    out[..12].copy_from_slice(&rgb[0][..12]);
                    out[12..].copy_from_slice(&rgb[1][..12]);
                }
            }
            tiled
        }
    }

    /// `_mm256_shuffle_epi8`'s indices: bytes 0, 4, 8, 12 of each half
    /// three times each, then zeros (the top bit set).
    const GREY_TO_RGB: [u8; 32] = {
        let mut indices = [0x80u8; 32];
        let mut i = 0;
        while i < 12 {
            indices[i] = (i / 3 * 4) as u8;
            indices[16 + i] = (i / 3 * 4) as u8;
            i += 1;
        }
        indices
    };

    /// The 8 × 8 transpose: lane `r` of input `k` becomes lane `k` of
    /// output `r`. Bits are moved, never computed on (NaNs pass unchanged).
    #[inline(always)]
    fn transpose(simd: V3, m: [__m256; TILE]) -> [__m256; TILE] {
        let avx = simd.avx;
        let t0 = avx._mm256_unpacklo_ps(m[0], m[1]);
        let t1 = avx._mm256_unpackhi_ps(m[0], m[1]);
        let t2 = avx._mm256_unpacklo_ps(m[2], m[3]);
        let t3 = avx._mm256_unpackhi_ps(m[2], m[3]);
        let t4 = avx._mm256_unpacklo_ps(m[4], m[5]);
        let t5 = avx._mm256_unpackhi_ps(m[4], m[5]);
        let t6 = avx._mm256_unpacklo_ps(m[6], m[7]);
        let t7 = avx._mm256_unpackhi_ps(m[6], m[7]);
        let s0 = avx._mm256_shuffle_ps::<0x44>(t0, t2);
        let s1 = avx._mm256_shuffle_ps::<0xEE>(t0, t2);
        let s2 = avx._mm256_shuffle_ps::<0x44>(t1, t3);
        let s3 = avx._mm256_shuffle_ps::<0xEE>(t1, t3);
        let s4 = avx._mm256_shuffle_ps::<0x44>(t4, t6);
        let s5 = avx._mm256_shuffle_ps::<0xEE>(t4, t6);
        let s6 = avx._mm256_shuffle_ps::<0x44>(t5, t7);
        let s7 = avx._mm256_shuffle_ps::<0xEE>(t5, t7);
        [
            avx._mm256_permute2f128_ps::<0x20>(s0, s4),
            avx._mm256_permute2f128_ps::<0x20>(s1, s5),
            avx._mm256_permute2f128_ps::<0x20>(s2, s6),
            avx._mm256_permute2f128_ps::<0x20>(s3, s7),
            avx._mm256_permute2f128_ps::<0x31>(s0, s4),
            avx._mm256_permute2f128_ps::<0x31>(s1, s5),
            avx._mm256_permute2f128_ps::<0x31>(s2, s6),
            avx._mm256_permute2f128_ps::<0x31>(s3, s7),
        ]
    }
}

/// No tiles off x86-64: every pixel one at a time.
#[cfg(not(target_arch = "x86_64"))]
mod tiles {
    pub(super) fn write_band(
        _: &super::Scratch<'_>,
        _: usize,
        _: &mut crate::camera::PixelsMut<'_>,
    ) -> usize {
        0
    }
}

/// One image column being walked: its rows' nearest depth and grey so far.
struct Column<'a> {
    intrinsics: &'a Intrinsics,
    /// [`FaceGreys`] of `scene.boxes`, same order.
    box_faces: &'a [FaceGreys],
    /// The terrain's triangles shaded, at [`Terrain::plane_index`].
    terrain_greys: &'a [u8],
    rows: &'a Rows,
    depth: &'a mut [f32],
    grey: &'a mut [u8],
}

impl Column<'_> {
    fn render(&mut self, scene: &Scene, c: [f32; 3], dir: [f32; 2]) {
        self.depth.fill(f32::INFINITY);
        self.grey.fill(0);
        self.boxes(scene, c, dir);
        // Depths out of the camera's range become NaN as the frame is
        // written (`Scratch`), eight at a time.
        self.terrain_walk(scene, c, dir);
    }

    /// Intersects every box crossed by this column's plane.
    fn boxes(&mut self, scene: &Scene, c: [f32; 3], dir: [f32; 2]) {
        let intr = self.intrinsics;
        let rows = self.rows;
        for (b, faces) in scene.boxes.iter().zip(self.box_faces) {
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
            let v_end = v_hi as usize + 1;
            let span = BoxSpan {
                te,
                tx,
                grey_side: faces.facing(side_normal),
            };
            // Rows looking up enter through the bottom, rows looking down
            // through the top, a level row only through a side.
            let up = v_lo..v_end.min(rows.first_level);
            span.cover(self.rows_mut(up), (c[2] - zmin, c[2] - zmax), faces.bottom);
            let down = v_lo.max(rows.first_down)..v_end;
            span.cover(self.rows_mut(down), (c[2] - zmax, c[2] - zmin), faces.top);
            if c[2] >= zmin && c[2] <= zmax {
                let level = v_lo.max(rows.first_level)..v_end.min(rows.first_down);
                for v in level {
                    if te < self.depth[v] {
                        self.depth[v] = te;
                        self.grey[v] = span.grey_side;
                    }
                }
            }
        }
    }

    /// The depth, grey and inverse slope of `rows` (empty if the range is).
    fn rows_mut(&mut self, rows: std::ops::Range<usize>) -> ColumnRows<'_> {
        let rows = rows.start.min(rows.end)..rows.end;
        ColumnRows {
            depth: &mut self.depth[rows.clone()],
            grey: &mut self.grey[rows.clone()],
            inv_slopes: &self.rows.inv_slopes[rows],
        }
    }

    /// Walks the terrain profile under this column front to back, cell by
    /// cell (a grid DDA), splitting each cell at its diagonal.
    fn terrain_walk(&mut self, scene: &Scene, c: [f32; 3], dir: [f32; 2]) {
        let terrain = &*scene.terrain;
        let row_slopes = &self.rows.slopes;
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
        let mut next = row_slopes.len() as isize - 1;
        let mut t = T_START.max(grid_enter);
        let mut cell = line.cell_at(t, terrain);
        'walk: while t < t_end {
            // Rows already hit by a box nearer than `t` are final.
            while next >= 0 && self.depth[next as usize] <= t {
                next -= 1;
            }
            if next < 0 {
                break;
            }
            // Skip ahead while even the steepest open ray is above every hill.
            let slope = row_slopes[next as usize];
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
                let grey = self.terrain_greys[terrain.plane_index(cell.ix, cell.iy, upper)];
                let h1 = plane.height(c[0] + segment_end * dir[0], c[1] + segment_end * dir[1]);
                // Along the ray: ground = hc + t·s, ray = c.z − t·b.
                let hc = plane.height(c[0], c[1]);
                let s = plane.gx * dir[0] + plane.gy * dir[1];
                while next >= 0 {
                    let row = next as usize;
                    let slope = row_slopes[row];
                    if c[2] - segment_end * slope > h1 {
                        break; // above ground here, and so is every row above it
                    }
                    // `clamp` without its bounds assertion: start < end here.
                    let hit = (c[2] - hc) / (slope + s);
                    let hit = if hit < segment_start {
                        segment_start
                    } else if hit > segment_end {
                        segment_end
                    } else {
                        hit
                    };
                    if hit < self.depth[row] {
                        self.depth[row] = hit;
                        self.grey[row] = grey;
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

/// Where a box lies along a column: entered at `te` through a side, left
/// at `tx`.
struct BoxSpan {
    te: f32,
    tx: f32,
    grey_side: u8,
}

/// Some consecutive rows of a column, all looking up or all looking down.
struct ColumnRows<'a> {
    depth: &'a mut [f32],
    grey: &'a mut [u8],
    inv_slopes: &'a [f32],
}

impl BoxSpan {
    /// Where each row's ray meets the box, if nearer than what it saw: the
    /// ray is between the box's cap heights for `t` in `[enter, leave] /
    /// slope`, from `heights = (c.z − entered cap, c.z − left cap)`.
    ///
    /// The rows' inverse slopes decrease along the rows (they all look up,
    /// or all down), so `t_in = heights.0 · inv` and `t_out = heights.1 ·
    /// inv` are monotone: the rows entering through the side (`t_in ≤ te`)
    /// are one run, and those of them that see the side before leaving
    /// through a cap (`t_out ≥ te`) another. Both runs are found by binary
    /// search with the per-row comparisons themselves, so every pixel is
    /// what a row-by-row test gives ([`reference_cover`] in the tests), and
    /// the side's rows (a wall: most of a column) cost a compare each.
    #[inline]
    fn cover(&self, rows: ColumnRows<'_>, heights: (f32, f32), cap_grey: u8) {
        let (te, tx) = (self.te, self.tx);
        let n = rows
            .depth
            .len()
            .min(rows.grey.len())
            .min(rows.inv_slopes.len());
        let (depth, grey, inv_slopes) = (
            &mut rows.depth[..n],
            &mut rows.grey[..n],
            &rows.inv_slopes[..n],
        );
        let t_in = |i: usize| heights.0 * inv_slopes[i];
        let t_out = |i: usize| heights.1 * inv_slopes[i];
        // t_in grows along the rows when heights.0 < 0: the side first.
        let side = run(0..n, |i| te >= t_in(i), heights.0 < 0.0);
        // t_out shrinks along the rows when heights.1 > 0: seen first.
        let seen = run(side.clone(), |i| t_out(i) >= te, heights.1 > 0.0);
        for i in seen {
            if te < depth[i] {
                depth[i] = te;
                grey[i] = self.grey_side;
            }
        }
        // The other rows enter through the cap (t_in > te).
        for i in (0..side.start).chain(side.end..n) {
            let entry = t_in(i);
            let exit = t_out(i).min(tx);
            if entry <= exit && entry < depth[i] {
                depth[i] = entry;
                grey[i] = cap_grey;
            }
        }
    }
}

/// The run of `range` where `holds`, a predicate that changes at most
/// once along it: true then false if `true_first`, else false then true.
fn run(
    range: std::ops::Range<usize>,
    holds: impl Fn(usize) -> bool,
    true_first: bool,
) -> std::ops::Range<usize> {
    let first = |wanted: bool| {
        let (mut lo, mut hi) = (range.start, range.end);
        while lo < hi {
            let mid = lo + (hi - lo) / 2;
            if holds(mid) == wanted {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        lo
    };
    if true_first {
        range.start..first(false)
    } else {
        first(true)..range.end
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

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The row-by-row definition [`BoxSpan::cover`] must equal.
    fn reference_cover(span: &BoxSpan, rows: ColumnRows<'_>, heights: (f32, f32), cap: u8) {
        for ((depth, grey), &inv) in rows.depth.iter_mut().zip(rows.grey).zip(rows.inv_slopes) {
            let (tz_in, tz_out) = (heights.0 * inv, heights.1 * inv);
            let entry = span.te.max(tz_in);
            if entry > span.tx.min(tz_out) || entry >= *depth {
                continue;
            }
            *depth = entry;
            *grey = if span.te >= tz_in {
                span.grey_side
            } else {
                cap
            };
        }
    }

    /// Every item is done once, and the pool's threads do some: the
    /// caller's first item waits until another thread has taken one (a
    /// pool never used fails here, after a bounded wait, instead of
    /// passing).
    #[test]
    fn work_is_shared_with_the_pool_and_done_once() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .expect("pool");
        let caller = std::thread::current().id();
        let (taken_elsewhere, helper_started) = std::sync::mpsc::channel();
        // Each end in a mutex: the work closure is shared between threads.
        let taken_elsewhere = std::sync::Mutex::new(taken_elsewhere);
        let helper_started = std::sync::Mutex::new(helper_started);
        let done: Vec<AtomicUsize> = (0..40).map(|_| AtomicUsize::new(0)).collect();
        let elsewhere = AtomicUsize::new(0);
        on_threads(Some(&pool), 0..done.len(), |i| {
            if std::thread::current().id() == caller {
                if i == 0 {
                    let started = helper_started.lock().expect("receiver");
                    let waited = started.recv_timeout(std::time::Duration::from_secs(30));
                    assert!(waited.is_ok(), "no pool thread took an item");
                }
            } else {
                elsewhere.fetch_add(1, Ordering::Relaxed);
                let _ = taken_elsewhere.lock().expect("sender").send(());
            }
            done[i].fetch_add(1, Ordering::Relaxed);
        });
        assert!(done.iter().all(|d| d.load(Ordering::Relaxed) == 1));
        assert!(elsewhere.load(Ordering::Relaxed) >= 1);
        // One item: nothing to share, the caller does it.
        let once = AtomicUsize::new(0);
        on_threads(Some(&pool), 0..1, |_| {
            assert_eq!(std::thread::current().id(), caller);
            once.fetch_add(1, Ordering::Relaxed);
        });
        assert_eq!(once.load(Ordering::Relaxed), 1);
    }

    /// Relighting shades as a renderer built with the new light does (the
    /// terrain's cached greys are the old light's otherwise).
    #[test]
    fn a_relit_renderer_renders_as_a_new_one() {
        let world = crate::WorldSpec::builtin("monolith").expect("world");
        let scene = Scene::build(&world);
        let intrinsics = Intrinsics::resized(&world.camera, 32, 24);
        let pose = CameraPose::level([-1.0, 0.5, 0.25], 0.3);
        let mut dimmer = world.light.clone();
        dimmer.ambient *= 0.5;
        dimmer.diffuse *= 0.5;
        let mut relit = ColumnRenderer::new(intrinsics, &world.light);
        let mut frame = RgbdFrame::new(32, 24);
        relit.render(&scene, &pose, &mut frame);
        let before = frame.rgb.clone();
        relit.set_light(&dimmer);
        relit.render(&scene, &pose, &mut frame);
        let mut fresh = RgbdFrame::new(32, 24);
        ColumnRenderer::new(intrinsics, &dimmer).render(&scene, &pose, &mut fresh);
        assert_ne!(before, fresh.rgb, "the light made a difference");
        assert_eq!(frame.rgb, fresh.rgb);
    }

    /// The tiled transposition, band by band, writes every pixel's bits as
    /// one pixel at a time does, NaNs, infinities and range limits
    /// included, at sizes with and without partial tiles (on a CPU without
    /// AVX2 both are the pixel path).
    #[test]
    fn the_tiled_frame_equals_the_pixel_by_pixel_one() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(5);
        for (w, h) in [
            (8, 8),
            (16, 24),
            (84, 84),
            (13, 9),
            (3, 5),
            (320, 240),
            (64, 48),
        ] {
            let n = w * h;
            let depth: Vec<f32> = (0..n)
                .map(|i| match i % 11 {
                    0 => f32::NAN,
                    1 => f32::INFINITY,
                    2 => 0.5,
                    _ => rng.random_range(0.0..9.0),
                })
                .collect();
            let grey: Vec<u8> = (0..n).map(|_| rng.random()).collect();
            let intrinsics = Intrinsics {
                width: w as u32,
                height: h as u32,
                fx: 1.0,
                fy: 1.0,
                cx: 0.0,
                cy: 0.0,
                min_range: 0.5,
                max_range: 8.0,
            };
            let scratch = Scratch {
                intrinsics: &intrinsics,
                depth: &depth,
                grey: &grey,
            };
            let frame = |write: &dyn Fn(&mut PixelsMut<'_>)| {
                let (mut rgb, mut depth) = (vec![7u8; n * 3], vec![-1.0f32; n]);
                write(&mut PixelsMut {
                    rgb: &mut rgb,
                    depth: &mut depth,
                });
                (rgb, depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>())
            };
            let bands = |pixels: &mut PixelsMut<'_>, write: &dyn Fn(usize, &mut PixelsMut<'_>)| {
                let rows = pixels.depth.chunks_mut(TILE_ROWS * w);
                let rows = rows.zip(pixels.rgb.chunks_mut(TILE_ROWS * w * 3));
                for (b, (depth, rgb)) in rows.enumerate() {
                    write(b * TILE_ROWS, &mut PixelsMut { rgb, depth });
                }
            };
            let tiled = frame(&|pixels| bands(pixels, &|top, band| scratch.write_band(top, band)));
            let one_at_a_time =
                frame(&|pixels| bands(pixels, &|top, band| scratch.write_pixels(top, 0..w, band)));
            assert!(tiled == one_at_a_time, "{w}×{h}");
            // And it is the transpose, grey as RGB, depth out of range NaN.
            let (rgb, bits) = one_at_a_time;
            for (u, v) in [(w - 1, h / 2), (0, 0), (w / 2, h - 1)] {
                let d = depth[u * h + v];
                let d = if (0.5..=8.0).contains(&d) {
                    d
                } else {
                    f32::NAN
                };
                assert_eq!(bits[v * w + u], d.to_bits(), "{w}×{h} ({u}, {v})");
                assert_eq!(rgb[(v * w + u) * 3..][..3], [grey[u * h + v]; 3]);
            }
        }
    }

    /// Random boxes, camera heights and earlier depths over the rows of
    /// several images (an odd height has a level row): the run-based cover
    /// writes exactly what the row-by-row test writes.
    #[test]
    fn box_cover_equals_the_row_by_row_test() {
        let light = crate::world::WorldSpec::builtin("monolith")
            .expect("world")
            .light;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        for (w, h) in [(320, 240), (84, 84), (80, 61)] {
            let spec = crate::world::WorldSpec::builtin("monolith")
                .expect("world")
                .camera;
            let renderer = ColumnRenderer::new(Intrinsics::resized(&spec, w, h), &light);
            let rows = &renderer.rows;
            let halves = [0..rows.first_level, rows.first_down..h as usize];
            for _ in 0..20_000 {
                let half = halves[rng.random_range(0..2)].clone();
                let a = rng.random_range(half.clone());
                let b = rng.random_range(a..=half.end);
                let cz: f32 = rng.random_range(0.0..0.4);
                let zmin = *[0.0, cz, rng.random_range(0.0..0.3)]
                    .get(rng.random_range(0..3))
                    .expect("index");
                let zmax = zmin
                    + *[0.0, cz - zmin, rng.random_range(0.01..0.6)]
                        .get(rng.random_range(0..3))
                        .expect("index");
                let te = rng.random_range(T_START..4.0);
                let span = BoxSpan {
                    te,
                    tx: te + rng.random_range(1e-4..1.0),
                    grey_side: 7,
                };
                let looking_down = half.start == rows.first_down;
                let heights = if looking_down {
                    (cz - zmax, cz - zmin)
                } else {
                    (cz - zmin, cz - zmax)
                };
                let depth: Vec<f32> = (a..b)
                    .map(|_| match rng.random_range(0..3) {
                        0 => f32::INFINITY,
                        _ => rng.random_range(0.0..5.0),
                    })
                    .collect();
                let grey: Vec<u8> = (a..b).map(|_| rng.random()).collect();
                let (mut fast_depth, mut fast_grey) = (depth.clone(), grey.clone());
                let (mut slow_depth, mut slow_grey) = (depth, grey);
                let inv_slopes = &rows.inv_slopes[a..b];
                let fast = ColumnRows {
                    depth: &mut fast_depth,
                    grey: &mut fast_grey,
                    inv_slopes,
                };
                span.cover(fast, heights, 9);
                let slow = ColumnRows {
                    depth: &mut slow_depth,
                    grey: &mut slow_grey,
                    inv_slopes,
                };
                reference_cover(&span, slow, heights, 9);
                let bits = |d: &[f32]| d.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(
                    bits(&fast_depth),
                    bits(&slow_depth),
                    "{w}x{h} rows {a}..{b}"
                );
                assert_eq!(fast_grey, slow_grey, "{w}x{h} rows {a}..{b}");
            }
        }
    }

    /// One renderer over scenes with other terrains (a reset that draws a
    /// new relief, another albedo): each frame equals a new renderer's.
    #[test]
    fn a_renderer_reshades_when_the_terrain_changes() {
        let world = crate::world::WorldSpec::builtin("monolith_obstacle").expect("world");
        let intrinsics = Intrinsics::resized(&world.camera, 84, 84);
        let mut darker = world.clone();
        darker.terrain.albedo *= 0.5;
        let first = Scene::build(&world);
        // The same terrain (one allocation) under another albedo.
        let darker = Scene {
            world: darker,
            ..first.clone()
        };
        let scenes = [
            first,
            darker,
            Scene::with_terrain(&world, Terrain::flat(&world.enclosure, 8, 6, 0.05)),
            Scene::build(&world),
        ];
        let pose = CameraPose::level([-1.0, -0.5, 0.2], 0.3);
        let mut reused = ColumnRenderer::new(intrinsics, &world.light);
        let mut frames = Vec::new();
        for scene in &scenes {
            let mut frame = RgbdFrame::new(84, 84);
            reused.render(scene, &pose, &mut frame);
            let mut fresh = RgbdFrame::new(84, 84);
            ColumnRenderer::new(intrinsics, &world.light).render(scene, &pose, &mut fresh);
            assert_eq!(frame.rgb, fresh.rgb);
            frames.push(frame);
        }
        assert_ne!(
            frames[0].rgb, frames[1].rgb,
            "the darker floor looks the same"
        );
        assert_ne!(
            frames[0].rgb, frames[2].rgb,
            "the flat floor looks the same"
        );
    }
}
