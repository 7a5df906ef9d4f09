//! The agent's configuration: which robot graph to drive, its limits and
//! the safety timings. Loaded from TOML; every field has a default that
//! fits a ROSbot 2 on rmw_zenoh.

use std::path::{Path, PathBuf};
use std::time::Duration;

use offworld_runtime::ros2::{KeyStyle, RobotTopics, RosGraph};
use offworld_runtime::WorldSpec;
use serde::{Deserialize, Serialize};

use crate::base_check::BaseCheck;
use crate::error::AgentError;
use crate::guard::GuardConfig;
use crate::nav::NavConfig;

/// Velocity and acceleration limits enforced on every command.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Limits {
    /// |linear x| ≤ this, m/s.
    pub max_linear: f64,
    /// |angular z| ≤ this, rad/s.
    pub max_angular: f64,
    /// Linear acceleration, m/s².
    pub max_linear_accel: f64,
    /// Angular acceleration, rad/s².
    pub max_angular_accel: f64,
}

impl Default for Limits {
    /// The ROSbot's range (the continuous action space's physical range).
    fn default() -> Self {
        Self {
            max_linear: 0.7,
            max_angular: 2.5,
            max_linear_accel: 1.5,
            max_angular_accel: 12.0,
        }
    }
}

/// Everything the agent needs besides a Zenoh session and an env id.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AgentConfig {
    /// How the robot's ROS 2 topics appear in Zenoh.
    pub key_style: KeyStyle,
    /// The robot's ROS 2 namespace (`""` = root).
    pub ros_namespace: String,
    /// The robot's topic names.
    pub topics: RobotTopics,
    /// Limits clamped (with a warning) on every command.
    pub limits: Limits,
    /// Stop when neither a command nor a controller heartbeat arrived for
    /// this long, ms.
    pub watchdog_ms: u64,
    /// Wait after the wheels stop before capturing the answer, ms.
    pub settle_ms: u64,
    /// Give up on camera frames after this long, ms.
    pub frame_timeout_ms: u64,
    /// A command in progress fails at once when no camera frame arrived
    /// for this long (the camera, its driver or the robot's computer is
    /// down), ms.
    pub camera_stale_ms: u64,
    /// Velocity commands per second while moving.
    pub control_hz: f64,
    /// A tracker pose older than this cannot steer navigation, ms.
    pub pose_stale_ms: u64,
    /// A reset drive held still this long (watchdog tripped by a
    /// heartbeat gap, or no fresh tracker pose) gives up, ms. Shorter
    /// holds are ridden out: the robot stops and drives on when the
    /// heartbeats or poses are back.
    pub nav_hold_ms: u64,
    /// The enclosure layout (built-in world name or TOML path): the map
    /// reset navigation plans on.
    pub world: String,
    /// Reset navigation tuning.
    pub nav: NavConfig,
    /// File that remembers an engaged e-stop across agent restarts (see
    /// [`crate::latch`]); `None`: an e-stop lasts as long as the process.
    pub estop_latch: Option<PathBuf>,
    /// The site's command key file ([`offworld_runtime::seal`]): when set,
    /// the agent obeys only commands, heartbeats and reset drives sealed
    /// with it (by the real-site controller); anything else is ignored and
    /// logged.
    pub command_key: Option<PathBuf>,
    /// The site's tracker key file: when set, reset navigation steers only
    /// on poses and tracking reports sealed with it (by the tracker agent).
    pub tracker_key: Option<PathBuf>,
    /// Refuse to move until the robot's independent base guard
    /// ([`crate::guard`], the `base_guard` process) declares itself: without
    /// it, a killed or frozen agent leaves a base without its own command
    /// timeout driving at its last velocity. `false` only for a base whose
    /// own command timeout (e.g. ros2_control's `cmd_vel_timeout`) was
    /// verified.
    pub require_base_guard: bool,
    /// Without the base guard: the base driver's own command timeout, ms,
    /// which the agent verifies before the first motion (a slow turn, then
    /// silence: the base must stop within it, see [`crate::base_check`]).
    pub base_cmd_timeout_ms: u64,
    /// Skip that check: the operator vouches for the base's timeout.
    pub skip_base_timeout_check: bool,
    /// The base guard's timings (read by `base_guard`).
    pub guard: GuardConfig,
}

impl Default for AgentConfig {
    fn default() -> Self {
        Self {
            key_style: KeyStyle::default(),
            ros_namespace: String::new(),
            topics: RobotTopics::default(),
            limits: Limits::default(),
            watchdog_ms: 200,
            settle_ms: 250,
            frame_timeout_ms: 2000,
            camera_stale_ms: 500,
            control_hz: 50.0,
            pose_stale_ms: 500,
            nav_hold_ms: 3000,
            world: "monolith".into(),
            nav: NavConfig::default(),
            estop_latch: None,
            command_key: None,
            tracker_key: None,
            require_base_guard: true,
            base_cmd_timeout_ms: 500,
            skip_base_timeout_check: false,
            guard: GuardConfig::default(),
        }
    }
}

impl AgentConfig {
    /// Reads `path`, or the defaults (a ROSbot on rmw_zenoh) without one.
    pub fn load_or_default(path: Option<&Path>) -> Result<Self, AgentError> {
        path.map_or_else(|| Ok(Self::default()), Self::load)
    }

    /// Reads a TOML file.
    pub fn load(path: &Path) -> Result<Self, AgentError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| AgentError::Config(format!("{}: {e}", path.display())))?;
        let config: Self = toml::from_str(&text)
            .map_err(|e| AgentError::Config(format!("{}: {e}", path.display())))?;
        config.validate()?;
        Ok(config)
    }

    /// Rejects values that would make the robot unsafe or the agent stuck.
    pub fn validate(&self) -> Result<(), AgentError> {
        let l = &self.limits;
        let positive = [
            l.max_linear,
            l.max_angular,
            l.max_linear_accel,
            l.max_angular_accel,
            self.control_hz,
        ];
        if positive.iter().any(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(AgentError::Config(
                "limits and control_hz must be finite and positive".into(),
            ));
        }
        if self.control_hz > 1000.0 {
            return Err(AgentError::Config(format!(
                "control_hz must be at most 1000, got {}",
                self.control_hz
            )));
        }
        if self.watchdog_ms == 0 || self.watchdog_ms > 5_000 {
            return Err(AgentError::Config(format!(
                "watchdog_ms must be in 1..=5000, got {}",
                self.watchdog_ms
            )));
        }
        if !(50..=10_000).contains(&self.camera_stale_ms) {
            return Err(AgentError::Config(format!(
                "camera_stale_ms must be in 50..=10000, got {}",
                self.camera_stale_ms
            )));
        }
        if self.nav_hold_ms == 0 || self.nav_hold_ms > 60_000 {
            return Err(AgentError::Config(format!(
                "nav_hold_ms must be in 1..=60000, got {}",
                self.nav_hold_ms
            )));
        }
        if self.base_cmd_timeout_ms == 0 || self.base_cmd_timeout_ms > 5_000 {
            return Err(AgentError::Config(format!(
                "base_cmd_timeout_ms must be in 1..=5000, got {}",
                self.base_cmd_timeout_ms
            )));
        }
        self.guard.validate()?;
        self.graph()?;
        Ok(())
    }

    /// The robot's ROS graph.
    pub fn graph(&self) -> Result<RosGraph, AgentError> {
        Ok(RosGraph::new(self.key_style.clone(), &self.ros_namespace)?)
    }

    /// The enclosure map.
    pub fn world_spec(&self) -> Result<WorldSpec, AgentError> {
        let world = if self.world.ends_with(".toml") {
            WorldSpec::load(Path::new(&self.world))
        } else {
            WorldSpec::builtin(&self.world)
        };
        world.map_err(|e| AgentError::Config(e.to_string()))
    }

    /// The start-up check of the base's own command timeout: only when no
    /// base guard is required and the operator did not skip it.
    pub fn base_check(&self) -> BaseCheck {
        if self.require_base_guard || self.skip_base_timeout_check {
            BaseCheck::skipped()
        } else {
            BaseCheck::new(Duration::from_millis(self.base_cmd_timeout_ms))
        }
    }

    /// The watchdog window.
    pub fn watchdog(&self) -> Duration {
        Duration::from_millis(self.watchdog_ms)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_example_file_is_the_default_configuration() -> Result<(), AgentError> {
        let path = offworld_test_support::package_dir().join("robot.example.toml");
        assert_eq!(AgentConfig::load(&path)?, AgentConfig::default());
        Ok(())
    }

    #[test]
    fn unsafe_values_are_typed_errors() {
        let config = AgentConfig {
            watchdog_ms: 0,
            ..AgentConfig::default()
        };
        assert!(matches!(config.validate(), Err(AgentError::Config(_))));
        let mut config = AgentConfig::default();
        config.limits.max_linear = f64::NAN;
        assert!(matches!(config.validate(), Err(AgentError::Config(_))));
        let parsed: Result<AgentConfig, _> = toml::from_str("watchdog = 5");
        assert!(parsed.is_err(), "unknown fields are refused");
    }
}
