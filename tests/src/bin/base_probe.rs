//! `base_probe`: test helper. Prints the emulated base's odometry, one line
//! per sample (`yaw x y moving`), for an observer that cannot reach the
//! hardware itself (a test whose robot runs in a network namespace of its
//! own starts this probe inside it).
//!
//! ```text
//! ip netns exec ow-robot-1 base_probe --connect tcp/127.0.0.1:7448
//! ```

use std::io::Write;

use clap::Parser;
use offworld_runtime::codec;
use offworld_runtime::msg::Odometry;
use offworld_runtime::ros2::{RobotTopics, RosGraph, RosType};
use offworld_runtime::session::Mode;
use offworld_runtime::SessionConfig;
use offworld_tests::faults::BaseState;

#[derive(Parser)]
#[command(
    version,
    about = "Print the emulated base's odometry, one line per sample"
)]
struct Args {
    /// The hardware's Zenoh endpoint (a peer).
    #[arg(long)]
    connect: String,
}

#[tokio::main(flavor = "multi_thread", worker_threads = 1)]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut config = SessionConfig::connecting(&args.connect);
    config.mode = Mode::Peer;
    let session = config.open().await.map_err(|e| anyhow::anyhow!("{e}"))?;
    let key = RosGraph::new(Default::default(), "")?
        .subscription_key(&RobotTopics::default().odom, RosType::Odometry)?;
    let odometry = session
        .declare_subscriber(key)
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut out = std::io::stdout().lock();
    while let Ok(sample) = odometry.recv_async().await {
        let Ok(odom) = codec::decode_payload::<Odometry>(sample.payload()) else {
            continue;
        };
        writeln!(out, "{}", BaseState::of(&odom))?;
        out.flush()?;
    }
    Ok(())
}
