//! `lab_web`: see [`offworld_web::cli`] (also `offworld web`).

use clap::Parser;

fn main() -> std::process::ExitCode {
    offworld_web::cli::run(offworld_web::cli::Args::parse())
}
