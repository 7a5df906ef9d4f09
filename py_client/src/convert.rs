//! Type conversions between Python and the contract: observations to numpy
//! arrays, Python actions and options to messages.

use numpy::{PyArray1, PyArrayMethods};
use offworld_runtime::msg::{
    Action, ActionSpace, AlgorithmMode, Channels, DType, DepthFormat, LearningType, ObsArray,
    ObsOptions, StepInfo,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

/// An observation as a numpy array of shape (height, width, channels).
pub fn observation<'py>(py: Python<'py>, obs: ObsArray) -> PyResult<Bound<'py, PyAny>> {
    let shape = [
        obs.height as usize,
        obs.width as usize,
        obs.channels as usize,
    ];
    match obs.dtype {
        DType::U8 => Ok(PyArray1::from_vec(py, obs.data).reshape(shape)?.into_any()),
        DType::F32 => {
            let floats: Vec<f32> = obs
                .data
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            Ok(PyArray1::from_vec(py, floats).reshape(shape)?.into_any())
        }
    }
}

/// `info` dict of a step or reset.
pub fn info<'py>(py: Python<'py>, info: &StepInfo) -> PyResult<Bound<'py, PyDict>> {
    let dict = PyDict::new(py);
    dict.set_item("episode_id", info.episode_id)?;
    dict.set_item("step", info.step)?;
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

/// Observation options from the Python keyword arguments.
pub fn obs_options(
    channels: &str,
    height: u32,
    width: u32,
    depth_format: &str,
) -> PyResult<ObsOptions> {
    let channels = match channels {
        "depth" => Channels::DepthOnly,
        "rgb" => Channels::RgbOnly,
        "rgbd" => Channels::Rgbd,
        other => return Err(PyValueError::new_err(format!("unknown channels `{other}`"))),
    };
    let depth_format = match depth_format {
        "uint8" => DepthFormat::Uint8,
        "meters" => DepthFormat::Meters,
        other => {
            return Err(PyValueError::new_err(format!(
                "depth_format must be \"uint8\" or \"meters\", got {other:?}"
            )))
        }
    };
    Ok(ObsOptions {
        channels,
        height,
        width,
        depth_format,
    })
}

/// `learning_type` from its string.
pub fn learning_type(value: &str) -> PyResult<LearningType> {
    match value {
        "end2end" => Ok(LearningType::EndToEnd),
        "sim2real" => Ok(LearningType::SimToReal),
        "humandemos" => Ok(LearningType::HumanDemos),
        other => Err(PyValueError::new_err(format!(
            "learning_type must be end2end, sim2real or humandemos, got {other:?}"
        ))),
    }
}

/// `algorithm_mode` from its string.
pub fn algorithm_mode(value: &str) -> PyResult<AlgorithmMode> {
    match value {
        "train" => Ok(AlgorithmMode::Train),
        "test" => Ok(AlgorithmMode::Test),
        other => Err(PyValueError::new_err(format!(
            "algorithm_mode must be train or test, got {other:?}"
        ))),
    }
}
