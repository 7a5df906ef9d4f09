//! The twin's state as the ROS 2 messages a real robot and tracker publish:
//! one place for both the twin node and the emulated enclosure.

use offworld_runtime::msg::{
    Header, ImageView, Odometry, PixelEncoding, Point, Pose, PoseStamped, PoseWithCovariance,
    Quaternion, Time, Twist, TwistWithCovariance,
};

use crate::camera::RgbdFrame;
use crate::physics::BodyPose;
use crate::twin::SimTwin;

/// Frame id of colour images.
pub const COLOR_FRAME: &str = "camera_color_optical_frame";
/// Frame id of depth images.
pub const DEPTH_FRAME: &str = "camera_depth_optical_frame";

/// Wheel odometry (`odom` → `base_link`), with the servo's current twist.
pub fn odometry(twin: &SimTwin, stamp: Time) -> Odometry {
    let o = twin.physics().odometry();
    let servo = twin.physics().servo();
    Odometry {
        header: Header::new(stamp, "odom"),
        child_frame_id: "base_link".into(),
        pose: PoseWithCovariance {
            pose: Pose {
                position: Point {
                    x: f64::from(o.x),
                    y: f64::from(o.y),
                    z: 0.0,
                },
                orientation: Quaternion::from_yaw(f64::from(o.yaw)),
            },
            covariance: [0.0; 36],
        },
        twist: TwistWithCovariance {
            twist: Twist::planar(f64::from(servo.linear), f64::from(servo.angular)),
            covariance: [0.0; 36],
        },
    }
}

/// A base_link pose in the world frame.
pub fn world_pose(reading: &BodyPose, stamp: Time) -> PoseStamped {
    let [x, y, z] = reading.position.map(f64::from);
    let [qx, qy, qz, qw] = reading.orientation.map(f64::from);
    PoseStamped {
        header: Header::new(stamp, "world"),
        pose: Pose {
            position: Point { x, y, z },
            orientation: Quaternion {
                x: qx,
                y: qy,
                z: qz,
                w: qw,
            },
        },
    }
}

/// The colour (`rgb8`) and depth images of `frame` as a ROS camera driver
/// publishes them, borrowed from the render buffers: encoding them copies
/// each pixel once, straight into the message. Depth is `32FC1` metres (NaN
/// = no return) or `16UC1` millimetres (0 = no return, like an Astra
/// driver); `scratch` holds the depth bytes when they need converting.
pub fn frame_images<'a>(
    frame: &'a RgbdFrame,
    stamp: Time,
    depth_encoding: PixelEncoding,
    scratch: &'a mut Vec<u8>,
) -> (ImageView<'a>, ImageView<'a>) {
    let color = image_view(stamp, COLOR_FRAME, frame, PixelEncoding::Rgb8, &frame.rgb);
    let depth_bytes = depth_bytes(frame, depth_encoding, scratch);
    let depth = image_view(stamp, DEPTH_FRAME, frame, depth_encoding, depth_bytes);
    (color, depth)
}

fn depth_bytes<'a>(
    frame: &'a RgbdFrame,
    encoding: PixelEncoding,
    scratch: &'a mut Vec<u8>,
) -> &'a [u8] {
    scratch.clear();
    match encoding {
        PixelEncoding::Depth16UC1 => {
            scratch.reserve(frame.depth.len() * 2);
            for d in &frame.depth {
                let mm = if d.is_finite() {
                    (d * 1000.0).round().clamp(0.0, f32::from(u16::MAX)) as u16
                } else {
                    0
                };
                scratch.extend_from_slice(&mm.to_le_bytes());
            }
            scratch
        }
        // The render buffer already is little-endian `32FC1`.
        _ if cfg!(target_endian = "little") => bytemuck::cast_slice(&frame.depth),
        _ => {
            scratch.reserve(frame.depth.len() * 4);
            for d in &frame.depth {
                scratch.extend_from_slice(&d.to_le_bytes());
            }
            scratch
        }
    }
}

fn image_view<'a>(
    stamp: Time,
    frame_id: &str,
    frame: &RgbdFrame,
    encoding: PixelEncoding,
    data: &'a [u8],
) -> ImageView<'a> {
    ImageView {
        data,
        ..image_header(stamp, frame_id, frame.width, frame.height, encoding)
    }
}

/// A `width × height` image's fields other than its pixels (`data` empty).
pub fn image_header(
    stamp: Time,
    frame_id: &str,
    width: u32,
    height: u32,
    encoding: PixelEncoding,
) -> ImageView<'static> {
    ImageView {
        header: Header::new(stamp, frame_id),
        height,
        width,
        encoding: encoding.as_str(),
        is_bigendian: 0,
        step: width * encoding.bytes_per_pixel(),
        data: &[],
    }
}
