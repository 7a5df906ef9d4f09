//! What recording episodes costs (issue 23):
//!
//! 1. the embedded step rate at 84×84 depth without and with `record`
//!    (rounds interleaved, so slow spells of a shared machine hit both);
//! 2. the writer's time per real-robot step: a 320×240 RGBD frame the twin
//!    rendered, its pose and step record, written and flushed as a chunk
//!    (on the real path this runs on the recorder's thread; the step itself
//!    only queues the frame).
//!
//! Run: `cargo bench --bench record_cost`
//! (`RECORD_COST_ROUNDS=N` for more rounds than the default 5: the cost is
//! the median of each round's paired ratio, so more rounds narrow it).
//!
//! Wall clock on a shared 2-core VM swings by several points from one run
//! to the next, so the cost is also counted in instructions, which do not
//! (two runs agree within 0.1 %): `RECORD_COST_INSTRUCTIONS=1` runs the
//! bench itself under callgrind, with and without recording, for
//! [`FEW_STEPS`] and [`STEPS`] + [`FEW_STEPS`] steps: the difference of the
//! two counts is 1,000 steps' work on every thread, without the setup.

use offworld_runtime::Resolution;
use std::path::{Path, PathBuf};
use std::time::Instant;

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::{connect, Target};
use offworld_recorder::episode_file::{Channel, Compression, EpisodeFile};
use offworld_recorder::msg::{EpisodeEnd, EpisodeInfo};
use offworld_runtime::msg::*;
use offworld_test_support::callgrind;

const DEFAULT_ROUNDS: usize = 5;
const STEPS: usize = 1000;
/// The shorter run of an instruction count (its setup is subtracted).
const FEW_STEPS: usize = 200;

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "offworld-record-bench-{name}-{}",
        offworld_runtime::keys::random_id()
    ));
    std::fs::create_dir_all(&dir).expect("scratch");
    dir
}

/// Steps/s of `steps` random-ish steps on a fresh embedded env.
async fn steps_per_s(
    steps: usize,
    (w, h): (u32, u32),
    channels: Channels,
    record: Option<&Path>,
) -> anyhow::Result<f64> {
    let connection = connect(
        Target::Embedded {
            task: "MonolithDiscrete".into(),
            resolution: Resolution::new(w, h),
            count: 1,
            record: record.map(Path::to_owned),
            twin_profile: offworld_deploy::TwinProfile::default(),
        },
        "MonolithDiscrete",
    )
    .await?;
    let request = OpenRequest::anonymous(ObsOptions {
        channels,
        height: h,
        width: w,
        depth_format: DepthFormat::Uint8,
    });
    let mut client = EnvClient::open(
        &connection.session,
        &connection.envs[0],
        request,
        ClientTimeouts::default(),
    )
    .await
    .map_err(|e| anyhow::anyhow!("{e}"))?;
    client
        .reset(Seed::Fixed(1))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let start = Instant::now();
    for i in 0..steps {
        let reply = client
            .step(Action::Discrete((i % 3) as i64))
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        if reply.terminated || reply.truncated {
            client
                .reset(Seed::Continue)
                .await
                .map_err(|e| anyhow::anyhow!("{e}"))?;
        }
    }
    let rate = steps as f64 / start.elapsed().as_secs_f64();
    client.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok(rate)
}

/// The writer's time per step for real frames: `frames` (colour, depth,
/// pose, step payloads as recorded) written again into a new file.
fn writer_ms_per_step(frames: &[[Vec<u8>; 4]], dir: &Path) -> anyhow::Result<Vec<f64>> {
    let info = EpisodeInfo {
        header: Header::default(),
        env_id: "real/bench".into(),
        task: "MonolithDiscrete".into(),
        world: "monolith".into(),
        experiment_id: 1,
        experiment: "bench".into(),
        learning_type: "end2end".into(),
        algorithm_mode: "train".into(),
        episode_id: 0,
        seeded: false,
        seed: 0,
        embodiment: "robot".into(),
        software_version: String::new(),
        max_episode_steps: 100,
        requested_start: [0.0; 3],
    };
    let mut file = EpisodeFile::create(&dir.join("bench.mcap"), &info, Some(Compression::Zstd))?;
    let mut per_step = Vec::new();
    for (i, [color, depth, pose, step]) in frames.iter().enumerate() {
        let start = Instant::now();
        let at = i as u64 * 1_000_000;
        file.write_cdr(Channel::Color, at, at, color)?;
        file.write_cdr(Channel::Depth, at, at, depth)?;
        file.write_cdr(Channel::Pose, at, at, pose)?;
        file.write_cdr(Channel::Step, at, at, step)?;
        file.end_step()?;
        per_step.push(start.elapsed().as_secs_f64() * 1e3);
    }
    file.finish(
        &EpisodeEnd {
            header: Header::default(),
            episode_id: 0,
            steps: frames.len() as u32,
            episode_return: 0.0,
            success: false,
            terminated: false,
            truncated: true,
            end_reason: "step_limit".into(),
        },
        true,
    )?;
    Ok(per_step)
}

/// Per step of every recorded file under `dir`: colour, depth, pose, step CDR.
fn recorded_frames(dir: &Path) -> anyhow::Result<Vec<[Vec<u8>; 4]>> {
    let mut frames = Vec::new();
    for path in offworld_recorder::read::episode_files(dir)? {
        let buf = std::fs::read(&path)?;
        let mut current: [Vec<u8>; 4] = Default::default();
        for message in mcap::MessageStream::new(&buf)? {
            let message = message?;
            let slot = match message.channel.topic.as_str() {
                "/camera/color/image_raw" => 0,
                "/camera/depth/image_raw" => 1,
                "/tracker/pose" => 2,
                "/offworld/step" => 3,
                _ => continue,
            };
            current[slot] = message.data.into_owned();
            if slot == 3 {
                frames.push(std::mem::take(&mut current));
            }
        }
    }
    Ok(frames)
}

/// The positive whole number in variable `name`, or `default`.
fn count_from_env(name: &str, default: usize) -> anyhow::Result<usize> {
    match std::env::var(name) {
        Ok(n) => n
            .parse::<usize>()
            .ok()
            .filter(|n| *n > 0)
            .ok_or_else(|| anyhow::anyhow!("{name}={n}: a positive whole number")),
        Err(_) => Ok(default),
    }
}

/// One embedded env, with or without recording, for an instruction count.
async fn only(mode: &str, steps: usize) -> anyhow::Result<()> {
    let dir = scratch("only");
    let record = match mode {
        "with" => Some(dir.join("runs")),
        "without" => None,
        other => anyhow::bail!("RECORD_COST_ONLY={other}: `with` or `without`"),
    };
    let rate = steps_per_s(steps, (84, 84), Channels::DepthOnly, record.as_deref()).await?;
    println!("{mode} recording: {steps} steps, {rate:.0} steps/s");
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// The cost of recording in instructions per step, all threads counted.
fn instructions() -> anyhow::Result<()> {
    println!(
        "instructions per embedded step, 84×84 depth, all threads (callgrind; {STEPS} steps = \
         {} − {FEW_STEPS}):",
        STEPS + FEW_STEPS
    );
    let mut per_step = Vec::new();
    for mode in ["without", "with"] {
        let exe = std::env::current_exe()?;
        let instructions = callgrind::per_unit(
            |steps| {
                let mut run = callgrind::command(&exe);
                run.env("RECORD_COST_ONLY", mode)
                    .env("RECORD_COST_STEPS", steps.to_string())
                    .env_remove("RECORD_COST_INSTRUCTIONS");
                run
            },
            FEW_STEPS,
            STEPS,
        )
        .map_err(|e| anyhow::anyhow!(e))?;
        println!("  {mode:>7} recording: {instructions:.0}");
        per_step.push(instructions);
    }
    println!(
        "  cost: {:.1} % more instructions per step",
        100.0 * (per_step[1] / per_step[0] - 1.0)
    );
    Ok(())
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    if let Ok(mode) = std::env::var("RECORD_COST_ONLY") {
        return only(&mode, count_from_env("RECORD_COST_STEPS", STEPS)?).await;
    }
    if std::env::var_os("RECORD_COST_INSTRUCTIONS").is_some() {
        return instructions();
    }
    let rounds = count_from_env("RECORD_COST_ROUNDS", DEFAULT_ROUNDS)?;
    let dir = scratch("rate");
    println!("embedded step rate, 84×84 depth, {STEPS} steps × {rounds} rounds (interleaved):");
    let (mut plain, mut recorded, mut costs) = (Vec::new(), Vec::new(), Vec::new());
    for round in 0..rounds {
        let without = steps_per_s(STEPS, (84, 84), Channels::DepthOnly, None).await?;
        let into = dir.join(format!("round-{round}"));
        let with = steps_per_s(STEPS, (84, 84), Channels::DepthOnly, Some(&into)).await?;
        let _ = std::fs::remove_dir_all(&into);
        plain.push(without);
        recorded.push(with);
        // Paired: a slow spell of a shared machine hits both halves alike.
        costs.push(100.0 * (1.0 - with / without));
    }
    let (plain, recorded) = (median(&mut plain), median(&mut recorded));
    println!("  without recording: {plain:.0} steps/s (median)");
    println!("  with recording:    {recorded:.0} steps/s (median)");
    let cost = median(&mut costs);
    println!(
        "  cost: {cost:.1} % of the step rate (median of the rounds' paired costs; min {:.1}, max {:.1})",
        costs[0],
        costs[costs.len() - 1]
    );
    let _ = std::fs::remove_dir_all(&dir);

    // Real frames: 320×240 RGBD as the twin renders them.
    let dir = scratch("frames");
    steps_per_s(STEPS, (320, 240), Channels::Rgbd, Some(&dir.join("runs"))).await?;
    let frames = recorded_frames(&dir.join("runs"))?;
    let bytes: usize = frames.iter().flatten().map(Vec::len).sum();
    let mut per_step = writer_ms_per_step(&frames, &dir)?;
    let written = std::fs::metadata(dir.join("bench.mcap"))?.len();
    per_step.sort_by(f64::total_cmp);
    let p99 = per_step[(per_step.len() - 1) * 99 / 100];
    println!(
        "writer per real step, 320×240 RGBD ({} steps, {:.0} KiB raw per step → {:.0} KiB on disk): median {:.2} ms, p99 {:.2} ms",
        frames.len(),
        bytes as f64 / frames.len() as f64 / 1024.0,
        written as f64 / frames.len() as f64 / 1024.0,
        median(&mut per_step),
        p99
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
