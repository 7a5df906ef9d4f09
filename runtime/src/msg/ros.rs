//! ROS 2 message types with their exact CDR layouts (`std_msgs`,
//! `geometry_msgs`, `nav_msgs`, `sensor_msgs`), so a ROS 2 peer over
//! rmw_zenoh or zenoh-bridge-ros2dds reads our bytes as its own.

use serde::{Deserialize, Serialize};
use serde_big_array::BigArray;

/// `builtin_interfaces/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds since the epoch (or since sim start).
    pub sec: i32,
    /// Nanoseconds within the second.
    pub nanosec: u32,
}

impl Time {
    /// Builds a time from seconds; negative or non-finite values clamp to 0.
    pub fn from_secs_f64(secs: f64) -> Self {
        let secs = if secs.is_finite() { secs.max(0.0) } else { 0.0 };
        let whole = secs.floor();
        Self {
            sec: whole.min(i32::MAX as f64) as i32,
            nanosec: (((secs - whole) * 1e9) as u32).min(999_999_999),
        }
    }

    /// Wall-clock now.
    pub fn now() -> Self {
        Self::from_unix_nanos(Self::now_unix_nanos())
    }

    /// Wall-clock now in nanoseconds since the epoch (0 before it).
    pub fn now_unix_nanos() -> u64 {
        Self::unix_nanos(std::time::SystemTime::now())
    }

    /// `at` in nanoseconds since the epoch (0 before it).
    pub fn unix_nanos(at: std::time::SystemTime) -> u64 {
        at.duration_since(std::time::UNIX_EPOCH).map_or(0, |since| {
            u64::try_from(since.as_nanos()).unwrap_or(u64::MAX)
        })
    }

    /// Seconds as a float.
    pub fn as_secs_f64(&self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }

    /// Builds a time from nanoseconds since the epoch, exactly (a float
    /// keeps only about a quarter of a microsecond); past `i32::MAX`
    /// seconds it clamps there.
    pub fn from_unix_nanos(nanos: u64) -> Self {
        let sec = nanos / 1_000_000_000;
        if sec > i32::MAX as u64 {
            return Self {
                sec: i32::MAX,
                nanosec: 999_999_999,
            };
        }
        Self {
            sec: sec as i32,
            nanosec: (nanos % 1_000_000_000) as u32,
        }
    }

    /// Nanoseconds since the epoch (a negative time is 0).
    pub fn as_unix_nanos(&self) -> u64 {
        u64::try_from(self.sec).unwrap_or(0) * 1_000_000_000 + u64::from(self.nanosec)
    }
}

/// `std_msgs/Header`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// Acquisition time.
    pub stamp: Time,
    /// Coordinate frame of the data.
    pub frame_id: String,
}

impl Header {
    /// A header for `frame_id` at `stamp`.
    pub fn new(stamp: Time, frame_id: &str) -> Self {
        Self {
            stamp,
            frame_id: frame_id.to_owned(),
        }
    }
}

/// `geometry_msgs/Vector3`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Vector3 {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/Point`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/Quaternion` (x, y, z, w order on the wire).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Quaternion {
    /// No rotation.
    pub const IDENTITY: Quaternion = Quaternion {
        x: 0.0,
        y: 0.0,
        z: 0.0,
        w: 1.0,
    };

    /// A rotation of `yaw` radians about +z.
    pub fn from_yaw(yaw: f64) -> Self {
        let (s, c) = (yaw * 0.5).sin_cos();
        Self {
            x: 0.0,
            y: 0.0,
            z: s,
            w: c,
        }
    }

    /// The heading (rotation about +z) of this orientation, in (−π, π].
    pub fn yaw(&self) -> f64 {
        let siny_cosp = 2.0 * (self.w * self.z + self.x * self.y);
        let cosy_cosp = 1.0 - 2.0 * (self.y * self.y + self.z * self.z);
        siny_cosp.atan2(cosy_cosp)
    }
}

/// `geometry_msgs/Pose`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}

/// `geometry_msgs/PoseStamped`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

/// `geometry_msgs/Twist`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Twist {
    pub linear: Vector3,
    pub angular: Vector3,
}

impl Twist {
    /// A planar twist: forward speed (m/s) and yaw rate (rad/s).
    pub fn planar(linear_x: f64, angular_z: f64) -> Self {
        Self {
            linear: Vector3 {
                x: linear_x,
                ..Vector3::default()
            },
            angular: Vector3 {
                z: angular_z,
                ..Vector3::default()
            },
        }
    }
}

/// `geometry_msgs/PoseWithCovariance`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct PoseWithCovariance {
    pub pose: Pose,
    #[serde(with = "BigArray")]
    pub covariance: [f64; 36],
}

impl Default for PoseWithCovariance {
    fn default() -> Self {
        Self {
            pose: Pose::default(),
            covariance: [0.0; 36],
        }
    }
}

/// `geometry_msgs/TwistWithCovariance`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct TwistWithCovariance {
    pub twist: Twist,
    #[serde(with = "BigArray")]
    pub covariance: [f64; 36],
}

impl Default for TwistWithCovariance {
    fn default() -> Self {
        Self {
            twist: Twist::default(),
            covariance: [0.0; 36],
        }
    }
}

/// `nav_msgs/Odometry`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[allow(missing_docs)]
pub struct Odometry {
    pub header: Header,
    pub child_frame_id: String,
    pub pose: PoseWithCovariance,
    pub twist: TwistWithCovariance,
}

/// Pixel encodings we produce and accept (`sensor_msgs/image_encodings`).
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, strum::IntoStaticStr, strum::EnumIter, strum::VariantNames,
)]
pub enum PixelEncoding {
    /// 3 × u8, red first.
    #[strum(serialize = "rgb8")]
    Rgb8,
    /// 3 × u8, blue first (some cameras; converted on ingest).
    #[strum(serialize = "bgr8")]
    Bgr8,
    /// Depth, u16 millimetres, 0 = invalid.
    #[strum(serialize = "16UC1")]
    Depth16UC1,
    /// Depth, f32 metres, NaN = invalid.
    #[strum(serialize = "32FC1")]
    Depth32FC1,
}

impl PixelEncoding {
    /// The ROS encoding string.
    pub fn as_str(self) -> &'static str {
        self.into()
    }

    /// Bytes per pixel.
    pub fn bytes_per_pixel(self) -> u32 {
        match self {
            PixelEncoding::Rgb8 | PixelEncoding::Bgr8 => 3,
            PixelEncoding::Depth16UC1 => 2,
            PixelEncoding::Depth32FC1 => 4,
        }
    }

    /// Parses a ROS encoding string.
    pub fn parse(s: &str) -> Option<Self> {
        crate::named::parse("encoding", s).ok()
    }
}

/// `sensor_msgs/Image`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Image {
    /// Stamp and camera frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// ROS encoding string, see [`PixelEncoding`].
    pub encoding: String,
    /// 0 = little-endian pixels (all we produce).
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// Row-major pixel bytes.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// Why an [`Image`] is not usable.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ImageError {
    /// The encoding string is not one we handle.
    #[error("unsupported image encoding `{0}`")]
    UnsupportedEncoding(String),
    /// Big-endian pixel data.
    #[error("big-endian images are not supported")]
    BigEndian,
    /// Sizes disagree with the data.
    #[error("image {width}x{height} step {step} does not fit {len} data bytes")]
    BadGeometry {
        /// Columns.
        width: u32,
        /// Rows.
        height: u32,
        /// Bytes per row.
        step: u32,
        /// Data length.
        len: usize,
    },
}

impl Image {
    /// An image with tightly packed rows.
    pub fn packed(
        header: Header,
        width: u32,
        height: u32,
        encoding: PixelEncoding,
        data: Vec<u8>,
    ) -> Self {
        Self {
            header,
            height,
            width,
            encoding: encoding.as_str().to_owned(),
            is_bigendian: 0,
            step: width * encoding.bytes_per_pixel(),
            data,
        }
    }

    /// The image borrowed: same fields, same wire bytes.
    pub fn view(&self) -> ImageView<'_> {
        ImageView {
            header: self.header.clone(),
            height: self.height,
            width: self.width,
            encoding: &self.encoding,
            is_bigendian: self.is_bigendian,
            step: self.step,
            data: &self.data,
        }
    }

    /// Checks encoding, endianness and geometry; returns the encoding.
    pub fn validate(&self) -> Result<PixelEncoding, ImageError> {
        self.view().validate()
    }
}

/// `sensor_msgs/Image` borrowed from a received payload: decoding it copies
/// no pixel, so a frame is read in place where it arrived.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImageView<'a> {
    /// Stamp and camera frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// ROS encoding string, see [`PixelEncoding`].
    pub encoding: &'a str,
    /// 0 = little-endian pixels.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// Row-major pixel bytes.
    #[serde(borrow, with = "serde_bytes")]
    pub data: &'a [u8],
}

impl ImageView<'_> {
    /// Checks encoding, endianness and geometry; returns the encoding.
    pub fn validate(&self) -> Result<PixelEncoding, ImageError> {
        let encoding = PixelEncoding::parse(self.encoding)
            .ok_or_else(|| ImageError::UnsupportedEncoding(self.encoding.to_owned()))?;
        if self.is_bigendian != 0 {
            return Err(ImageError::BigEndian);
        }
        let row = u64::from(self.width) * u64::from(encoding.bytes_per_pixel());
        let needed = u64::from(self.step) * u64::from(self.height);
        if u64::from(self.step) < row || needed != self.data.len() as u64 {
            return Err(ImageError::BadGeometry {
                width: self.width,
                height: self.height,
                step: self.step,
                len: self.data.len(),
            });
        }
        Ok(encoding)
    }
}
