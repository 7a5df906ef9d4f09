//! The physics twin of the OffWorld enclosure.
//!
//! It stands in for the robot and the tracker: it takes the same motion
//! commands on the same keys and answers with the same frames and poses, so
//! nothing upstream can tell it from the real enclosure except by namespace.
//!
//! - [`world`]: enclosure definitions (re-exported from the contract).
//! - [`terrain`], [`scene`]: the seeded lunar floor and the static boxes.
//! - [`physics`]: the ROSbot in rapier3d.
//! - [`camera`]: intrinsics and the ray-cast RGBD renderers.
//! - [`tracker`]: the simulated Vive tracker.
//! - [`twin`]: all of it as one deterministic simulator.
//! - [`profile`]: the twin profile, what makes the twin match one physical
//!   robot (`docs/twin-profile.md`).
//! - [`overhead`]: the enclosure's overhead camera (top-down view for spectators).
//! - [`ros_out`]: twin state as the ROS messages a real robot publishes.
//! - [`node`]: the twin served over Zenoh (lockstep or real time).
//!
//! The twin behaving like the hardware (ROS 2 topics and a raw tracker
//! stream) for the real stack to run against is `offworld_deploy::hardware`.

pub mod camera;
#[cfg(feature = "programs")]
pub mod cli;
mod error;
pub mod frame_payload;
pub mod node;
pub mod overhead;
pub mod physics;
pub mod profile;
pub mod ros_out;
pub mod scene;
pub mod terrain;
pub mod tracker;
pub mod twin;

pub use error::SimError;
pub use node::{Clock, NodeOptions, Stepping, TwinNode, TwinStats};
/// World definitions live in the contract (shared with the controller and agents).
pub use offworld_runtime::world;
pub use offworld_runtime::WorldSpec;
pub use physics::PlanarPose;
pub use profile::{CameraProfile, DepthProfile, MotionProfile, TwinProfile, PROFILE_FORMAT};
pub use twin::{Randomization, SimTwin, TwinConfig, RENDER_THREADS_LIMIT};
