//! The robot behind a trait: what the agent needs from a base and a camera.
//! [`crate::ros2::Ros2Robot`] is the production backend.

use std::future::Future;
use std::sync::Arc;
use std::time::Instant;

use offworld_runtime::msg::{Image, Odometry};
use tokio::sync::watch;

use crate::error::AgentError;
use crate::limiter::Velocity;

/// One sensor message and when it arrived.
#[derive(Debug, Clone)]
pub struct Received<T> {
    /// The message.
    pub msg: Arc<T>,
    /// Arrival time on the agent's clock.
    pub at: Instant,
}

/// The newest message of every sensor.
#[derive(Debug, Clone, Default)]
pub struct Sensors {
    /// Colour image.
    pub color: Option<Received<Image>>,
    /// Depth image.
    pub depth: Option<Received<Image>>,
    /// Wheel odometry.
    pub odom: Option<Received<Odometry>>,
}

/// A mobile base with an RGBD camera.
pub trait RobotHardware: Send + Sync + 'static {
    /// Commands a body velocity (the agent repeats it at its control rate).
    fn drive(&self, velocity: Velocity) -> impl Future<Output = Result<(), AgentError>> + Send;

    /// The newest sensor messages, updated as they arrive.
    fn sensors(&self) -> watch::Receiver<Sensors>;
}
