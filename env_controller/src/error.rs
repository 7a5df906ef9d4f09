//! Errors of the controller.

use offworld_runtime::WireError;

/// What can go wrong inside the controller.
#[derive(Debug, thiserror::Error)]
pub enum ControllerError {
    /// Bad configuration (task, world, tokens).
    #[error("configuration: {0}")]
    Config(String),
    /// The database failed.
    #[error("store: {0}")]
    Store(String),
    /// A value in a request (or a command line) is not acceptable; the
    /// message says which and what would be.
    #[error("{0}")]
    InvalidArgument(String),
    /// Something that must exist does not.
    #[error("{0}")]
    NotFound(String),
    /// Something that must not exist does.
    #[error("{0}")]
    Conflict(String),
    /// Zenoh refused an operation (declaring a key expression, a
    /// publisher, a subscriber or a queryable).
    #[error("zenoh: {0}")]
    Zenoh(#[from] zenoh::Error),
    /// What an env needs never came online, or could not start (its twin,
    /// its robot); the message names it.
    #[error("{0}")]
    Offline(String),
    /// A session could not be opened on the deployment (unreachable,
    /// misconfigured).
    #[error(transparent)]
    Session(#[from] offworld_runtime::ContractError),
    /// The deployment answered a request with an error.
    #[error(transparent)]
    Remote(#[from] WireError),
    /// Someone else holds it (a booked slot).
    #[error("{0}")]
    Busy(String),
    /// Not allowed for this user.
    #[error("{0}")]
    Unauthorized(String),
    /// Episodes cannot be recorded where asked (checked at start).
    #[error("{0}")]
    Record(#[from] offworld_recorder::RecordError),
}

impl From<ControllerError> for WireError {
    fn from(e: ControllerError) -> Self {
        match e {
            ControllerError::NotFound(m) => WireError::not_found(m),
            ControllerError::InvalidArgument(m) => WireError::bad_request(m),
            ControllerError::Conflict(m) => WireError::bad_request(m),
            ControllerError::Config(m) => WireError::bad_request(m),
            ControllerError::Busy(m) => WireError::busy(m),
            ControllerError::Unauthorized(m) => WireError::unauthorized(m),
            // Store details stay in the server log; a Zenoh refusal is named.
            ControllerError::Store(m) => {
                tracing::error!("store failure: {m}");
                WireError::internal("the experiment store failed; the episode was not recorded")
            }
            ControllerError::Zenoh(e) => WireError::internal(format!("zenoh: {e}")),
            ControllerError::Offline(m) => WireError::unavailable(m),
            ControllerError::Session(e) => WireError::from(e),
            ControllerError::Remote(e) => e,
            ControllerError::Record(e) => WireError::internal(e.to_string()),
        }
    }
}
