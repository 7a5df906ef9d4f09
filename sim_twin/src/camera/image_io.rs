//! Writing frames as PNG files for people to look at.

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;

use super::RgbdFrame;
use crate::error::SimError;

fn write_png(
    path: &Path,
    width: u32,
    height: u32,
    color: png::ColorType,
    data: &[u8],
) -> Result<(), SimError> {
    let io = |e: std::io::Error| SimError::Io(format!("{}: {e}", path.display()));
    let file = File::create(path).map_err(io)?;
    let mut encoder = png::Encoder::new(BufWriter::new(file), width, height);
    encoder.set_color(color);
    encoder.set_depth(png::BitDepth::Eight);
    let mut writer = encoder
        .write_header()
        .map_err(|e| SimError::Io(format!("{}: {e}", path.display())))?;
    writer
        .write_image_data(data)
        .map_err(|e| SimError::Io(format!("{}: {e}", path.display())))
}

/// Writes the colour image.
pub fn write_rgb_png(frame: &RgbdFrame, path: &Path) -> Result<(), SimError> {
    write_png(
        path,
        frame.width,
        frame.height,
        png::ColorType::Rgb,
        &frame.rgb,
    )
}

/// Writes depth as grey: near = bright, `max_m` and beyond = black,
/// invalid = black.
pub fn write_depth_png(frame: &RgbdFrame, path: &Path, max_m: f32) -> Result<(), SimError> {
    let grey: Vec<u8> = frame
        .depth
        .iter()
        .map(|d| {
            if d.is_finite() {
                (255.0 * (1.0 - (d / max_m).clamp(0.0, 1.0))) as u8
            } else {
                0
            }
        })
        .collect();
    write_png(
        path,
        frame.width,
        frame.height,
        png::ColorType::Grayscale,
        &grey,
    )
}
