//! Rust-only step rate through the embedded deployment (controller + twin
//! over Zenoh), the baseline the Python benchmark compares against.
//!
//! `cargo run --release --example client_steps -- 84 84 1000 [rgbd]`
//! (width, height, steps; depth only unless `rgbd`)

use offworld_runtime::Resolution;
use std::time::Instant;

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::Target;
use offworld_runtime::msg::*;

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let args: Vec<u32> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let (w, h, n) = match args[..] {
        [w, h, n] => (w, h, n as usize),
        _ => (84, 84, 1000),
    };
    let channels = if std::env::args().any(|a| a == "rgbd") {
        Channels::Rgbd
    } else {
        Channels::DepthOnly
    };
    let task = "MonolithDiscrete";
    let connection = offworld_deploy::connect(
        Target::Embedded {
            task: task.into(),
            resolution: Resolution::new(w, h),
            count: 1,
            record: None,
            twin_profile: offworld_deploy::TwinProfile::default(),
        },
        task,
    )
    .await?;
    let request = OpenRequest::anonymous(ObsOptions {
        channels,
        height: h,
        width: w,
        depth_format: DepthFormat::Uint8,
    });
    let mut env = EnvClient::open(
        &connection.session,
        &connection.envs[0],
        request,
        ClientTimeouts::default(),
    )
    .await
    .map_err(|e| anyhow::anyhow!(e))?;
    env.reset(Seed::Fixed(0))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    let start = Instant::now();
    for i in 0..n {
        let r = env
            .step(Action::Discrete((i % 4) as i64))
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
        if r.terminated || r.truncated {
            env.reset(Seed::Continue)
                .await
                .map_err(|e| anyhow::anyhow!(e))?;
        }
    }
    let rate = n as f64 / start.elapsed().as_secs_f64();
    println!("rust_steps_per_s {rate:.1}");
    env.close().await.map_err(|e| anyhow::anyhow!(e))?;
    Ok(())
}
