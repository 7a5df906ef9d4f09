//! Every Rust → Python error mapping, in one place. Server errors keep their
//! typed code and message; each code has its own exception class, a
//! subclass of the natural Python builtin.

use offworld_runtime::{ErrorCode, WireError};
use pyo3::create_exception;
use pyo3::exceptions::{
    PyConnectionError, PyLookupError, PyPermissionError, PyRuntimeError, PyTimeoutError,
    PyValueError,
};
use pyo3::prelude::*;

create_exception!(
    offworld_gym.errors,
    OffWorldGymError,
    PyRuntimeError,
    "Base of every offworld_gym error."
);
create_exception!(
    offworld_gym.errors,
    BadRequest,
    PyValueError,
    "The request or action is invalid (code 400)."
);
create_exception!(
    offworld_gym.errors,
    Unauthorized,
    PyPermissionError,
    "Missing or wrong token, lease or booking (401)."
);
create_exception!(
    offworld_gym.errors,
    NotFound,
    PyLookupError,
    "No such env, session or experiment (404)."
);
create_exception!(
    offworld_gym.errors,
    Busy,
    OffWorldGymError,
    "The env is leased or booked by someone else, or the controller is at a request limit (409): nothing was done; retry later."
);
create_exception!(
    offworld_gym.errors,
    InvalidState,
    OffWorldGymError,
    "Not now: step before reset, after the end (412)."
);
create_exception!(
    offworld_gym.errors,
    Unavailable,
    PyConnectionError,
    "Maintenance, offline, or tracking lost (503)."
);
create_exception!(
    offworld_gym.errors,
    Timeout,
    PyTimeoutError,
    "A component did not answer in time (504)."
);
create_exception!(
    offworld_gym.errors,
    Internal,
    OffWorldGymError,
    "A server-side failure (500)."
);

/// A wire error as the matching Python exception; `.code` is set too.
pub fn to_py(e: WireError) -> PyErr {
    let message = format!("{} ({}): {}", e.code.name(), e.code as u16, e.message);
    let err = match e.code {
        ErrorCode::BadRequest => BadRequest::new_err(message),
        ErrorCode::Unauthorized => Unauthorized::new_err(message),
        ErrorCode::NotFound => NotFound::new_err(message),
        ErrorCode::Busy => Busy::new_err(message),
        ErrorCode::InvalidState => InvalidState::new_err(message),
        ErrorCode::Unavailable => Unavailable::new_err(message),
        ErrorCode::Timeout => Timeout::new_err(message),
        ErrorCode::Internal => Internal::new_err(message),
    };
    Python::attach(|py| {
        let _ = err.value(py).setattr("code", e.code as u16);
    });
    err
}

/// Registers the exception classes on the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("OffWorldGymError", py.get_type::<OffWorldGymError>())?;
    m.add("BadRequest", py.get_type::<BadRequest>())?;
    m.add("Unauthorized", py.get_type::<Unauthorized>())?;
    m.add("NotFound", py.get_type::<NotFound>())?;
    m.add("Busy", py.get_type::<Busy>())?;
    m.add("InvalidState", py.get_type::<InvalidState>())?;
    m.add("Unavailable", py.get_type::<Unavailable>())?;
    m.add("Timeout", py.get_type::<Timeout>())?;
    m.add("Internal", py.get_type::<Internal>())?;
    Ok(())
}
