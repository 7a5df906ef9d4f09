//! tracker_agent — runs next to the lighthouse PC: ingests HTC Vive tracker
//! poses, applies the tracker→world and tracker→base_link calibration, and
//! publishes the robot's base_link pose (`pose`, `geometry_msgs/PoseStamped`
//! in frame `world`) and tracking status (`tracking`,
//! [`TrackingStatus`](offworld_runtime::msg::TrackingStatus)) under the env's
//! namespace, so the controller never scores a step on a stale pose.
//!
//! # Modules
//!
//! - [`protocol`]: the line protocol and its typed errors.
//! - [`source`]: pose sources (`stdin`, `tcp://`, `udp://`, `replay:`)
//!   behind the [`PoseSource`] trait.
//! - [`calibration`]: the two transforms, their TOML file, and the
//!   Kabsch/SVD solver behind `tracker_agent calibrate`.
//! - [`filter`]: outlier rejection (speed / yaw-rate limits, re-lock).
//! - [`agent`]: the node publishing poses and tracking status.
//!
//! # Line protocol
//!
//! UTF-8, one pose per line, `\n` terminated:
//!
//! ```text
//! [<device_id>] <timestamp_s> <x> <y> <z> <qx> <qy> <qz> <qw>
//! LHR-1A2B3C4D 1718000000.004 1.250 -0.300 0.182 0.0 0.0 0.3826834 0.9238795
//! ```
//!
//! - 8 whitespace-separated numbers, optionally preceded by one non-numeric
//!   device id token.
//! - Position in metres in the tracking (lighthouse) frame; the tracker
//!   device's orientation in that frame as a Hamilton unit quaternion in
//!   `x y z w` order (ROS order).
//! - Timestamp in seconds of the source's clock, monotonic per device (may
//!   be unix time); it drives the outlier filter's `dt` and replay timing.
//! - Blank lines and lines starting with `#` are ignored.
//! - A malformed line (wrong token count, non-number, NaN/inf, quaternion
//!   norm off by more than 0.01, over 1024 bytes, not UTF-8) is a
//!   [`ProtocolError`] with its line number: counted and skipped, never the
//!   end of the stream.
//!
//! # Calibration
//!
//! ```text
//! base_link_in_world = world_from_tracking * device_in_tracking * tracker_in_base_link⁻¹
//! ```
//!
//! Both transforms live in one TOML file (see [`calibration`]);
//! `tracker_agent calibrate` solves `world_from_tracking` from ≥ 3
//! non-collinear surveyed marks.
//!
//! # Library use
//!
//! ```no_run
//! # async fn demo(session: zenoh::Session) -> Result<(), Box<dyn std::error::Error>> {
//! use offworld_tracker_agent::{AgentConfig, Calibration, SourceSpec, TrackerAgent};
//! let env = "real/monolith-0".parse()?;
//! let source = "tcp://127.0.0.1:6969".parse::<SourceSpec>()?.open().await?;
//! let agent = TrackerAgent::spawn(&session, env, Calibration::default(), source, AgentConfig::default()).await?;
//! // … later:
//! let stats = agent.stop().await?;
//! # Ok(()) }
//! ```

pub mod agent;
pub mod calibration;
pub mod cli;
pub mod filter;
pub mod protocol;
pub mod source;

pub use agent::{run, AgentConfig, AgentError, AgentStats, TrackerAgent, TrackerNode};
pub use calibration::{Calibration, CalibrationError, ReferenceFile, Solution};
pub use filter::{FilterConfig, OutlierFilter, Verdict};
pub use protocol::{parse_line, ProtocolError, ProtocolErrorKind, TrackerSample};
pub use source::{PoseSource, SourceError, SourceSpec, SourceSpecError};
