//! Sim↔real parity (issue 24): recorded episodes (MCAP, see
//! `docs/recording.md`) replayed in the twin, and the gap between the two
//! measured per step — pose, depth, colour, reward and termination.
//!
//! - [`recorded`] reads an episode file into its steps.
//! - [`replay`] replays them in a [`offworld_sim_twin::SimTwin`] built
//!   with a [`offworld_sim_twin::TwinProfile`].
//! - [`report`] sums the gaps up as a Markdown report.
//! - [`plots`] draws the replay as PNG figures the report links:
//!   trajectories over the enclosure map, errors over the steps, depth
//!   images of the worst steps.
//! - [`identify`] fits a twin profile to recorded episodes; [`timing`]
//!   its latency and settle time to their odometry time series.
//! - [`rrd`] writes the replay as a rerun recording, robot and twin side
//!   by side.

pub mod cli;
pub mod identify;
pub mod plots;
pub mod recorded;
pub mod replay;
pub mod report;
pub mod rrd;
pub mod timing;

use std::path::PathBuf;

/// Why episodes cannot be replayed. Each names the file and the reason.
#[derive(Debug, thiserror::Error)]
pub enum ParityError {
    /// The file cannot be read as an episode (not MCAP, cut, bad message).
    #[error(transparent)]
    Record(#[from] offworld_recorder::RecordError),
    /// The file is an episode, but not one that can be replayed.
    #[error("{}: {reason}", path.display())]
    Unusable {
        /// The episode file.
        path: PathBuf,
        /// What is wrong with it.
        reason: String,
    },
    /// Not enough data to fit a profile.
    #[error("too little data: {reason}")]
    TooFew {
        /// What is missing.
        reason: String,
    },
    /// An output file could not be written.
    #[error("{}: {reason}", path.display())]
    Output {
        /// The file.
        path: PathBuf,
        /// Why.
        reason: String,
    },
    /// The optimiser failed.
    #[error("the fit failed: {0}")]
    Fit(String),
    /// The twin refused the episode's world, profile or a command.
    #[error("{}: the twin: {reason}", path.display())]
    Twin {
        /// The episode file.
        path: PathBuf,
        /// The twin's error.
        reason: String,
    },
}
