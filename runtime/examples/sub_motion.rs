//! Subscribes to motion commands of one env and prints them.
//! Run with `cargo run --release --example sub_motion`,
//! then `--example pub_motion` in another shell.

use clap::Parser;
use offworld_program::CommonArgs;
use offworld_runtime::msg::MotionCommand;
use offworld_runtime::{codec, EnvId, Topic};

#[derive(Parser)]
struct Args {
    /// Env to listen to.
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
    let key = args.env.key(Topic::Cmd);
    let subscriber = session
        .declare_subscriber(&key)
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    println!("listening on {key}");
    while let Ok(sample) = subscriber.recv_async().await {
        match codec::decode_payload::<MotionCommand>(sample.payload()) {
            Ok(cmd) => println!(
                "seq {}: linear {:+.2} m/s, angular {:+.2} rad/s for {:.1} s",
                cmd.seq, cmd.linear_x, cmd.angular_z, cmd.duration_s
            ),
            // A malformed message is reported and skipped; we keep serving.
            Err(e) => eprintln!("rejected a malformed command: {e}"),
        }
    }
    Ok(())
}
