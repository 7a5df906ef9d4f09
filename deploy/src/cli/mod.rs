//! The `offworld` commands that put pieces together: `serve` (the gym
//! server, with in-process twins on request), `emulate-hardware` (a twin
//! behaving like the enclosure's hardware), `emulate-enclosure` (the real
//! stack against that hardware, as processes) and `farm` (sim twins and a
//! gym server behind the site's router).

pub mod enclosure;
pub mod farm;
pub mod hardware;
pub mod serve;

use std::future::Future;
use std::os::unix::process::ExitStatusExt;
use std::process::ExitCode;
use std::time::Duration;

use anyhow::Context;
use offworld_runtime::shutdown::{ShutdownSignal, ShutdownSignals};

use crate::process::Process;

/// How long a command told to stop has before it is killed.
const COMMAND_STOP_LIMIT: Duration = Duration::from_secs(5);

/// How long a signal that has just arrived may take to be seen: the
/// runtime reads it from its signal pipe, not at once.
const SIGNAL_GRACE: Duration = Duration::from_millis(200);

/// How long a command has to stop on its own after Ctrl-C, which a terminal
/// sends to the whole process group (the command too) before this program
/// passes it on: a Python trainer would otherwise get a second
/// `KeyboardInterrupt` in the middle of its cleanup.
const INTERRUPT_GRACE: Duration = Duration::from_secs(1);

/// A signal's name for `kill` and the exit status a shell gives for it
/// (128 + its number).
fn signal_name_and_status(signal: ShutdownSignal) -> (&'static str, u8) {
    match signal {
        ShutdownSignal::Interrupt => ("INT", 128 + 2),
        ShutdownSignal::Terminate => ("TERM", 128 + 15),
        ShutdownSignal::Hangup => ("HUP", 128 + 1),
    }
}

/// Starts a deployment (`start`: its processes, then the wait until it
/// serves) unless a stop signal comes first. The caller installed
/// `signals` before, so a stop during the start is kept and answered here:
/// `Err` carries the exit status (128 + the signal's number), and what was
/// started is dropped, so taken down, instead of this program dying and
/// leaving it behind. A start that fails just after a stop (Ctrl-C at a
/// terminal reaches the router and the other children too) is reported as
/// the stop.
async fn started_unless_stopped<T>(
    signals: &mut ShutdownSignals,
    start: impl Future<Output = anyhow::Result<T>>,
) -> anyhow::Result<Result<T, ExitCode>> {
    let stopped = |signal: ShutdownSignal| {
        eprintln!("stopped ({signal}) while starting");
        Ok(Err(ExitCode::from(signal_name_and_status(signal).1)))
    };
    let started = tokio::select! {
        biased;
        signal = signals.recv() => return stopped(signal),
        started = start => started,
    };
    match started {
        Ok(deployment) => Ok(Ok(deployment)),
        Err(e) => match tokio::time::timeout(SIGNAL_GRACE, signals.recv()).await {
            Ok(signal) => stopped(signal),
            Err(_) => Err(e),
        },
    }
}

/// What a started deployment does next: serves until a stop signal (a
/// normal end: exit 0) when `command` is empty, else runs it against the
/// deployment ([`run_against`]).
async fn serve_or_run(
    signals: &mut ShutdownSignals,
    command: &[String],
    environment: Vec<(String, String)>,
) -> anyhow::Result<ExitCode> {
    if command.is_empty() {
        eprintln!("Ctrl-C to stop");
        let signal = signals.recv().await;
        eprintln!("stopped ({signal})");
        return Ok(ExitCode::SUCCESS);
    }
    run_against(signals, command, environment).await
}

/// Runs `command` (program and arguments, non-empty) with `environment`
/// added, while the caller's deployment keeps serving; its exit status
/// becomes this program's (a failure is said on standard error; a command
/// killed by a signal gives 128 + its number, as a shell does). A stop
/// signal (Ctrl-C, SIGTERM, SIGHUP) is passed on to the command, which is
/// killed if it has not exited within 5 s, and gives 128 + the signal's
/// number, so the caller takes its deployment down instead of dying and
/// leaving it behind (Ctrl-C, which a terminal sends to the command too, is
/// passed on only if the command has not exited 1 s later). The signal
/// reaches the command alone, not processes it started (it shares this
/// program's terminal and process group, so Ctrl-C at a terminal reaches
/// them all anyway).
async fn run_against(
    signals: &mut ShutdownSignals,
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
    let status = loop {
        if let Some(status) = child.0.try_wait()? {
            break status;
        }
        tokio::select! {
            _ = tokio::time::sleep(Duration::from_millis(50)) => {}
            signal = signals.recv() => {
                let (name, status) = signal_name_and_status(signal);
                let exited = signal == ShutdownSignal::Interrupt
                    && child.wait_exit(INTERRUPT_GRACE).is_some();
                if !exited {
                    child.signal(name);
                    child.wait_exit(COMMAND_STOP_LIMIT);
                }
                eprintln!("stopped ({signal}): {program} was stopped too");
                return Ok(ExitCode::from(status));
            }
        }
    };
    if status.success() {
        return Ok(ExitCode::SUCCESS);
    }
    eprintln!("{program} failed: {status}");
    let code = match (status.code(), status.signal()) {
        (Some(code), _) => code.clamp(1, 255),
        (None, Some(signal)) => (128 + signal).min(255),
        (None, None) => 1,
    };
    Ok(ExitCode::from(code as u8))
}
