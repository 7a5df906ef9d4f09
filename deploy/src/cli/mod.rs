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

use anyhow::Context;

/// Runs `command` (program and arguments, non-empty) with `environment`
/// added, while the caller's deployment keeps serving; its exit status
/// becomes this program's (a failure is said on standard error).
async fn run_against(
    command: &[String],
    environment: Vec<(String, String)>,
) -> anyhow::Result<ExitCode> {
    let Some((program, rest)) = command.split_first() else {
        anyhow::bail!("no command to run");
    };
    let mut child = std::process::Command::new(program);
    child.args(rest).envs(environment);
    let status = tokio::task::spawn_blocking(move || child.status())
        .await?
        .with_context(|| format!("running {program}"))?;
    if status.success() {
        return Ok(ExitCode::SUCCESS);
    }
    eprintln!("{program} failed: {status}");
    Ok(ExitCode::from(
        status.code().unwrap_or(1).clamp(1, 255) as u8
    ))
}
