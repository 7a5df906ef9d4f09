//! `tracker_agent`: see [`offworld_tracker_agent::cli`] (also `offworld tracker`).

use clap::Parser;

fn main() -> std::process::ExitCode {
    offworld_tracker_agent::cli::run(offworld_tracker_agent::cli::Args::parse())
}
