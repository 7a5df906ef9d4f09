//! `recorder`: see [`offworld_recorder::cli`] (also `offworld recorder`).

use clap::Parser;

fn main() -> std::process::ExitCode {
    offworld_recorder::cli::run(offworld_recorder::cli::Args::parse())
}
