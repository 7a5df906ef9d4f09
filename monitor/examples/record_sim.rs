//! Records a few episodes of an embedded sim env (twin + controller, random
//! actions) to an `.rrd`, the way `monitor --save` would:
//! `cargo run --release --example record_sim -- run.rrd [steps] [task]`
//! then `rerun run.rrd`.

use std::time::Duration;

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::embedded::{Embedded, SimEnv, Stepping, TwinProfile};
use offworld_env_controller::Store;
use offworld_monitor::{Monitor, MonitorConfig, Scope, Sink};
use offworld_runtime::msg::*;
use offworld_runtime::session::loopback_pair;
use offworld_runtime::EnvId;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    offworld_program::init_logging();
    let mut args = std::env::args().skip(1);
    let path = args.next().unwrap_or_else(|| "run.rrd".into());
    let steps: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(200);
    let task = args
        .next()
        .unwrap_or_else(|| "MonolithObstacleDiscrete".into());
    let (server, client) = loopback_pair().await?;
    let env = EnvId::sim("demo-0")?;
    let sim = SimEnv {
        env: env.clone(),
        task,
        resolution: None,
        seed: 7,
        profile: TwinProfile::default(),
        render_threads: 1,
        stepping: Stepping::OwnThread,
    };
    let _embedded = Embedded::start(&server, &[sim], Store::in_memory()?).await?;
    // The monitor rides on the env's own session, as an embedded one would.
    let monitor = Monitor::spawn(
        &server,
        MonitorConfig::new(Sink::File(path.clone().into())).scope(Scope::env(env.clone())),
    )?;
    let request = OpenRequest::anonymous(ObsOptions {
        channels: Channels::Rgbd,
        height: 84,
        width: 84,
        depth_format: DepthFormat::Uint8,
    });
    let mut gym = EnvClient::open_when_ready(
        &client,
        &env,
        request,
        ClientTimeouts::default(),
        Duration::from_secs(5),
    )
    .await
    .map_err(|e| anyhow::anyhow!(e))?;
    let n = match &gym.spec().action_space {
        ActionSpace::Discrete { n, .. } => i64::from(*n),
        ActionSpace::Box { .. } => anyhow::bail!("this example drives discrete tasks"),
    };
    gym.reset(Seed::Fixed(7))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    let mut state = 0x9e37_79b9_7f4a_7c15_u64;
    for _ in 0..steps {
        // xorshift: a reproducible random agent without a dependency.
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        let r = gym
            .step(Action::Discrete((state % n as u64) as i64))
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
        if r.terminated || r.truncated {
            gym.reset(Seed::Continue)
                .await
                .map_err(|e| anyhow::anyhow!(e))?;
        }
    }
    gym.close().await.map_err(|e| anyhow::anyhow!(e))?;
    let stats = tokio::task::spawn_blocking(move || monitor.shutdown()).await??;
    println!("{path}: {stats:?}");
    Ok(())
}
