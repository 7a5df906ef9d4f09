//! robot_agent — runs on the robot's computer.
//!
//! - Executes the controller's motion commands (`cmd`) on the robot's ROS 2
//!   stack over Zenoh ([`ros2::Ros2Robot`]: `geometry_msgs/Twist` out,
//!   `sensor_msgs/Image` colour + depth and `nav_msgs/Odometry` in, rmw_zenoh
//!   or zenoh-bridge-ros2dds keys), holds the velocity for the command's
//!   duration, stops, lets the robot settle, then publishes the first colour
//!   and depth frames captured after the motion ended on `obs`, tagged with
//!   the command's sequence number (odometry on `odom`); the same frame on
//!   `preview` for viewers while someone watches (`offworld_runtime::preview`).
//! - Safety ([`watchdog`], [`limiter`]): zero velocity and motion refused
//!   while no command or controller heartbeat arrived within the window
//!   (default 200 ms) or the controller's liveliness token is gone; `estop`
//!   (per env and site-wide) acts immediately; speeds and accelerations are
//!   clamped with a warning. An engaged e-stop survives an agent restart
//!   when [`latch`] keeps it on disk.
//! - Reset navigation ([`nav`]): `goto` drives to a pose on the tracker's
//!   localization with an A* plan over the known map and a path follower,
//!   with a timeout and typed failures.
//!
//! - Defence in depth ([`guard`]): the `base_guard` process, separate from
//!   the agent, zeroes the base when the agent dies, freezes or goes silent
//!   mid-motion; the agent refuses to move until it is there
//!   (`require_base_guard`).
//!
//! The hardware sits behind [`hardware::RobotHardware`]; [`agent::spawn`]
//! runs the node.

pub mod agent;
pub mod base_check;
pub mod cli;
pub mod config;
mod error;
pub mod guard;
pub mod guard_cli;
pub mod hardware;
pub mod latch;
pub mod limiter;
pub mod nav;
pub mod ros2;
pub mod watchdog;

pub use agent::{spawn, AgentHandle, NodeHandle};
pub use config::{AgentConfig, Limits};
pub use error::AgentError;
pub use guard::GuardConfig;
pub use ros2::{CmdVelPublisher, Ros2Robot};
