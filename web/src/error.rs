//! HTTP errors: one type for every failure a request can meet, answered as
//! JSON under `/api/` and as a page elsewhere, always with a status that
//! says what happened and a sentence that says why.

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use offworld_runtime::{ErrorCode, WireError};
use serde::Serialize;

/// How the error is answered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// A page (browsers).
    Html,
    /// `{"error": {...}}` (scripts).
    Json,
}

impl Format {
    /// JSON for paths under `/api/`, a page elsewhere.
    pub fn for_path(path: &str) -> Self {
        if path == "/api" || path.starts_with("/api/") {
            Format::Json
        } else {
            Format::Html
        }
    }
}

/// What went wrong, as a stable word (the JSON `kind`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Kind {
    /// The request's values are invalid (a form field, a slot the
    /// controller's rules refuse).
    BadRequest,
    /// Not signed in, or the controller refused the access token.
    Unauthorized,
    /// A POST from another site, or without its CSRF token.
    Forbidden,
    /// Not now: the slot overlaps another, the controller is busy.
    Conflict,
    /// No such page or env.
    NotFound,
    /// Only GET (and HEAD) are served.
    MethodNotAllowed,
    /// This client sends requests too fast.
    RateLimited,
    /// Too many requests or event streams at once.
    Overloaded,
    /// The deployment did not answer in time.
    Timeout,
    /// The deployment answered with an error or not at all.
    Unavailable,
    /// A bug.
    Internal,
}

/// An HTTP error.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HttpError {
    /// Status code.
    pub status: StatusCode,
    /// Stable word.
    pub kind: Kind,
    /// One sentence for people.
    pub message: String,
    /// Seconds after which a retry may succeed (`Retry-After`).
    pub retry_after_s: Option<u64>,
    /// How it is answered.
    pub format: Format,
}

impl HttpError {
    fn new(status: StatusCode, kind: Kind, message: impl Into<String>) -> Self {
        Self {
            status,
            kind,
            message: message.into(),
            retry_after_s: None,
            format: Format::Html,
        }
    }

    /// 404.
    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, Kind::NotFound, message)
    }

    /// 405.
    pub fn method_not_allowed() -> Self {
        Self::new(
            StatusCode::METHOD_NOT_ALLOWED,
            Kind::MethodNotAllowed,
            "this address does not take that method: pages are GET and HEAD, \
             only the booking and sign-in forms are POSTed",
        )
    }

    /// 400.
    pub fn bad_request(message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, Kind::BadRequest, message)
    }

    /// 401.
    pub fn unauthorized(message: impl Into<String>) -> Self {
        Self::new(StatusCode::UNAUTHORIZED, Kind::Unauthorized, message)
    }

    /// 403.
    pub fn forbidden(message: impl Into<String>) -> Self {
        Self::new(StatusCode::FORBIDDEN, Kind::Forbidden, message)
    }

    /// A controller's typed refusal of a user's request about `what`,
    /// passed on with its meaning: 400 (invalid), 401 (token), 404, 409
    /// (overlap, busy, not now); its failures as in [`HttpError::from_wire`].
    pub fn from_controller(what: &str, e: &WireError) -> Self {
        let message = format!("{what}: {}", e.message);
        match e.code {
            ErrorCode::BadRequest => Self::bad_request(message),
            ErrorCode::Unauthorized => Self::unauthorized(message),
            ErrorCode::Busy | ErrorCode::InvalidState => {
                Self::new(StatusCode::CONFLICT, Kind::Conflict, message)
            }
            _ => Self::from_wire(what, e),
        }
    }

    /// 429.
    pub fn rate_limited(retry_after_s: u64) -> Self {
        Self {
            retry_after_s: Some(retry_after_s),
            ..Self::new(
                StatusCode::TOO_MANY_REQUESTS,
                Kind::RateLimited,
                format!("too many requests from your address: retry in {retry_after_s} s"),
            )
        }
    }

    /// 503, the service's own limits.
    pub fn overloaded(what: &str) -> Self {
        Self {
            retry_after_s: Some(1),
            ..Self::new(
                StatusCode::SERVICE_UNAVAILABLE,
                Kind::Overloaded,
                format!("the service is at its limit of {what}: retry shortly"),
            )
        }
    }

    /// 504, a request over its deadline.
    pub fn timeout(message: impl Into<String>) -> Self {
        Self::new(StatusCode::GATEWAY_TIMEOUT, Kind::Timeout, message)
    }

    /// 503, the deployment cannot be asked now.
    pub fn unavailable(message: impl Into<String>) -> Self {
        Self::new(StatusCode::SERVICE_UNAVAILABLE, Kind::Unavailable, message)
    }

    /// 500.
    pub fn internal(message: impl Into<String>) -> Self {
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, Kind::Internal, message)
    }

    /// The same error answered as `format`.
    pub fn as_format(mut self, format: Format) -> Self {
        self.format = format;
        self
    }

    /// A deployment's typed error about `what`.
    pub fn from_wire(what: &str, e: &WireError) -> Self {
        let message = format!("{what}: {}", e.message);
        match e.code {
            ErrorCode::NotFound => Self::not_found(message),
            ErrorCode::Timeout => Self::timeout(message),
            // The deployment's failures are a gateway's problem, not a bug
            // of this service: 502 (an answer we cannot use) or 503.
            ErrorCode::Internal => Self::new(StatusCode::BAD_GATEWAY, Kind::Unavailable, message),
            _ => Self::new(StatusCode::SERVICE_UNAVAILABLE, Kind::Unavailable, message),
        }
    }
}

#[derive(Serialize)]
struct JsonBody<'a> {
    error: JsonError<'a>,
}

#[derive(Serialize)]
struct JsonError<'a> {
    status: u16,
    kind: Kind,
    message: &'a str,
}

impl IntoResponse for HttpError {
    fn into_response(self) -> Response {
        let mut response = match self.format {
            Format::Json => {
                let body = JsonBody {
                    error: JsonError {
                        status: self.status.as_u16(),
                        kind: self.kind,
                        message: &self.message,
                    },
                };
                crate::api::json_response(self.status, &body)
            }
            Format::Html => (
                self.status,
                crate::pages::error_page(self.status, &self.message),
            )
                .into_response(),
        };
        if let Some(seconds) = self.retry_after_s {
            response
                .headers_mut()
                .insert(header::RETRY_AFTER, HeaderValue::from(seconds));
        }
        response
    }
}
