//! `env_controller`: see [`offworld_env_controller::cli`] (also `offworld serve`).

use clap::Parser;

fn main() -> std::process::ExitCode {
    offworld_env_controller::cli::run(offworld_env_controller::cli::Args::parse())
}
