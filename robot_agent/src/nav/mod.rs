//! Reset navigation: drives the robot to a requested pose (position and
//! heading) using tracker poses and the known map.
//!
//! - [`OccupancyGrid::from_world`] rasterises the enclosure with walls,
//!   monolith and boulders inflated; built once per world.
//! - [`plan`] finds a path: A* with a clearance cost, then line-of-sight
//!   shortcutting; a start too close to something first leaves along a
//!   straight escape leg.
//! - [`PathFollower`] turns tracker poses into velocity commands until
//!   [`NavCommand::Arrived`]; [`PathFollower::off_path`] says when to
//!   re-plan (it never re-plans itself).
//! - [`Navigator`] ties planner and follower together for one reset and
//!   re-plans when the robot strays.
//! - [`estimate_travel_time`] predicts how long a path takes.
//!
//! The caller runs the loop (~20 Hz: latest pose → [`Navigator::step`] or
//! [`PathFollower::step`] → velocity to the robot), stops on `Arrived` or
//! an error, and owns the overall timeout.

mod config;
mod error;
mod estimate;
mod follow;
mod geometry;
mod grid;
mod navigator;
mod plan;
#[cfg(test)]
mod testkit;

pub use config::NavConfig;
pub use error::NavError;
pub use estimate::estimate_travel_time;
pub use follow::{NavCommand, PathFollower};
pub use geometry::Point;
pub use grid::OccupancyGrid;
pub use navigator::Navigator;
pub use plan::{plan, Path};
