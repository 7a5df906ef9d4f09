//! Messages between the controller and whatever embodies the robot (sim
//! twin or robot_agent + tracker_agent). Our own types, CDR-encoded like the
//! ROS ones they embed.

use serde::{Deserialize, Serialize};

use super::ros::{Image, ImageView, Time};

/// A motion: drive at (`linear_x`, `angular_z`) for `duration_s`, then stop.
/// The robot answers with a [`CameraFrame`] carrying the same `seq`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MotionCommand {
    /// Sequence number; every answer echoes it.
    pub seq: u64,
    /// Forward speed, m/s.
    pub linear_x: f64,
    /// Yaw rate, rad/s (positive = left).
    pub angular_z: f64,
    /// How long to hold the velocity, s. 0 = just observe.
    pub duration_s: f64,
}

/// A motion command the robot cannot answer (no camera frames after it,
/// say): the controller fails the step with `reason` at once.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct MotionFault {
    /// The command concerned ([`MotionFault::ANY_COMMAND`]: whichever is
    /// in flight).
    pub seq: u64,
    /// Why it will not be answered.
    pub reason: String,
}

impl MotionFault {
    /// The `seq` of a fault that fails whatever command is in flight (the
    /// base guard's: it stopped the base without knowing which command
    /// moved it).
    pub const ANY_COMMAND: u64 = u64::MAX;
}

/// A planar pose in the world frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose2D {
    /// m.
    pub x: f64,
    /// m.
    pub y: f64,
    /// Heading about +z, rad.
    pub yaw: f64,
}

/// The camera frames captured after motion `seq` ended.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraFrame {
    /// The command this frame answers.
    pub seq: u64,
    /// `rgb8`.
    pub color: Image,
    /// `32FC1` metres (NaN = no return) or `16UC1` millimetres (0 = no return).
    pub depth: Image,
}

impl CameraFrame {
    /// The frame borrowed (see [`CameraFrameView`]).
    pub fn view(&self) -> CameraFrameView<'_> {
        CameraFrameView {
            seq: self.seq,
            color: self.color.view(),
            depth: self.depth.view(),
        }
    }
}

/// A [`CameraFrame`] read in place from its payload (same wire bytes).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraFrameView<'a> {
    /// The command this frame answers.
    pub seq: u64,
    /// `rgb8` or `bgr8`.
    #[serde(borrow)]
    pub color: ImageView<'a>,
    /// `32FC1` metres or `16UC1` millimetres.
    #[serde(borrow)]
    pub depth: ImageView<'a>,
}

/// Tag attached (as the Zenoh attachment) to pose and odometry samples that
/// answer a command, so their ROS payloads stay untouched.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SeqTag {
    /// The command answered.
    pub seq: u64,
}

/// Move the robot to a pose: the sim twin teleports, the real robot drives
/// there. Answered by [`GotoReply`] once it has arrived.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GotoRequest {
    /// Sequence number, echoed.
    pub seq: u64,
    /// Where to go.
    pub target: Pose2D,
    /// Give up after this long, s.
    pub timeout_s: f64,
}

/// The robot has arrived (as close as it could).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GotoReply {
    /// The request answered.
    pub seq: u64,
    /// Where the robot actually is.
    pub achieved: Pose2D,
    /// How long the move took, s.
    pub elapsed_s: f64,
}

/// Keeps the robot's watchdog armed between commands.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Heartbeat {
    /// Sender's wall clock.
    pub stamp: Time,
    /// Increments per beat.
    pub counter: u64,
}

/// Emergency stop: engaged stops the robot at once and refuses motion until
/// released.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct EStop {
    /// true = stop now.
    pub engaged: bool,
    /// Who and why, for the log.
    pub reason: String,
    /// The operator's id for this press, echoed in every [`EStopAck`]
    /// (0: nobody waits for acknowledgements).
    pub press_id: u64,
}

impl EStop {
    /// An engage (`engaged`) or release nobody waits acknowledgements for.
    pub fn new(engaged: bool, reason: impl Into<String>) -> Self {
        Self {
            engaged,
            reason: reason.into(),
            press_id: 0,
        }
    }
}

/// One e-stop latch (site-wide, or one env's): engaged or not, why, and
/// when it last changed (the newer of two reports wins when a restarted
/// component merges what the network remembers).
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct LatchState {
    /// Motion refused while true.
    pub engaged: bool,
    /// The operator's reason of the last change.
    pub reason: String,
    /// Wall clock of the last change (zero: never changed).
    pub changed: Time,
}

/// The e-stop latches that apply to one env: the site's and its own. They
/// are independent: releasing one never clears the other.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct EStopState {
    /// The site-wide latch.
    pub site: LatchState,
    /// This env's latch.
    pub env: LatchState,
}

/// A robot agent's or twin's acknowledgement of an e-stop it received and
/// applied (the robot is already stopped when it is sent).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct EStopAck {
    /// The press acknowledged ([`EStop::press_id`]).
    pub press_id: u64,
    /// Who acknowledges (`robot_agent`, `sim_twin`).
    pub component: String,
    /// The env it serves.
    pub env: String,
    /// The latches in force after applying it.
    pub state: EStopState,
}

/// Whether localization is currently trustworthy.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TrackingStatus {
    /// false = poses stopped or are rejected; do not score on them.
    pub tracking: bool,
    /// Age of the last accepted pose, s.
    pub last_pose_age_s: f64,
    /// Human-readable cause.
    pub reason: String,
}
