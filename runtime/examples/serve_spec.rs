//! Serves an env's `spec` queryable, as a controller would.

use clap::Parser;
use offworld_program::CommonArgs;
use offworld_runtime::msg::{ActionSpace, EnvSpec};
use offworld_runtime::{wire, EnvId, Topic};

#[derive(Parser)]
struct Args {
    /// Env to serve.
    #[arg(long, default_value = "sim/monolith-0")]
    env: EnvId,
    #[command(flatten)]
    common: CommonArgs,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    offworld_program::init_logging();
    let args = Args::parse();
    let session = args.common.server_config().open().await?;
    let key = args.env.key(Topic::Spec);
    let spec = EnvSpec {
        env_id: args.env.to_string(),
        task: "MonolithDiscrete".into(),
        world: "monolith".into(),
        action_space: ActionSpace::Discrete {
            n: 4,
            names: ["LEFT", "RIGHT", "FORWARD", "BACKWARD"]
                .map(String::from)
                .to_vec(),
        },
        native_height: 240,
        native_width: 320,
        depth_max_m: 5.0,
        max_episode_steps: 100,
    };
    let queryable = session
        .declare_queryable(&key)
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    println!("serving {key}");
    while let Ok(query) = queryable.recv_async().await {
        if let Err(e) = wire::reply(&query, Ok(&spec)).await {
            eprintln!("reply failed: {e}");
        }
    }
    Ok(())
}
