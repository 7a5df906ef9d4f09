//! `sim_twin`: see [`offworld_sim_twin::cli`] (also `offworld twin`).

use clap::Parser;

fn main() -> std::process::ExitCode {
    offworld_sim_twin::cli::run(offworld_sim_twin::cli::Args::parse())
}
