//! Cross-component tests: the shipped binaries run as separate processes
//! and meet over TCP on loopback (see `tests/processes.rs`), the emulated
//! enclosure deployment ([`emulated`], `tests/real_side.rs`), plus the
//! independent Python peers under `tests/python/` that other suites drive.

pub mod emulated;
pub mod faults;
pub mod link;
pub mod netns;
pub mod site;

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

/// The directory holding the workspace's release binaries: next to the
/// running executable, or one level up from a test executable's `deps/`.
pub fn binary_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap_or_default();
    let dir = exe.parent().map(PathBuf::from).unwrap_or_default();
    if dir.file_name().is_some_and(|n| n == "deps") {
        dir.parent().map(PathBuf::from).unwrap_or_default()
    } else {
        dir
    }
}

/// A child process killed when dropped.
pub struct Process(pub Child);

impl Process {
    /// Starts a workspace binary with arguments.
    pub fn spawn(binary: &str, args: &[&str]) -> std::io::Result<Self> {
        Self::spawn_logged(binary, args, "warn")
    }

    /// Starts a workspace binary with arguments and a `RUST_LOG` filter.
    pub fn spawn_logged(binary: &str, args: &[&str], log: &str) -> std::io::Result<Self> {
        Self::spawn_in(None, binary, args, log)
    }

    /// Starts a program found on `PATH` (e.g. `zenohd`, installed by
    /// `.ci/setup`) with arguments and a `RUST_LOG` filter.
    pub fn spawn_from_path(program: &str, args: &[&str], log: &str) -> std::io::Result<Self> {
        Self::spawn_from_path_in(None, program, args, log)
    }

    /// Like [`Process::spawn_from_path`], inside network namespace `netns`
    /// if given.
    pub fn spawn_from_path_in(
        netns: Option<&str>,
        program: &str,
        args: &[&str],
        log: &str,
    ) -> std::io::Result<Self> {
        Self::spawn_path(netns, PathBuf::from(program), args, log, Stdio::null())
    }

    /// Like [`Process::spawn_in`], with the child's standard output piped
    /// to the caller (`self.0.stdout`).
    pub fn spawn_piped_in(
        netns: Option<&str>,
        binary: &str,
        args: &[&str],
        log: &str,
    ) -> std::io::Result<Self> {
        Self::spawn_path(netns, binary_dir().join(binary), args, log, Stdio::piped())
    }

    /// Like [`Process::spawn_logged`], inside network namespace `netns` if
    /// given (`ip netns exec` execs the binary: the child is the binary).
    pub fn spawn_in(
        netns: Option<&str>,
        binary: &str,
        args: &[&str],
        log: &str,
    ) -> std::io::Result<Self> {
        Self::spawn_path(netns, binary_dir().join(binary), args, log, Stdio::null())
    }

    fn spawn_path(
        netns: Option<&str>,
        path: PathBuf,
        args: &[&str],
        log: &str,
        stdout: Stdio,
    ) -> std::io::Result<Self> {
        let mut command = match netns {
            Some(ns) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", ns]).arg(&path);
                c
            }
            None => Command::new(&path),
        };
        command
            .args(args)
            .env(
                "RUST_LOG",
                std::env::var("OFFWORLD_CHILD_LOG").unwrap_or_else(|_| log.to_owned()),
            )
            .stdout(stdout)
            .stderr(Stdio::inherit())
            .spawn()
            .map(Self)
            .map_err(|e| std::io::Error::new(e.kind(), format!("{}: {e}", path.display())))
    }
}

impl Process {
    /// Sends `signal` (`STOP`, `CONT`, `TERM`, `HUP`, `INT`, `KILL`).
    pub fn signal(&self, signal: &str) {
        let _ = Command::new("kill")
            .args([format!("-{signal}"), self.0.id().to_string()])
            .status();
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}
