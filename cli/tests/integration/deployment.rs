//! The smallest multi-process deployment, with no router: `offworld serve`
//! listening and a standalone `offworld twin` connecting to it, both with
//! default modes. Whatever else connects (a monitor, the e-stop CLI, a
//! listing) reaches the twin through the controller: its presence is
//! listed and its e-stop acknowledged.

use std::process::{Child, Command, Stdio};
use std::time::Duration;

use offworld_client::operator::{press_estop, EStopScope};
use offworld_program::CommonArgs;
use offworld_runtime::keys::EnvId;
use offworld_test_support::ScratchDir;

/// `offworld ARGS` with the connection modes left to their defaults.
fn offworld(args: &[&str]) -> Command {
    let mut command = Command::new(env!("CARGO_BIN_EXE_offworld"));
    command
        .args(args)
        .env("RUST_LOG", "warn")
        .env_remove("OFFWORLD_ZENOH_MODE")
        .stdout(Stdio::null())
        .stderr(Stdio::inherit());
    command
}

/// A program of the deployment, killed when the test ends.
struct Running(Child);

impl Running {
    fn start(args: &[&str]) -> Self {
        Self::spawn(&mut offworld(args))
    }

    fn spawn(command: &mut Command) -> Self {
        Self(command.spawn().expect("offworld starts"))
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_standalone_twin_behind_a_peer_controller_is_reachable_by_every_client() {
    let endpoint = offworld_runtime::session::loopback_endpoint().expect("a free port");
    let scratch = ScratchDir::new("cli-deployment");
    let db = scratch.join("site.db");
    let db_arg = db.to_str().expect("utf-8").to_owned();
    let _controller = Running::start(&[
        "--db",
        &db_arg,
        "serve",
        "--env",
        "sim/alone-0=MonolithDiscrete",
        "--listen",
        &endpoint,
    ]);
    let _twin = Running::start(&["twin", "--env", "sim/alone-0", "--connect", &endpoint]);

    // Connected as every program connects by default (`client_config`).
    let session = CommonArgs {
        connect: vec![endpoint.clone()],
        ..CommonArgs::default()
    }
    .client_config()
    .open_reaching(Duration::from_secs(10))
    .await
    .expect("the controller answers");
    let env = EnvId::sim("alone-0").expect("env id");
    let mut components = Vec::new();
    for _ in 0..100 {
        let listed = offworld_client::discover(&session, Duration::from_secs(2))
            .await
            .expect("a listing");
        if let Some(listing) = listed.iter().find(|l| l.env == env) {
            components = listing.components.clone();
            if components.iter().any(|c| c == "sim_twin") {
                break;
            }
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(components, ["controller", "sim_twin"]);

    let report = press_estop(
        &session,
        &EStopScope::Env(env.clone()),
        true,
        "deployment test",
        Duration::from_secs(5),
        Duration::from_secs(5),
    )
    .await
    .expect("the twin acknowledges through the controller");
    assert_eq!(report.acknowledged.len(), 1, "{report:?}");
    assert_eq!(report.acknowledged[0].component, "sim_twin");
    assert_eq!(report.acknowledged[0].state.summary(), "env");
    let _ = session.close().await;
}

/// A connecting program waits for its server (programs start in any
/// order), and a stop while it waits ends it, saying so.
#[test]
fn a_client_waiting_for_its_server_stops_when_told() {
    let endpoint = offworld_runtime::session::loopback_endpoint().expect("a free port");
    let mut running = Running::spawn(
        offworld(&["twin", "--env", "sim/waiting-0", "--connect", &endpoint])
            .env("RUST_LOG", "info")
            .env("RUST_BACKTRACE", "0")
            .stderr(Stdio::piped()),
    );
    let child = &mut running.0;
    // Still waiting after a while: nobody listens there.
    std::thread::sleep(Duration::from_millis(1500));
    assert!(child.try_wait().expect("status").is_none(), "it waits");
    let _ = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status();
    let mut status = None;
    for _ in 0..200 {
        status = child.try_wait().expect("status");
        if status.is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let Some(status) = status else {
        panic!("still running 10 s after SIGTERM");
    };
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().expect("piped"), &mut stderr)
        .expect("stderr");
    assert_eq!(status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains(&format!(
            "stopped (SIGTERM) while waiting for {endpoint} to answer"
        )),
        "{stderr}"
    );
}
