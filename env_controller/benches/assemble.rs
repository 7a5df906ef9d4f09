//! What building an observation from a camera frame costs, per layout.
//! Run: `cargo bench --bench assemble`

use std::time::Instant;

use offworld_env_controller::observation::assemble;
use offworld_runtime::msg::{
    CameraFrame, Channels, DepthFormat, Header, Image, ObsArray, ObsOptions, PixelEncoding,
};

const ROUNDS: usize = 400;

fn frame(w: u32, h: u32) -> CameraFrame {
    let rgb = (0..w * h * 3).map(|i| (i % 251) as u8).collect();
    let depth = (0..w * h)
        .flat_map(|i| {
            let d = if i % 97 == 0 {
                f32::NAN
            } else {
                0.2 + (i % 500) as f32 * 0.01
            };
            d.to_le_bytes()
        })
        .collect();
    CameraFrame {
        seq: 1,
        color: Image::packed(Header::default(), w, h, PixelEncoding::Rgb8, rgb),
        depth: Image::packed(Header::default(), w, h, PixelEncoding::Depth32FC1, depth),
    }
}

fn median_us(mut work: impl FnMut()) -> f64 {
    let mut times = Vec::with_capacity(ROUNDS);
    for _ in 0..ROUNDS {
        let start = Instant::now();
        work();
        times.push(start.elapsed().as_secs_f64() * 1e6);
    }
    times.sort_by(f64::total_cmp);
    times[ROUNDS / 2]
}

fn main() {
    let native = frame(320, 240);
    // The machine's yardstick: copying an observation's worth of bytes.
    let src = vec![3u8; 320 * 240 * 4];
    let mut dst = vec![0u8; src.len()];
    let copy = median_us(|| dst.copy_from_slice(std::hint::black_box(&src)));
    println!("memcpy of 307200 B (the machine's yardstick): {copy:7.1} µs");
    let small = frame(84, 84);
    println!("assemble, median of {ROUNDS}:");
    // (source frame, layout): native sizes are what the twin renders for a
    // client; 84x84 from 320x240 is the robot's camera resampled.
    for (source, channels, (w, h), depth_format) in [
        (&native, Channels::Rgbd, (320, 240), DepthFormat::Uint8),
        (&native, Channels::Rgbd, (320, 240), DepthFormat::Meters),
        (&native, Channels::DepthOnly, (320, 240), DepthFormat::Uint8),
        (&native, Channels::Rgbd, (84, 84), DepthFormat::Uint8),
        (&small, Channels::Rgbd, (84, 84), DepthFormat::Uint8),
        (&small, Channels::DepthOnly, (84, 84), DepthFormat::Uint8),
    ] {
        let view = source.view();
        let opts = ObsOptions {
            channels,
            width: w,
            height: h,
            depth_format,
        };
        let mut times = Vec::with_capacity(ROUNDS);
        let mut out = ObsArray::default();
        for _ in 0..ROUNDS {
            let start = Instant::now();
            assemble(&view, &opts, 5.0, &mut out).expect("assemble");
            times.push(start.elapsed().as_secs_f64() * 1e6);
        }
        times.sort_by(f64::total_cmp);
        println!(
            "  {:?} {w}x{h} {:?} from {}x{}: {:7.2} µs",
            channels,
            depth_format,
            source.color.width,
            source.color.height,
            times[ROUNDS / 2]
        );
    }
}
