//! Queries an env's `spec`, as a client would.

use std::time::Duration;

use clap::Parser;
use offworld_program::CommonArgs;
use offworld_runtime::msg::EnvSpec;
use offworld_runtime::{wire, EnvId, Topic};

#[derive(Parser)]
struct Args {
    /// Env to query.
    #[arg(long, default_value = "sim/monolith-0")]
    env: EnvId,
    #[command(flatten)]
    common: CommonArgs,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    offworld_program::init_logging();
    let args = Args::parse();
    let session = args.common.client_config().open().await?;
    let key = args.env.key(Topic::Spec);
    // Give the connection a moment to learn the remote queryable.
    tokio::time::sleep(Duration::from_millis(300)).await;
    match wire::request::<_, EnvSpec>(&session, &key, &(), Duration::from_secs(2)).await {
        Ok(spec) => println!("{spec:#?}"),
        Err(e) => {
            let e = e.into_wire();
            eprintln!("{e}");
            std::process::exit(1);
        }
    }
    Ok(())
}
