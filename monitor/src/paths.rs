//! Entity paths of the recording: every env under its own root
//! `envs/<realm>/<name>`, so many envs share one recording.
//!
//! ```text
//! /envs/<realm>/<name>                 ViewCoordinates (right-handed, z up), static
//! ├── world/                           static, once per env (re-logged if the world changes)
//! │   ├── terrain                      Mesh3D: flat ground at the terrain's mean height
//! │   ├── walls                        Boxes3D (wireframe)
//! │   ├── monolith                     Boxes3D
//! │   ├── boulders                     Boxes3D (worlds with obstacles only)
//! │   ├── boundary                     LineStrips3D: the task's out-of-bounds box
//! │   └── success_radius               LineStrips3D: circle around the monolith
//! ├── robot                            Transform3D: tracker pose of base_link (one row per `pose`)
//! │   ├── body                         Boxes3D, static
//! │   └── camera                       Transform3D (mount) + Pinhole, static
//! │       ├── color                    Image (one row per `obs`)
//! │       └── depth                    DepthImage (one row per `obs`)
//! ├── trajectory                       LineStrips3D: this episode's tracker path (≤ 10 Hz)
//! ├── odom                             Transform3D: odom frame in the world (anchored at each reset)
//! │   └── robot                        Transform3D: odometry pose (one row per `odom`)
//! │       └── body                     Boxes3D (wireframe), static
//! ├── overhead/<camera>                Image (one row per overhead frame)
//! ├── metrics/
//! │   ├── linear_x, angular_z          Scalars, one row per `cmd`
//! │   ├── reward, return               Scalars, one row per `reward` event
//! │   └── success, episode_length      Scalars, one row per finished episode
//! └── events                           TextLog: episode start/end, tracking, status, e-stop, liveliness
//! /events                              TextLog: site-wide e-stop
//! /monitor/{dropped_frames,dropped_messages,decode_errors}   Scalars, the monitor's own health
//! ```
//!
//! Timelines: `step` (sequence: the env's motion-command `seq`; data without
//! a seq of its own takes the env's latest), `sim_time` (duration: the
//! message header stamp — seconds since the twin started, or since the epoch
//! on a real robot), `wall_time` (timestamp: when the monitor received it;
//! in a replay, when the recorder did).

use offworld_runtime::EnvId;

/// Root of one env: `envs/<realm>/<name>`.
pub fn env_root(env: &EnvId) -> String {
    format!("envs/{}/{}", env.realm().as_str(), env.name())
}

/// `envs/<realm>/<name>/<relative>` (joined without `format!`: the monitor
/// builds a few of these per step).
pub fn env_path(env: &EnvId, relative: &str) -> String {
    [
        "envs/",
        env.realm().as_str(),
        "/",
        env.name(),
        "/",
        relative,
    ]
    .concat()
}

/// Static world geometry.
pub const WORLD: &str = "world";
/// Ground mesh.
pub const TERRAIN: &str = "world/terrain";
/// Enclosure walls.
pub const WALLS: &str = "world/walls";
/// The goal.
pub const MONOLITH: &str = "world/monolith";
/// Obstacles.
pub const BOULDERS: &str = "world/boulders";
/// The task's boundary box.
pub const BOUNDARY: &str = "world/boundary";
/// Success circle around the monolith.
pub const SUCCESS_RADIUS: &str = "world/success_radius";
/// The robot (tracker pose).
pub const ROBOT: &str = "robot";
/// The robot's body box.
pub const ROBOT_BODY: &str = "robot/body";
/// The RGBD camera (pinhole).
pub const CAMERA: &str = "robot/camera";
/// Colour images.
pub const COLOR: &str = "robot/camera/color";
/// Depth images.
pub const DEPTH: &str = "robot/camera/depth";
/// This episode's tracker path.
pub const TRAJECTORY: &str = "trajectory";
/// The odometry frame, anchored in the world.
pub const ODOM: &str = "odom";
/// The odometry pose.
pub const ODOM_ROBOT: &str = "odom/robot";
/// The odometry pose's body box.
pub const ODOM_BODY: &str = "odom/robot/body";
/// Parent of the overhead cameras.
pub const OVERHEAD: &str = "overhead";
/// Commanded forward speed.
pub const LINEAR_X: &str = "metrics/linear_x";
/// Commanded yaw rate.
pub const ANGULAR_Z: &str = "metrics/angular_z";
/// Step reward.
pub const REWARD: &str = "metrics/reward";
/// Episode return so far.
pub const RETURN: &str = "metrics/return";
/// 1 if a finished episode reached the monolith, else 0.
pub const SUCCESS: &str = "metrics/success";
/// Steps of a finished episode.
pub const EPISODE_LENGTH: &str = "metrics/episode_length";
/// How far from its spawn pose the last reset left the robot, m.
pub const RESET_POSITION_ERROR: &str = "metrics/reset/position_error_m";
/// The last reset's heading error, rad.
pub const RESET_YAW_ERROR: &str = "metrics/reset/yaw_error_rad";
/// How long the last reset took, s.
pub const RESET_DURATION: &str = "metrics/reset/duration_s";
/// Per-env event log.
pub const EVENTS: &str = "events";

/// One overhead camera: `overhead/<camera>`.
pub fn overhead(camera: &str) -> String {
    format!("{OVERHEAD}/{camera}")
}

/// Site-wide event log (global e-stop).
pub const SITE_EVENTS: &str = "events";
/// Frames the monitor dropped (recording-level).
pub const MONITOR_DROPPED_FRAMES: &str = "monitor/dropped_frames";
/// Messages the monitor dropped.
pub const MONITOR_DROPPED_MESSAGES: &str = "monitor/dropped_messages";
/// Undecodable messages the monitor skipped.
pub const MONITOR_DECODE_ERRORS: &str = "monitor/decode_errors";

/// Timeline: the env's motion-command sequence number.
pub const TIMELINE_STEP: &str = "step";
/// Timeline: message header stamps.
pub const TIMELINE_SIM_TIME: &str = "sim_time";
/// Timeline: when the monitor received the message.
pub const TIMELINE_WALL_TIME: &str = "wall_time";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn env_paths_nest_under_realm_and_name() {
        let env = EnvId::real("enclosure-a").expect("valid");
        assert_eq!(env_root(&env), "envs/real/enclosure-a");
        assert_eq!(
            env_path(&env, COLOR),
            "envs/real/enclosure-a/robot/camera/color"
        );
        assert_eq!(
            env_path(&env, &overhead("cam1")),
            "envs/real/enclosure-a/overhead/cam1"
        );
    }
}
