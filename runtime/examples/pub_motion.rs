//! Publishes the four discrete motions of the Monolith task in a loop, as
//! the controller does: `cmd` at the control priority, each message also on
//! its viewers' copy (`preview_cmd`) while a live monitor watches.

use std::time::Duration;

use clap::Parser;
use offworld_program::CommonArgs;
use offworld_runtime::msg::MotionCommand;
use offworld_runtime::preview::WatchedPublisher;
use offworld_runtime::wire::{self, Delivery};
use offworld_runtime::{EnvId, Topic};

#[derive(Parser)]
struct Args {
    /// Env to command.
    #[arg(long, default_value = "sim/monolith-0")]
    env: EnvId,
    /// Commands to send (0 = forever).
    #[arg(long, default_value_t = 0)]
    count: u64,
    #[command(flatten)]
    common: CommonArgs,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    offworld_program::init_logging();
    let args = Args::parse();
    let session = args.common.client_config().open().await?;
    let key = args.env.key(Topic::Cmd);
    let cmd = wire::publisher(&session, key.clone(), Delivery::Every)
        .priority(wire::CONTROL_PRIORITY)
        .await
        .map_err(|e| anyhow::anyhow!("declaring `{key}`: {e}"))?;
    let cmd = WatchedPublisher::new(&session, &args.env, Topic::Cmd, cmd);
    let table = [
        (0.07, 1.25, 1.2),
        (0.07, -1.25, 1.2),
        (0.1, 0.0, 0.6),
        (-0.1, 0.0, 0.6),
    ];
    let mut seq = 0;
    while args.count == 0 || seq < args.count {
        let (linear_x, angular_z, duration_s) = table[(seq % 4) as usize];
        let motion = MotionCommand {
            seq,
            linear_x,
            angular_z,
            duration_s,
        };
        cmd.publish_sealed(&motion, None)?;
        println!("sent seq {seq} on {key}");
        seq += 1;
        tokio::time::sleep(Duration::from_millis(500)).await;
    }
    Ok(())
}
