//! Rust-only step rate through the embedded deployment (controller + twin
//! over Zenoh), the baseline the Python benchmark compares against.
//!
//! `cargo run --release --example client_steps -- 84 84 1000 [rgbd] [envs=2] [no-recycle]`
//! (width, height, steps in all; depth only unless `rgbd`; `envs=N` steps N
//! envs at once through a `VecEnvClient`, as `make_vec` does; `no-recycle`
//! drops each observation instead of handing its buffer back, as every
//! client did before observation buffers were pooled)

use offworld_runtime::Resolution;
use std::time::Instant;

use offworld_client::{ClientTimeouts, EnvClient, VecEnvClient};
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
    let count = std::env::args()
        .find_map(|a| a.strip_prefix("envs=").and_then(|n| n.parse().ok()))
        .unwrap_or(1usize)
        .max(1);
    let recycle = !std::env::args().any(|a| a == "no-recycle");
    let task = "MonolithDiscrete";
    let connection = offworld_deploy::connect(
        Target::Embedded {
            task: task.into(),
            resolution: Resolution::new(w, h),
            count,
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
    let mut clients = Vec::new();
    for env in &connection.envs {
        let client = EnvClient::open(
            &connection.session,
            env,
            request.clone(),
            ClientTimeouts::default(),
        )
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
        clients.push(client);
    }
    let mut envs = VecEnvClient::new(clients);
    envs.reset(&vec![Seed::Fixed(0); count])
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    let rounds = n / count;
    let start = Instant::now();
    for i in 0..rounds {
        let action = Action::Discrete((i % 4) as i64);
        // One env steps as `gymnasium.make` does: an ended episode is reset
        // at once and the reset is not counted. Several step as `make_vec`
        // does: an ended episode resets at its next step.
        let replies = if count == 1 {
            let env = envs.get_mut(0).ok_or_else(|| anyhow::anyhow!("no env"))?;
            let reply = env.step(action).await.map_err(|e| anyhow::anyhow!(e))?;
            if reply.terminated || reply.truncated {
                let reset = env.reset(Seed::Continue).await;
                let reset = reset.map_err(|e| anyhow::anyhow!(e))?;
                env.observation_buffers().recycle(reset.observation.data);
            }
            vec![reply]
        } else {
            let steps = envs.step(vec![action; count]).await;
            let steps = steps.map_err(|e| anyhow::anyhow!(e))?;
            steps.into_iter().map(|s| s.reply).collect()
        };
        // Done with the pixels: their memory serves a later step, as the
        // Python package's arrays do when dropped.
        for (env, reply) in (0..count).filter_map(|k| envs.get(k)).zip(replies) {
            if recycle {
                env.observation_buffers().recycle(reply.observation.data);
            }
        }
    }
    let rate = (rounds * count) as f64 / start.elapsed().as_secs_f64();
    println!("rust_steps_per_s {rate:.1}");
    envs.close().await.map_err(|e| anyhow::anyhow!(e))?;
    Ok(())
}
