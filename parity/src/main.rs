//! `parity`: see [`offworld_parity::cli`] (also `offworld parity`).

use clap::Parser;

fn main() -> std::process::ExitCode {
    offworld_parity::cli::run(offworld_parity::cli::Args::parse())
}
