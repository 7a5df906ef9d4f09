//! Cross-component tests: the shipped binaries run as separate processes
//! and meet over TCP on loopback (see `tests/integration/processes.rs`), the emulated
//! enclosure deployment ([`emulated`], `tests/integration/real_side.rs`), plus the
//! independent Python peers under `tests/python/` that other suites drive.

pub mod emulated;
pub mod faults;
pub mod link;
pub mod netns;

use std::path::Path;
use std::process::Stdio;
use std::time::Duration;

pub use offworld_deploy::process::{binary_dir, Process};

/// Starting the workspace's binaries and `PATH` programs as [`Process`]es
/// (test helpers over [`Process::start`]).
pub trait Spawn {
    /// Starts a workspace binary with arguments.
    fn spawn(binary: &str, args: &[&str]) -> std::io::Result<Process> {
        Self::spawn_logged(binary, args, "warn")
    }

    /// Starts a workspace binary with arguments and a `RUST_LOG` filter.
    fn spawn_logged(binary: &str, args: &[&str], log: &str) -> std::io::Result<Process> {
        Self::spawn_in(None, binary, args, log)
    }

    /// Starts a program found on `PATH` (e.g. `zenohd`, installed by
    /// `.ci/setup`) with arguments and a `RUST_LOG` filter.
    fn spawn_from_path(program: &str, args: &[&str], log: &str) -> std::io::Result<Process> {
        Self::spawn_from_path_in(None, program, args, log)
    }

    /// Like [`Spawn::spawn_from_path`], inside network namespace `netns`
    /// if given.
    fn spawn_from_path_in(
        netns: Option<&str>,
        program: &str,
        args: &[&str],
        log: &str,
    ) -> std::io::Result<Process> {
        Process::start(netns, Path::new(program), args, log, Stdio::null())
    }

    /// Like [`Spawn::spawn_in`], with the child's standard output piped
    /// to the caller (`self.0.stdout`).
    fn spawn_piped_in(
        netns: Option<&str>,
        binary: &str,
        args: &[&str],
        log: &str,
    ) -> std::io::Result<Process> {
        Process::start(netns, &binary_dir().join(binary), args, log, Stdio::piped())
    }

    /// Like [`Spawn::spawn_logged`], inside network namespace `netns` if
    /// given (`ip netns exec` execs the binary: the child is the binary).
    fn spawn_in(
        netns: Option<&str>,
        binary: &str,
        args: &[&str],
        log: &str,
    ) -> std::io::Result<Process> {
        Process::start(netns, &binary_dir().join(binary), args, log, Stdio::null())
    }
}

impl Spawn for Process {}

/// Whether a liveliness token on `key` is seen through `session` (one ask,
/// answered within 500 ms); `None` when the ask itself failed.
pub async fn token_seen(session: &zenoh::Session, key: &str) -> Option<bool> {
    let replies = session
        .liveliness()
        .get(key)
        .timeout(Duration::from_millis(500))
        .await
        .ok()?;
    let mut seen = false;
    while let Ok(reply) = replies.recv_async().await {
        seen |= reply.result().is_ok();
    }
    Some(seen)
}
