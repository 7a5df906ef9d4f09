//! Sample messages of every type, shared by the runtime's integration tests.
#![allow(dead_code)]

use offworld_runtime::msg::*;
use offworld_runtime::{ErrorCode, WireError};

pub fn header() -> Header {
    Header::new(
        Time {
            sec: 1_700_000_123,
            nanosec: 456_789,
        },
        "base_link",
    )
}

pub fn twist() -> Twist {
    Twist {
        linear: Vector3 {
            x: 0.1,
            y: -0.0,
            z: 1e-9,
        },
        angular: Vector3 {
            x: 0.0,
            y: 0.25,
            z: -1.25,
        },
    }
}

pub fn pose() -> Pose {
    Pose {
        position: Point {
            x: 0.0109,
            y: -0.2034,
            z: 0.2838,
        },
        orientation: Quaternion::from_yaw(0.7),
    }
}

pub fn pose_stamped() -> PoseStamped {
    PoseStamped {
        header: Header::new(header().stamp, "world"),
        pose: pose(),
    }
}

pub fn odometry() -> Odometry {
    let mut cov = [0.0; 36];
    for (i, c) in cov.iter_mut().enumerate() {
        *c = i as f64 * 0.5 - 3.0;
    }
    Odometry {
        header: Header::new(header().stamp, "odom"),
        child_frame_id: "base_link".into(),
        pose: PoseWithCovariance {
            pose: pose(),
            covariance: cov,
        },
        twist: TwistWithCovariance {
            twist: twist(),
            covariance: cov.map(|c| -c),
        },
    }
}

/// A 3×2 rgb8 image (the size the interop facts were checked with).
pub fn image_rgb() -> Image {
    Image::packed(
        Header::new(header().stamp, "camera_color_optical_frame"),
        3,
        2,
        PixelEncoding::Rgb8,
        (0u8..18).collect(),
    )
}

/// A 2×2 32FC1 depth image with one invalid (NaN) pixel.
pub fn image_depth() -> Image {
    let depths = [0.5f32, 1.25, f32::NAN, 4.0];
    Image::packed(
        Header::new(header().stamp, "camera_depth_optical_frame"),
        2,
        2,
        PixelEncoding::Depth32FC1,
        depths.iter().flat_map(|d| d.to_le_bytes()).collect(),
    )
}

/// A 2×1 16UC1 depth image in millimetres.
pub fn image_depth_mm() -> Image {
    Image::packed(
        Header::new(header().stamp, "camera_depth_optical_frame"),
        2,
        1,
        PixelEncoding::Depth16UC1,
        [1500u16, 0].iter().flat_map(|d| d.to_le_bytes()).collect(),
    )
}

pub fn motion() -> MotionCommand {
    MotionCommand {
        seq: 42,
        linear_x: 0.07,
        angular_z: 1.25,
        duration_s: 1.2,
    }
}

pub fn camera_frame() -> CameraFrame {
    CameraFrame {
        seq: 42,
        color: image_rgb(),
        depth: image_depth(),
    }
}

pub fn goto_request() -> GotoRequest {
    GotoRequest {
        seq: 7,
        target: Pose2D {
            x: 1.0,
            y: -0.5,
            yaw: 3.0,
        },
        timeout_s: 30.0,
    }
}

pub fn goto_reply() -> GotoReply {
    GotoReply {
        seq: 7,
        achieved: Pose2D {
            x: 0.98,
            y: -0.51,
            yaw: 2.95,
        },
        elapsed_s: 12.5,
    }
}

pub fn spec() -> EnvSpec {
    EnvSpec {
        env_id: "sim/monolith-0".into(),
        task: "MonolithDiscrete".into(),
        world: "monolith".into(),
        action_space: ActionSpace::Discrete {
            n: 4,
            names: ["LEFT", "RIGHT", "FORWARD", "BACKWARD"]
                .map(String::from)
                .to_vec(),
        },
        native_height: 240,
        native_width: 320,
        depth_max_m: 5.0,
        max_episode_steps: 100,
    }
}

pub fn obs_array() -> ObsArray {
    ObsArray {
        height: 2,
        width: 3,
        channels: 1,
        dtype: DType::U8,
        data: vec![0, 10, 20, 30, 40, 255],
    }
}

pub fn open_request() -> OpenRequest {
    OpenRequest {
        token: "secret-token".into(),
        client_id: "client-1".into(),
        experiment_name: "dqn-depth".into(),
        resume_experiment: true,
        learning_type: LearningType::SimToReal,
        algorithm_mode: AlgorithmMode::Test,
        obs: ObsOptions {
            channels: Channels::Rgbd,
            height: 84,
            width: 84,
            depth_format: DepthFormat::Meters,
        },
    }
}

pub fn experiment() -> ExperimentInfo {
    ExperimentInfo {
        id: 3,
        name: "dqn-depth".into(),
        episodes: 12,
        steps: 840,
    }
}

pub fn open_reply() -> OpenReply {
    OpenReply {
        session_id: "s-1".into(),
        lease_until_unix_ms: 1_700_000_999_000,
        spec: spec(),
        experiment: experiment(),
    }
}

pub fn step_request() -> StepRequest {
    StepRequest {
        session_id: "s-1".into(),
        seq: 9,
        action: Action::Continuous(vec![0.5, -1.0]),
    }
}

pub fn step_reply() -> StepReply {
    StepReply {
        seq: 9,
        observation: obs_array(),
        reward: 1.0,
        terminated: true,
        truncated: false,
        info: StepInfo {
            episode_id: 4,
            step: 17,
            is_success: true,
            end_reason: "success".into(),
            pose_shared: true,
            x: 0.25,
            y: -0.5,
            yaw: 1.5,
            distance_to_goal: 0.125,
        },
    }
}

pub fn reset_request() -> ResetRequest {
    ResetRequest {
        session_id: "s-1".into(),
        seed: Seed::Fixed(1234),
    }
}

pub fn reset_reply() -> ResetReply {
    ResetReply {
        observation: obs_array(),
        info: StepInfo {
            episode_id: 5,
            step: 0,
            // Not empty: the cdr crate also reads an empty string written
            // with length 0 (not 1 + NUL), which the byte-flip test would
            // report as a misread; the strings of a wire test are not
            // semantic.
            end_reason: "-".into(),
            pose_shared: true,
            x: -1.0,
            y: 0.75,
            yaw: -3.0,
            distance_to_goal: 1.5,
            ..StepInfo::default()
        },
    }
}

pub fn episode_event() -> EpisodeEvent {
    EpisodeEvent {
        experiment: "dqn-depth".into(),
        episode_id: 4,
        step: 17,
        reward: 1.0,
        episode_return: 1.0,
        terminated: true,
        truncated: false,
        success: true,
        end_reason: "reached monolith".into(),
        experiment_id: 3,
        command_seq: 35,
    }
}

pub fn estop_state() -> EStopState {
    EStopState {
        site: LatchState {
            engaged: true,
            reason: "fire alarm".into(),
            changed: header().stamp,
        },
        env: LatchState::default(),
    }
}

pub fn env_status() -> EnvStatus {
    EnvStatus {
        env_id: "real/enclosure-a".into(),
        state: EnvState::Leased {
            until_unix_ms: 1_700_000_999_000,
            holder: "ada".into(),
        },
        estop: estop_state(),
        last_reset: ResetAccuracy::measure(
            Pose2D {
                x: 1.0,
                y: -0.5,
                yaw: 0.25,
            },
            Pose2D {
                x: 1.03,
                y: -0.46,
                yaw: 0.2,
            },
            41.5,
            1_700_000_998_000,
        ),
    }
}

pub fn wire_error() -> WireError {
    WireError::new(ErrorCode::Busy, "leased until 12:00 UTC")
}

/// Calls `$body` with `(name, sample)` for every message type.
#[macro_export]
macro_rules! for_each_sample {
    ($f:ident) => {{
        use $crate::common::*;
        $f("Twist", twist());
        $f("PoseStamped", pose_stamped());
        $f("Odometry", odometry());
        $f("Image rgb8", image_rgb());
        $f("Image 32FC1", image_depth());
        $f("Image 16UC1", image_depth_mm());
        $f("MotionCommand", motion());
        $f("CameraFrame", camera_frame());
        $f("SeqTag", SeqTag { seq: 5 });
        $f(
            "ClientTag",
            ClientTag {
                client_id: "3fa9c0d1e2b4a567".into(),
            },
        );
        $f(
            "MotionFault",
            MotionFault {
                seq: 12,
                reason: "no camera frames".into(),
            },
        );
        $f("GotoRequest", goto_request());
        $f("GotoReply", goto_reply());
        $f(
            "Heartbeat",
            Heartbeat {
                stamp: header().stamp,
                counter: 99,
            },
        );
        $f(
            "EStop",
            EStop {
                engaged: true,
                reason: "operator".into(),
                press_id: 0x1234_5678_9abc,
            },
        );
        $f("EStopState", estop_state());
        $f(
            "EStopAck",
            EStopAck {
                press_id: 7,
                component: "robot_agent".into(),
                env: "real/enclosure-a".into(),
                state: estop_state(),
            },
        );
        $f(
            "TrackingStatus",
            TrackingStatus {
                tracking: false,
                last_pose_age_s: 0.75,
                reason: "no poses".into(),
            },
        );
        $f("OpenRequest", open_request());
        $f("OpenReply", open_reply());
        $f("EnvSpec", spec());
        $f("StepRequest", step_request());
        $f(
            "StepRequest discrete",
            StepRequest {
                action: Action::Discrete(2),
                ..step_request()
            },
        );
        $f("StepReply", step_reply());
        $f("ResetRequest", reset_request());
        $f(
            "ResetRequest continue",
            ResetRequest {
                seed: Seed::Continue,
                ..reset_request()
            },
        );
        $f("ResetReply", reset_reply());
        $f(
            "CloseRequest",
            CloseRequest {
                session_id: "s-1".into(),
            },
        );
        $f(
            "CloseReply",
            CloseReply {
                experiment: experiment(),
            },
        );
        $f("EpisodeEvent", episode_event());
        $f("EnvStatus", env_status());
        $f(
            "EnvStatus maintenance",
            EnvStatus {
                env_id: "real/a".into(),
                state: EnvState::Maintenance {
                    message: "wheels".into(),
                    by: "ops".into(),
                    back_unix_ms: 1_700_000_999_000,
                },
                estop: EStopState::default(),
                last_reset: ResetAccuracy::default(),
            },
        );
        $f(
            "AdminRequest",
            AdminRequest::SetMaintenance {
                token: "op".into(),
                message: "m".into(),
                back_unix_ms: 0,
            },
        );
        $f(
            "AdminRequest revoke",
            AdminRequest::RevokeLease {
                token: "op".into(),
                reason: "demo".into(),
            },
        );
        $f(
            "AdminReply",
            AdminReply {
                user: "ops".into(),
                operator: true,
                status: env_status(),
            },
        );
        $f("WireError", wire_error());
        $f(
            "BookingRequest",
            BookingRequest::Make {
                token: "t".into(),
                start_unix_ms: 1_800_000_000_000,
                end_unix_ms: 1_800_000_900_000,
            },
        );
        $f("BookingRequest", BookingRequest::List { from_unix_ms: -1 });
        $f(
            "BookingRequest",
            BookingRequest::Cancel {
                token: "t".into(),
                id: 7,
            },
        );
        $f(
            "Bookings",
            Bookings {
                bookings: vec![Booking {
                    id: 7,
                    env_id: "real/enclosure-a".into(),
                    user: "alice".into(),
                    start_unix_ms: 1_800_000_000_000,
                    end_unix_ms: 1_800_000_900_000,
                }],
            },
        );
    }};
}
