//! The `offworld` commands that put pieces together: `serve` (the gym
//! server, with in-process twins on request), `emulate-hardware` (a twin
//! behaving like the enclosure's hardware), `emulate-enclosure` (the real
//! stack against that hardware, as processes) and `farm` (sim twins and a
//! gym server behind the site's router).

pub mod enclosure;
pub mod farm;
pub mod hardware;
pub mod serve;

use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;

use crate::process::Process;

/// How long a command told to stop (SIGTERM) has before it is killed.
const COMMAND_STOP_LIMIT: Duration = Duration::from_secs(5);

/// Runs `command` (program and arguments, non-empty) with `environment`
/// added, while the caller's deployment keeps serving; its exit status
/// becomes this program's (a failure is said on standard error). A stop
/// signal (Ctrl-C, SIGTERM) ends the command too and returns 130, so the
/// caller takes its deployment down instead of dying and leaving it behind.
async fn run_against(
    command: &[String],
    environment: Vec<(String, String)>,
) -> anyhow::Result<ExitCode> {
    let Some((program, rest)) = command.split_first() else {
        anyhow::bail!("no command to run");
    };
    let mut child = Process(
        std::process::Command::new(program)
            .args(rest)
            .envs(environment)
            .spawn()
            .with_context(|| format!("running {program}"))?,
    );
    let stop = offworld_runtime::shutdown::signalled();
    tokio::pin!(stop);
    let status = loop {
        if let Some(status) = child.0.try_wait()? {
            break status;
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_millis(50)) => {}
            signal = &mut stop => {
                child.signal("TERM");
                child.wait_exit(COMMAND_STOP_LIMIT);
                let signal = signal.map_or_else(|e| e.to_string(), |s| s.to_string());
                eprintln!("stopped ({signal}): {program} was stopped too");
                return Ok(ExitCode::from(130));
            }
        }
    };
    if status.success() {
        return Ok(ExitCode::SUCCESS);
    }
    eprintln!("{program} failed: {status}");
    Ok(ExitCode::from(
        status.code().unwrap_or(1).clamp(1, 255) as u8
    ))
}
