//! `offworld` as a user runs it: one command whose subcommands are the
//! project's programs, each with its own flags, version and help, and the
//! exit status and messages of the program it runs.

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use offworld_env_controller::Store;
use offworld_test_support::ScratchDir;

const SUBCOMMANDS: [&str; 17] = [
    "serve",
    "users",
    "experiments",
    "leaderboard",
    "estop",
    "twin",
    "emulate-hardware",
    "emulate-enclosure",
    "farm",
    "robot",
    "guard",
    "tracker",
    "monitor",
    "recorder",
    "parity",
    "web",
    "gym",
];

/// One emulated enclosure at a time in this file (both are
/// `real/monolith-0`).
static ONE_ENCLOSURE: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn one_enclosure() -> std::sync::MutexGuard<'static, ()> {
    ONE_ENCLOSURE
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner())
}

fn offworld(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_offworld"))
        .args(args)
        .env("RUST_LOG", "warn")
        .env_remove("OFFWORLD_DB")
        .output()
        .expect("offworld runs")
}

fn text(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).into_owned()
}

/// `site.db` in a directory of its own.
fn scratch_db(scratch: &ScratchDir) -> PathBuf {
    scratch.join("site.db")
}

#[test]
fn every_program_is_a_subcommand_with_its_own_help() {
    let version = offworld(&["--version"]);
    assert!(version.status.success());
    assert_eq!(
        text(&version.stdout).trim(),
        format!("offworld {}", env!("CARGO_PKG_VERSION"))
    );
    let help = offworld(&["--help"]);
    assert!(help.status.success());
    let help = text(&help.stdout);
    for sub in SUBCOMMANDS {
        assert!(
            help.lines()
                .any(|l| l.trim_start().starts_with(&format!("{sub} "))),
            "`{sub}` listed in:\n{help}"
        );
        let own = offworld(&[sub, "--help"]);
        assert!(own.status.success(), "{sub} --help: {}", text(&own.stderr));
        let own = text(&own.stdout);
        assert!(
            own.contains(&format!("Usage: offworld {sub}")),
            "{sub}'s usage names it:\n{own}"
        );
    }
    // The flags are the component's own: e.g. the twin's world and the
    // zenoh endpoints every program shares.
    let twin = text(&offworld(&["twin", "--help"]).stdout);
    for flag in [
        "--env",
        "--world",
        "--connect",
        "--listen",
        "--zenoh-config",
    ] {
        assert!(twin.contains(flag), "twin {flag}:\n{twin}");
    }
}

/// The whole real-side deployment as processes, a command run against
/// it with the deployment's address and tokens, and the command's exit
/// status passed on; an unknown task is refused before anything starts.
#[test]
fn the_emulated_enclosure_runs_a_command_and_passes_on_its_status() {
    let _alone = one_enclosure();
    let out = offworld(&[
        "emulate-enclosure",
        "--",
        "sh",
        "-c",
        "test -n \"$OFFWORLD_GYM_ACCESS_TOKEN\" && echo \"$OFFWORLD_GYM_CONNECT\" && exit 3",
    ]);
    let said = text(&out.stderr);
    assert_eq!(out.status.code(), Some(3), "{said}");
    let endpoint = text(&out.stdout).trim().to_owned();
    assert!(endpoint.starts_with("tcp/127.0.0.1:"), "{endpoint}");
    assert!(
        said.contains(&format!("OFFWORLD_GYM_CONNECT={endpoint}")),
        "{said}"
    );
    assert!(
        said.contains("emulated enclosure real/monolith-0 serving MonolithDiscrete"),
        "{said}"
    );

    let out = offworld(&["emulate-enclosure", "--task", "Monolith", "--", "true"]);
    let said = text(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{said}");
    assert!(said.contains("unknown task `Monolith`"), "{said}");
    assert!(
        said.contains("MonolithDiscrete"),
        "the known tasks are listed: {said}"
    );
    assert!(!said.contains("starting"), "nothing started: {said}");
}

/// The trainer's commands (`offworld gym`; `python -m offworld_gym` runs
/// the same code) against the real stack on emulated hardware, with the
/// token and endpoint the enclosure gives its command: who the token is, a
/// slot booked and listed, empty records said so, a refusal typed.
/// (`envs` is not asked here: in two full test runs its listing right
/// after this enclosure's start held only some of the env's liveliness
/// tokens, the tokens reaching a new session over a moment; `whoami` and
/// `bookings` look again while no controller is seen, a listing cannot
/// know what it misses. `offworld gym envs` is the code the Python CLI
/// tests run against the farm.)
#[test]
fn a_trainer_books_and_asks_with_offworld_gym() {
    let _alone = one_enclosure();
    let scratch = ScratchDir::new("cli-gym");
    let script = format!(
        "set -e; g() {{ '{}' gym \"$@\"; }}; \
         start=$(date -u -d '+1 hour' +%Y-%m-%dT%H:%M:00Z); \
         g whoami; ( g whoami; echo \"into a closed pipe: $?\" >&2 ) | :; \
         g book --env real/monolith-0 --start \"$start\" --minutes 30 --json; \
         g bookings --env real/monolith-0; g leaderboard --env real/monolith-0; \
         g episodes --env real/monolith-0 --id 1 || echo \"episodes: $?\"",
        env!("CARGO_BIN_EXE_offworld")
    );
    let out = Command::new(env!("CARGO_BIN_EXE_offworld"))
        .args(["emulate-enclosure", "--", "sh", "-c", &script])
        .current_dir(scratch.path())
        .env("RUST_LOG", "warn")
        .env_remove("OFFWORLD_DB")
        .output()
        .expect("offworld runs");
    let (stdout, said) = (text(&out.stdout), text(&out.stderr));
    assert!(out.status.success(), "{said}");
    let (who, rest) = stdout.split_once('\n').expect("whoami's line");
    assert_eq!(who, "researcher");
    let json_end = rest.find("\n]\n").expect("the booking as JSON") + 3;
    let booked: serde_json::Value = serde_json::from_str(&rest[..json_end]).expect("JSON");
    let slot = &booked[0];
    assert_eq!(
        (
            &slot["env_id"],
            &slot["user"],
            booked.as_array().map(Vec::len)
        ),
        (&"real/monolith-0".into(), &"researcher".into(), Some(1))
    );
    let length = slot["end_unix_ms"]
        .as_i64()
        .zip(slot["start_unix_ms"].as_i64());
    assert_eq!(length.map(|(end, start)| end - start), Some(1_800_000));
    let listing = &rest[json_end..];
    let slot_line = listing.lines().next().expect("the env's slots");
    assert!(
        slot_line.starts_with("    1  real/monolith-0 ") && slot_line.ends_with("  researcher"),
        "{listing}"
    );
    assert!(listing.ends_with("episodes: 1\n"), "{listing}");
    // A reader that stopped reading (`| :`): the command ends quietly.
    assert!(said.contains("\ninto a closed pipe: 0\n"), "{said}");
    assert!(!said.contains("panicked"), "{said}");
    assert!(said.contains("\nno test-mode experiments yet\n"), "{said}");
    assert!(
        said.contains("\nerror: NotFound (404): no experiment 1 of yours on real/monolith-0\n"),
        "{said}"
    );
}

/// A sim farm behind the real router: the command runs with the
/// trainer's environment (its role file written by the farm, which needs
/// no checkout), its status is passed on, and the farm's files are gone
/// once it stops. A bad twin count is refused with the accepted range.
#[test]
fn the_farm_runs_a_command_with_the_trainer_environment() {
    let out = offworld(&[
        "farm",
        "--twins",
        "1",
        "--",
        "sh",
        "-c",
        "echo \"$OFFWORLD_ZENOH_CONFIG\"; echo \"$OFFWORLD_FARM_ENVS\"; \
         echo \"$OFFWORLD_GYM_CONNECT\"; test -n \"$OFFWORLD_GYM_ACCESS_TOKEN\" && \
         grep -q 'mode: \"client\"' \"$OFFWORLD_ZENOH_CONFIG\" && exit 4",
    ]);
    let said = text(&out.stderr);
    assert_eq!(out.status.code(), Some(4), "{said}");
    let stdout = text(&out.stdout);
    let lines: Vec<&str> = stdout.lines().collect();
    let [role_file, envs, connect] = lines[..] else {
        panic!("three lines expected: {stdout}");
    };
    assert!(role_file.ends_with("/roles/trainer.json5"), "{role_file}");
    assert!(
        !std::path::Path::new(role_file).exists(),
        "the farm's files are removed when it stops"
    );
    assert_eq!(envs, "sim/farm-0");
    assert!(connect.starts_with("quic/127.0.0.2:"), "{connect}");
    assert!(
        said.contains("sim farm serving sim/farm-0 (MonolithDiscrete)"),
        "{said}"
    );
    assert!(
        !said.contains("multiple network interfaces"),
        "zenoh's interface warning is not shown: {said}"
    );

    let out = offworld(&["farm", "--twins", "0", "--", "true"]);
    let said = text(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{said}");
    assert!(said.contains("0 is not in 1..=64"), "{said}");
}

/// A stop signal while a command runs against the farm stops the command
/// and the farm with it (exit 128 + 15, as a shell gives for SIGTERM): no
/// router, twin or file is left behind.
#[test]
fn a_stopped_farm_takes_its_command_and_processes_down() {
    let mut farm = Command::new(env!("CARGO_BIN_EXE_offworld"))
        .args(["farm", "--twins", "1", "--", "sh", "-c"])
        .arg("echo \"$OFFWORLD_ZENOH_CONFIG\"; exec sleep 60")
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("offworld runs");
    let mut role_file = String::new();
    std::io::BufReader::new(farm.stdout.take().expect("piped"))
        .read_line(&mut role_file)
        .expect("the command's first line");
    let site = Path::new(role_file.trim())
        .parent()
        .and_then(Path::parent)
        .expect("<site>/roles/trainer.json5")
        .to_owned();
    assert!(site.is_dir(), "{}", site.display());
    let status = terminate(&mut farm);
    assert_eq!(
        status.code(),
        Some(128 + 15),
        "a shell's status for SIGTERM"
    );
    assert!(!site.exists(), "the farm's files are removed");
    assert_eq!(
        processes_naming(&site),
        "",
        "no process of the farm is left (router, twin, gym server)"
    );
}

/// Sends `farm` SIGTERM and waits (bounded) for it to exit.
fn terminate(farm: &mut std::process::Child) -> std::process::ExitStatus {
    let pid = farm.id().to_string();
    let sent = Command::new("kill").args(["-TERM", &pid]).status();
    assert!(sent.expect("kill").success());
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Some(status) = farm.try_wait().expect("wait") {
            break status;
        }
        assert!(Instant::now() < deadline, "the farm did not stop");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The processes whose command line names `dir` (`pgrep -f`), one a line.
fn processes_naming(dir: &Path) -> String {
    let found = Command::new("pgrep")
        .args(["-a", "-f", &dir.to_string_lossy()])
        .output()
        .expect("pgrep");
    text(&found.stdout)
}

#[test]
fn a_farm_stopped_while_starting_leaves_nothing_behind() {
    // The site's directory and every process's files live under TMPDIR.
    let scratch = ScratchDir::new("cli-farm-start");
    let mut farm = Command::new(env!("CARGO_BIN_EXE_offworld"))
        .args(["farm", "--twins", "2", "--", "true"])
        .env("RUST_LOG", "warn")
        .env("TMPDIR", scratch.path())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("offworld runs");
    // The router is frozen as soon as it runs. The farm's check that it
    // listens is a bare connect, which the kernel answers for a frozen
    // listener, so the farm goes on to spawn its twins and gym server, but
    // nothing can come up through the router: the farm is still starting
    // when it is stopped however fast it starts (over the router's socket,
    // a farm became ready before a stop sent on seeing its twins). Frozen
    // before it listened, the router is let run 5 ms every 200 ms until
    // the twins are spawned.
    let deadline = Instant::now() + Duration::from_secs(60);
    let mut frozen_at: Option<Instant> = None;
    let signal = |signal: &str, pid: &str| {
        let sent = Command::new("kill").args([signal, pid]).status();
        assert!(sent.expect("kill").success());
    };
    // Stopped once the gym server, the last process it starts, is running.
    loop {
        let running = processes_naming(scratch.path());
        let router = running
            .lines()
            .find(|line| line.contains("zenohd "))
            .and_then(|line| line.split_whitespace().next());
        if let Some(router) = router {
            match frozen_at {
                None => {
                    signal("-STOP", router);
                    frozen_at = Some(Instant::now());
                }
                Some(at)
                    if at.elapsed() > Duration::from_millis(200) && !running.contains(" twin ") =>
                {
                    signal("-CONT", router);
                    std::thread::sleep(Duration::from_millis(5));
                    signal("-STOP", router);
                    frozen_at = Some(Instant::now());
                }
                Some(_) => {}
            }
        }
        if frozen_at.is_some() && running.contains(" serve ") {
            break;
        }
        assert!(farm.try_wait().expect("wait").is_none(), "the farm exited");
        assert!(Instant::now() < deadline, "the gym server never started");
        std::thread::sleep(Duration::from_millis(20));
    }
    let status = terminate(&mut farm);
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut farm.stderr.take().expect("piped"), &mut stderr)
        .expect("stderr");
    assert_eq!(status.code(), Some(128 + 15), "{stderr}");
    assert!(
        stderr.contains("stopped (SIGTERM) while starting"),
        "{stderr}"
    );
    assert_eq!(
        processes_naming(scratch.path()),
        "",
        "router, twins, gym server"
    );
    let left: Vec<_> = std::fs::read_dir(scratch.path())
        .expect("scratch")
        .map(|entry| entry.expect("entry").path())
        .collect();
    assert!(left.is_empty(), "the farm's files are removed: {left:?}");
}

#[test]
fn site_records_are_kept_through_it() {
    let scratch = ScratchDir::new("cli-users");
    let db = scratch_db(&scratch);
    let db_arg = db.to_str().expect("utf-8 path");
    let added = offworld(&["--db", db_arg, "users", "add", "alice"]);
    assert!(added.status.success(), "{}", text(&added.stderr));
    let token = text(&added.stdout).trim().to_owned();
    assert_eq!(token.len(), 32, "{token}");
    let store = Store::open_existing(&db).expect("the database it made");
    assert_eq!(
        store.authenticate(&token).expect("lookup").map(|u| u.name),
        Some("alice".to_owned())
    );
    let listed = offworld(&["--db", db_arg, "users", "list"]);
    assert!(listed.status.success(), "{}", text(&listed.stderr));
    let listed = text(&listed.stdout);
    assert!(listed.lines().any(|l| l.starts_with("alice ")), "{listed}");
    assert!(!listed.contains(&token), "a list never shows a token");
    // A reader that has stopped reading (`offworld users list | head -0`):
    // the command ends as `ls` would, killed by SIGPIPE, not by a panic.
    let (reader, writer) = std::io::pipe().expect("a pipe");
    drop(reader);
    let unread = Command::new(env!("CARGO_BIN_EXE_offworld"))
        .args(["--db", db_arg, "users", "list"])
        .env("RUST_LOG", "warn")
        .stdout(writer)
        .stderr(Stdio::piped())
        .output()
        .expect("offworld runs");
    use std::os::unix::process::ExitStatusExt;
    assert_eq!(unread.status.signal(), Some(13), "SIGPIPE: {unread:?}");
    assert_eq!(text(&unread.stderr), "");
    // The database can also come from the environment, as for env_controller.
    let from_env = Command::new(env!("CARGO_BIN_EXE_offworld"))
        .args(["experiments", "list"])
        .env("OFFWORLD_DB", &db)
        .env("RUST_LOG", "warn")
        .output()
        .expect("offworld runs");
    assert!(from_env.status.success(), "{}", text(&from_env.stderr));
}

#[test]
fn failures_exit_non_zero_with_the_programs_message() {
    let scratch = ScratchDir::new("cli-fail");
    let missing = scratch.join("typo.db");
    let listed = offworld(&["--db", missing.to_str().expect("utf-8"), "users", "list"]);
    assert_eq!(listed.status.code(), Some(1));
    let message = text(&listed.stderr);
    assert!(message.contains("no database at"), "{message}");
    assert!(message.contains("typo.db"), "{message}");
    assert!(!missing.exists(), "a mistyped --db created a database");

    let nowhere = scratch.join("no-such-dir");
    let info = offworld(&["recorder", "info", nowhere.to_str().expect("utf-8")]);
    assert_eq!(info.status.code(), Some(1));
    let message = text(&info.stderr);
    assert!(message.starts_with("recorder: "), "{message}");
    assert!(message.contains("no-such-dir"), "{message}");

    // A database named for a command that keeps no records: refused, not ignored.
    let misplaced = offworld(&["--db", "site.db", "recorder", "info", "x.mcap"]);
    assert_eq!(misplaced.status.code(), Some(2));
    let message = text(&misplaced.stderr);
    assert!(
        message.contains("--db names the gym server's database"),
        "{message}"
    );

    // A mistyped subcommand: clap's usage error (status 2) with a suggestion.
    let typo = offworld(&["monitr"]);
    assert_eq!(typo.status.code(), Some(2));
    assert!(
        text(&typo.stderr).contains("monitor"),
        "{}",
        text(&typo.stderr)
    );
}

/// The units of `deploy/systemd/` are valid for systemd itself
/// (`systemd-analyze verify`: directives, values, the programs they start),
/// with `/usr/local/bin/offworld` as the binary under test.
#[test]
fn the_systemd_units_verify() {
    let scratch = ScratchDir::new("cli-units");
    let units = offworld_test_support::package_dir().join("../deploy/systemd");
    // The router unit starts zenohd (installed by .ci/setup); any
    // executable stands in for it where it is not on PATH.
    let zenohd = Command::new("sh")
        .args(["-c", "command -v zenohd || command -v true"])
        .output()
        .expect("sh");
    let zenohd = text(&zenohd.stdout).trim().to_owned();
    let mut copied = Vec::new();
    for entry in std::fs::read_dir(&units).expect("deploy/systemd") {
        let path = entry.expect("entry").path();
        if path.extension().is_none_or(|e| e != "service") {
            continue;
        }
        let unit = std::fs::read_to_string(&path)
            .expect("readable")
            .replace("/usr/local/bin/offworld", env!("CARGO_BIN_EXE_offworld"))
            .replace("/usr/local/bin/zenohd", &zenohd);
        let copy = scratch.join(path.file_name().expect("name"));
        std::fs::write(&copy, unit).expect("writable");
        copied.push(copy);
    }
    assert_eq!(copied.len(), 8, "{copied:?}");
    let verified = Command::new("systemd-analyze")
        .arg("verify")
        .args(&copied)
        .output()
        .expect("systemd-analyze runs (Debian's systemd package, installed by .ci/setup)");
    assert!(
        verified.status.success() && verified.stderr.is_empty(),
        "{}{}",
        text(&verified.stdout),
        text(&verified.stderr)
    );
}
