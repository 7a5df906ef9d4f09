//! robot_agent — runs on the robot's computer: executes motion commands on
//! the robot's ROS 2 stack over Zenoh (rmw_zenoh keys, CDR), publishes the
//! camera frames and odometry that answer them, and stops the motors when
//! commands and controller heartbeats stop coming.
//!
//! Not built yet: this crate reserves its place in the workspace. The
//! contract it will speak (`cmd`, `obs`, `odom`, `goto`, `heartbeat`,
//! `estop`, `alive/robot_agent`) is defined in `offworld-runtime`, and the
//! sim twin already speaks the same keys.
