//! Every Rust → Python error mapping, in one place. The exception classes
//! are defined in Python (`offworld_gym/errors.py`), where one class can
//! derive from both `OffWorldGymError` and the natural builtin (`NotFound`
//! is a `LookupError` too); here each server error code picks its class.

use offworld_runtime::WireError;
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;

/// `offworld_gym.errors.<class_name>(message)` with `code` set, as a PyErr.
fn raise(class_name: &str, message: String, code: Option<u16>) -> PyErr {
    Python::attach(|py| {
        let made = (|| -> PyResult<PyErr> {
            let class = py.import("offworld_gym.errors")?.getattr(class_name)?;
            let err = class.call1((message.clone(),))?;
            if let Some(code) = code {
                err.setattr("code", code)?;
            }
            Ok(PyErr::from_value(err))
        })();
        // Only if the package's own module is broken: still an error, and
        // the reason is in its message.
        made.unwrap_or_else(|e| {
            PyRuntimeError::new_err(format!("{message} (offworld_gym.errors unusable: {e})"))
        })
    })
}

/// A wire error as the matching Python exception; `.code` is set too.
pub fn to_py(e: WireError) -> PyErr {
    let message = format!("{} ({}): {}", e.code.name(), e.code as u16, e.message);
    // The class of each code has the code's name (`ErrorCode::name`).
    raise(e.code.name(), message, Some(e.code as u16))
}

/// A failure of this process's side (the runtime, the monitor): an
/// `OffWorldGymError` without a server code.
pub fn local(message: String) -> PyErr {
    raise("OffWorldGymError", message, None)
}

/// A caller's mistake found before anything is sent: `BadRequest` (also a
/// `ValueError`) without a server code.
pub fn raise_bad_request(message: String) -> PyErr {
    raise("BadRequest", message, None)
}
