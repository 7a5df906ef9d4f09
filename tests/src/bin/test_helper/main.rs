//! `test_helper`: the programs the cross-component tests start as
//! separate processes (a probe inside a network namespace, a misbehaving
//! trainer), one binary so a checkout links the stack once for all of
//! them. Not for users: the tests in `tests/tests/integration/` run it.
//!
//! ```text
//! test_helper base-probe --connect tcp/127.0.0.1:7448
//! test_helper floods-tokens -c trainer.json5 --connect quic/127.0.0.1:7447 --env sim/a-0
//! test_helper stops-reading -c trainer.json5 --connect quic/127.0.0.1:7447 --key offworld/@v1/sim/a-0/spec
//! ```

mod base_probe;
mod floods_tokens;
mod stops_reading;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    version,
    about = "Processes the cross-component tests start: a probe, misbehaving trainers"
)]
struct Cli {
    #[command(subcommand)]
    helper: Helper,
}

#[derive(Subcommand)]
enum Helper {
    /// Print the emulated base's odometry, one line per sample.
    BaseProbe(base_probe::Args),
    /// Declare and drop distinct client liveliness tokens in rounds.
    FloodsTokens(floods_tokens::Args),
    /// Send a burst of queries, then stop this process before reading the
    /// answers.
    StopsReading(stops_reading::Args),
}

#[tokio::main(flavor = "multi_thread", worker_threads = 1)]
async fn main() -> anyhow::Result<()> {
    match Cli::parse().helper {
        Helper::BaseProbe(args) => base_probe::run(args).await,
        Helper::FloodsTokens(args) => floods_tokens::run(args).await,
        Helper::StopsReading(args) => stops_reading::run(args).await,
    }
}
