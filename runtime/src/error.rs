//! Errors: the typed error that crosses the wire ([`WireError`]) and the
//! local errors of this crate.

use serde::{Deserialize, Serialize};

/// Stable error codes carried on the wire. The numbers never change meaning;
/// new codes are only ever added.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(into = "u16", try_from = "u16")]
#[repr(u16)]
pub enum ErrorCode {
    /// The request is malformed or its values are invalid (bad action, bad options).
    BadRequest = 400,
    /// Missing, unknown or expired credentials, lease or booking.
    Unauthorized = 401,
    /// The env, session or experiment does not exist.
    NotFound = 404,
    /// Not now, someone else first: the env is leased or booked by someone
    /// else (the message says until when), or the controller is at one of
    /// its request limits — this env's queue is full, or this client has
    /// too many requests queued or sends them too fast (the message says
    /// which limit and when to retry). Nothing was done; retry later.
    Busy = 409,
    /// The request is valid but not now: step before reset, step after the episode ended.
    InvalidState = 412,
    /// The env is in maintenance, offline, or tracking is lost.
    Unavailable = 503,
    /// A component did not answer in time.
    Timeout = 504,
    /// Anything else; a bug or a failed dependency.
    Internal = 500,
}

impl ErrorCode {
    /// Every code, for tables and bindings.
    pub const ALL: [ErrorCode; 8] = [
        ErrorCode::BadRequest,
        ErrorCode::Unauthorized,
        ErrorCode::NotFound,
        ErrorCode::Busy,
        ErrorCode::InvalidState,
        ErrorCode::Unavailable,
        ErrorCode::Timeout,
        ErrorCode::Internal,
    ];

    /// A short, stable name (used for Python exception classes).
    pub fn name(self) -> &'static str {
        match self {
            ErrorCode::BadRequest => "BadRequest",
            ErrorCode::Unauthorized => "Unauthorized",
            ErrorCode::NotFound => "NotFound",
            ErrorCode::Busy => "Busy",
            ErrorCode::InvalidState => "InvalidState",
            ErrorCode::Unavailable => "Unavailable",
            ErrorCode::Timeout => "Timeout",
            ErrorCode::Internal => "Internal",
        }
    }
}

impl From<ErrorCode> for u16 {
    fn from(code: ErrorCode) -> u16 {
        code as u16
    }
}

impl TryFrom<u16> for ErrorCode {
    type Error = String;
    fn try_from(value: u16) -> Result<Self, Self::Error> {
        ErrorCode::ALL
            .into_iter()
            .find(|c| *c as u16 == value)
            .ok_or_else(|| format!("unknown error code {value}"))
    }
}

/// The typed error reply of every queryable: a stable code and a message for humans.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, thiserror::Error)]
#[error("{} ({}): {message}", code.name(), *code as u16)]
pub struct WireError {
    /// Machine-readable kind.
    pub code: ErrorCode,
    /// Human-readable explanation (never contains secrets).
    pub message: String,
}

impl WireError {
    /// Builds an error.
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        Self {
            code,
            message: message.into(),
        }
    }

    /// [`ErrorCode::BadRequest`].
    pub fn bad_request(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::BadRequest, message)
    }
    /// [`ErrorCode::Unauthorized`].
    pub fn unauthorized(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::Unauthorized, message)
    }
    /// [`ErrorCode::NotFound`].
    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::NotFound, message)
    }
    /// [`ErrorCode::Busy`].
    pub fn busy(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::Busy, message)
    }
    /// [`ErrorCode::InvalidState`].
    pub fn invalid_state(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::InvalidState, message)
    }
    /// [`ErrorCode::Unavailable`].
    pub fn unavailable(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::Unavailable, message)
    }
    /// [`ErrorCode::Timeout`].
    pub fn timeout(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::Timeout, message)
    }
    /// [`ErrorCode::Internal`].
    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(ErrorCode::Internal, message)
    }
}

/// Why bytes could not be decoded into a message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// Shorter than the 4-byte encapsulation header.
    #[error("payload of {0} bytes is shorter than the CDR header")]
    TooShort(usize),
    /// Not little-endian plain CDR (`00 01 00 00`).
    #[error("unsupported CDR encapsulation {0:02x?}, expected [00, 01, 00, 00]")]
    BadHeader([u8; 4]),
    /// The bytes ended inside a value.
    #[error("payload truncated: needed {needed} more bytes at offset {offset}")]
    Truncated {
        /// Offset (after the header) of the value being read.
        offset: usize,
        /// Bytes missing.
        needed: usize,
    },
    /// Bytes left over after the message (beyond alignment padding).
    #[error("{0} unexpected trailing bytes after the message")]
    TrailingBytes(usize),
    /// A value is not valid for its type (bad bool, bad UTF-8, unknown enum tag…).
    #[error("invalid value: {0}")]
    Invalid(String),
}

/// Why a message could not be encoded.
#[derive(Debug, thiserror::Error)]
#[error("CDR encoding failed: {0}")]
pub struct EncodeError(pub String);

impl From<EncodeError> for WireError {
    fn from(e: EncodeError) -> Self {
        WireError::internal(e.to_string())
    }
}

/// Errors of the contract's local helpers (ids, config, sessions).
#[derive(Debug, thiserror::Error)]
pub enum ContractError {
    /// An env id or key chunk is not valid.
    #[error("invalid env id: {0}")]
    InvalidEnvId(String),
    /// A ROS 2 topic name or namespace is not valid.
    #[error("invalid ROS name {0}")]
    InvalidRosName(String),
    /// An image size is not `WIDTHxHEIGHT`.
    #[error("invalid resolution {0}")]
    InvalidResolution(String),
    /// A Zenoh configuration could not be built.
    #[error("invalid zenoh configuration: {0}")]
    Config(String),
    /// Zenoh refused an operation.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// No router or peer answered at the endpoints a session was told to
    /// connect to: an unreachable deployment, not an empty one.
    #[error(
        "nothing answered at {endpoints} within {waited_ms} ms: is the deployment running there? \
         Check the endpoint (connect= / OFFWORLD_GYM_CONNECT / --connect) and the network"
    )]
    Unreachable {
        /// The endpoints tried, comma-separated.
        endpoints: String,
        /// How long the session waited for one of them.
        waited_ms: u64,
    },
}

impl From<zenoh::Error> for ContractError {
    fn from(e: zenoh::Error) -> Self {
        ContractError::Zenoh(e.to_string())
    }
}

/// A contract failure as a caller sees it: what it asked for is malformed
/// (`BadRequest`), or the deployment cannot be reached (`Unavailable`,
/// transient: worth trying again).
impl From<ContractError> for WireError {
    fn from(e: ContractError) -> Self {
        let code = match e {
            ContractError::InvalidEnvId(_)
            | ContractError::InvalidRosName(_)
            | ContractError::InvalidResolution(_)
            | ContractError::Config(_) => ErrorCode::BadRequest,
            ContractError::Zenoh(_) | ContractError::Unreachable { .. } => ErrorCode::Unavailable,
        };
        WireError::new(code, e.to_string())
    }
}
