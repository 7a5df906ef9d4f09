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
//! - [`node`]: the twin served over Zenoh.

pub mod camera;
mod error;
pub mod node;
pub mod physics;
pub mod scene;
pub mod terrain;
pub mod tracker;
pub mod twin;

pub use error::SimError;
pub use node::{Clock, TwinNode};
/// World definitions live in the contract (shared with the controller and agents).
pub use offworld_runtime::world;
pub use offworld_runtime::WorldSpec;
pub use physics::PlanarPose;
pub use twin::{Randomization, SimTwin, TwinConfig};
