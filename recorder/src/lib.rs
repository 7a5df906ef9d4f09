//! Episodes as datasets: every episode an env serves recorded as one MCAP
//! file in the ROS 2 profile (rosbag2's conventions), which the field's
//! tools open as they are (`rosbags`, `mcap`, `ros2 bag`, Foxglove, rerun).
//!
//! - [`schema`]: the `ros2msg` schemas, as rosbag2 writes them;
//! - [`msg`]: our own recorded types (`offworld_msgs/msg/*`);
//! - [`episode_file`]: one episode, one file, crash-safe step by step;
//! - [`recording`]: an env's recorder, fed by the controller, writing on a
//!   thread of its own;
//! - [`read`]: reading files back (summaries, recovering a crashed one);
//! - `follow`: recording from outside the controller, as a subscriber
//!   (`recorder record`; with the `programs` feature, as is `cli`).
//!
//! The format is documented in `docs/recording.md`.

#[cfg(feature = "programs")]
pub mod cli;
pub mod episode_file;
#[cfg(feature = "programs")]
pub mod follow;
pub mod msg;
pub mod read;
pub mod recording;
pub mod schema;

use std::path::{Path, PathBuf};

pub use episode_file::{Channel, EpisodeFile};
pub use recording::{EnvRecorder, RecordTo, RecordedFile, StepRecord};

/// What can go wrong recording or reading an episode file.
#[derive(Debug, thiserror::Error)]
pub enum RecordError {
    /// The recordings directory cannot be written.
    #[error("cannot record into {}: {reason}", dir.display())]
    Unwritable {
        /// The directory.
        dir: PathBuf,
        /// Why (the operating system's words).
        reason: String,
    },
    /// Reading or writing a file failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
    /// The MCAP library refused or failed.
    #[error("{}: {message}", path.display())]
    Mcap {
        /// The file.
        path: PathBuf,
        /// The library's words.
        message: String,
    },
    /// A message could not be encoded.
    #[error("cannot encode a message: {0}")]
    Encode(String),
    /// A message type has no definition.
    #[error("{0}")]
    Schema(String),
    /// A Zenoh subscription failed.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// A file is not what the command needs.
    #[error("{}: {reason}", path.display())]
    Invalid {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

impl RecordError {
    fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_owned(),
            source,
        }
    }

    fn mcap(path: &Path, e: mcap::McapError) -> Self {
        Self::Mcap {
            path: path.to_owned(),
            message: e.to_string(),
        }
    }
}
