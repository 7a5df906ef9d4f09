//! Errors of the sim twin.

use offworld_runtime::{WireError, WorldError};

/// What can go wrong in the twin.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// A world file is unknown, unreadable or invalid.
    #[error(transparent)]
    World(#[from] WorldError),
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
