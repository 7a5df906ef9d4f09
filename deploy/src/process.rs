//! Deployments as processes: each component a child process (killed with
//! its handle), the `offworld` command that runs them all, and waiting for
//! a listener to come up.

use std::net::{SocketAddr, TcpStream};
use std::os::unix::net::UnixStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use offworld_runtime::session::UNIX_SOCKET_LINK;

/// A child process, killed (and reaped) when dropped.
pub struct Process(pub Child);

impl Process {
    /// Starts `program` with `args`, its log filter `RUST_LOG=log` (unless
    /// `OFFWORLD_CHILD_LOG` overrides it), inside network namespace `netns`
    /// if given (`ip netns exec` execs the program: the child is the
    /// program). Standard error is inherited.
    pub fn start(
        netns: Option<&str>,
        program: &Path,
        args: &[&str],
        log: &str,
        stdout: Stdio,
    ) -> std::io::Result<Self> {
        let mut command = match netns {
            Some(ns) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", ns]).arg(program);
                c
            }
            None => Command::new(program),
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
            .map_err(|e| std::io::Error::new(e.kind(), format!("{}: {e}", program.display())))
    }

    /// Sends `signal` (`STOP`, `CONT`, `TERM`, `HUP`, `INT`, `KILL`).
    pub fn signal(&self, signal: &str) {
        let _ = Command::new("kill")
            .args([format!("-{signal}"), self.0.id().to_string()])
            .status();
    }

    /// Waits (bounded) for the process to exit by itself.
    pub fn wait_exit(&mut self, limit: Duration) -> Option<std::process::ExitStatus> {
        let deadline = Instant::now() + limit;
        while Instant::now() < deadline {
            if let Ok(Some(status)) = self.0.try_wait() {
                return Some(status);
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        None
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The directory of the running executable, or the one above a test
/// executable's `deps/`: where cargo puts the workspace's binaries.
pub fn binary_dir() -> PathBuf {
    let exe = std::env::current_exe().unwrap_or_default();
    let dir = exe.parent().map(PathBuf::from).unwrap_or_default();
    if dir.file_name().is_some_and(|n| n == "deps") {
        dir.parent().map(PathBuf::from).unwrap_or_default()
    } else {
        dir
    }
}

/// The `offworld` command that runs every component: this program when it
/// is `offworld`, else the one beside it (a test or bench in the build
/// directory), else the one on `PATH` (installed with the Python package).
pub fn offworld_command() -> PathBuf {
    let exe = std::env::current_exe().unwrap_or_default();
    if exe.file_stem().is_some_and(|s| s == "offworld") {
        return exe;
    }
    let beside = binary_dir().join("offworld");
    if beside.is_file() {
        beside
    } else {
        PathBuf::from("offworld")
    }
}

/// The address of a `PROTOCOL/HOST:PORT` endpoint (`tcp/`, `tls/`, …;
/// `#…` options ignored).
pub fn endpoint_addr(endpoint: &str) -> std::io::Result<SocketAddr> {
    let (_, addr) = endpoint.split_once('/').unwrap_or(("", endpoint));
    addr.split('#')
        .next()
        .unwrap_or(addr)
        .parse()
        .map_err(|e| std::io::Error::other(format!("{endpoint}: {e}")))
}

/// Waits (bounded) until something accepts connections at a
/// `tcp/HOST:PORT` or `tls/HOST:PORT` endpoint (inside network namespace
/// `netns` if given) or at a `unixsock-stream/PATH` one.
pub fn wait_until_listening(
    netns: Option<&str>,
    endpoint: &str,
    limit: Duration,
) -> std::io::Result<()> {
    enum Listener<'a> {
        Socket(&'a str),
        Address(SocketAddr),
    }
    let listener = match endpoint.strip_prefix(UNIX_SOCKET_LINK) {
        Some(path) => Listener::Socket(path),
        None => Listener::Address(endpoint_addr(endpoint)?),
    };
    let deadline = Instant::now() + limit;
    loop {
        let listening = match (&listener, netns) {
            // A path: the same in every network namespace.
            (Listener::Socket(path), _) => UnixStream::connect(path).is_ok(),
            (Listener::Address(addr), None) => {
                TcpStream::connect_timeout(addr, Duration::from_millis(200)).is_ok()
            }
            // This process cannot reach into the namespace: a shell there can.
            (Listener::Address(addr), Some(ns)) => Command::new("ip")
                .args(["netns", "exec", ns, "bash", "-c"])
                .arg(format!("exec 3<>/dev/tcp/{}/{}", addr.ip(), addr.port()))
                .stderr(Stdio::null())
                .status()?
                .success(),
        };
        if listening {
            return Ok(());
        }
        if Instant::now() >= deadline {
            let place = netns.map(|ns| format!(" in {ns}")).unwrap_or_default();
            return Err(std::io::Error::other(format!(
                "nothing listens at {endpoint}{place} after {limit:?}"
            )));
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}
