//! Errors of the sim twin.

use offworld_runtime::WireError;

/// What can go wrong in the twin.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// No built-in world of that name.
    #[error("unknown world `{0}` (built-in: monolith, monolith_obstacle)")]
    UnknownWorld(String),
    /// A world file is unreadable or invalid.
    #[error("invalid world: {0}")]
    World(String),
    /// A command or request with impossible values.
    #[error("bad command: {0}")]
    BadCommand(String),
    /// A file could not be written.
    #[error("io: {0}")]
    Io(String),
    /// Zenoh refused an operation.
    #[error("zenoh: {0}")]
    Zenoh(String),
}

impl From<SimError> for WireError {
    fn from(e: SimError) -> Self {
        match e {
            SimError::BadCommand(m) => WireError::bad_request(m),
            other => WireError::internal(other.to_string()),
        }
    }
}
