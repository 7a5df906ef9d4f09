//! The OffWorld Gym contract: everything two components must agree on to
//! talk over Zenoh, defined once.
//!
//! - [`keys`]: the key space `offworld/@v1/<realm>/<name>/<topic>`;
//!   nothing else formats keys.
//! - [`msg`]: message types — ROS 2 layouts where a ROS type exists, our own
//!   request/reply types otherwise.
//! - [`named`]: enums named by fixed strings, read back with one error.
//! - [`estop`]: the site and env e-stop latches, merged by age.
//! - [`ros2`]: key expressions of a ROS 2 robot's topics (rmw_zenoh or
//!   zenoh-bridge-ros2dds) and rmw_zenoh's attachment.
//! - [`codec`]: little-endian CDR with the encapsulation header; decoding
//!   untrusted bytes never panics.
//! - [`wire`]: typed put / request / reply over a Zenoh session.
//! - [`session`]: opening sessions from files, environment or endpoints.
//! - [`pool`]: recycled payload buffers.
//! - [`preview`]: the camera's preview for viewers, thinned and droppable.
//! - [`seal`]: sealed control messages of a real site.
//! - [`shutdown`]: SIGINT, SIGTERM and SIGHUP as one "stop cleanly" (a
//!   session still waiting for its endpoint gives up on it).
//! - [`world`]: enclosure definitions (`runtime/worlds/*.toml`) every
//!   component reads: geometry, task, robot, camera.
//! - [`WireError`]: the one typed error every reply can carry.
//!
//! The client library is `offworld_client`; what programs share (flags,
//! logging, entry point) is `offworld_program`.

pub mod codec;
mod error;
pub mod estop;
pub mod keys;
pub mod msg;
pub mod named;
pub mod pool;
pub mod preview;
mod resolution;
pub mod ros2;
pub mod seal;
pub mod session;
pub mod shutdown;
pub mod wire;
pub mod world;

pub use error::{ContractError, DecodeError, EncodeError, ErrorCode, WireError};
pub use keys::{Component, EnvId, Realm, Topic};
pub use resolution::Resolution;
pub use session::SessionConfig;
pub use wire::RequestError;
pub use world::{WorldError, WorldSpec};
