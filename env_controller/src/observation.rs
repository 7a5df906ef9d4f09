//! Builds the client's observation from the robot's camera frames: channel
//! selection, server-side resize (nearest pixel centre, so depth is never
//! blended across edges), and depth as uint8 or metres.

use offworld_runtime::msg::{
    CameraFrameView, Channels, DType, DepthFormat, ObsArray, ObsOptions, PixelEncoding,
};
use offworld_runtime::WireError;

/// Largest observation side accepted.
pub const MAX_SIDE: u32 = 1024;

/// Checks a client's observation options.
pub fn validate_options(opts: &ObsOptions) -> Result<(), WireError> {
    if opts.width == 0 || opts.height == 0 || opts.width > MAX_SIDE || opts.height > MAX_SIDE {
        return Err(WireError::bad_request(format!(
            "resolution {}x{} outside 1..={MAX_SIDE}",
            opts.height, opts.width
        )));
    }
    Ok(())
}

/// Assembles `out` from `frame` per `opts`. Invalid depth becomes 0 in
/// both formats; uint8 depth is `clip(d / depth_max_m, 0, 1) · 255`.
pub fn assemble(
    frame: &CameraFrameView,
    opts: &ObsOptions,
    depth_max_m: f32,
    out: &mut ObsArray,
) -> Result<(), WireError> {
    let bad = |what: String| WireError::internal(format!("robot sent a bad frame: {what}"));
    let color_enc = frame.color.validate().map_err(|e| bad(e.to_string()))?;
    let depth_enc = frame.depth.validate().map_err(|e| bad(e.to_string()))?;
    if !matches!(color_enc, PixelEncoding::Rgb8 | PixelEncoding::Bgr8) {
        return Err(bad(format!("colour encoding {}", frame.color.encoding)));
    }
    if !matches!(
        depth_enc,
        PixelEncoding::Depth32FC1 | PixelEncoding::Depth16UC1
    ) {
        return Err(bad(format!("depth encoding {}", frame.depth.encoding)));
    }
    let (sw, sh) = (frame.color.width as usize, frame.color.height as usize);
    if (frame.depth.width as usize, frame.depth.height as usize) != (sw, sh) || sw == 0 || sh == 0 {
        return Err(bad("colour and depth sizes differ".into()));
    }
    let (w, h) = (opts.width as usize, opts.height as usize);
    let channels = opts.channels.count() as usize;
    let dtype = match opts.depth_format {
        DepthFormat::Uint8 => DType::U8,
        DepthFormat::Meters => DType::F32,
    };
    out.height = opts.height;
    out.width = opts.width;
    out.channels = channels as u32;
    out.dtype = dtype;
    out.data.clear();
    out.data.resize(w * h * channels * dtype.size(), 0);
    let rows = Rows {
        frame,
        src_x: (0..w)
            .map(|x| ((x * 2 + 1) * sw / (w * 2)).min(sw - 1))
            .collect(),
        bgr: color_enc == PixelEncoding::Bgr8,
        depth_enc,
        depth_scale: 255.0 / depth_max_m.max(1e-6),
        identity: w == sw,
        metres: vec![0.0; w],
        depth_u8: vec![0; w],
    };
    // One monomorphised loop per layout: no per-pixel branching.
    match (opts.channels, dtype) {
        (Channels::DepthOnly, DType::U8) => rows.fill::<false, true, false>(&mut out.data, sh, h),
        (Channels::DepthOnly, DType::F32) => rows.fill::<false, true, true>(&mut out.data, sh, h),
        (Channels::RgbOnly, DType::U8) => rows.fill::<true, false, false>(&mut out.data, sh, h),
        (Channels::RgbOnly, DType::F32) => rows.fill::<true, false, true>(&mut out.data, sh, h),
        (Channels::Rgbd, DType::U8) => rows.fill::<true, true, false>(&mut out.data, sh, h),
        (Channels::Rgbd, DType::F32) => rows.fill::<true, true, true>(&mut out.data, sh, h),
    }
    Ok(())
}

/// Row-by-row resampling state.
struct Rows<'f, 'a> {
    frame: &'f CameraFrameView<'a>,
    /// Source column of each output column.
    src_x: Vec<usize>,
    bgr: bool,
    depth_enc: PixelEncoding,
    depth_scale: f32,
    /// Native resolution: output column x is source column x.
    identity: bool,
    /// Metres of the current output row (invalid → 0).
    metres: Vec<f32>,
    /// The same as uint8.
    depth_u8: Vec<u8>,
}

impl Rows<'_, '_> {
    /// Converts the depth of output row `y` (source row `sy`) in tight
    /// loops: the encoding is matched once per row, not per pixel.
    fn load_depth<const F32: bool>(&mut self, sy: usize) {
        let depth = &self.frame.depth;
        let bytes = &depth.data[sy * depth.step as usize..];
        let metres = |d: f32| if d.is_finite() { d } else { 0.0 };
        // 0 mm is "no return", which is 0 m already.
        let millimetres = |b: &[u8]| f32::from(u16::from_le_bytes([b[0], b[1]])) * 1e-3;
        match (self.depth_enc, self.identity) {
            (PixelEncoding::Depth32FC1, true) => {
                for (m, b) in self.metres.iter_mut().zip(bytes.chunks_exact(4)) {
                    *m = metres(f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
                }
            }
            (PixelEncoding::Depth32FC1, false) => {
                for (m, &sx) in self.metres.iter_mut().zip(&self.src_x) {
                    let b = &bytes[sx * 4..sx * 4 + 4];
                    *m = metres(f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
                }
            }
            (_, true) => {
                for (m, b) in self.metres.iter_mut().zip(bytes.chunks_exact(2)) {
                    *m = millimetres(b);
                }
            }
            (_, false) => {
                for (m, &sx) in self.metres.iter_mut().zip(&self.src_x) {
                    *m = millimetres(&bytes[sx * 2..sx * 2 + 2]);
                }
            }
        }
        if !F32 {
            let scale = self.depth_scale;
            for (v, m) in self.depth_u8.iter_mut().zip(&self.metres) {
                // Saturating cast: clips to 0..=255.
                *v = (m * scale) as u8;
            }
        }
    }

    fn fill<const RGB: bool, const DEPTH: bool, const F32: bool>(
        mut self,
        data: &mut [u8],
        sh: usize,
        h: usize,
    ) {
        let channels = usize::from(RGB) * 3 + usize::from(DEPTH);
        let pixel = channels * if F32 { 4 } else { 1 };
        let w = self.src_x.len();
        let color_step = self.frame.color.step as usize;
        let (r, b) = if self.bgr { (2, 0) } else { (0, 2) };
        let src_x = self.src_x.clone();
        for (y, out_row) in data.chunks_exact_mut(w * pixel).enumerate() {
            let sy = ((y * 2 + 1) * sh / (h * 2)).min(sh - 1);
            if DEPTH {
                self.load_depth::<F32>(sy);
            }
            let color_row = &self.frame.color.data[sy * color_step..];
            let write = |(x, px): (usize, &mut [u8])| {
                let sx = src_x[x];
                let mut c = 0;
                if RGB {
                    let s = &color_row[sx * 3..sx * 3 + 3];
                    let rgb = [s[r], s[1], s[b]];
                    if F32 {
                        for (k, v) in rgb.into_iter().enumerate() {
                            px[k * 4..k * 4 + 4].copy_from_slice(&f32::from(v).to_le_bytes());
                        }
                    } else {
                        px[..3].copy_from_slice(&rgb);
                    }
                    c = 3;
                }
                if DEPTH {
                    if F32 {
                        px[c * 4..c * 4 + 4].copy_from_slice(&self.metres[x].to_le_bytes());
                    } else {
                        px[c] = self.depth_u8[x];
                    }
                }
            };
            out_row.chunks_exact_mut(pixel).enumerate().for_each(write);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use offworld_runtime::msg::{CameraFrame, Header, Image};

    fn frame() -> CameraFrame {
        // 4×2: colour = (x, y, 7); depth = 0.5·(x + 1) m except one NaN.
        let (w, h) = (4u32, 2u32);
        let mut rgb = Vec::new();
        let mut depth = Vec::new();
        for y in 0..h {
            for x in 0..w {
                rgb.extend_from_slice(&[x as u8, y as u8, 7]);
                let d = if (x, y) == (3, 1) {
                    f32::NAN
                } else {
                    0.5 * (x + 1) as f32
                };
                depth.extend_from_slice(&d.to_le_bytes());
            }
        }
        CameraFrame {
            seq: 1,
            color: Image::packed(Header::default(), w, h, PixelEncoding::Rgb8, rgb),
            depth: Image::packed(Header::default(), w, h, PixelEncoding::Depth32FC1, depth),
        }
    }

    #[test]
    fn channels_formats_and_resize() {
        let f = frame();
        let mut out = ObsArray::default();
        let opts = |channels, width, height, depth_format| ObsOptions {
            channels,
            width,
            height,
            depth_format,
        };
        assemble(
            &f.view(),
            &opts(Channels::DepthOnly, 4, 2, DepthFormat::Uint8),
            2.0,
            &mut out,
        )
        .expect("ok");
        assert_eq!(
            (out.height, out.width, out.channels, out.dtype),
            (2, 4, 1, DType::U8)
        );
        // 0.5 m of 2 m → 63; 2.0 m → 255; NaN → 0.
        assert_eq!(out.data, vec![63, 127, 191, 255, 63, 127, 191, 0]);
        assemble(
            &f.view(),
            &opts(Channels::Rgbd, 2, 1, DepthFormat::Uint8),
            2.0,
            &mut out,
        )
        .expect("ok");
        // Pixel centres of a 2×1 output fall on source (1, 1) and (3, 1);
        // (3, 1) has no depth return → 0.
        assert_eq!(out.data, vec![1, 1, 7, 127, 3, 1, 7, 0]);
        assert!(out.is_consistent());
        assemble(
            &f.view(),
            &opts(Channels::Rgbd, 4, 2, DepthFormat::Meters),
            2.0,
            &mut out,
        )
        .expect("ok");
        assert_eq!(out.dtype, DType::F32);
        let floats: Vec<f32> = out
            .data
            .chunks(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        assert_eq!(&floats[..4], &[0.0, 0.0, 7.0, 0.5]);
        assert_eq!(floats[floats.len() - 1], 0.0, "invalid depth is 0 m");
        assemble(
            &f.view(),
            &opts(Channels::RgbOnly, 4, 2, DepthFormat::Uint8),
            2.0,
            &mut out,
        )
        .expect("ok");
        assert_eq!(out.data.len(), 4 * 2 * 3);
    }

    #[test]
    fn bgr_and_millimetre_depth_are_normalised() {
        let mut f = frame();
        f.color.encoding = "bgr8".into();
        let mm: Vec<u8> = [500u16, 1000, 0, 2000, 500, 1000, 1500, 2000]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        f.depth = Image::packed(Header::default(), 4, 2, PixelEncoding::Depth16UC1, mm);
        let mut out = ObsArray::default();
        let opts = ObsOptions {
            channels: Channels::Rgbd,
            width: 4,
            height: 2,
            depth_format: DepthFormat::Meters,
        };
        assemble(&f.view(), &opts, 2.0, &mut out).expect("ok");
        let floats: Vec<f32> = out
            .data
            .chunks(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        assert_eq!(
            &floats[..4],
            &[7.0, 0.0, 0.0, 0.5],
            "bgr swapped to rgb, mm to m"
        );
        assert_eq!(floats[2 * 4 + 3], 0.0, "0 mm is invalid");
    }

    #[test]
    fn bad_frames_and_options_are_typed_errors() {
        let mut f = frame();
        f.depth.data.pop();
        let mut out = ObsArray::default();
        assert!(assemble(&f.view(), &ObsOptions::default(), 5.0, &mut out).is_err());
        let mut f = frame();
        f.color.encoding = "mono8".into();
        assert!(assemble(&f.view(), &ObsOptions::default(), 5.0, &mut out).is_err());
        for (w, h) in [(0, 10), (10, 0), (2000, 10)] {
            let o = ObsOptions {
                width: w,
                height: h,
                ..ObsOptions::default()
            };
            assert!(validate_options(&o).is_err());
        }
    }
}
