//! `test_helper base-probe`: prints the emulated base's odometry, one line
//! per sample (`yaw x y moving`), for an observer that cannot reach the
//! hardware itself (a test whose robot runs in a network namespace of its
//! own starts this probe inside it).
//!
//! ```text
//! ip netns exec ow-robot-1 test_helper base-probe --connect tcp/127.0.0.1:7448
//! ```

use std::io::Write;

use offworld_runtime::codec;
use offworld_runtime::msg::Odometry;
use offworld_runtime::ros2::{RobotTopics, RosGraph, RosType};
use offworld_runtime::session::Mode;
use offworld_runtime::SessionConfig;
use offworld_tests::faults::BaseState;

#[derive(clap::Args)]
pub struct Args {
    /// The hardware's Zenoh endpoint (a peer).
    #[arg(long)]
    connect: String,
}

pub async fn run(args: Args) -> anyhow::Result<()> {
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
