//! `robot_agent`: see [`offworld_robot_agent::cli`] (also `offworld robot`).

use clap::Parser;

fn main() -> std::process::ExitCode {
    offworld_robot_agent::cli::run(offworld_robot_agent::cli::Args::parse())
}
