//! Instruction counts under callgrind: the benches' figure that a noisy,
//! shared machine does not move (two runs agree within 0.1 %), beside their
//! wall-clock rates.
//!
//! A bench re-runs its own executable under `valgrind --tool=callgrind`
//! twice, asking it (through environment variables of its choosing) for a
//! few units of work and for many more; the difference of the two counts
//! is the work of the extra units alone, on every thread, without the
//! setup both runs share.

use std::process::{Child, Command, Stdio};

/// `program` with `args` to run under callgrind, its output discarded.
pub fn command(program: impl AsRef<std::ffi::OsStr>) -> Command {
    let mut command = Command::new("valgrind");
    command
        .args(["--tool=callgrind", "--callgrind-out-file=/dev/null"])
        .arg(program)
        .stdout(Stdio::null())
        .stderr(Stdio::piped());
    command
}

fn spawn(mut command: Command) -> Result<Child, String> {
    command
        .spawn()
        .map_err(|e| format!("cannot run valgrind (is it installed?): {e}"))
}

/// The instructions callgrind counted for a finished run.
fn collected(child: Child) -> Result<u64, String> {
    let output = child
        .wait_with_output()
        .map_err(|e| format!("waiting for valgrind: {e}"))?;
    let log = String::from_utf8_lossy(&output.stderr);
    if !output.status.success() {
        return Err(format!(
            "the run under callgrind failed ({}):\n{log}",
            output.status
        ));
    }
    log.lines()
        .find_map(|line| {
            line.split_once("Collected :")
                .and_then(|(_, n)| n.trim().parse().ok())
        })
        .ok_or_else(|| format!("no instruction count in callgrind's output:\n{log}"))
}

/// Instructions per unit of work: `run(n)` is the command doing `n` units
/// (build it with [`command`]); it runs for `few` and `few + many` units,
/// both at once (callgrind serialises a process's threads on one core, so
/// two fit a 2-core machine), and the difference is divided by `many`.
pub fn per_unit(run: impl Fn(usize) -> Command, few: usize, many: usize) -> Result<f64, String> {
    let short = spawn(run(few))?;
    let long = spawn(run(few + many))?;
    let (short, long) = (collected(short)?, collected(long)?);
    Ok(long.saturating_sub(short) as f64 / many as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `sh` counting to `n`: work that grows with `n`.
    fn count_to(n: usize) -> Command {
        let mut run = command("sh");
        run.args([
            "-c",
            &format!("i=0; while [ $i -lt {n} ]; do i=$((i+1)); done"),
        ]);
        run
    }

    #[test]
    fn counts_the_instructions_of_the_extra_units_only() {
        let per_loop = per_unit(count_to, 10, 200).expect("valgrind runs (.ci/setup installs it)");
        // A shell loop turn is thousands of instructions, not millions: the
        // setup both runs share (starting sh) is subtracted.
        assert!(
            (100.0..100_000.0).contains(&per_loop),
            "{per_loop} instructions per loop turn"
        );
    }

    #[test]
    fn a_failing_run_is_an_error_with_its_output() {
        let failing = |_| {
            let mut run = command("sh");
            run.args(["-c", "echo broken >&2; exit 3"]);
            run
        };
        let error = per_unit(failing, 1, 2).expect_err("the run failed");
        assert!(error.contains("failed"), "{error}");
        assert!(error.contains("broken"), "{error}");
    }
}
