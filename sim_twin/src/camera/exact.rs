//! The reference renderer: one parry ray cast per pixel against the terrain
//! heightfield and every box, for any camera orientation. Slow (tens of ms
//! at 320×240) and independent of the column walk's geometry code.

use parry3d::math::{Pose, Vec3};
use parry3d::query::{Ray, RayCast};
use parry3d::shape::{Cuboid, HeightField};

use super::{CameraPose, Intrinsics, PixelsMut, RgbdFrame, Shading};
use crate::scene::Scene;
use crate::world::LightSpec;

/// Per-pixel ray casting with parry.
pub struct ExactRenderer {
    intrinsics: Intrinsics,
    shading: Shading,
    terrain: (HeightField, Pose),
    boxes: Vec<(Cuboid, Pose, f32)>,
    terrain_albedo: f32,
}

impl ExactRenderer {
    /// Builds parry shapes for `scene`.
    pub fn new(intrinsics: Intrinsics, light: &LightSpec, scene: &Scene) -> Self {
        let boxes = scene
            .boxes
            .iter()
            .map(|b| {
                let [hx, hy, hz] = b.half_extents();
                let [x, y, z] = b.center();
                (
                    Cuboid::new(Vec3::new(hx, hy, hz)),
                    Pose::from_translation(Vec3::new(x, y, z)),
                    b.albedo,
                )
            })
            .collect();
        Self {
            intrinsics,
            shading: Shading::new(light),
            terrain: scene.terrain.to_parry(),
            boxes,
            terrain_albedo: scene.world.terrain.albedo,
        }
    }

    /// Renders a frame from `pose`, honouring pitch and roll.
    pub fn render(&self, pose: &CameraPose) -> RgbdFrame {
        let intr = self.intrinsics;
        let mut frame = RgbdFrame::new(intr.width, intr.height);
        self.render_into(pose, &mut frame.pixels_mut());
        frame
    }

    /// The intrinsics rendered with.
    pub fn intrinsics(&self) -> &Intrinsics {
        &self.intrinsics
    }

    /// Renders into `pixels`, which must have the sizes of the intrinsics
    /// (every pixel is written); returns false, writing nothing, if not.
    pub fn render_into(&self, pose: &CameraPose, pixels: &mut PixelsMut<'_>) -> bool {
        let intr = self.intrinsics;
        let n = (intr.width * intr.height) as usize;
        if pixels.rgb.len() != n * 3 || pixels.depth.len() != n {
            return false;
        }
        let (forward, right, up) = camera_axes(pose);
        let origin = Vec3::from(pose.position);
        for v in 0..intr.height {
            for u in 0..intr.width {
                let (a, b) = (intr.col_slope(u), intr.row_slope(v));
                // Unnormalised: the time of impact is the z-depth.
                let dir = forward + right * a - up * b;
                let ray = Ray::new(origin, dir);
                let mut best: Option<(f32, Vec3, f32)> = None;
                let (hf, hf_pose) = &self.terrain;
                let candidates =
                    std::iter::once((hf as &dyn RayCast, hf_pose, self.terrain_albedo)).chain(
                        self.boxes
                            .iter()
                            .map(|(c, p, a)| (c as &dyn RayCast, p, *a)),
                    );
                for (shape, shape_pose, albedo) in candidates {
                    let limit = best.map_or(f32::MAX, |b| b.0);
                    if let Some(hit) = shape.cast_ray_and_get_normal(shape_pose, &ray, limit, true)
                    {
                        if hit.time_of_impact < limit {
                            best = Some((hit.time_of_impact, hit.normal, albedo));
                        }
                    }
                }
                let i = (v * intr.width + u) as usize;
                let (depth, grey) = match best {
                    Some((d, n, albedo)) => {
                        // Face the normal towards the camera.
                        let n = if n.dot(dir) > 0.0 { -n } else { n };
                        let depth = intr.reported_depth(d);
                        (depth, self.shading.grey([n.x, n.y, n.z], albedo))
                    }
                    None => (f32::NAN, 0),
                };
                pixels.depth[i] = depth;
                pixels.rgb[i * 3..i * 3 + 3].fill(grey);
            }
        }
        true
    }
}

/// World-frame forward, right and up axes of the camera.
pub(crate) fn camera_axes(pose: &CameraPose) -> (Vec3, Vec3, Vec3) {
    let (sy, cy) = pose.yaw.sin_cos();
    let forward = Vec3::new(cy, sy, 0.0);
    let right = Vec3::new(sy, -cy, 0.0);
    let up = Vec3::Z;
    // Pitch (nose down) about the right axis, then roll about forward.
    let (sp, cp) = pose.pitch.sin_cos();
    let forward_p = forward * cp - up * sp;
    let up_p = up * cp + forward * sp;
    let (sr, cr) = pose.roll.sin_cos();
    let right_r = right * cr - up_p * sr;
    let up_r = up_p * cr + right * sr;
    (forward_p, right_r, up_r)
}
