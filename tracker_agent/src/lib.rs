//! tracker_agent — runs next to the lighthouse PC: ingests Vive tracker
//! poses, applies the tracker→world and tracker→base_link calibration, and
//! publishes the robot's base_link pose (`pose`) and tracking status
//! (`tracking`) under the env's namespace.
//!
//! Not built yet: this crate reserves its place in the workspace. The keys
//! and messages it will publish are defined in `offworld-runtime`; the
//! controller already consumes them (untagged streaming poses, tracking
//! loss).
