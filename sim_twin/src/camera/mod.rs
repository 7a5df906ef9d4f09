//! The RGBD camera: intrinsics, frames, shading, and two renderers.
//!
//! - [`ColumnRenderer`] (the fast path): treats the camera as **level**
//!   (zero pitch and roll: the mount has no tilt; the chassis' tilt on the
//!   terrain is ignored by the render). Each image column is then a vertical
//!   plane through the scene, walked once front to back across the exact
//!   terrain triangles and the boxes; the result is exact for a level camera.
//! - [`ExactRenderer`] (the reference): one parry ray cast per pixel against
//!   the heightfield and every box, any camera orientation. Tests hold the
//!   fast path to it.

mod column;
mod exact;
mod image_io;

pub use column::ColumnRenderer;
pub use exact::ExactRenderer;
pub use image_io::{write_depth_png, write_rgb_png};

use crate::world::{CameraSpec, LightSpec};

/// Pinhole intrinsics for an image of `width × height`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Focal lengths, px.
    pub fx: f32,
    /// Focal lengths, px.
    pub fy: f32,
    /// Principal point, px.
    pub cx: f32,
    /// Principal point, px.
    pub cy: f32,
    /// Valid depth range, m.
    pub min_range: f32,
    /// Valid depth range, m.
    pub max_range: f32,
}

impl Intrinsics {
    /// `depth` as the camera reports it: NaN outside its valid range (and
    /// for NaN).
    pub(crate) fn reported_depth(&self, depth: f32) -> f32 {
        if depth >= self.min_range && depth <= self.max_range {
            depth
        } else {
            f32::NAN
        }
    }

    /// The native camera of a world.
    pub fn native(spec: &CameraSpec) -> Self {
        Self::resized(spec, spec.width, spec.height)
    }

    /// The native camera resampled to `width × height`: the same view a
    /// resize of the native image gives (so 84×84 squeezes 4:3 like the real
    /// pipeline does).
    pub fn resized(spec: &CameraSpec, width: u32, height: u32) -> Self {
        let f = spec.focal_px();
        let sx = width as f32 / spec.width as f32;
        let sy = height as f32 / spec.height as f32;
        Self {
            width,
            height,
            fx: f * sx,
            fy: f * sy,
            cx: width as f32 * 0.5,
            cy: height as f32 * 0.5,
            min_range: spec.min_range,
            max_range: spec.max_range,
        }
    }

    /// Ray slope right of the optical axis for column `u` (pixel centre).
    #[inline]
    pub fn col_slope(&self, u: u32) -> f32 {
        (u as f32 + 0.5 - self.cx) / self.fx
    }

    /// Ray slope below the optical axis for row `v` (pixel centre).
    #[inline]
    pub fn row_slope(&self, v: u32) -> f32 {
        (v as f32 + 0.5 - self.cy) / self.fy
    }
}

/// Where the camera is: optical centre and orientation in the world.
/// `roll`/`pitch` are honoured only by the exact renderer.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CameraPose {
    /// Optical centre, m.
    pub position: [f32; 3],
    /// Heading about +z, rad.
    pub yaw: f32,
    /// Nose-down rotation about the camera's right axis, rad.
    pub pitch: f32,
    /// Rotation about the optical axis, rad.
    pub roll: f32,
}

impl CameraPose {
    /// A level camera.
    pub fn level(position: [f32; 3], yaw: f32) -> Self {
        Self {
            position,
            yaw,
            pitch: 0.0,
            roll: 0.0,
        }
    }
}

/// Where a renderer writes a frame's pixels (row-major, the sizes of its
/// intrinsics): an [`RgbdFrame`]'s buffers, or the pixel fields of a message
/// payload, which is then encoded without copying them.
pub struct PixelsMut<'a> {
    /// `width × height × 3` bytes.
    pub rgb: &'a mut [u8],
    /// `width × height` metres.
    pub depth: &'a mut [f32],
}

/// One RGBD frame: row-major `rgb8` and `f32` depth in metres along the
/// optical axis (NaN = no valid return).
#[derive(Debug, Clone, PartialEq)]
pub struct RgbdFrame {
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// `width × height × 3` bytes.
    pub rgb: Vec<u8>,
    /// `width × height` metres.
    pub depth: Vec<f32>,
}

impl RgbdFrame {
    /// A blank frame.
    pub fn new(width: u32, height: u32) -> Self {
        let n = (width * height) as usize;
        Self {
            width,
            height,
            rgb: vec![0; n * 3],
            depth: vec![f32::NAN; n],
        }
    }

    /// Its pixel buffers, for a renderer.
    pub fn pixels_mut(&mut self) -> PixelsMut<'_> {
        PixelsMut {
            rgb: &mut self.rgb,
            depth: &mut self.depth,
        }
    }

    /// Depth at a pixel.
    pub fn depth_at(&self, u: u32, v: u32) -> f32 {
        self.depth[(v * self.width + u) as usize]
    }

    /// Depth as little-endian bytes (`32FC1`).
    pub fn depth_bytes(&self) -> Vec<u8> {
        self.depth.iter().flat_map(|d| d.to_le_bytes()).collect()
    }
}

/// Lambertian grey shading with one directional light.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shading {
    light: [f32; 3],
    ambient: f32,
    diffuse: f32,
}

impl Shading {
    /// From the world's light.
    pub fn new(light: &LightSpec) -> Self {
        let [x, y, z] = light.direction;
        let n = (x * x + y * y + z * z).sqrt().max(1e-6);
        Self {
            light: [x / n, y / n, z / n],
            ambient: light.ambient,
            diffuse: light.diffuse,
        }
    }

    /// Grey level 0–255 of a surface with unit normal `n` and `albedo`.
    #[inline]
    pub fn grey(&self, n: [f32; 3], albedo: f32) -> u8 {
        let lambert = (n[0] * self.light[0] + n[1] * self.light[1] + n[2] * self.light[2]).max(0.0);
        let value = albedo * (self.ambient + self.diffuse * lambert);
        (value.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
    }
}
