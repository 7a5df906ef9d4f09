//! `monitor`: see [`offworld_monitor::cli`] (also `offworld monitor`).

use clap::Parser;

fn main() -> std::process::ExitCode {
    offworld_monitor::cli::run(offworld_monitor::cli::Args::parse())
}
