//! The twin's state as the ROS 2 messages a real robot and tracker publish:
//! one place for both the twin node and the emulated enclosure.

use offworld_runtime::msg::{
    Header, Image, Odometry, PixelEncoding, Point, Pose, PoseStamped, PoseWithCovariance,
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

/// Writes the colour image of `frame` into `image` (reusing its buffers).
pub fn fill_color(image: &mut Image, frame: &RgbdFrame, stamp: Time) {
    set_header(
        image,
        stamp,
        COLOR_FRAME,
        frame.width,
        frame.height,
        PixelEncoding::Rgb8,
    );
    image.data.clear();
    image.data.extend_from_slice(&frame.rgb);
}

/// Writes the depth image of `frame` into `image` as `32FC1` metres (NaN =
/// no return) or `16UC1` millimetres (0 = no return, like an Astra driver).
pub fn fill_depth(image: &mut Image, frame: &RgbdFrame, stamp: Time, encoding: PixelEncoding) {
    set_header(
        image,
        stamp,
        DEPTH_FRAME,
        frame.width,
        frame.height,
        encoding,
    );
    let bytes = encoding.bytes_per_pixel() as usize;
    image.data.clear();
    image.data.resize(frame.depth.len() * bytes, 0);
    let pixels = image.data.chunks_exact_mut(bytes).zip(&frame.depth);
    match encoding {
        PixelEncoding::Depth16UC1 => {
            for (out, d) in pixels {
                let mm = if d.is_finite() {
                    (d * 1000.0).round().clamp(0.0, f32::from(u16::MAX)) as u16
                } else {
                    0
                };
                out.copy_from_slice(&mm.to_le_bytes());
            }
        }
        _ => {
            for (out, d) in pixels {
                out.copy_from_slice(&d.to_le_bytes());
            }
        }
    }
}

fn set_header(
    image: &mut Image,
    stamp: Time,
    frame_id: &str,
    w: u32,
    h: u32,
    encoding: PixelEncoding,
) {
    image.header.stamp = stamp;
    if image.header.frame_id != frame_id {
        image.header.frame_id = frame_id.to_owned();
    }
    image.width = w;
    image.height = h;
    if image.encoding != encoding.as_str() {
        image.encoding = encoding.as_str().to_owned();
    }
    image.is_bigendian = 0;
    image.step = w * encoding.bytes_per_pixel();
}
