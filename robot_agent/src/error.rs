//! Errors of the robot agent.

/// What can go wrong on the robot side.
#[derive(Debug, thiserror::Error)]
pub enum AgentError {
    /// The configuration is unusable.
    #[error("configuration: {0}")]
    Config(String),
    /// Zenoh refused an operation.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// A message could not be encoded.
    #[error("encoding: {0}")]
    Encode(String),
}

impl From<zenoh::Error> for AgentError {
    fn from(e: zenoh::Error) -> Self {
        AgentError::Zenoh(e.to_string())
    }
}

impl From<offworld_runtime::ContractError> for AgentError {
    fn from(e: offworld_runtime::ContractError) -> Self {
        AgentError::Config(e.to_string())
    }
}
