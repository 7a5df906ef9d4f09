//! Invariants of the controller's use of received camera frames: a frame
//! payload read in place (`CameraFrameView`) and assembled into the
//! client's observation (`env_controller::observation`: validation,
//! channel selection, resize, depth conversion, in the widest SIMD the CPU
//! has) must equal a plain per-pixel reference, or be refused with a typed
//! error; never a panic.
//!
//! Shared by the fuzz target and `env_controller/tests/integration/fuzz_corpus.rs`.

use offworld_env_controller::observation::{assemble, assemble_into, validate_options, MAX_SIDE};
use offworld_runtime::codec;
use offworld_runtime::msg::{
    CameraFrame, CameraFrameView, Channels, DType, DepthFormat, Header, Image, ObsArray,
    ObsOptions, PixelEncoding,
};
use offworld_runtime::ErrorCode;

/// Depth ranges of the spec (`EnvSpec::depth_max_m`) tried; 1e-9 is below
/// the 1e-6 floor the conversion applies.
const DEPTH_MAX: [f32; 6] = [5.0, 2.0, 0.3, 65.535, 1e-9, 1e30];

/// Encodings tried for structured frames (the last one is unsupported).
const ENCODINGS: [&str; 5] = ["rgb8", "bgr8", "16UC1", "32FC1", "mono8"];

fn side(byte: u8) -> u32 {
    match byte {
        255 => MAX_SIDE + 1,
        b => u32::from(b % 41),
    }
}

/// Builds a frame from `[cw, ch, color enc, depth enc, color pad, depth
/// pad, flags, pixel bytes…]` (pixel bytes cycled to fill both images).
fn structured(data: &[u8]) -> Vec<u8> {
    let Some((&[cw, ch, ce, de, cp, dp, flags], pixels)) = data.split_first_chunk::<7>() else {
        return Vec::new();
    };
    let mut source = pixels.iter().copied().cycle();
    let mut image = |width: u32, height: u32, encoding: &str, pad: u8| {
        let bpp = PixelEncoding::parse(encoding).map_or(1, PixelEncoding::bytes_per_pixel);
        let step = width * bpp + u32::from(pad % 4);
        let len = (step * height) as usize;
        let data: Vec<u8> = if pixels.is_empty() {
            vec![0; len]
        } else {
            source.by_ref().take(len).collect()
        };
        Image {
            header: Header::default(),
            height,
            width,
            encoding: encoding.to_owned(),
            is_bigendian: 0,
            step,
            data,
        }
    };
    let (cw, ch) = (u32::from(cw % 25), u32::from(ch % 25));
    let color = image(cw, ch, ENCODINGS[usize::from(ce % 5)], cp);
    let mut depth = image(
        cw + u32::from(flags & 1),
        ch,
        ENCODINGS[usize::from(de % 5)],
        dp,
    );
    depth.is_bigendian = (flags >> 1) & 1;
    let frame = CameraFrame {
        seq: u64::from(flags),
        color,
        depth,
    };
    codec::encode(&frame).expect("frames encode")
}

/// The observation per the documented semantics, pixel by pixel; `None`
/// where the frame must be refused.
fn reference(frame: &CameraFrameView, opts: &ObsOptions, depth_max_m: f32) -> Option<Vec<u8>> {
    let color_enc = frame.color.validate().ok()?;
    let depth_enc = frame.depth.validate().ok()?;
    if !matches!(color_enc, PixelEncoding::Rgb8 | PixelEncoding::Bgr8)
        || !matches!(
            depth_enc,
            PixelEncoding::Depth16UC1 | PixelEncoding::Depth32FC1
        )
    {
        return None;
    }
    let (sw, sh) = (frame.color.width as usize, frame.color.height as usize);
    if (frame.depth.width, frame.depth.height) != (frame.color.width, frame.color.height)
        || sw == 0
        || sh == 0
    {
        return None;
    }
    let (w, h) = (opts.width as usize, opts.height as usize);
    // Nearest source pixel centre.
    let source = |i: usize, n: usize, sn: usize| ((i * 2 + 1) * sn / (n * 2)).min(sn - 1);
    let scale = 255.0 / depth_max_m.max(1e-6);
    let mut out = Vec::new();
    for y in 0..h {
        let sy = source(y, h, sh);
        let color_row = &frame.color.data[sy * frame.color.step as usize..];
        let depth_row = &frame.depth.data[sy * frame.depth.step as usize..];
        for x in 0..w {
            let sx = source(x, w, sw);
            let c = &color_row[sx * 3..sx * 3 + 3];
            let rgb = match color_enc {
                PixelEncoding::Bgr8 => [c[2], c[1], c[0]],
                _ => [c[0], c[1], c[2]],
            };
            let metres = match depth_enc {
                PixelEncoding::Depth32FC1 => {
                    let b = &depth_row[sx * 4..sx * 4 + 4];
                    let m = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
                    if m.is_finite() {
                        m
                    } else {
                        0.0
                    }
                }
                _ => {
                    let b = &depth_row[sx * 2..sx * 2 + 2];
                    f32::from(u16::from_le_bytes([b[0], b[1]])) * 1e-3
                }
            };
            let rgb_wanted = opts.channels != Channels::DepthOnly;
            let depth_wanted = opts.channels != Channels::RgbOnly;
            match opts.depth_format {
                DepthFormat::Uint8 => {
                    if rgb_wanted {
                        out.extend(rgb);
                    }
                    if depth_wanted {
                        // Saturating: clip(d · 255 / depth_max, 0, 255).
                        out.push((metres * scale) as u8);
                    }
                }
                DepthFormat::Meters => {
                    if rgb_wanted {
                        for v in rgb {
                            out.extend(f32::from(v).to_le_bytes());
                        }
                    }
                    if depth_wanted {
                        out.extend(metres.to_le_bytes());
                    }
                }
            }
        }
    }
    Some(out)
}

/// Input: `[channels, depth format, width, height, depth range, mode,
/// frame…]`; an even `mode` takes the frame bytes as the CDR payload, an
/// odd one builds a frame from them (see `structured`) and encodes it.
pub fn observation(data: &[u8]) {
    let Some((&[channels, format, width, height, range, mode], rest)) =
        data.split_first_chunk::<6>()
    else {
        return;
    };
    let opts = ObsOptions {
        channels: [Channels::DepthOnly, Channels::RgbOnly, Channels::Rgbd]
            [usize::from(channels % 3)],
        height: side(height),
        width: side(width),
        depth_format: [DepthFormat::Uint8, DepthFormat::Meters][usize::from(format % 2)],
    };
    let depth_max_m = DEPTH_MAX[usize::from(range) % DEPTH_MAX.len()];
    let payload = if mode % 2 == 0 {
        rest.to_vec()
    } else {
        structured(rest)
    };
    let Ok(frame) = codec::decode_borrowed::<CameraFrameView>(&payload) else {
        return;
    };
    if validate_options(&opts).is_err() {
        assert!(
            opts.width == 0 || opts.height == 0 || opts.width > MAX_SIDE || opts.height > MAX_SIDE,
            "valid options refused: {opts:?}"
        );
        return;
    }
    // A reused observation of another shape, as the controller's buffers are.
    let mut out = ObsArray {
        height: 1,
        width: 1,
        channels: 1,
        dtype: DType::F32,
        data: vec![0xaa; 7],
    };
    let result = assemble(&frame, &opts, depth_max_m, &mut out);
    let expected = reference(&frame, &opts, depth_max_m);
    match (result, expected) {
        (Ok(()), Some(expected)) => {
            let want = opts.shape();
            assert_eq!(
                (out.height, out.width, out.channels, out.dtype),
                (want.height, want.width, want.channels, want.dtype),
                "observation shape"
            );
            assert!(out.is_consistent(), "observation length");
            assert!(
                out.data == expected,
                "observation differs from the reference for {opts:?}, depth max {depth_max_m}, \
                 frame {}x{} {} / {}",
                frame.color.width,
                frame.color.height,
                frame.color.encoding,
                frame.depth.encoding
            );
        }
        (Err(e), None) => assert_eq!(e.code, ErrorCode::Internal, "refusal code"),
        (result, expected) => panic!(
            "assemble gave {result:?} but the reference {}",
            if expected.is_some() {
                "accepts the frame"
            } else {
                "refuses it"
            }
        ),
    }
    // A buffer of the wrong size is an error, never a panic.
    let mut wrong = vec![0u8; opts.shape().shape_len() as usize + 1];
    assert!(assemble_into(&frame, &opts, depth_max_m, &mut wrong).is_err());
}

/// Seeds of [`observation`].
pub fn observation_seeds() -> Vec<Vec<u8>> {
    let raw = {
        let color = Image::packed(
            Header::default(),
            4,
            2,
            PixelEncoding::Rgb8,
            (0u8..24).collect(),
        );
        let depth = Image::packed(
            Header::default(),
            4,
            2,
            PixelEncoding::Depth32FC1,
            [0.5f32, 1.0, 1.5, 2.0, f32::NAN, -1.0, 0.0, 7.5]
                .iter()
                .flat_map(|d| d.to_le_bytes())
                .collect(),
        );
        codec::encode(&CameraFrame {
            seq: 1,
            color,
            depth,
        })
        .expect("seed frame encodes")
    };
    let mut seeds = Vec::new();
    // Native size, resized, every channel set and format.
    for (channels, format, w, h) in [
        (2u8, 0u8, 4u8, 2u8),
        (0, 1, 2, 1),
        (1, 0, 8, 3),
        (2, 1, 3, 5),
    ] {
        let mut seed = vec![channels, format, w, h, 0, 0];
        seed.extend(&raw);
        seeds.push(seed);
    }
    for (head, frame) in [
        ([2u8, 0, 16, 16, 1, 1], [16u8, 16, 1, 2, 0, 0, 0]),
        ([0, 1, 7, 9, 2, 1], [20, 12, 0, 3, 3, 1, 0]),
        ([1, 0, 24, 3, 3, 1], [8, 8, 0, 2, 2, 0, 0]),
    ] {
        let mut seed = head.to_vec();
        seed.extend(frame);
        seed.extend((0u8..=255).rev());
        seeds.push(seed);
    }
    seeds
}
