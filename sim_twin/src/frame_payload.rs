//! Camera frames rendered straight into their wire payload: the renderer
//! writes the pixels once, into a recycled buffer laid out as the encoded
//! `CameraFrame` (`rgb8` + `32FC1`). No 0.5 MB copy into a fresh buffer per
//! step; the same bytes as encoding the rendered frame.

use offworld_runtime::codec::{self, CDR_LE_HEADER};
use offworld_runtime::msg::{CameraFrameView, PixelEncoding, Time};
use offworld_runtime::pool::BufferPool;
use offworld_runtime::EncodeError;
use zenoh::bytes::ZBytes;

use crate::camera::PixelsMut;
use crate::ros_out::{self, COLOR_FRAME, DEPTH_FRAME};
use crate::twin::SimTwin;

/// Renders frames into payloads whose buffers come back once every reader
/// has dropped them.
#[derive(Default)]
pub struct FramePayloads {
    buffers: BufferPool,
}

impl FramePayloads {
    /// No buffers yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Renders the twin's view as the encoded `CameraFrame` answering `seq`.
    pub fn render(&self, twin: &mut SimTwin, seq: u64, stamp: Time) -> Result<ZBytes, EncodeError> {
        let intrinsics = twin.intrinsics();
        let (width, height) = (intrinsics.width, intrinsics.height);
        let pixels = (width * height) as usize;
        let (rgb_len, depth_len) = (pixels * 3, pixels * 4);
        let color = ros_out::image_header(stamp, COLOR_FRAME, width, height, PixelEncoding::Rgb8);
        let depth =
            ros_out::image_header(stamp, DEPTH_FRAME, width, height, PixelEncoding::Depth32FC1);
        // The frame is [seq, colour fields][colour pixels][depth fields]
        // [depth pixels]. Encoded apart, the fields between the pixels have
        // the same bytes while the colour pixels keep 4-byte alignment (the
        // most any field after them needs).
        if !rgb_len.is_multiple_of(4) || cfg!(target_endian = "big") {
            return self.render_copied(twin, seq, stamp);
        }
        let front = codec::encode_open_tail(&(seq, &color), rgb_len)?;
        let middle = codec::encode_open_tail(&depth, depth_len)?;
        // A part continuing a message has no encapsulation header.
        let middle = &middle[CDR_LE_HEADER.len()..];
        let mut buffer = self
            .buffers
            .take(front.len() + rgb_len + middle.len() + depth_len);
        let (front_bytes, rest) = buffer.split_at_mut(front.len());
        front_bytes.copy_from_slice(&front);
        let (rgb, rest) = rest.split_at_mut(rgb_len);
        let (middle_bytes, depth_bytes) = rest.split_at_mut(middle.len());
        middle_bytes.copy_from_slice(middle);
        // Aligned for f32 unless the allocator is unusual: then copy.
        let Ok(depth) = bytemuck::try_cast_slice_mut::<u8, f32>(depth_bytes) else {
            return self.render_copied(twin, seq, stamp);
        };
        if !twin.render_into(PixelsMut { rgb, depth }) {
            return Err(EncodeError("frame buffers of the wrong size".into()));
        }
        Ok(self.buffers.payload(buffer))
    }

    /// The plain path: render, then encode a copy of the pixels.
    fn render_copied(
        &self,
        twin: &mut SimTwin,
        seq: u64,
        stamp: Time,
    ) -> Result<ZBytes, EncodeError> {
        let mut scratch = Vec::new();
        let frame = twin.render();
        let (color, depth) =
            ros_out::frame_images(frame, stamp, PixelEncoding::Depth32FC1, &mut scratch);
        Ok(codec::encode(&CameraFrameView { seq, color, depth })?.into())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::physics::PlanarPose;
    use crate::twin::TwinConfig;
    use offworld_runtime::Resolution;

    fn twin(resolution: Resolution) -> SimTwin {
        let mut config = TwinConfig::builtin("monolith").expect("world");
        config.resolution = Some(resolution);
        let mut twin = SimTwin::new(config).expect("twin");
        let facing_the_monolith = PlanarPose {
            x: -1.0,
            y: -0.2,
            yaw: 0.0,
        };
        twin.teleport(facing_the_monolith).expect("teleport");
        twin
    }

    /// What the plain path sends: the rendered frame, encoded.
    fn plain(twin: &mut SimTwin, seq: u64, stamp: Time) -> Vec<u8> {
        let mut scratch = Vec::new();
        let frame = twin.render();
        let (color, depth) =
            ros_out::frame_images(frame, stamp, PixelEncoding::Depth32FC1, &mut scratch);
        codec::encode(&CameraFrameView { seq, color, depth }).expect("encode")
    }

    #[test]
    fn payloads_have_the_bytes_of_the_encoded_frame() {
        let stamp = Time {
            sec: 17,
            nanosec: 5,
        };
        // 320×240 renders in place; 5×3 (15 colour bytes: unaligned) copies.
        for resolution in [
            Resolution::new(320, 240),
            Resolution::new(84, 84),
            Resolution::new(5, 3),
        ] {
            let mut twin = twin(resolution);
            let payloads = FramePayloads::new();
            for seq in [1, 2, u64::MAX] {
                let sent = payloads.render(&mut twin, seq, stamp).expect("render");
                let expected = plain(&mut twin, seq, stamp);
                assert_eq!(sent.to_bytes(), expected, "{resolution:?} seq {seq}");
                let frame = codec::decode_borrowed::<CameraFrameView>(&expected).expect("decodes");
                assert!(frame.depth.data.iter().any(|b| *b != 0), "rendered depth");
            }
        }
    }

    #[test]
    fn buffers_are_reused_once_readers_drop_them() {
        let mut twin = twin(Resolution::new(84, 84));
        let payloads = FramePayloads::new();
        let stamp = Time::default();
        let first = payloads.render(&mut twin, 1, stamp).expect("render");
        let held = first.to_bytes().as_ptr();
        // Held by a reader: the next frame gets another buffer.
        let second = payloads.render(&mut twin, 2, stamp).expect("render");
        assert_ne!(second.to_bytes().as_ptr(), held);
        drop(first);
        let third = payloads.render(&mut twin, 3, stamp).expect("render");
        assert_eq!(third.to_bytes().as_ptr(), held, "the dropped buffer back");
        assert_eq!(third.to_bytes(), plain(&mut twin, 3, stamp));
    }
}
