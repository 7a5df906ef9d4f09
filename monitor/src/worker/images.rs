//! Camera and overhead frames as rerun images (depth, colour), and the
//! pinhole kept at the frame's resolution.

use super::*;

impl Worker {
    pub(super) fn on_obs(
        &mut self,
        env: &EnvId,
        sample: &Sample,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let frame: CameraFrame = codec::decode_payload(sample.payload())?;
        self.log_frame(env, Some(frame.seq), frame.color, frame.depth, wall)
    }

    /// A camera frame (`obs`, or a recording's colour and depth images): a
    /// 0×0 image is absent, not both. At `seq`, else the env's current step.
    pub fn log_frame(
        &mut self,
        env: &EnvId,
        seq: Option<u64>,
        color: Image,
        depth: Image,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let stamp = if color.width > 0 {
            color.header.stamp
        } else {
            depth.header.stamp
        };
        let size = if color.width > 0 {
            (color.width, color.height)
        } else {
            (depth.width, depth.height)
        };
        let color = picture(color)?;
        let depth = picture(depth)?;
        if color.is_none() && depth.is_none() {
            return Err(Skip::Decode("camera frame without images".into()));
        }
        self.set_camera_resolution(env, size)?;
        let seq = seq.or(self.view(env).seq);
        let stamp = Self::stamp(seq, Some(&stamp), wall);
        for row in [color, depth].into_iter().flatten() {
            let path = match row {
                Row::Depth(..) => paths::DEPTH,
                _ => paths::COLOR,
            };
            self.columns.push(env_path(env, path), stamp, row);
        }
        self.count(&self.shared.counters.frames);
        Ok(())
    }

    /// Logs the pinhole for this resolution once the world's camera is known.
    pub(super) fn set_camera_resolution(
        &mut self,
        env: &EnvId,
        size: (u32, u32),
    ) -> Result<(), Skip> {
        let view = self.view(env);
        view.camera_res = Some(size);
        if view.pinhole_res == Some(size) {
            return Ok(());
        }
        let Some(camera) = view.world.as_ref().map(|w| w.camera.clone()) else {
            return Ok(());
        };
        view.pinhole_res = Some(size);
        self.rec.reset_time();
        scene::log_camera(&self.rec, env, &camera, size.0, size.1)?;
        Ok(())
    }

    pub(super) fn on_overhead(
        &mut self,
        env: &EnvId,
        camera: &str,
        sample: &Sample,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        if EnvId::sim(camera).is_err() {
            return Err(Skip::Decode(format!("bad overhead camera name `{camera}`")));
        }
        let image: Image = codec::decode_payload(sample.payload())?;
        let stamp = image.header.stamp;
        let Some(row) = picture(image)? else {
            return Err(Skip::Decode("empty overhead image".into()));
        };
        let step = self.view(env).seq;
        self.columns.push(
            env_path(env, &paths::overhead(camera)),
            Self::stamp(step, Some(&stamp), wall),
            row,
        );
        self.count(&self.shared.counters.overhead_frames);
        Ok(())
    }
}

/// Rows without padding: `data` as-is when already packed.
pub(super) fn packed_rows(image: Image, bytes_per_pixel: u32) -> Vec<u8> {
    let row = (image.width * bytes_per_pixel) as usize;
    let step = image.step as usize;
    if step == row {
        return image.data;
    }
    let mut out = Vec::with_capacity(row * image.height as usize);
    for chunk in image.data.chunks_exact(step) {
        out.extend_from_slice(&chunk[..row]);
    }
    out
}

/// A validated ROS image as an `Image` or `DepthImage` row; `None` for an
/// absent (0×0) image.
pub(super) fn picture(image: Image) -> Result<Option<Row>, Skip> {
    if image.width == 0 || image.height == 0 {
        return Ok(None);
    }
    let encoding = image.validate()?;
    let size = [image.width, image.height];
    let data = packed_rows(image, encoding.bytes_per_pixel());
    let color = |model| ImageFormat::from_color_model(size, model, ChannelDatatype::U8);
    Ok(Some(match encoding {
        PixelEncoding::Rgb8 => Row::Image(data, color(ColorModel::RGB)),
        PixelEncoding::Bgr8 => Row::Image(data, color(ColorModel::BGR)),
        PixelEncoding::Depth32FC1 => {
            Row::Depth(data, ImageFormat::depth(size, ChannelDatatype::F32), 1.0)
        }
        PixelEncoding::Depth16UC1 => {
            Row::Depth(data, ImageFormat::depth(size, ChannelDatatype::U16), 1000.0)
        }
    }))
}
