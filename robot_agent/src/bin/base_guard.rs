//! `base_guard`: see [`offworld_robot_agent::guard_cli`] (also `offworld guard`).

use clap::Parser;

fn main() -> std::process::ExitCode {
    offworld_robot_agent::guard_cli::run(offworld_robot_agent::guard_cli::Args::parse())
}
