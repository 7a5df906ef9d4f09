//! A recorded episode read into its steps: what was commanded, where the
//! robot ended up, what its camera saw, and how the step was judged.

use std::path::{Path, PathBuf};

use offworld_recorder::msg::{EpisodeInfo, Step};
use offworld_recorder::read::EpisodeData;
use offworld_recorder::Channel;
use offworld_runtime::msg::{ImageView, Odometry, PixelEncoding, Pose2D, PoseStamped};

use crate::ParityError;

/// A depth image in metres (NaN: no return), row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct DepthImage {
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Metres per pixel.
    pub metres: Vec<f32>,
}

/// An RGB image, 3 bytes per pixel, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorImage {
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Red, green, blue per pixel.
    pub rgb: Vec<u8>,
}

/// One step as recorded (step 0 is the reset).
#[derive(Debug, Clone)]
pub struct RecordedStep {
    /// The step record: command, reward, termination.
    pub step: Step,
    /// The pose the step was judged from (the tracker's on a robot).
    pub pose: Pose2D,
    /// The step's depth image, if recorded.
    pub depth: Option<DepthImage>,
    /// The step's colour image, if recorded.
    pub color: Option<ColorImage>,
    /// When its command was sent (the `/cmd_vel` log time, ns since the
    /// epoch); none for the reset.
    pub commanded_ns: Option<u64>,
}

/// One wheel-odometry message: the base's speeds at a time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct OdometrySample {
    /// The message's stamp (its capture time), ns since the epoch.
    pub at_ns: u64,
    /// Forward speed, m/s.
    pub linear: f64,
    /// Yaw rate, rad/s.
    pub angular: f64,
}

/// How well the episode's reset placed the robot: where it was asked to
/// start and where it started (the reset step's recorded pose).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResetRecord {
    /// The pose the reset asked for.
    pub requested: Pose2D,
    /// The pose the episode started from.
    pub achieved: Pose2D,
    /// How long the reset took, s, when its recorder noted it.
    pub duration_s: Option<f64>,
}

impl ResetRecord {
    /// Planar distance between requested and achieved, m.
    pub fn position_error_m(&self) -> f64 {
        (self.achieved.x - self.requested.x).hypot(self.achieved.y - self.requested.y)
    }

    /// Absolute heading difference, rad.
    pub fn yaw_error_rad(&self) -> f64 {
        crate::replay::yaw_error(self.achieved.yaw, self.requested.yaw)
    }
}

/// An episode file read into its steps.
#[derive(Debug, Clone)]
pub struct RecordedEpisode {
    /// The file.
    pub path: PathBuf,
    /// Its first record: env, task, world, embodiment.
    pub info: EpisodeInfo,
    /// Its steps in order, the reset first.
    pub steps: Vec<RecordedStep>,
    /// The reset's accuracy.
    pub reset: ResetRecord,
    /// The wheel odometry recorded during the episode, by stamp, each stamp
    /// once (a robot agent streams it; a twin in lockstep records one per
    /// step).
    pub odometry: Vec<OdometrySample>,
}

impl RecordedEpisode {
    /// Reads `path` (a complete file, or a `.partial` up to its cut). An
    /// episode without its info record, a reset, or a pose for a step is
    /// refused, naming the file.
    pub fn read(path: &Path) -> Result<Self, ParityError> {
        let unusable = |reason: String| ParityError::Unusable {
            path: path.to_owned(),
            reason,
        };
        let data = EpisodeData::read(path)?;
        let mut info = None;
        let mut steps = Vec::new();
        let (mut pose, mut depth, mut color, mut commanded_ns) = (None, None, None, None);
        let mut odometry = Vec::new();
        for message in data.messages()? {
            let message = message?;
            match message.channel {
                Some(Channel::Episode) => info = Some(data.decode::<EpisodeInfo>(&message)?),
                Some(Channel::Pose) => {
                    let stamped: PoseStamped = data.decode(&message)?;
                    pose = Some(Pose2D {
                        x: stamped.pose.position.x,
                        y: stamped.pose.position.y,
                        yaw: stamped.pose.orientation.yaw(),
                    });
                }
                Some(Channel::Depth) => {
                    let image = image_view(&message.data).map_err(&unusable)?;
                    depth = Some(depth_image(&image).map_err(&unusable)?);
                }
                Some(Channel::Color) => {
                    let image = image_view(&message.data).map_err(&unusable)?;
                    color = Some(color_image(&image).map_err(&unusable)?);
                }
                Some(Channel::CmdVel) => commanded_ns = Some(message.log_time_ns),
                Some(Channel::Odom) => {
                    let odom: Odometry = data.decode(&message)?;
                    let twist = &odom.twist.twist;
                    if twist.linear.x.is_finite() && twist.angular.z.is_finite() {
                        odometry.push(OdometrySample {
                            at_ns: offworld_recorder::episode_file::stamp_ns(&odom.header.stamp),
                            linear: twist.linear.x,
                            angular: twist.angular.z,
                        });
                    }
                }
                Some(Channel::Step) => {
                    let step: Step = data.decode(&message)?;
                    let Some(pose) = pose.take() else {
                        return Err(unusable(format!("step {} has no pose", step.step)));
                    };
                    steps.push(RecordedStep {
                        step,
                        pose,
                        depth: depth.take(),
                        color: color.take(),
                        commanded_ns: commanded_ns.take(),
                    });
                }
                _ => {}
            }
        }
        let info = info.ok_or_else(|| unusable("no episode record (/offworld/episode)".into()))?;
        if steps.first().map(|s| s.step.step) != Some(0) {
            return Err(unusable("no reset step (step 0)".into()));
        }
        let [x, y, yaw] = info.requested_start;
        let duration_s = data
            .metadata()?
            .get(offworld_recorder::episode_file::RESET_DURATION_NOTE)
            .and_then(|d| d.parse::<f64>().ok())
            .filter(|d| d.is_finite() && *d >= 0.0);
        let reset = ResetRecord {
            requested: Pose2D { x, y, yaw },
            achieved: steps[0].pose,
            duration_s,
        };
        // The answer to a command is also streamed: the same stamp twice.
        odometry.sort_by_key(|o| o.at_ns);
        odometry.dedup_by_key(|o| o.at_ns);
        Ok(Self {
            path: path.to_owned(),
            info,
            steps,
            reset,
            odometry,
        })
    }
}

/// An image message read in place (its pixels are not copied).
fn image_view(data: &[u8]) -> Result<ImageView<'_>, String> {
    offworld_runtime::codec::decode_borrowed(data).map_err(|e| format!("a bad image message: {e}"))
}

/// `image` (`32FC1` metres or `16UC1` millimetres) in metres.
pub fn depth_image(image: &ImageView<'_>) -> Result<DepthImage, String> {
    let encoding = image.validate().map_err(|e| format!("depth image: {e}"))?;
    let (w, h, step) = (
        image.width as usize,
        image.height as usize,
        image.step as usize,
    );
    let mut metres = Vec::with_capacity(w * h);
    for row in image.data.chunks_exact(step.max(1)).take(h) {
        match encoding {
            PixelEncoding::Depth32FC1 => metres.extend(
                row[..w * 4]
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            ),
            PixelEncoding::Depth16UC1 => metres.extend(row[..w * 2].chunks_exact(2).map(|b| {
                match u16::from_le_bytes([b[0], b[1]]) {
                    0 => f32::NAN,
                    mm => f32::from(mm) / 1000.0,
                }
            })),
            other => return Err(format!("a depth image in {}", other.as_str())),
        }
    }
    Ok(DepthImage {
        width: image.width,
        height: image.height,
        metres,
    })
}

/// `image` (`rgb8` or `bgr8`) as RGB.
pub fn color_image(image: &ImageView<'_>) -> Result<ColorImage, String> {
    let encoding = image.validate().map_err(|e| format!("colour image: {e}"))?;
    let (w, h, step) = (
        image.width as usize,
        image.height as usize,
        image.step as usize,
    );
    let mut rgb = Vec::with_capacity(w * h * 3);
    for row in image.data.chunks_exact(step.max(1)).take(h) {
        match encoding {
            PixelEncoding::Rgb8 => rgb.extend_from_slice(&row[..w * 3]),
            PixelEncoding::Bgr8 => {
                for p in row[..w * 3].chunks_exact(3) {
                    rgb.extend_from_slice(&[p[2], p[1], p[0]]);
                }
            }
            other => return Err(format!("a colour image in {}", other.as_str())),
        }
    }
    Ok(ColorImage {
        width: image.width,
        height: image.height,
        rgb,
    })
}
