//! Why a reset navigation cannot be planned.

/// A navigation request that cannot be served. The caller stops the robot
/// and reports the reset as failed; none of these is retried internally.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NavError {
    /// A pose coordinate is NaN or infinite.
    #[error("{what} pose is not finite")]
    NonFinite {
        /// `"start"` or `"goal"`.
        what: &'static str,
    },
    /// The goal position is not strictly inside the enclosure walls.
    #[error("goal ({x:.3}, {y:.3}) is outside the enclosure")]
    GoalOutsideEnclosure {
        /// m.
        x: f64,
        /// m.
        y: f64,
    },
    /// The goal position is inside an obstacle or closer to one (or to a
    /// wall) than the inflation radius: the robot cannot stand there.
    #[error("goal ({x:.3}, {y:.3}) is inside an obstacle or its inflation")]
    GoalBlocked {
        /// m.
        x: f64,
        /// m.
        y: f64,
    },
    /// The start position (tracker pose) is not strictly inside the walls:
    /// the tracker and the map disagree.
    #[error("start ({x:.3}, {y:.3}) is outside the enclosure")]
    StartOutsideEnclosure {
        /// m.
        x: f64,
        /// m.
        y: f64,
    },
    /// The start position lies in an obstacle footprint: the tracker and
    /// the map disagree.
    #[error("start ({x:.3}, {y:.3}) is inside an obstacle footprint")]
    StartInsideObstacle {
        /// m.
        x: f64,
        /// m.
        y: f64,
    },
    /// The start is inside inflated space and no free cell connected to the
    /// goal can be reached in a straight line within the escape distance.
    #[error("start ({x:.3}, {y:.3}) is boxed in: no free space within the escape distance")]
    StartBlocked {
        /// m.
        x: f64,
        /// m.
        y: f64,
    },
    /// Start and goal are in free space that is not connected.
    #[error("goal is unreachable from the start")]
    Unreachable,
    /// A [`NavConfig`](super::NavConfig) value is out of range.
    #[error("invalid navigation config: {0}")]
    InvalidConfig(&'static str),
    /// The world's geometry is unusable (empty enclosure, non-finite sizes).
    #[error("invalid map: {0}")]
    InvalidMap(&'static str),
}
