//! The replay as a rerun recording: robot and twin side by side, step by
//! step — both trajectories over the enclosure, the depth and colour the
//! robot recorded next to the twin's at the same pose, the depth error
//! image, and the errors as time series. Open it with `rerun FILE.rrd`.
//!
//! ```text
//! <episode>/recorded/trajectory   LineStrips3D: the recorded poses
//! <episode>/twin/trajectory       LineStrips3D: the open-loop twin's
//! <episode>/recorded/depth        DepthImage (m)   <episode>/recorded/color  Image
//! <episode>/twin/depth            DepthImage (m)   <episode>/twin/color      Image
//! <episode>/error/depth           DepthImage: |twin − robot| (m), pixels valid in both
//! <episode>/error/{open_loop_position_m, one_step_position_m, one_step_yaw_rad, depth_mae_m}  Scalars
//! ```
//! on the timeline `step`.

use std::path::Path;

use rerun::components::ImageFormat;
use rerun::datatypes::ChannelDatatype;
use rerun::{Color, DepthImage, Image, LineStrips3D, RecordingStream, Scalars};

use crate::recorded::RecordedStep;
use crate::replay::{EpisodeReplay, StepGap};
use crate::ParityError;

/// The application id the recording is filed under in the viewer.
pub const APPLICATION_ID: &str = "offworld_parity";
/// The step timeline.
pub const TIMELINE: &str = "step";

fn failed(path: &Path, e: impl std::fmt::Display) -> ParityError {
    ParityError::Output {
        path: path.to_owned(),
        reason: e.to_string(),
    }
}

/// A rerun recording being written.
pub struct SideBySide {
    rec: RecordingStream,
    path: std::path::PathBuf,
}

fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

impl SideBySide {
    /// Starts writing `path` (`.rrd`).
    pub fn create(path: &Path) -> Result<Self, ParityError> {
        let rec = rerun::RecordingStreamBuilder::new(APPLICATION_ID)
            .save(path)
            .map_err(|e| failed(path, e))?;
        Ok(Self {
            rec,
            path: path.to_owned(),
        })
    }

    /// Logs one replayed step of the episode `name`: the recorded step,
    /// the twin's frame at the recorded pose, the gap.
    pub fn step(
        &self,
        name: &str,
        recorded: &RecordedStep,
        twin: &offworld_sim_twin::camera::RgbdFrame,
        gap: &StepGap,
    ) -> Result<(), ParityError> {
        let rec = &self.rec;
        let err = |e: rerun::RecordingStreamError| failed(&self.path, e);
        rec.set_time_sequence(TIMELINE, i64::from(gap.step));
        let size = [twin.width, twin.height];
        let depth_format = ImageFormat::depth(size, ChannelDatatype::F32);
        rec.log(
            format!("{name}/twin/depth"),
            &DepthImage::new(f32_bytes(&twin.depth), depth_format).with_meter(1.0),
        )
        .map_err(err)?;
        rec.log(
            format!("{name}/twin/color"),
            &Image::from_rgb24(twin.rgb.clone(), size),
        )
        .map_err(err)?;
        if let Some(d) = &recorded.depth {
            rec.log(
                format!("{name}/recorded/depth"),
                &DepthImage::new(
                    f32_bytes(&d.metres),
                    ImageFormat::depth([d.width, d.height], ChannelDatatype::F32),
                )
                .with_meter(1.0),
            )
            .map_err(err)?;
            if (d.width, d.height) == (twin.width, twin.height) {
                let error: Vec<f32> = twin
                    .depth
                    .iter()
                    .zip(&d.metres)
                    .map(|(t, r)| (t - r).abs())
                    .collect();
                rec.log(
                    format!("{name}/error/depth"),
                    &DepthImage::new(f32_bytes(&error), depth_format).with_meter(1.0),
                )
                .map_err(err)?;
            }
        }
        if let Some(c) = &recorded.color {
            rec.log(
                format!("{name}/recorded/color"),
                &Image::from_rgb24(c.rgb.clone(), [c.width, c.height]),
            )
            .map_err(err)?;
        }
        for (series, value) in [
            ("open_loop_position_m", gap.open_loop_position_m),
            ("one_step_position_m", gap.one_step_position_m),
            ("one_step_yaw_rad", gap.one_step_yaw_rad),
            ("depth_mae_m", gap.depth_mae_m),
        ] {
            if value.is_finite() {
                rec.log(format!("{name}/error/{series}"), &Scalars::single(value))
                    .map_err(err)?;
            }
        }
        Ok(())
    }

    /// Logs the episode's two trajectories (recorded, open-loop twin).
    pub fn trajectories(&self, name: &str, replay: &EpisodeReplay) -> Result<(), ParityError> {
        let lift = |x: f64, y: f64| [x as f32, y as f32, 0.02];
        let start = lift(replay.start.x, replay.start.y);
        let recorded: Vec<[f32; 3]> = std::iter::once(start)
            .chain(
                replay
                    .steps
                    .iter()
                    .map(|s| lift(s.recorded.x, s.recorded.y)),
            )
            .collect();
        let twin: Vec<[f32; 3]> = std::iter::once(start)
            .chain(
                replay
                    .steps
                    .iter()
                    .map(|s| lift(s.open_loop.x, s.open_loop.y)),
            )
            .collect();
        let err = |e: rerun::RecordingStreamError| failed(&self.path, e);
        for (who, strip, color) in [
            ("recorded", recorded, Color::from_rgb(40, 160, 255)),
            ("twin", twin, Color::from_rgb(255, 140, 40)),
        ] {
            self.rec
                .log_static(
                    format!("{name}/{who}/trajectory"),
                    &LineStrips3D::new([strip]).with_colors([color]),
                )
                .map_err(err)?;
        }
        Ok(())
    }

    /// Finishes the file.
    pub fn finish(self) -> Result<(), ParityError> {
        self.rec.flush_blocking().map_err(|e| failed(&self.path, e))
    }
}
