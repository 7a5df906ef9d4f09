//! The live monitor behind `rerun=`: linked in the default build (feature
//! `monitor`). The demo's lean build (`.ci/setup --demo`) leaves rerun out —
//! about half of a cold build's compile time — and a request for a monitor
//! there is refused, saying how to get one.

use offworld_runtime::EnvId;
use pyo3::prelude::*;

use crate::errors;

#[cfg(feature = "monitor")]
pub use offworld_monitor::{MonitorHandle as Handle, Sink};

/// Where a monitor would log (none can be made in this build).
#[cfg(not(feature = "monitor"))]
pub enum Sink {}

/// A running monitor (none can run in this build).
#[cfg(not(feature = "monitor"))]
pub enum Handle {}

/// `rerun=`'s value as a sink.
pub fn parse_sink(rerun: &str) -> PyResult<Sink> {
    #[cfg(feature = "monitor")]
    {
        rerun
            .parse()
            .map_err(|e: offworld_monitor::MonitorError| errors::raise_bad_request(e.to_string()))
    }
    #[cfg(not(feature = "monitor"))]
    Err(errors::raise_bad_request(format!(
        "rerun={rerun:?} (or OFFWORLD_GYM_RERUN): this offworld_gym was built \
         without the live monitor (the demo's lean build); `bash .ci/setup` \
         builds the full package"
    )))
}

/// Starts logging `envs` of `session` to `sink` (a blocking call: run it on
/// a blocking pool).
#[cfg_attr(not(feature = "monitor"), allow(unused_variables))]
pub fn start(session: &zenoh::Session, envs: Vec<EnvId>, sink: Sink) -> PyResult<Handle> {
    #[cfg(feature = "monitor")]
    {
        use offworld_monitor::{Monitor, MonitorConfig, Scope};
        let config = MonitorConfig::new(sink).scope(Scope::Envs(envs));
        Monitor::spawn(session, config).map_err(|e| errors::local(format!("monitor: {e}")))
    }
    #[cfg(not(feature = "monitor"))]
    match sink {}
}

/// Completes the monitor's recording (a blocking call).
pub fn finish(handle: Handle) -> PyResult<()> {
    #[cfg(feature = "monitor")]
    {
        handle
            .shutdown()
            .map(drop)
            .map_err(|e| errors::local(format!("monitor: {e}")))
    }
    #[cfg(not(feature = "monitor"))]
    match handle {}
}
