//! Type conversions between Python and the contract: observations to numpy
//! arrays, Python actions and options to messages.

use numpy::ndarray::{ArrayViewMutD, IxDyn};
use numpy::{Element, PyArray1, PyArrayDyn, PyArrayMethods};
use offworld_runtime::msg::{
    Action, ActionSpace, AlgorithmMode, Channels, DType, DepthFormat, LearningType, ObsArray,
    ObsOptions, StepInfo,
};
use offworld_runtime::pool::BufferPool;
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};

use crate::errors;

/// An observation as a numpy array of shape (height, width, channels),
/// over the decoded pixels themselves: no copy, and when numpy drops the
/// array the buffer goes back to `buffers` (the env's pool) for a later
/// step instead of being freed — allocating and freeing 307 KB a step
/// page-faults the memory in again each time.
pub fn observation<'py>(
    py: Python<'py>,
    obs: ObsArray,
    buffers: &BufferPool,
) -> PyResult<Bound<'py, PyAny>> {
    let shape = [
        obs.height as usize,
        obs.width as usize,
        obs.channels as usize,
    ];
    pixels(py, obs.data, buffers, obs.dtype, &shape)
}

/// A vector env's observations, decoded env after env into `batch` (a
/// buffer of `batches`), as one array of shape (envs, height, width,
/// channels), lent like [`observation`]; `first` is the first env's
/// (shape and type, its pixels in `batch`).
pub fn stacked<'py>(
    py: Python<'py>,
    batch: Vec<u8>,
    batches: &BufferPool,
    first: &ObsArray,
    envs: usize,
) -> PyResult<Bound<'py, PyAny>> {
    let [height, width, channels] = [first.height, first.width, first.channels].map(|n| n as usize);
    pixels(
        py,
        batch,
        batches,
        first.dtype,
        &[envs, height, width, channels],
    )
}

/// `data` (little-endian elements of `dtype`) as a numpy array of `shape`,
/// lent to numpy: back to `pool` when the array is dropped.
fn pixels<'py>(
    py: Python<'py>,
    mut data: Vec<u8>,
    pool: &BufferPool,
    dtype: DType,
    shape: &[usize],
) -> PyResult<Bound<'py, PyAny>> {
    let fills = shape
        .iter()
        .try_fold(dtype.size(), |bytes, n| bytes.checked_mul(*n));
    if fills != Some(data.len()) {
        return Err(errors::local(format!(
            "an observation of {} bytes does not fill its shape {shape:?} ({dtype:?})",
            data.len()
        )));
    }
    // The heap buffer's address: it stays put when the Vec moves into its owner.
    let start = data.as_mut_ptr();
    // Little-endian floats are read in place where the buffer is aligned
    // for them (the allocator's 16 bytes); otherwise decoded anew.
    let in_place = match dtype {
        DType::U8 => true,
        DType::F32 => cfg!(target_endian = "little") && start.align_offset(4) == 0,
    };
    if !in_place {
        let floats: Vec<f32> = data
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        pool.recycle(data);
        return Ok(PyArray1::from_vec(py, floats).reshape(shape)?.into_any());
    }
    let owner = Bound::new(
        py,
        LentPixels {
            data,
            pool: pool.clone(),
        },
    )?;
    Ok(match dtype {
        DType::U8 => lend(start, shape, owner),
        DType::F32 => lend(start.cast::<f32>(), shape, owner),
    })
}

/// The pixels behind an observation array (its numpy `base`), back to
/// their pool when the array is dropped.
#[pyclass(frozen, module = "offworld_gym._native")]
pub struct LentPixels {
    data: Vec<u8>,
    pool: BufferPool,
}

impl Drop for LentPixels {
    fn drop(&mut self) {
        self.pool.recycle(std::mem::take(&mut self.data));
    }
}

/// A writable numpy array of `shape` over `start`, the first element of
/// `owner`'s pixels.
#[allow(unsafe_code)] // rust-numpy's one way to lend memory: see SAFETY
fn lend<'py, T: Element>(
    start: *mut T,
    shape: &[usize],
    owner: Bound<'py, LentPixels>,
) -> Bound<'py, PyAny> {
    // SAFETY: `start` is the start of `owner.data`'s heap buffer, aligned
    // for `T` and holding exactly `shape`'s elements (checked by
    // `pixels`). Rust neither reads, writes, moves nor frees that buffer
    // while it is lent: the class is frozen and exposes no field, and only
    // its `Drop` takes the buffer back, once no array holds `owner` (each
    // array over it has `owner` as its base). numpy alone writes to it.
    unsafe {
        let view = ArrayViewMutD::from_shape_ptr(IxDyn(shape), start);
        PyArrayDyn::borrow_from_array(&view, owner.into_any())
    }
    .into_any()
}

/// `info` dict of a step or reset.
pub fn info<'py>(py: Python<'py>, info: &StepInfo) -> PyResult<Bound<'py, PyDict>> {
    let dict = PyDict::new(py);
    dict.set_item("episode_id", info.episode_id)?;
    dict.set_item("step", info.step)?;
    dict.set_item("is_success", info.is_success)?;
    dict.set_item("end_reason", &info.end_reason)?;
    if info.pose_shared {
        dict.set_item("pose", (info.x, info.y, info.yaw))?;
        dict.set_item("distance_to_goal", info.distance_to_goal)?;
    }
    Ok(dict)
}

/// A Python action for `space`: an int for discrete, a length-2 sequence
/// of floats for continuous (shape and range are checked by the server).
pub fn action(space: &ActionSpace, value: &Bound<'_, PyAny>) -> PyResult<Action> {
    match space {
        ActionSpace::Discrete { .. } => {
            let index = value
                .call_method0("__index__")
                .and_then(|i| i.extract::<i64>())
                .map_err(|_| {
                    PyValueError::new_err(format!("a discrete action must be an int, got {value}"))
                })?;
            Ok(Action::Discrete(index))
        }
        ActionSpace::Box { .. } => {
            let list = if value.hasattr("tolist")? {
                value.call_method0("tolist")?
            } else {
                value.clone()
            };
            let values: Vec<f64> = list.extract().map_err(|_| {
                PyValueError::new_err(format!(
                    "a continuous action must be a sequence of floats, got {value}"
                ))
            })?;
            Ok(Action::Continuous(
                values.into_iter().map(|v| v as f32).collect(),
            ))
        }
    }
}

/// `Channels` from the Python enum of the same name
/// (`offworld_gym.envs.common.channels`), read by its value.
pub fn channels(value: &Bound<'_, PyAny>) -> PyResult<Channels> {
    match value.extract::<i64>() {
        Ok(1) => Ok(Channels::DepthOnly),
        Ok(2) => Ok(Channels::RgbOnly),
        Ok(3) => Ok(Channels::Rgbd),
        _ => Err(PyValueError::new_err(format!(
            "channels must be a Channels (DEPTH_ONLY, RGB_ONLY or RGBD), got {value}"
        ))),
    }
}

/// Observation options from the Python keyword arguments.
pub fn obs_options(
    channels: Channels,
    height: i64,
    width: i64,
    depth_format: &str,
) -> PyResult<ObsOptions> {
    use offworld_env_controller::observation::{validate_options, MAX_SIDE};
    // Python ints of any size: a negative or huge side is named, not an
    // OverflowError from the conversion.
    let side = |v: i64| u32::try_from(v).unwrap_or(MAX_SIDE + 1);
    let depth_format = match depth_format {
        "uint8" => DepthFormat::Uint8,
        "meters" => DepthFormat::Meters,
        other => {
            return Err(PyValueError::new_err(format!(
                "depth_format must be \"uint8\" or \"meters\", got {other:?}"
            )))
        }
    };
    let options = ObsOptions {
        channels,
        height: side(height),
        width: side(width),
        depth_format,
    };
    if validate_options(&options).is_err() {
        return Err(errors::raise_bad_request(format!(
            "resolution (height, width) = ({height}, {width}): each side must be 1..={MAX_SIDE} pixels"
        )));
    }
    Ok(options)
}

/// `learning_type` from its string.
pub fn learning_type(value: &str) -> PyResult<LearningType> {
    offworld_runtime::named::parse("learning_type", value).map_err(PyValueError::new_err)
}

/// `algorithm_mode` from its string.
pub fn algorithm_mode(value: &str) -> PyResult<AlgorithmMode> {
    offworld_runtime::named::parse("algorithm_mode", value).map_err(PyValueError::new_err)
}

/// How long to wait in an env's line, from Python's `wait=` seconds
/// (finite, not negative; checked again here for direct callers).
pub fn wait(seconds: f64) -> PyResult<std::time::Duration> {
    std::time::Duration::try_from_secs_f64(seconds).map_err(|_| {
        PyValueError::new_err(format!(
            "wait must be a number of seconds from 0 to a year, got {seconds}"
        ))
    })
}

/// A timeout in seconds from Python (finite, positive).
pub fn timeout(seconds: f64) -> PyResult<std::time::Duration> {
    if seconds.is_finite() && seconds > 0.0 {
        Ok(std::time::Duration::from_secs_f64(seconds))
    } else {
        Err(PyValueError::new_err(format!(
            "timeout must be a positive number of seconds, got {seconds}"
        )))
    }
}

/// One discovered env as a dict.
pub fn listing<'py>(
    py: Python<'py>,
    listing: &offworld_client::EnvListing,
) -> PyResult<Bound<'py, PyDict>> {
    // The same shape as `offworld gym envs --json`.
    let info = offworld_client::cli::EnvInfo::from(listing);
    let dict = PyDict::new(py);
    dict.set_item("env_id", &info.env_id)?;
    dict.set_item("task", info.task)?;
    dict.set_item("state", info.state)?;
    dict.set_item("until_unix_ms", info.until_unix_ms)?;
    dict.set_item("message", info.message)?;
    dict.set_item("who", info.who)?;
    dict.set_item("components", info.components)?;
    let bookings = PyList::empty(py);
    for b in info.bookings {
        bookings.append(booking(py, b)?)?;
    }
    dict.set_item("bookings", bookings)?;
    dict.set_item("estops", info.estops)?;
    dict.set_item("last_reset", reset_accuracy(py, &listing.last_reset)?)?;
    Ok(dict)
}

/// A reset's accuracy as a dict, or None when not measured.
fn reset_accuracy<'py>(
    py: Python<'py>,
    reset: &offworld_runtime::msg::ResetAccuracy,
) -> PyResult<Option<Bound<'py, PyDict>>> {
    if !reset.measured {
        return Ok(None);
    }
    let pose = |p: &offworld_runtime::msg::Pose2D| (p.x, p.y, p.yaw);
    let dict = PyDict::new(py);
    dict.set_item("requested", pose(&reset.requested))?;
    dict.set_item("achieved", pose(&reset.achieved))?;
    dict.set_item("position_error_m", reset.position_error_m)?;
    dict.set_item("yaw_error_rad", reset.yaw_error_rad)?;
    dict.set_item("duration_s", reset.duration_s)?;
    dict.set_item("unix_ms", reset.unix_ms)?;
    Ok(Some(dict))
}

/// One booking as a dict.
pub fn booking<'py>(
    py: Python<'py>,
    booking: &offworld_runtime::msg::Booking,
) -> PyResult<Bound<'py, PyDict>> {
    let dict = PyDict::new(py);
    dict.set_item("id", booking.id)?;
    dict.set_item("env_id", &booking.env_id)?;
    dict.set_item("user", &booking.user)?;
    dict.set_item("start_unix_ms", booking.start_unix_ms)?;
    dict.set_item("end_unix_ms", booking.end_unix_ms)?;
    Ok(dict)
}

/// Experiments as dicts (the fields of `ExperimentRecord`).
pub fn experiments<'py>(
    py: Python<'py>,
    experiments: &[offworld_runtime::msg::ExperimentRecord],
) -> PyResult<Bound<'py, PyList>> {
    let out = PyList::empty(py);
    for e in experiments {
        out.append(experiment(py, e)?)?;
    }
    Ok(out)
}

fn experiment<'py>(
    py: Python<'py>,
    e: &offworld_runtime::msg::ExperimentRecord,
) -> PyResult<Bound<'py, PyDict>> {
    let dict = PyDict::new(py);
    dict.set_item("id", e.id)?;
    dict.set_item("user", &e.user)?;
    dict.set_item("env_id", &e.env_id)?;
    dict.set_item("task", &e.task)?;
    dict.set_item("name", &e.name)?;
    dict.set_item("learning_type", &e.learning_type)?;
    dict.set_item("algorithm_mode", &e.algorithm_mode)?;
    dict.set_item("episodes", e.episodes)?;
    dict.set_item("steps", e.steps)?;
    dict.set_item("created_unix_ms", e.created_unix_ms)?;
    dict.set_item("updated_unix_ms", e.updated_unix_ms)?;
    Ok(dict)
}

/// (experiment dict, [episode dict]); an episode's `seed` is None when its
/// reset had none, its `recordings` a list of dicts (path, bytes, complete).
pub fn experiment_with_episodes<'py>(
    py: Python<'py>,
    e: &offworld_runtime::msg::ExperimentRecord,
    episodes: &[offworld_runtime::msg::EpisodeRecordEntry],
) -> PyResult<Bound<'py, PyTuple>> {
    let out = PyList::empty(py);
    for ep in episodes {
        let dict = PyDict::new(py);
        dict.set_item("index", ep.index)?;
        dict.set_item("seed", ep.seeded.then_some(ep.seed))?;
        dict.set_item("steps", ep.steps)?;
        dict.set_item("episode_return", ep.episode_return)?;
        dict.set_item("success", ep.success)?;
        dict.set_item("end_reason", &ep.end_reason)?;
        dict.set_item("started_unix_ms", ep.started_unix_ms)?;
        dict.set_item("ended_unix_ms", ep.ended_unix_ms)?;
        dict.set_item("reset", reset_accuracy(py, &ep.reset)?)?;
        let recordings = PyList::empty(py);
        for r in &ep.recordings {
            let file = PyDict::new(py);
            file.set_item("path", &r.path)?;
            file.set_item("bytes", r.bytes)?;
            file.set_item("complete", r.complete)?;
            recordings.append(file)?;
        }
        dict.set_item("recordings", recordings)?;
        out.append(dict)?;
    }
    PyTuple::new(py, [experiment(py, e)?.into_any(), out.into_any()])
}

/// Leaderboard entries as dicts, best first, with their `rank` (from 1).
pub fn leaderboard<'py>(
    py: Python<'py>,
    board: &offworld_runtime::msg::Leaderboard,
) -> PyResult<Bound<'py, PyList>> {
    let out = PyList::empty(py);
    for (rank, e) in board.entries.iter().enumerate() {
        let dict = PyDict::new(py);
        dict.set_item("rank", rank + 1)?;
        dict.set_item("experiment", &e.experiment)?;
        dict.set_item("user", &e.user)?;
        dict.set_item("learning_type", &e.learning_type)?;
        dict.set_item("episodes", e.episodes)?;
        dict.set_item("success_rate", e.success_rate)?;
        dict.set_item("mean_return", e.mean_return)?;
        out.append(dict)?;
    }
    Ok(out)
}
