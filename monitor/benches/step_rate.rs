//! Step rate of a sim env with and without a monitor attached (issue 25:
//! the monitor must cost at most 3 %). An embedded twin + controller at 84×84
//! RGBD on one session, the gym client on a second, the monitor (a live
//! view as `offworld monitor --serve` runs one: the viewers' copies, served
//! to rerun viewers over gRPC) on
//! the first (embedded) or a third (remote), all over loopback TCP; a bare
//! subscriber to every key of the env (`obs` too) on the third shows what
//! Zenoh's delivery of every frame costs. Rounds alternate the modes and
//! the medians are compared, with the process CPU per step (every thread)
//! and each group of threads' CPU per step while the steps run (the
//! scheduler's count: the twin, its render helpers, the client and the
//! controller, Zenoh, the monitor's worker, rerun's and any other threads),
//! whose last two, the monitor's own threads, are steady on a shared
//! machine. Run:
//! `cargo bench --bench step_rate` (`STEP_RATE_ROUNDS`, `STEP_RATE_STEPS`,
//! `STEP_RATE_MODES`: a comma list of `off,embedded,remote,bare`).

use offworld_runtime::Resolution;
use std::time::{Duration, Instant};

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::embedded::{render_threads_for, Embedded, SimEnv, Stepping, TwinProfile};
use offworld_env_controller::{EnvOptions, RequestLimits, Store};
use offworld_monitor::{Monitor, MonitorConfig, MonitorStats, Scope, Sink};
use offworld_runtime::msg::*;
use offworld_runtime::session::{loopback_endpoint, SessionConfig};
use offworld_runtime::EnvId;

const W: u32 = 84;
const H: u32 = 84;
fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn steps() -> usize {
    env_usize("STEP_RATE_STEPS", 2000)
}

fn rounds() -> usize {
    env_usize("STEP_RATE_ROUNDS", 4)
}

/// The modes to run (`STEP_RATE_MODES`, e.g. `off,embedded` to profile
/// two of them; default all four).
fn modes() -> anyhow::Result<Vec<usize>> {
    const NAMES: [&str; 4] = ["off", "embedded", "remote", "bare"];
    let Ok(list) = std::env::var("STEP_RATE_MODES") else {
        return Ok(vec![0, 1, 2, 3]);
    };
    let mut modes = Vec::new();
    for name in list.split(',').map(str::trim) {
        let Some(mode) = NAMES.iter().position(|n| *n == name) else {
            anyhow::bail!("STEP_RATE_MODES: `{name}` is none of {NAMES:?}");
        };
        if !modes.contains(&mode) {
            modes.push(mode);
        }
    }
    Ok(modes)
}

/// The median (NaN for a mode not run).
fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// CPU time this process has used (every thread, living or ended: client,
/// controller, twin, monitor), s, in the kernel's 10 ms ticks: steadier than
/// a rate on a shared machine. NaN if it cannot be read.
fn process_cpu() -> f64 {
    use sysinfo::{ProcessRefreshKind, ProcessesToUpdate, System};
    let Ok(pid) = sysinfo::get_current_pid() else {
        return f64::NAN;
    };
    let mut system = System::new();
    system.refresh_processes_specifics(
        ProcessesToUpdate::Some(&[pid]),
        false,
        ProcessRefreshKind::nothing().with_cpu(),
    );
    system
        .process(pid)
        .map_or(f64::NAN, |p| p.accumulated_cpu_time() as f64 * 1e-3)
}

/// Each thread's name and CPU time, ns, by thread id.
type ThreadCpu = std::collections::HashMap<u32, (String, u64)>;

/// CPU time of each of this process's living threads, by thread id: its
/// name and ns on a CPU (`/proc/self/task/*/schedstat`, the scheduler's own
/// count, not ticks). Empty where the kernel keeps no such file.
fn thread_cpu() -> ThreadCpu {
    let mut threads = ThreadCpu::new();
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return threads;
    };
    for task in tasks.flatten() {
        let Some(tid) = task.file_name().to_str().and_then(|t| t.parse().ok()) else {
            continue;
        };
        let read = |file: &str| std::fs::read_to_string(task.path().join(file)).ok();
        let ns = read("schedstat")
            .and_then(|s| s.split_whitespace().next().and_then(|n| n.parse().ok()));
        if let (Some(ns), Some(name)) = (ns, read("comm")) {
            threads.insert(tid, (name.trim().to_owned(), ns));
        }
    }
    threads
}

/// The groups a thread's CPU is counted in, by the thread's name.
const GROUPS: [&str; 6] = [
    "twin",
    "render",
    "client+ctl",
    "zenoh",
    "monitor",
    "rerun+rest",
];

/// Which of [`GROUPS`] thread `tid` named `name` belongs to: the twin's
/// thread, its render helpers, the bench's runtime and main thread (the
/// client and the controller), Zenoh's runtimes, the monitor's worker, and
/// the rest (rerun's threads, the monitor's world lookup).
fn group_of(tid: u32, name: &str) -> usize {
    const ZENOH: [&str; 5] = ["rx-", "tx-", "net-", "acc-", "app-"];
    if name.starts_with("sim_twin") {
        0
    } else if name.starts_with("render-") {
        1
    } else if name.starts_with("step-rate") || tid == std::process::id() {
        2
    } else if ZENOH.iter().any(|prefix| name.starts_with(prefix)) {
        3
    } else if name.starts_with("offworld-monito") {
        4
    } else {
        5
    }
}

/// CPU each group of threads used since `since`, ns (a thread started
/// since counts whole; one that ended is lost: none does while steps run).
fn cpu_by_group(since: &ThreadCpu) -> [f64; GROUPS.len()] {
    let mut groups = [0.0; GROUPS.len()];
    for (tid, (name, ns)) in thread_cpu() {
        let before = since.get(&tid).map_or(0, |(_, ns)| *ns);
        groups[group_of(tid, &name)] += ns.saturating_sub(before) as f64;
    }
    groups
}

/// What a block of steps measured.
struct Steps {
    /// Step durations (resets excluded), s.
    times: Vec<f64>,
    /// Process CPU, s.
    cpu: f64,
    /// CPU per group of threads ([`GROUPS`]), ns.
    groups: [f64; GROUPS.len()],
}

/// Runs `steps()` steps.
async fn run_steps(gym: &mut EnvClient) -> anyhow::Result<Steps> {
    let threads = thread_cpu();
    let cpu = process_cpu();
    let mut times = Vec::with_capacity(steps());
    for i in 0..steps() {
        let start = Instant::now();
        let r = gym
            .step(Action::Discrete((i % 4) as i64))
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
        times.push(start.elapsed().as_secs_f64());
        if r.terminated || r.truncated {
            gym.reset(Seed::Continue)
                .await
                .map_err(|e| anyhow::anyhow!(e))?;
        }
    }
    let cpu = process_cpu() - cpu;
    Ok(Steps {
        times,
        cpu,
        groups: cpu_by_group(&threads),
    })
}

/// One round of steps with a live monitor on `session`, the process CPU
/// including the monitor's flush at its shutdown, and its stats.
async fn with_monitor(
    session: &zenoh::Session,
    env: &EnvId,
    gym: &mut EnvClient,
) -> anyhow::Result<(Steps, MonitorStats)> {
    let monitor = Monitor::spawn(
        session,
        // A live view as `offworld monitor --serve` runs one (the viewers'
        // copies, each camera's newest frame, rerun's gRPC server holding
        // a quarter of RAM of history for viewers; none connected). A file's own default,
        // every message, cost 15–21 % of the rate here (docs/performance.md,
        // session 33).
        MonitorConfig::new(Sink::Serve {
            // No viewer connects: the kernel picks the port.
            addr: std::net::SocketAddr::from(([127, 0, 0, 1], 0)),
            memory_limit_bytes: None,
        })
        .scope(Scope::env(env.clone()))
        .newest_frames(),
    )?;
    tokio::time::sleep(Duration::from_millis(300)).await; // subscription routed
    let mut steps = run_steps(gym).await?;
    let flush_cpu = process_cpu();
    let stats = tokio::task::spawn_blocking(move || monitor.shutdown()).await??;
    steps.cpu += process_cpu() - flush_cpu;
    Ok((steps, stats))
}

fn main() -> anyhow::Result<()> {
    // Named, so that no thread of the bench's own runtime (its blocking
    // pool starts threads as the controller needs them) passes for one of
    // the monitor's, whose rerun server runs a tokio runtime of its own.
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .thread_name("step-rate")
        .enable_all()
        .build()?
        .block_on(bench())
}

async fn bench() -> anyhow::Result<()> {
    let modes = modes()?;
    let endpoint = loopback_endpoint()?;
    let server = SessionConfig::listening(&endpoint).open().await?;
    let client = SessionConfig::connecting(&endpoint).open().await?;
    let watcher = SessionConfig::connecting(&endpoint).open().await?;
    let env = EnvId::sim("bench-monitor")?;
    let sim = SimEnv {
        env: env.clone(),
        task: "MonolithDiscrete".into(),
        resolution: Some(Resolution::new(W, H)),
        seed: 0,
        profile: TwinProfile::default(),
        // What one embedded env renders on (`gymnasium.make` with its
        // live monitor): the monitor competes with the render's helpers.
        render_threads: render_threads_for(1)?,
        // Its twin on a thread of its own: this bench's client is on a
        // session of its own, and a step begun on Zenoh's receive thread
        // with two render threads ran 10-12 % slower here than on the
        // twin's thread (`gymnasium.make`, whose client shares the session,
        // gains from `Stepping::OnArrival`: docs/performance.md).
        stepping: Stepping::OwnThread,
    };
    // As `gymnasium.make` serves itself: no request rate a client can reach
    // (a site's 2,000 a second would cap long rounds of this bench).
    let _embedded = Embedded::start_with(
        &server,
        &[sim],
        Store::in_memory()?,
        EnvOptions::default(),
        RequestLimits::in_process(),
        None,
    )
    .await?;
    let request = OpenRequest::anonymous(ObsOptions {
        channels: Channels::Rgbd,
        height: H,
        width: W,
        depth_format: DepthFormat::Uint8,
    });
    // The controller's queryables take a moment to reach the client session.
    let mut gym = EnvClient::open_when_ready(
        &client,
        &env,
        request,
        ClientTimeouts::default(),
        Duration::from_secs(5),
    )
    .await
    .map_err(|e| anyhow::anyhow!(e))?;
    gym.reset(Seed::Fixed(0))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    run_steps(&mut gym).await?; // warm-up

    // Step times per mode: off, embedded monitor, remote monitor, bare remote subscriber.
    let mut times: [Vec<f64>; 4] = Default::default();
    // Process CPU per mode, s.
    let mut cpu = [f64::NAN; 4];
    for &mode in &modes {
        cpu[mode] = 0.0;
    }
    let (mut dropped, mut superseded) = (0, 0);
    // CPU per group of threads per mode, ns.
    let mut groups = [[0.0; GROUPS.len()]; 4];
    // Modes run in ABCD DCBA order so a slow drift of the machine (other
    // load, clocks) weighs on every mode alike.
    for round in 0..rounds() {
        let mut order = modes.clone();
        if round % 2 == 1 {
            order.reverse();
        }
        let mut rates = [0.0; 4];
        for mode in order {
            let steps = match mode {
                0 => run_steps(&mut gym).await?,
                // The monitor embedded next to the env (its session: local delivery).
                1 | 2 => {
                    let session = if mode == 1 { &server } else { &watcher };
                    let (steps, stats) = with_monitor(session, &env, &mut gym).await?;
                    dropped += stats.dropped_frames;
                    superseded += stats.superseded_frames;
                    steps
                }
                // Every key of the env (`obs` too) to a subscriber that drops
                // everything: what Zenoh's delivery of every frame costs.
                _ => {
                    let sub = watcher
                        .declare_subscriber(format!("{}/**", env.prefix()))
                        .callback(|_sample| {})
                        .await
                        .map_err(|e| anyhow::anyhow!(e))?;
                    tokio::time::sleep(Duration::from_millis(300)).await;
                    let measured = run_steps(&mut gym).await?;
                    sub.undeclare().await.map_err(|e| anyhow::anyhow!(e))?;
                    measured
                }
            };
            cpu[mode] += steps.cpu;
            for (total, used) in groups[mode].iter_mut().zip(steps.groups) {
                *total += used;
            }
            rates[mode] = 1.0 / median(steps.times.clone());
            times[mode].extend(steps.times);
        }
        println!(
            "round {round}: off {:6.0}, embedded {:6.0}, remote {:6.0}, bare remote subscriber to every frame {:6.0} steps/s",
            rates[0], rates[1], rates[2], rates[3]
        );
    }
    gym.close().await.map_err(|e| anyhow::anyhow!(e))?;
    let [off, embedded, remote, bare] = times.map(|t| 1.0 / median(t));
    let cost = |rate: f64| (1.0 - rate / off) * 100.0;
    // CPU per step, µs, per mode.
    // Each mode named runs once a round; a mode not named stays NaN.
    let steps_per_mode = (rounds() * steps()) as f64;
    let [cpu_off, cpu_embedded, cpu_remote, cpu_bare] = cpu.map(|c| c / steps_per_mode * 1e6);
    let extra = |c: f64| (c / cpu_off - 1.0) * 100.0;
    println!(
        "step rate at {W}x{H} RGBD (1 / median step time over {} rounds of {} steps; {dropped} frames dropped for the viewer, {superseded} superseded by newer ones):",
        rounds(),
        steps()
    );
    println!("  without monitor                 : {off:6.0} steps/s");
    println!(
        "  monitor embedded (same session) : {embedded:6.0} steps/s  ({:+.1} %; target within 3 %: {})",
        -cost(embedded),
        if cost(embedded) <= 3.0 { "met" } else { "NOT met" }
    );
    println!(
        "  monitor remote (own session)    : {remote:6.0} steps/s  ({:+.1} %)",
        -cost(remote)
    );
    println!(
        "  bare remote subscriber, obs too : {bare:6.0} steps/s  ({:+.1} %: Zenoh delivering every frame)",
        -cost(bare)
    );
    println!("process CPU per step (every thread, ended ones too):");
    println!("  without monitor                 : {cpu_off:6.0} µs");
    println!(
        "  monitor embedded (same session) : {cpu_embedded:6.0} µs  ({:+.1} %)",
        extra(cpu_embedded)
    );
    println!(
        "  monitor remote (own session)    : {cpu_remote:6.0} µs  ({:+.1} %)",
        extra(cpu_remote)
    );
    println!(
        "  bare remote subscriber, obs too : {cpu_bare:6.0} µs  ({:+.1} %)",
        extra(cpu_bare)
    );
    // Where each mode's CPU went, by thread: the monitor's own threads
    // (monitor, rerun) and what it costs the others (the twin's and the
    // controller's threads put the viewers' copies to its callbacks).
    println!("CPU per step by thread (the scheduler's count while the steps ran), µs:");
    println!(
        "  {:32}  {}",
        "",
        GROUPS.map(|g| format!("{g:>11}")).join("")
    );
    let names = [
        "without monitor                 ",
        "monitor embedded (same session) ",
        "monitor remote (own session)    ",
        "bare remote subscriber, obs too ",
    ];
    for &mode in &modes {
        let per_step = groups[mode].map(|ns| ns / steps_per_mode / 1e3);
        println!(
            "  {}: {}",
            names[mode],
            per_step.map(|us| format!("{us:11.1}")).join("")
        );
    }
    for mode in [1, 2] {
        if !modes.contains(&mode) {
            continue;
        }
        // The last group also holds threads that are not the monitor's:
        // what it took without a monitor is taken off, when measured.
        let rest_without = if modes.contains(&0) {
            groups[0][5]
        } else {
            0.0
        };
        let own = (groups[mode][4] + groups[mode][5] - rest_without) / steps_per_mode / 1e3;
        println!(
            "  {}: its own threads (monitor, rerun+rest less its level without a monitor) {own:.1} µs a step, {:.1} % of a step without monitor",
            names[mode],
            own / cpu_off * 100.0
        );
    }
    Ok(())
}
