//! The OffWorld gym server.
//!
//! It owns the task: episodes, rewards, termination and resets computed from
//! the robot's pose; sessions, leases and access; experiment records in
//! SQLite. It drives whatever embodies the robot under an env's namespace —
//! the sim twin or the real robot + tracker agents — and never knows which.
//!
//! - [`task`]: the four tasks as data; action validation and mapping.
//! - [`episode`]: reward/termination rules and the seeded spawn sampler.
//! - [`observation`]: client observations from camera frames.
//! - [`link`]: commands out, frames and poses back; fails fast when the
//!   robot, its tracker or the way to them is gone.
//! - [`step`]: one command's life on the link, from sent to judged and
//!   replied (once each).
//! - [`estops`]: the site and env e-stop latches each env obeys.
//! - [`store`]: users, experiments, episodes, leaderboard.
//! - [`env`]: one env's sessions, leases and request handlers.
//! - [`admission`]: request limits (size, per-client rate and queue, per-env
//!   queue), decided without waiting.
//! - [`server`]: many envs served over Zenoh.
//! - `start`: a step's work begun on the thread that received it.
//! - `cli`: `env_controller serve | users | experiments | leaderboard | estop`
//!   (the `programs` feature: the `offworld` command enables it, an
//!   embedding such as the Python package need not).
//!
//! It links no simulator: in-process twins are put beside it by
//! `offworld_deploy`.

pub mod admission;
#[cfg(feature = "programs")]
pub mod cli;
pub mod env;
pub mod episode;
mod error;
pub mod estops;
pub mod link;
pub mod observation;
pub mod server;
mod start;
pub mod step;
pub mod store;
pub mod task;
#[cfg(test)]
mod test_strategies;

pub use admission::RequestLimits;
pub use env::{EnvOptions, EnvServer};
pub use error::ControllerError;
pub use server::Controller;
pub use store::Store;
pub use task::Task;
