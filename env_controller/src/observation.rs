//! Builds the client's observation from the robot's camera frames: channel
//! selection, server-side resize (nearest pixel centre, so depth is never
//! blended across edges), and depth as uint8 or metres.

use offworld_runtime::msg::{
    CameraFrameView, Channels, DType, ImageView, ObsArray, ObsOptions, PixelEncoding,
};
use offworld_runtime::WireError;

#[cfg(target_arch = "x86_64")]
mod avx2;

/// Largest observation side accepted.
pub const MAX_SIDE: u32 = 1024;

/// Checks a client's observation options.
pub fn validate_options(opts: &ObsOptions) -> Result<(), WireError> {
    if opts.width == 0 || opts.height == 0 || opts.width > MAX_SIDE || opts.height > MAX_SIDE {
        return Err(WireError::bad_request(format!(
            "resolution (height, width) = ({}, {}): each side must be 1..={MAX_SIDE} pixels",
            opts.height, opts.width
        )));
    }
    Ok(())
}

/// Assembles `out` from `frame` per `opts` (see [`assemble_into`]).
pub fn assemble(
    frame: &CameraFrameView,
    opts: &ObsOptions,
    depth_max_m: f32,
    out: &mut ObsArray,
) -> Result<(), WireError> {
    let mut data = std::mem::take(&mut out.data);
    *out = opts.shape();
    data.clear();
    data.resize(out.shape_len() as usize, 0);
    assemble_into(frame, opts, depth_max_m, &mut data)?;
    out.data = data;
    Ok(())
}

/// Writes the data of the observation [`shape`]`(opts)` from `frame` into
/// `data`. Invalid depth becomes 0 in both formats; uint8 depth is
/// `clip(d / depth_max_m, 0, 1) · 255`.
pub fn assemble_into(
    frame: &CameraFrameView,
    opts: &ObsOptions,
    depth_max_m: f32,
    data: &mut [u8],
) -> Result<(), WireError> {
    assemble_with(frame, opts, depth_max_m, data, Loops::Fastest)
}

/// Which loops write an observation: the fastest this CPU has, or the
/// portable ones (which the tests hold to the same bytes on any CPU).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Loops {
    Fastest,
    #[cfg(test)]
    Portable,
}

fn assemble_with(
    frame: &CameraFrameView,
    opts: &ObsOptions,
    depth_max_m: f32,
    data: &mut [u8],
    loops: Loops,
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
    let obs = opts.shape();
    let (channels, dtype) = (obs.channels as usize, obs.dtype);
    if obs.shape_len() != data.len() as u64 {
        return Err(WireError::internal(format!(
            "{} bytes for an observation of {}",
            data.len(),
            obs.shape_len()
        )));
    }
    let depth_scale = 255.0 / depth_max_m.max(1e-6);
    let source_row = |y: usize| ((y * 2 + 1) * sh / (h * 2)).min(sh - 1);
    let native_u8 = loops == Loops::Fastest
        && w == sw
        && depth_enc == PixelEncoding::Depth32FC1
        && dtype == DType::U8
        && opts.channels != Channels::RgbOnly;
    if !(native_u8 && write_native_u8(frame, opts.channels, &source_row, depth_scale, data)) {
        let layout = Layout {
            frame,
            src_x: (0..w)
                .map(|x| ((x * 2 + 1) * sw / (w * 2)).min(sw - 1))
                .collect(),
            identity: w == sw,
            depth_enc,
            depth_scale,
            source_row: &source_row,
        };
        pulp::Arch::new().dispatch(Fill {
            layout: &layout,
            data,
            channels: opts.channels,
            dtype,
        });
    }
    if color_enc == PixelEncoding::Bgr8 && opts.channels != Channels::DepthOnly {
        swap_red_blue(data, channels, dtype.size());
    }
    Ok(())
}

/// One layout's fill, compiled once per instruction set (AVX-512, AVX2,
/// baseline) and run in the one the CPU has: the row loops vectorise 2-4×
/// wider than baseline x86-64 allows.
struct Fill<'l, 'f, 'a, 'd> {
    layout: &'l Layout<'f, 'a>,
    data: &'d mut [u8],
    channels: Channels,
    dtype: DType,
}

impl pulp::WithSimd for Fill<'_, '_, '_, '_> {
    type Output = ();

    // Inlined into each instruction set's entry point, so the loops below
    // are compiled for it.
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let Self { layout, data, .. } = self;
        // One monomorphised loop per layout: no per-pixel branching.
        match (self.channels, self.dtype) {
            (Channels::DepthOnly, DType::U8) => layout.fill::<false, true, false>(data),
            (Channels::DepthOnly, DType::F32) => layout.fill::<false, true, true>(data),
            (Channels::RgbOnly, DType::U8) => layout.fill::<true, false, false>(data),
            (Channels::RgbOnly, DType::F32) => layout.fill::<true, false, true>(data),
            (Channels::Rgbd, DType::U8) => layout.fill::<true, true, false>(data),
            (Channels::Rgbd, DType::F32) => layout.fill::<true, true, true>(data),
        }
    }
}

/// Where each output pixel samples the source frame.
struct Layout<'f, 'a> {
    frame: &'f CameraFrameView<'a>,
    /// Source column of each output column.
    src_x: Vec<usize>,
    /// Native resolution: output column x is source column x.
    identity: bool,
    depth_enc: PixelEncoding,
    /// uint8 levels per metre.
    depth_scale: f32,
    /// Output row `y` samples source row `source_row(y)`.
    source_row: &'f dyn Fn(usize) -> usize,
}

impl Layout<'_, '_> {
    /// Fills `data` a row at a time: depth is converted for the whole row
    /// first (a tight loop), then the row is interleaved.
    #[inline(always)]
    fn fill<const RGB: bool, const DEPTH: bool, const F32: bool>(&self, data: &mut [u8]) {
        let channels = usize::from(RGB) * 3 + usize::from(DEPTH);
        let pixel = channels * if F32 { 4 } else { 1 };
        let w = self.src_x.len();
        let color = &self.frame.color;
        let color_row_len = color.width as usize * 3;
        let mut metres = vec![0.0f32; if DEPTH && F32 { w } else { 0 }];
        let mut levels = vec![0u8; if DEPTH && !F32 { w } else { 0 }];
        let scale = self.depth_scale;
        for (y, out_row) in data.chunks_exact_mut(w * pixel).enumerate() {
            let sy = (self.source_row)(y);
            if DEPTH && F32 {
                self.depth_row(sy, &mut metres, |m| m);
            } else if DEPTH {
                self.depth_row(sy, &mut levels, |m| depth_level(m, scale));
            }
            // In bounds: the frame was validated (step · height = length).
            let color_row = row(color, sy, color_row_len);
            if self.identity && RGB && !F32 {
                // The common layouts (native RGBD / RGB uint8) in 4-pixel blocks.
                if DEPTH {
                    interleave_rgbd8(out_row, color_row, &levels);
                } else {
                    out_row.copy_from_slice(color_row);
                }
            } else if self.identity {
                write_row::<RGB, DEPTH, F32>(out_row, color_row.chunks_exact(3), &metres, &levels);
            } else {
                let colors = self.src_x.iter().map(|&sx| &color_row[sx * 3..sx * 3 + 3]);
                write_row::<RGB, DEPTH, F32>(out_row, colors, &metres, &levels);
            }
        }
    }

    /// Converts source row `sy`'s depth at every output column into `out`;
    /// no return (NaN, ±inf, 0 mm) is 0 m.
    #[inline(always)]
    fn depth_row<T>(&self, sy: usize, out: &mut [T], convert: impl Fn(f32) -> T) {
        let depth = &self.frame.depth;
        let sw = depth.width as usize;
        let row = row(depth, sy, depth.step as usize);
        let millimetres = |b: &[u8]| f32::from(u16::from_le_bytes([b[0], b[1]])) * 1e-3;
        match (self.depth_enc, self.identity) {
            (PixelEncoding::Depth32FC1, true) => {
                store(out, row[..sw * 4].chunks_exact(4).map(metres), convert);
            }
            (PixelEncoding::Depth32FC1, false) => {
                let src = self
                    .src_x
                    .iter()
                    .map(|&sx| metres(&row[sx * 4..sx * 4 + 4]));
                store(out, src, convert);
            }
            (_, true) => store(out, row[..sw * 2].chunks_exact(2).map(millimetres), convert),
            (_, false) => {
                let src = self
                    .src_x
                    .iter()
                    .map(|&sx| millimetres(&row[sx * 2..sx * 2 + 2]));
                store(out, src, convert);
            }
        }
    }
}

/// Row `y`'s first `len` bytes (in bounds for a validated image, whose
/// length is step · height, and `len` ≤ its step).
#[inline(always)]
fn row<'a>(image: &ImageView<'a>, y: usize, len: usize) -> &'a [u8] {
    &image.data[y * image.step as usize..][..len]
}

/// A little-endian `32FC1` depth; no return (NaN, ±inf) is 0 m.
#[inline(always)]
fn metres(b: &[u8]) -> f32 {
    let d = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    if d.is_finite() {
        d
    } else {
        0.0
    }
}

/// Writes a uint8 observation at the frame's own width with AVX2; false,
/// touching nothing, where the CPU has none.
fn write_native_u8(
    frame: &CameraFrameView,
    channels: Channels,
    source_row: &dyn Fn(usize) -> usize,
    scale: f32,
    data: &mut [u8],
) -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        let image = avx2::NativeU8 {
            color: (channels == Channels::Rgbd).then_some(&frame.color),
            depth: &frame.depth,
            width: frame.depth.width as usize,
            source_row,
            scale,
        };
        avx2::write_native_u8(&image, data)
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (frame, channels, source_row, scale, data);
        false
    }
}

/// `clip(m · scale, 0, 255)` truncated, exactly as the saturating cast
/// `(m * scale) as u8` for finite `m`, in float operations only, so the
/// row loop vectorises (a float-to-int cast does not, on baseline x86-64).
#[inline(always)]
fn depth_level(m: f32, scale: f32) -> u8 {
    // Adding 2^23 rounds to the nearest integer, which lands in the low
    // mantissa bits; one down if that rounded up.
    const ROUND: f32 = 8_388_608.0;
    let v = (m * scale).clamp(0.0, 255.0);
    let t = v + ROUND;
    let nearest = (t.to_bits() & 0xff) as u8;
    nearest - u8::from(t - ROUND > v)
}

/// Native-resolution RGBD uint8: `rgb` (3 bytes a pixel) and `levels` (1)
/// into `out` (4), eight pixels per step in 64-bit words (shifts and masks:
/// baseline x86-64 has no byte shuffle).
#[inline(always)]
fn interleave_rgbd8(out: &mut [u8], rgb: &[u8], levels: &[u8]) {
    let word = |bytes: &[u8]| {
        let mut w = [0u8; 8];
        w.copy_from_slice(bytes);
        u64::from_le_bytes(w)
    };
    let mut out_blocks = out.chunks_exact_mut(32);
    let mut rgb_blocks = rgb.chunks_exact(24);
    let mut level_blocks = levels.chunks_exact(8);
    for ((o, c), d) in (&mut out_blocks)
        .zip(&mut rgb_blocks)
        .zip(&mut level_blocks)
    {
        // Pixels 0-1 in a, 2 across a/b, 3-4 in b, 5 across b/c, 6-7 in c.
        let (a, b, c, l) = (word(&c[..8]), word(&c[8..16]), word(&c[16..]), word(d));
        let rgb = 0x00ff_ffff_u64;
        let level = |i: u32| ((l >> (8 * i)) & 0xff) << 24;
        let pair = |lo: u64, hi: u64| lo | (hi << 32);
        let words = [
            pair((a & rgb) | level(0), ((a >> 24) & rgb) | level(1)),
            pair(
                (a >> 48) | ((b & 0xff) << 16) | level(2),
                ((b >> 8) & rgb) | level(3),
            ),
            pair(
                ((b >> 32) & rgb) | level(4),
                (b >> 56) | ((c & 0xffff) << 8) | level(5),
            ),
            pair(((c >> 16) & rgb) | level(6), (c >> 40) | level(7)),
        ];
        for (o, w) in o.chunks_exact_mut(8).zip(words) {
            o.copy_from_slice(&w.to_le_bytes());
        }
    }
    let rest = out_blocks.into_remainder().chunks_exact_mut(4);
    let rest = rest.zip(rgb_blocks.remainder().chunks_exact(3));
    for ((o, c), &d) in rest.zip(level_blocks.remainder()) {
        o.copy_from_slice(&[c[0], c[1], c[2], d]);
    }
}

#[inline(always)]
fn store<T>(out: &mut [T], metres: impl Iterator<Item = f32>, convert: impl Fn(f32) -> T) {
    for (o, m) in out.iter_mut().zip(metres) {
        *o = convert(m);
    }
}

/// Interleaves one output row from its source colours and converted depth.
#[inline(always)]
fn write_row<'c, const RGB: bool, const DEPTH: bool, const F32: bool>(
    out: &mut [u8],
    colors: impl Iterator<Item = &'c [u8]>,
    metres: &[f32],
    levels: &[u8],
) {
    let f = |v: u8| f32::from(v).to_le_bytes();
    match (RGB, DEPTH, F32) {
        (true, true, false) => {
            for ((px, c), &d) in out.chunks_exact_mut(4).zip(colors).zip(levels) {
                px.copy_from_slice(&[c[0], c[1], c[2], d]);
            }
        }
        (true, false, false) => {
            for (px, c) in out.chunks_exact_mut(3).zip(colors) {
                px.copy_from_slice(&[c[0], c[1], c[2]]);
            }
        }
        (false, _, false) => out.copy_from_slice(levels),
        (true, true, true) => {
            for ((px, c), &d) in out.chunks_exact_mut(16).zip(colors).zip(metres) {
                px[..4].copy_from_slice(&f(c[0]));
                px[4..8].copy_from_slice(&f(c[1]));
                px[8..12].copy_from_slice(&f(c[2]));
                px[12..].copy_from_slice(&d.to_le_bytes());
            }
        }
        (true, false, true) => {
            for (px, c) in out.chunks_exact_mut(12).zip(colors) {
                px[..4].copy_from_slice(&f(c[0]));
                px[4..8].copy_from_slice(&f(c[1]));
                px[8..].copy_from_slice(&f(c[2]));
            }
        }
        (false, _, true) => {
            for (px, d) in out.chunks_exact_mut(4).zip(metres) {
                px.copy_from_slice(&d.to_le_bytes());
            }
        }
    }
}

/// `bgr8` sources: swaps the first and third channel of every pixel.
fn swap_red_blue(data: &mut [u8], channels: usize, component: usize) {
    for px in data.chunks_exact_mut(channels * component) {
        for k in 0..component {
            px.swap(k, 2 * component + k);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use offworld_runtime::msg::{CameraFrame, DepthFormat, Header, Image};

    /// The observation the fastest loops write, checked equal to the
    /// portable loops' (all a CPU without AVX2 runs).
    fn assembled(frame: &CameraFrameView, opts: &ObsOptions, depth_max: f32) -> Vec<u8> {
        let len = opts.shape().shape_len() as usize;
        let (mut fastest, mut portable) = (vec![0; len], vec![0; len]);
        assemble_with(frame, opts, depth_max, &mut fastest, Loops::Fastest).expect("assembles");
        assemble_with(frame, opts, depth_max, &mut portable, Loops::Portable).expect("assembles");
        assert_eq!(
            fastest, portable,
            "the fastest and the portable loops differ"
        );
        fastest
    }

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
    fn depth_levels_equal_the_saturating_cast() {
        let scale = 255.0 / 5.0;
        let samples = (0..400_000).map(|i| i as f32 * 2e-5 - 1.0);
        let edges = [
            0.0,
            5.0,
            4.999_999_5,
            1e30,
            -1e30,
            f32::MAX,
            f32::MIN_POSITIVE,
        ];
        for m in samples.chain(edges) {
            assert_eq!(depth_level(m, scale), (m * scale) as u8, "m = {m}");
        }
        for k in 0..=255u8 {
            let m = f32::from(k) / scale;
            assert_eq!(depth_level(m, scale), (m * scale) as u8, "level {k}");
        }
    }

    /// The fast paths against a per-pixel reference, at a width that is not
    /// a multiple of the 8-pixel block.
    #[test]
    fn every_layout_matches_a_per_pixel_reference() {
        let (sw, sh) = (23u32, 7u32);
        let px = |x: u32, y: u32| {
            [
                (x * 11 % 256) as u8,
                (y * 37 % 256) as u8,
                ((x + y) % 256) as u8,
            ]
        };
        let depth_at = |x: u32, y: u32| match (x + 3 * y) % 9 {
            0 => f32::NAN,
            1 => f32::INFINITY,
            k => k as f32 * 0.7,
        };
        let rgb = (0..sh)
            .flat_map(|y| (0..sw).flat_map(move |x| px(x, y)))
            .collect();
        let depth = (0..sh)
            .flat_map(|y| (0..sw).flat_map(move |x| depth_at(x, y).to_le_bytes()))
            .collect();
        let f = CameraFrame {
            seq: 1,
            color: Image::packed(Header::default(), sw, sh, PixelEncoding::Rgb8, rgb),
            depth: Image::packed(Header::default(), sw, sh, PixelEncoding::Depth32FC1, depth),
        };
        let depth_max = 4.0;
        for (w, h) in [(sw, sh), (9, 5), (30, 10)] {
            for channels in [Channels::Rgbd, Channels::RgbOnly, Channels::DepthOnly] {
                for depth_format in [DepthFormat::Uint8, DepthFormat::Meters] {
                    let opts = ObsOptions {
                        channels,
                        width: w,
                        height: h,
                        depth_format,
                    };
                    let out = assembled(&f.view(), &opts, depth_max);
                    let mut expected = Vec::new();
                    for y in 0..h {
                        for x in 0..w {
                            let sx = ((x * 2 + 1) * sw / (w * 2)).min(sw - 1);
                            let sy = ((y * 2 + 1) * sh / (h * 2)).min(sh - 1);
                            let d = depth_at(sx, sy);
                            let m = if d.is_finite() { d } else { 0.0 };
                            let mut values: Vec<f32> = Vec::new();
                            if channels != Channels::DepthOnly {
                                values.extend(px(sx, sy).map(f32::from));
                            }
                            if channels != Channels::RgbOnly {
                                values.push(m);
                            }
                            let last = values.len() - 1;
                            for (i, v) in values.into_iter().enumerate() {
                                let is_depth = channels != Channels::RgbOnly && i == last;
                                match depth_format {
                                    DepthFormat::Meters => expected.extend(v.to_le_bytes()),
                                    DepthFormat::Uint8 if is_depth => {
                                        expected.push((v * 255.0 / depth_max) as u8)
                                    }
                                    DepthFormat::Uint8 => expected.push(v as u8),
                                }
                            }
                        }
                    }
                    assert_eq!(out, expected, "{channels:?} {w}x{h} {depth_format:?}");
                }
            }
        }
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

    mod properties {
        use super::super::*;
        use offworld_runtime::msg::DepthFormat;
        use proptest::prelude::*;

        fn options() -> impl Strategy<Value = ObsOptions> {
            let side = prop_oneof![any::<u32>(), 0u32..=MAX_SIDE + 2];
            (
                side.clone(),
                side,
                prop_oneof![
                    Just(Channels::DepthOnly),
                    Just(Channels::RgbOnly),
                    Just(Channels::Rgbd)
                ],
                prop_oneof![Just(DepthFormat::Uint8), Just(DepthFormat::Meters)],
            )
                .prop_map(|(height, width, channels, depth_format)| ObsOptions {
                    channels,
                    height,
                    width,
                    depth_format,
                })
        }

        proptest! {
            /// Any resolution gets an answer: accepted exactly within
            /// 1..=MAX_SIDE per side, so the observation's size stays
            /// bounded (and its arithmetic far from overflow).
            #[test]
            fn resolutions(opts in options()) {
                let ok = (1..=MAX_SIDE).contains(&opts.width) && (1..=MAX_SIDE).contains(&opts.height);
                match validate_options(&opts) {
                    Ok(()) => {
                        prop_assert!(ok);
                        let max = u64::from(MAX_SIDE) * u64::from(MAX_SIDE) * 4 * 4;
                        prop_assert!(opts.shape().shape_len() <= max);
                    }
                    Err(e) => {
                        prop_assert!(!ok);
                        prop_assert_eq!(e.code, offworld_runtime::ErrorCode::BadRequest);
                    }
                }
            }

            /// At the camera's own width (AVX2 rows where the CPU has them,
            /// and the portable ones) a uint8 observation is its per-pixel
            /// definition, for any depth bits (NaN, ±inf, negative, huge,
            /// subnormal), any width around the 8-pixel block and any row
            /// resampling.
            #[test]
            fn native_uint8_is_its_definition(
                (w, h) in (1u32..40, 1u32..5),
                out_h in 1u32..6,
                depths in proptest::collection::vec(
                    prop_oneof![
                        4 => any::<u32>().prop_map(f32::from_bits),
                        4 => -1.0f32..12.0,
                        1 => prop_oneof![
                            Just(f32::INFINITY),
                            Just(f32::NEG_INFINITY),
                            Just(f32::NAN),
                            Just(-0.0),
                            Just(f32::MAX),
                            Just(f32::MIN_POSITIVE / 2.0),
                        ],
                    ],
                    200,
                ),
                colours in proptest::collection::vec(any::<u8>(), 600),
                depth_max in 0.1f32..10.0,
            ) {
                use offworld_runtime::msg::{CameraFrame, Header, Image};
                let n = (w * h) as usize;
                let depth = depths[..n].iter().flat_map(|d| d.to_le_bytes()).collect();
                let frame = CameraFrame {
                    seq: 1,
                    color: Image::packed(Header::default(), w, h, PixelEncoding::Rgb8, colours[..n * 3].to_vec()),
                    depth: Image::packed(Header::default(), w, h, PixelEncoding::Depth32FC1, depth),
                };
                let scale = 255.0 / depth_max;
                for channels in [Channels::Rgbd, Channels::DepthOnly] {
                    let opts = ObsOptions { channels, width: w, height: out_h, depth_format: DepthFormat::Uint8 };
                    let out = super::assembled(&frame.view(), &opts, depth_max);
                    let mut expected = Vec::new();
                    for y in 0..out_h {
                        let sy = ((y * 2 + 1) * h / (out_h * 2)).min(h - 1);
                        for x in 0..w {
                            let at = (sy * w + x) as usize;
                            if channels == Channels::Rgbd {
                                expected.extend_from_slice(&colours[at * 3..at * 3 + 3]);
                            }
                            let d = depths[at];
                            expected.push((if d.is_finite() { d } else { 0.0 } * scale) as u8);
                        }
                    }
                    prop_assert_eq!(&out, &expected, "{:?} {}x{} from {}x{}", channels, w, out_h, w, h);
                }
            }
        }
    }
}
