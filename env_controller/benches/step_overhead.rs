//! What the controller + Zenoh add to a step on loopback, side by side with
//! the floor: a raw Zenoh get/reply carrying the same observation bytes.
//!
//! Each step's overhead is its round trip minus the compute the twin itself
//! measured for it (physics + render, `TwinNode::stats`). The floor is
//! measured in a tight loop and interleaved with the steps (raw, step, raw,
//! …), so slow spells of a shared machine hit both alike; the ratio and the
//! µs above the floor are also taken per step against the floor run just
//! before it. Each resolution runs twice: the twin simulating on its own
//! thread (`offworld serve`, a farm, `make_vec`) and where its command
//! arrives (`gymnasium.make`'s one embedded env; here Zenoh's receive
//! thread). Run: `cargo bench --bench step_overhead` (one resolution:
//! `STEP_OVERHEAD_ONLY=84x84`; one stepping: `STEP_OVERHEAD_STEPPING=own-thread`
//! or `on-arrival`).

use offworld_runtime::Resolution;
use std::time::{Duration, Instant};

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::embedded::{Embedded, SimEnv, Stepping, TwinProfile};
use offworld_env_controller::Store;
use offworld_runtime::msg::*;
use offworld_runtime::session::loopback_pair;
use offworld_runtime::EnvId;

const STEPS: usize = 300;
const WARMUP: usize = 20;

/// The `q`-quantile (0..=1) of `v`.
fn quantile(v: &[f64], q: f64) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    // `STEP_OVERHEAD_ONLY=84x84` runs one resolution (for profiling one).
    let only = std::env::var("STEP_OVERHEAD_ONLY").ok();
    let only_stepping = std::env::var("STEP_OVERHEAD_STEPPING").ok();
    for (w, h) in [(320, 240), (84, 84)] {
        if only.as_deref().is_some_and(|o| o != format!("{w}x{h}")) {
            continue;
        }
        for (name, stepping) in [
            ("own-thread", Stepping::OwnThread),
            ("on-arrival", Stepping::OnArrival),
        ] {
            if only_stepping.as_deref().is_none_or(|o| o == name) {
                run(w, h, name, stepping).await?;
            }
        }
    }
    Ok(())
}

async fn run(w: u32, h: u32, stepping_name: &str, stepping: Stepping) -> anyhow::Result<()> {
    let obs_bytes = (w * h * 4) as usize; // RGBD uint8
    let (server, client) = loopback_pair().await?;

    // Floor: raw get/reply with a payload the size of the observation.
    let raw_key = format!("bench/raw/{w}x{h}/{stepping_name}");
    let raw_key = raw_key.as_str();
    let queryable = server
        .declare_queryable(raw_key)
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    let payload = vec![7u8; obs_bytes];
    let reply_key = raw_key.to_owned();
    let server_task = tokio::spawn(async move {
        while let Ok(q) = queryable.recv_async().await {
            let _ = q.reply(&reply_key, payload.clone()).await;
        }
    });
    let raw_round_trip = || async {
        let start = Instant::now();
        let replies = client
            .get(raw_key)
            .payload(vec![0u8; 32])
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
        let reply = replies
            .recv_async()
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let n = reply.result().map(|s| s.payload().len()).unwrap_or(0);
        anyhow::ensure!(n == obs_bytes, "raw reply of {n} bytes");
        Ok(start.elapsed().as_secs_f64() * 1e6)
    };

    // The controller and the twin node, embedded on the server session.
    let env = EnvId::sim(&format!("bench-{w}x{h}-{stepping_name}"))?;
    let sim = SimEnv {
        env: env.clone(),
        task: "MonolithDiscrete".into(),
        resolution: Some(Resolution::new(w, h)),
        seed: 0,
        profile: TwinProfile::default(),
        render_threads: 1,
        stepping,
    };
    let embedded = Embedded::start(&server, &[sim], Store::in_memory()?).await?;
    let request = OpenRequest::anonymous(ObsOptions {
        channels: Channels::Rgbd,
        height: h,
        width: w,
        depth_format: DepthFormat::Uint8,
    });
    let wait = Duration::from_secs(10);
    let mut gym =
        EnvClient::open_when_ready(&client, &env, request, ClientTimeouts::default(), wait)
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
    gym.reset(Seed::Fixed(0))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;

    let twin = &embedded.twins[0];

    for _ in 0..WARMUP {
        raw_round_trip().await?;
    }
    // The floor in a tight loop (hot caches, nothing else running)…
    let mut raw_hot = Vec::new();
    for _ in 0..STEPS {
        raw_hot.push(raw_round_trip().await?);
    }
    // …and interleaved with the steps, so it runs in the state a step leaves
    // the machine in, and slow spells of a shared machine hit all alike.
    let (mut raw, mut full, mut compute) = (Vec::new(), Vec::new(), Vec::new());
    for i in 0..STEPS {
        raw.push(raw_round_trip().await?);
        let before = twin.stats();
        let start = Instant::now();
        let r = gym
            .step(Action::Discrete((i % 4) as i64))
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
        full.push(start.elapsed().as_secs_f64() * 1e6);
        let after = twin.stats();
        anyhow::ensure!(r.observation.data.len() == obs_bytes);
        anyhow::ensure!(
            after.answered == before.answered + 1,
            "the twin answered {} commands in one step",
            after.answered - before.answered
        );
        compute.push((after.compute - before.compute).as_secs_f64() * 1e6);
        if r.terminated || r.truncated {
            gym.reset(Seed::Fixed(0))
                .await
                .map_err(|e| anyhow::anyhow!(e))?;
        }
    }
    gym.close().await.map_err(|e| anyhow::anyhow!(e))?;
    server_task.abort();

    let median = |v: &[f64]| quantile(v, 0.5);
    let overhead: Vec<f64> = (0..STEPS).map(|i| full[i] - compute[i]).collect();
    let (hot, raw_m, overhead_m) = (median(&raw_hot), median(&raw), median(&overhead));
    println!("step overhead at {w}x{h} RGBD uint8 ({obs_bytes} B observations), loopback TCP, the twin stepping {stepping_name}, medians of {STEPS}:");
    println!("  floor: raw zenoh get/reply, tight loop      : {hot:8.0} µs");
    println!("  floor: raw zenoh get/reply, between steps   : {raw_m:8.0} µs");
    println!(
        "  full step via controller + twin             : {:8.0} µs",
        median(&full)
    );
    println!(
        "  twin compute (physics + render), in the twin: {:8.0} µs",
        median(&compute)
    );
    println!("  controller + zenoh overhead = full − compute: {overhead_m:8.0} µs");
    for (name, floor) in [("tight-loop", hot), ("between-steps", raw_m)] {
        println!(
            "    vs the {name} floor: {:.2}×, {:.0} µs above it",
            overhead_m / floor,
            overhead_m - floor
        );
    }
    // Against the floor run just before each step: a slow spell then hits
    // both sides of a pair.
    let paired = |f: fn(f64, f64) -> f64| -> Vec<f64> {
        (0..STEPS).map(|i| f(overhead[i], raw[i])).collect()
    };
    println!(
        "  paired per step: {:.2}× its between-steps floor, {:.0} µs above it",
        median(&paired(|o, r| o / r)),
        median(&paired(|o, r| o - r))
    );
    Ok(())
}
