//! Errors of the sim twin.

use std::path::{Path, PathBuf};

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
    /// The renderer's threads could not be started.
    #[error("the render threads could not start: {0}")]
    Threads(String),
    /// Zenoh refused an operation.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// A twin profile is unreadable, unwritable or invalid.
    #[error("{}", profile_message(path.as_deref(), field.as_deref(), reason))]
    Profile {
        /// The profile file, if the profile came from one.
        path: Option<PathBuf>,
        /// The field at fault (`motion.linear_gain`, `format`), if one is.
        field: Option<String>,
        /// What is wrong.
        reason: String,
    },
}

fn profile_message(path: Option<&Path>, field: Option<&str>, reason: &str) -> String {
    let mut message = String::from("twin profile");
    if let Some(path) = path {
        message.push_str(&format!(" {}", path.display()));
    }
    if let Some(field) = field {
        message.push_str(&format!(": field `{field}`"));
    }
    format!("{message}: {reason}")
}

impl From<SimError> for WireError {
    fn from(e: SimError) -> Self {
        match e {
            SimError::BadCommand(m) => WireError::bad_request(m),
            // A caller's file or values.
            e @ SimError::Profile { .. } => WireError::bad_request(e.to_string()),
            other => WireError::internal(other.to_string()),
        }
    }
}
