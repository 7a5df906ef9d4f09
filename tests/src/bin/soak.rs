//! `soak`: the deployment under sustained load for a long time (issue 22,
//! item 8; not a CI test). Real processes — the `zenohd` router with the
//! repository's deployment files (or plain TCP peer to peer), one
//! `env_controller` serving two sim envs, a `sim_twin` process for each,
//! and a `monitor` attached to every env — while this program
//!
//! - steps both envs continuously (one gym client each, random seeded
//!   actions, a reset whenever an episode ends),
//! - floods the controller with `status` and booking-list queries
//!   (bounded rate, bursts larger than a client's queue: `Busy` answers
//!   are expected),
//! - drops a stepping client's Zenoh session at random (seeded) times
//!   without closing its gym session, then opens a new one (the
//!   controller must free the lease of the vanished holder),
//!
//! and samples the resident memory (`VmRSS`) of every process. It prints a
//! progress line every sample period (stderr) and a Markdown report at the
//! end (stdout); it exits 1 if a service's RSS grew more than
//! `--max-growth-pct` between the end of the warm-up and the end of the
//! run, a service died, or any unexpected error occurred (130 when stopped
//! early by Ctrl-C or SIGTERM, after reporting what ran).
//!
//! ```text
//! source .ci/env && cargo build --release --bins
//! "$CARGO_TARGET_DIR/release/soak"                               # 1 h, warm-up 5 min
//! "$CARGO_TARGET_DIR/release/soak" --duration 4m --warmup 1m     # a smoke run
//! "$CARGO_TARGET_DIR/release/soak" --topology peer --no-monitor  # bisect a leak
//! ```
//!
//! `docs/soak.md` explains what is checked and holds the latest figures.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::future::Future;
use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::process::{Command, ExitCode, Stdio};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::Context;
use clap::{Parser, ValueEnum};
use futures::stream::{FuturesUnordered, StreamExt};
use offworld_client::{self as client, ClientTimeouts, EnvClient};
use offworld_deploy::site::{Role, RouterSite};
use offworld_runtime::msg::{
    Action, ActionSpace, BookingRequest, Channels, DepthFormat, EnvSpec, EnvState, ObsOptions,
    OpenRequest, Seed,
};
use offworld_runtime::session::{free_loopback_port, loopback_endpoint};
use offworld_runtime::{EnvId, ErrorCode, SessionConfig, WireError};
use offworld_tests::{binary_dir, Process};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use tokio::sync::mpsc;
use tokio::time::Instant as TokioInstant;

/// How the processes meet.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Topology {
    /// Through the `zenohd` router built from `deploy/` (QUIC, TLS, mutual
    /// TLS, passwords, ACL), every component a Zenoh client in its role.
    Router,
    /// Peer to peer over TCP on loopback: the controller listens, the
    /// others connect to it.
    Peer,
}

#[derive(Debug, Parser)]
#[command(
    name = "soak",
    version,
    about = "Run the gym deployment under load for a long time and check that memory stays flat",
    long_about = "Runs zenohd (or peer to peer), env_controller with two sim envs, a sim_twin \
                  process per env and a monitor as real processes; steps both envs \
                  continuously, floods status and booking queries, drops client sessions at \
                  random; samples every process's VmRSS and reports the growth after the \
                  warm-up. Exits non-zero on RSS growth above --max-growth-pct, a dead service \
                  or any unexpected error. Progress on stderr, the Markdown report on stdout."
)]
struct Args {
    /// Total run time, e.g. `60m`, `1h`, `1h30m`, `90s`.
    #[arg(long, default_value = "1h", value_parser = parse_duration)]
    duration: Duration,
    /// Time before the RSS baseline is taken (caches, pools and queues
    /// reach their working size).
    #[arg(long, default_value = "5m", value_parser = parse_duration)]
    warmup: Duration,
    /// Seed of actions, reset seeds, disconnect times and targets.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// RSS sampling and progress period.
    #[arg(long, default_value = "10s", value_parser = parse_duration)]
    sample_every: Duration,
    /// How the processes meet.
    #[arg(long, value_enum, default_value_t = Topology::Router)]
    topology: Topology,
    /// Steps per second and env at most (0: as fast as the envs answer,
    /// which keeps every core busy).
    #[arg(long, default_value_t = 0.0)]
    step_rate: f64,
    /// Task of both envs.
    #[arg(long, default_value = "MonolithDiscrete")]
    task: String,
    /// Largest RSS growth of a service after the warm-up, percent.
    #[arg(long, default_value_t = 5.0)]
    max_growth_pct: f64,
    /// Status + booking-list queries per second (0: no flood).
    #[arg(long, default_value_t = 200)]
    flood_rate: u32,
    /// Flood queries sent together (the controller queues at most 8 per
    /// client and env: larger bursts meet `Busy`).
    #[arg(long, default_value_t = 20)]
    flood_burst: u32,
    /// Deadline of each flood query.
    #[arg(long, default_value = "5s", value_parser = parse_duration)]
    flood_timeout: Duration,
    /// Shortest time between two client disconnects.
    #[arg(long, default_value = "15s", value_parser = parse_duration)]
    disconnect_min: Duration,
    /// Longest time between two client disconnects.
    #[arg(long, default_value = "45s", value_parser = parse_duration)]
    disconnect_max: Duration,
    /// Never drop client sessions.
    #[arg(long)]
    no_disconnects: bool,
    /// After an intentional disconnect, the new session must hold the
    /// lease within this long; until then `Busy`, `Unavailable`,
    /// `NotFound` and `Timeout` answers to `open` are expected.
    #[arg(long, default_value = "30s", value_parser = parse_duration)]
    recover_within: Duration,
    /// Open the gym sessions as a registered user (the controller hands
    /// the lease over to the same user at once) instead of anonymously
    /// (the new session waits until the controller saw the old one vanish).
    #[arg(long)]
    registered: bool,
    /// Run without the monitor.
    #[arg(long)]
    no_monitor: bool,
    /// Where the monitor sends its recording: `serve` (a rerun gRPC
    /// server on a free loopback port, no viewer attached, history capped
    /// by --monitor-memory-mib), `null` (an `.rrd` stream written to
    /// /dev/null; rerun's file writer keeps the file's chunk index in
    /// memory until the end, so its RSS grows with the recording), or a
    /// path `FILE.rrd` (kept; GBs per hour).
    #[arg(long, value_name = "SINK", default_value = "serve")]
    monitor_sink: String,
    /// History the monitor's `serve` sink keeps, MiB.
    #[arg(long, value_name = "MIB", default_value_t = 64)]
    monitor_memory_mib: u64,
    /// Echo every log line of the services (default: ERROR lines only).
    #[arg(long)]
    echo_logs: bool,
    /// Unexpected error messages kept for the report.
    #[arg(long, default_value_t = 10)]
    keep_errors: usize,
}

/// `90`, `90s`, `500ms`, `4m`, `1h`, `1h30m`.
fn parse_duration(text: &str) -> Result<Duration, String> {
    let text = text.trim();
    if text.is_empty() {
        return Err("empty duration".into());
    }
    if let Ok(secs) = text.parse::<f64>() {
        return Duration::try_from_secs_f64(secs).map_err(|e| format!("`{text}`: {e}"));
    }
    let mut total = Duration::ZERO;
    let mut rest = text;
    while !rest.is_empty() {
        let digits = rest
            .find(|c: char| !(c.is_ascii_digit() || c == '.'))
            .ok_or_else(|| format!("`{text}`: a number needs a unit (ms, s, m, h)"))?;
        let (number, tail) = rest.split_at(digits);
        let value: f64 = number
            .parse()
            .map_err(|_| format!("`{text}`: `{number}` is not a number"))?;
        let unit_len = tail
            .find(|c: char| c.is_ascii_digit() || c == '.')
            .unwrap_or(tail.len());
        let (unit, next) = tail.split_at(unit_len);
        let scale = match unit {
            "ms" => 0.001,
            "s" => 1.0,
            "m" | "min" => 60.0,
            "h" => 3600.0,
            other => return Err(format!("`{text}`: unknown unit `{other}` (ms, s, m, h)")),
        };
        total +=
            Duration::try_from_secs_f64(value * scale).map_err(|e| format!("`{text}`: {e}"))?;
        rest = next;
    }
    Ok(total)
}

/// `1h02m03s`-style, whole seconds.
fn hms(d: Duration) -> String {
    let s = d.as_secs();
    match (s / 3600, s / 60 % 60, s % 60) {
        (0, 0, s) => format!("{s}s"),
        (0, m, s) => format!("{m}m{s:02}s"),
        (h, m, s) => format!("{h}h{m:02}m{s:02}s"),
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

// ---------------------------------------------------------------------------
// Counters and errors shared by the load tasks.

#[derive(Default)]
struct ErrorLog {
    /// (kind, expected) → count; kind is `<operation> <code>`.
    by_kind: BTreeMap<(String, bool), u64>,
    unexpected: u64,
    /// The first unexpected ones, with when they happened.
    first: Vec<String>,
}

struct Shared {
    start: Instant,
    deadline: TokioInstant,
    keep_errors: usize,
    steps: Vec<AtomicU64>,
    episodes: Vec<AtomicU64>,
    /// Episodes ended by the task (terminated) or cut at the step limit.
    ended: Vec<AtomicU64>,
    flood_sent: AtomicU64,
    flood_ok: AtomicU64,
    flood_busy: AtomicU64,
    /// Bursts not sent because too many queries were still in flight.
    flood_skipped: AtomicU64,
    disconnects: AtomicU64,
    recoveries: Mutex<Vec<Duration>>,
    errors: Mutex<ErrorLog>,
    /// Set when the run is stopped early (SIGINT, SIGTERM).
    stop: tokio::sync::watch::Sender<bool>,
}

impl Shared {
    fn new(envs: usize, deadline: TokioInstant, keep_errors: usize) -> Self {
        let counters = || (0..envs).map(|_| AtomicU64::new(0)).collect();
        Self {
            start: Instant::now(),
            deadline,
            keep_errors,
            steps: counters(),
            episodes: counters(),
            ended: counters(),
            flood_sent: AtomicU64::new(0),
            flood_ok: AtomicU64::new(0),
            flood_busy: AtomicU64::new(0),
            flood_skipped: AtomicU64::new(0),
            disconnects: AtomicU64::new(0),
            recoveries: Mutex::new(Vec::new()),
            errors: Mutex::new(ErrorLog::default()),
            stop: tokio::sync::watch::Sender::new(false),
        }
    }

    fn over(&self) -> bool {
        TokioInstant::now() >= self.deadline || *self.stop.borrow()
    }

    /// Completes at the deadline, or at once when the run is stopped.
    async fn end(&self) {
        let mut stop = self.stop.subscribe();
        tokio::select! {
            _ = tokio::time::sleep_until(self.deadline) => {}
            _ = stop.wait_for(|stopped| *stopped) => {}
        }
    }

    /// `fut`'s output, or `None` if the run ends first.
    async fn before_end<T>(&self, fut: impl Future<Output = T>) -> Option<T> {
        tokio::select! {
            _ = self.end() => None,
            r = fut => Some(r),
        }
    }

    fn error(&self, op: &str, code: &str, message: &str, expected: bool) {
        let mut log = lock(&self.errors);
        *log.by_kind
            .entry((format!("{op} {code}"), expected))
            .or_default() += 1;
        if !expected {
            log.unexpected += 1;
            let line = format!("[{}] {op} {code}: {message}", hms(self.start.elapsed()),);
            eprintln!("UNEXPECTED {line}");
            if log.first.len() < self.keep_errors {
                log.first.push(line);
            }
        }
    }

    fn wire_error(&self, op: &str, e: &WireError, expected: bool) {
        self.error(op, e.code.name(), &e.message, expected);
    }

    fn total(counters: &[AtomicU64]) -> u64 {
        counters.iter().map(|c| c.load(Ordering::Relaxed)).sum()
    }
}

// ---------------------------------------------------------------------------
// Load: steppers, flood, disconnects.

/// What a gym client needs to connect.
#[derive(Clone)]
struct ClientSetup {
    session: SessionConfig,
    request: OpenRequest,
    recover_within: Duration,
    /// Least time between two steps of one client.
    step_period: Option<Duration>,
}

enum Outcome<T> {
    Deadline,
    Kicked,
    Done(Result<T, WireError>),
}

/// Awaits `fut` unless the run ends or a disconnect is asked for.
async fn guarded<T>(
    shared: &Shared,
    kicks: &mut mpsc::Receiver<()>,
    fut: impl Future<Output = Result<T, WireError>>,
) -> Outcome<T> {
    tokio::select! {
        _ = shared.end() => Outcome::Deadline,
        Some(()) = kicks.recv() => Outcome::Kicked,
        r = fut => Outcome::Done(r),
    }
}

fn random_action(rng: &mut ChaCha8Rng, spec: &EnvSpec) -> Action {
    match &spec.action_space {
        ActionSpace::Discrete { n, .. } => Action::Discrete(i64::from(rng.random_range(0..*n))),
        ActionSpace::Box { low, high } => Action::Continuous(
            low.iter()
                .zip(high)
                .map(|(l, h)| if h > l { rng.random_range(*l..=*h) } else { *l })
                .collect(),
        ),
    }
}

/// Whether `open` may answer this while a new session takes over the
/// lease of a vanished one.
fn transient_open_error(code: ErrorCode) -> bool {
    matches!(
        code,
        ErrorCode::Busy | ErrorCode::Unavailable | ErrorCode::NotFound | ErrorCode::Timeout
    )
}

/// Steps env `idx` until the deadline; drops its Zenoh session whenever a
/// kick arrives and opens a new one.
async fn stepper(
    shared: Arc<Shared>,
    idx: usize,
    env: EnvId,
    setup: ClientSetup,
    mut kicks: mpsc::Receiver<()>,
    seed: u64,
) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(idx as u64 + 1);
    let timeouts = ClientTimeouts::default();
    // Set while a new session takes over after a dropped one: transient
    // `open` answers are expected until `recover_within` has passed.
    let mut dropped_at: Option<Instant> = None;
    let mut opened_before = false;
    let mut last_step = TokioInstant::now();
    'session: while !shared.over() {
        let session = match shared.before_end(setup.session.open()).await {
            None => break,
            Some(Ok(s)) => s,
            Some(Err(e)) => {
                shared.error("session", "open", &e.to_string(), false);
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
        };
        let mut gym = loop {
            // The experiment is made by the first open, resumed after.
            let mut request = setup.request.clone();
            request.resume_experiment = opened_before;
            let open = EnvClient::open(&session, &env, request, timeouts);
            let result = tokio::select! {
                _ = shared.end() => break 'session,
                r = open => r,
            };
            match result {
                Ok(gym) => {
                    opened_before = true;
                    break gym;
                }
                Err(e) => {
                    let recovering = dropped_at.is_some_and(|t| t.elapsed() < setup.recover_within);
                    let expected = recovering && transient_open_error(e.code);
                    shared.wire_error(if recovering { "reopen" } else { "open" }, &e, expected);
                    let pause = if expected { 100 } else { 1000 };
                    tokio::time::sleep(Duration::from_millis(pause)).await;
                }
            }
        };
        if let Some(t) = dropped_at.take() {
            lock(&shared.recoveries).push(t.elapsed());
        }
        // Disconnects asked for while this client was reconnecting.
        while kicks.try_recv().is_ok() {}
        let mut need_reset = true;
        // Left only at the deadline (disconnects and errors start a new
        // session).
        'steps: loop {
            if need_reset {
                let seed = Seed::Fixed(rng.random());
                match guarded(&shared, &mut kicks, gym.reset(seed)).await {
                    Outcome::Deadline => break 'steps,
                    Outcome::Kicked => {
                        drop(gym);
                        drop(session);
                        shared.disconnects.fetch_add(1, Ordering::Relaxed);
                        dropped_at = Some(Instant::now());
                        continue 'session;
                    }
                    Outcome::Done(Ok(_)) => {
                        shared.episodes[idx].fetch_add(1, Ordering::Relaxed);
                        need_reset = false;
                    }
                    Outcome::Done(Err(e)) => {
                        shared.wire_error("reset", &e, false);
                        // Start over with a fresh session (the error is
                        // counted; the takeover that follows is not).
                        drop(gym);
                        drop(session);
                        dropped_at = Some(Instant::now());
                        tokio::time::sleep(Duration::from_secs(1)).await;
                        continue 'session;
                    }
                }
            }
            if let Some(period) = setup.step_period {
                let due = last_step + period;
                tokio::select! {
                    _ = shared.end() => break 'steps,
                    _ = tokio::time::sleep_until(due) => {}
                }
            }
            last_step = TokioInstant::now();
            let action = random_action(&mut rng, gym.spec());
            match guarded(&shared, &mut kicks, gym.step(action)).await {
                Outcome::Deadline => break 'steps,
                Outcome::Kicked => {
                    // Abruptly: no `close`, the step in flight abandoned.
                    drop(gym);
                    drop(session);
                    shared.disconnects.fetch_add(1, Ordering::Relaxed);
                    dropped_at = Some(Instant::now());
                    continue 'session;
                }
                Outcome::Done(Ok(reply)) => {
                    shared.steps[idx].fetch_add(1, Ordering::Relaxed);
                    if reply.terminated || reply.truncated {
                        shared.ended[idx].fetch_add(1, Ordering::Relaxed);
                        need_reset = true;
                    }
                }
                Outcome::Done(Err(e)) => {
                    shared.wire_error("step", &e, false);
                    need_reset = true;
                }
            }
        }
        // The run is over: release the lease properly.
        let _ = tokio::time::timeout(Duration::from_secs(5), gym.close()).await;
        break;
    }
    // Reached on the deadline in any phase.
}

type FloodQuery = Pin<Box<dyn Future<Output = (&'static str, Result<(), WireError>)> + Send>>;

/// Status and booking-list queries in bursts at `rate` per second.
async fn flood(
    shared: Arc<Shared>,
    session: SessionConfig,
    envs: Vec<EnvId>,
    rate: u32,
    burst: u32,
    timeout: Duration,
) {
    let session = match shared.before_end(session.open()).await {
        None => return,
        Some(Ok(s)) => s,
        Some(Err(e)) => {
            shared.error("flood", "session", &e.to_string(), false);
            return;
        }
    };
    let burst = burst.max(1);
    let period = Duration::from_secs_f64(f64::from(burst) / f64::from(rate.max(1)));
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // At most four bursts in flight: a stalled controller makes the flood
    // skip bursts rather than pile up queries.
    let max_in_flight = 4 * burst as usize;
    let mut in_flight: FuturesUnordered<FloodQuery> = FuturesUnordered::new();
    let (mut n, mut bursts): (u64, usize) = (0, 0);
    loop {
        tokio::select! {
            _ = shared.end() => break,
            _ = tick.tick() => {
                if in_flight.len() + burst as usize > max_in_flight {
                    shared.flood_skipped.fetch_add(1, Ordering::Relaxed);
                    continue;
                }
                // A whole burst on one env: more queries than one client
                // may queue there.
                let env = envs[bursts % envs.len()].clone();
                bursts += 1;
                for _ in 0..burst {
                    let env = env.clone();
                    let session = session.clone();
                    let query: FloodQuery = if n % 2 == 0 {
                        Box::pin(async move {
                            let r = client::status(&session, &env, timeout).await;
                            ("flood-status", r.map(drop))
                        })
                    } else {
                        Box::pin(async move {
                            let now = std::time::SystemTime::now()
                                .duration_since(std::time::UNIX_EPOCH)
                                .unwrap_or_default();
                            let list = BookingRequest::List {
                                from_unix_ms: i64::try_from(now.as_millis()).unwrap_or(i64::MAX),
                            };
                            let r = client::book(&session, &env, &list, timeout).await;
                            ("flood-book", r.map(drop))
                        })
                    };
                    in_flight.push(query);
                    n += 1;
                    shared.flood_sent.fetch_add(1, Ordering::Relaxed);
                }
            }
            Some((op, result)) = in_flight.next(), if !in_flight.is_empty() => match result {
                Ok(()) => {
                    shared.flood_ok.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) if e.code == ErrorCode::Busy => {
                    shared.flood_busy.fetch_add(1, Ordering::Relaxed);
                    shared.wire_error(op, &e, true);
                }
                Err(e) => shared.wire_error(op, &e, false),
            },
        }
    }
    drop(in_flight);
    let _ = tokio::time::timeout(Duration::from_secs(5), session.close()).await;
}

/// Asks a random stepper to drop its session every `min..=max`.
async fn disconnects(
    shared: Arc<Shared>,
    kicks: Vec<mpsc::Sender<()>>,
    min: Duration,
    max: Duration,
    seed: u64,
) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(1000);
    loop {
        let wait = if max > min {
            rng.random_range(min..=max)
        } else {
            min
        };
        tokio::select! {
            _ = shared.end() => return,
            _ = tokio::time::sleep(wait) => {}
        }
        let target = rng.random_range(0..kicks.len());
        // A kick already pending (the client is still reconnecting) stays one.
        let _ = kicks[target].try_send(());
    }
}

// ---------------------------------------------------------------------------
// Processes: spawning with captured logs, RSS.

/// WARN / ERROR lines a service logged.
#[derive(Default)]
struct LogCounts {
    warn: u64,
    /// ERROR lines of our own crates (judged).
    error: u64,
    /// ERROR lines of dependencies (zenoh, rerun): reported, not judged.
    error_deps: u64,
    first_errors: Vec<String>,
    /// The latest `key=number` fields of the monitor's periodic stats line.
    monitor_stats: BTreeMap<String, u64>,
}

fn strip_ansi(line: &str) -> String {
    let mut out = String::with_capacity(line.len());
    let mut chars = line.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            // CSI: ESC [ … final byte in @..~
            for c in chars.by_ref() {
                if ('@'..='~').contains(&c) && c != '[' {
                    break;
                }
            }
        } else {
            out.push(c);
        }
    }
    out
}

/// The level of a `tracing_subscriber::fmt` line: `<time>  WARN target: …`.
fn level_of(line: &str) -> Option<&'static str> {
    let head: Vec<&str> = line.split_whitespace().take(2).collect();
    ["ERROR", "WARN"]
        .into_iter()
        .find(|level| head.contains(level))
}

/// Whether a log line's target (`<time> LEVEL target: …`) is one of this
/// workspace's crates or binaries rather than a dependency's.
fn ours(line: &str) -> bool {
    let target = line
        .split_whitespace()
        .nth(2)
        .unwrap_or("")
        .trim_end_matches(':');
    target.starts_with("offworld")
        || ["env_controller", "sim_twin", "monitor"]
            .iter()
            .any(|b| target == *b || target.starts_with(&format!("{b}::")))
}

/// A watched process.
struct Service {
    name: String,
    pid: u32,
    /// Owned processes (not the router, which its site owns).
    process: Option<Process>,
    /// Judged by the RSS criterion.
    judged: bool,
    logs: Option<Arc<Mutex<LogCounts>>>,
    /// (seconds since the start, KiB).
    samples: Vec<(f64, u64)>,
    exited: Option<String>,
}

/// Starts a workspace binary with its stderr read by a thread: counted,
/// ERROR lines (every line with `echo`) printed with the service's name.
fn spawn_service(
    name: &str,
    binary: &str,
    args: &[String],
    log: &str,
    echo: bool,
) -> anyhow::Result<Service> {
    let path = binary_dir().join(binary);
    anyhow::ensure!(
        path.exists(),
        "{} is missing: build the services first (`cargo build --release --bins`)",
        path.display()
    );
    let mut child = Command::new(&path)
        // Its own process group: a Ctrl-C at the terminal reaches only
        // `soak`, which then stops the run and the services in order.
        .process_group(0)
        .args(args)
        .env(
            "RUST_LOG",
            std::env::var("OFFWORLD_CHILD_LOG").unwrap_or_else(|_| log.to_owned()),
        )
        .env("NO_COLOR", "1")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .with_context(|| format!("starting {}", path.display()))?;
    let logs = Arc::new(Mutex::new(LogCounts::default()));
    if let Some(stderr) = child.stderr.take() {
        let (logs, name) = (logs.clone(), name.to_owned());
        std::thread::Builder::new()
            .name(format!("log-{name}"))
            .spawn(move || {
                for line in BufReader::new(stderr).lines() {
                    let Ok(line) = line else { break };
                    let line = strip_ansi(&line);
                    let level = level_of(&line);
                    let mut counts = lock(&logs);
                    match level {
                        Some("ERROR") if !ours(&line) => {
                            counts.error_deps += 1;
                            if counts.first_errors.len() < 5 {
                                counts.first_errors.push(line.clone());
                            }
                        }
                        Some("ERROR") => {
                            counts.error += 1;
                            if counts.first_errors.len() < 5 {
                                counts.first_errors.push(line.clone());
                            }
                        }
                        Some(_) => counts.warn += 1,
                        None => {}
                    }
                    if line.contains(" monitor: monitor ") {
                        for field in line.split_whitespace() {
                            if let Some((k, v)) = field.split_once('=') {
                                if let Ok(v) = v.parse() {
                                    counts.monitor_stats.insert(k.to_owned(), v);
                                }
                            }
                        }
                    }
                    drop(counts);
                    if echo || level == Some("ERROR") {
                        eprintln!("[{name}] {line}");
                    }
                }
            })?;
    }
    Ok(Service {
        name: name.to_owned(),
        pid: child.id(),
        process: Some(Process(child)),
        judged: true,
        logs: Some(logs),
        samples: Vec::new(),
        exited: None,
    })
}

/// `VmRSS` of a process, KiB; `None` when it is gone or a zombie.
fn rss_kib(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let mut rss = None;
    for line in status.lines() {
        if let Some(state) = line.strip_prefix("State:") {
            if state.trim_start().starts_with('Z') {
                return None;
            }
        }
        if let Some(value) = line.strip_prefix("VmRSS:") {
            rss = value.split_whitespace().next().and_then(|v| v.parse().ok());
        }
    }
    rss
}

/// Children of this process running `comm` (the router that
/// [`RouterSite`] starts and owns).
fn child_pids(comm: &str) -> Vec<u32> {
    let me = std::process::id();
    let Ok(entries) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    entries
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|pid| {
            let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else {
                return false;
            };
            // `pid (comm) state ppid …`; comm may hold spaces.
            let (Some(open), Some(close)) = (stat.find('('), stat.rfind(')')) else {
                return false;
            };
            let name = &stat[open + 1..close];
            let ppid = stat[close + 1..]
                .split_whitespace()
                .nth(1)
                .and_then(|p| p.parse::<u32>().ok());
            name == comm && ppid == Some(me)
        })
        .collect()
}

fn mib(kib: u64) -> f64 {
    kib as f64 / 1024.0
}

/// RSS figures of one process after the warm-up.
struct RssFigures {
    /// Median of the samples in the first window after the warm-up.
    baseline: u64,
    /// Median of the samples in the last window.
    end: u64,
    max: u64,
    growth_pct: f64,
    /// Least-squares slope over the samples after the warm-up, MiB/h.
    slope_mib_h: f64,
}

/// Judging window: a minute, or a quarter of the judged period if shorter.
const WINDOW_S: f64 = 60.0;

fn median(mut values: Vec<u64>) -> Option<u64> {
    values.sort_unstable();
    values.get(values.len() / 2).copied()
}

/// Baseline and end are medians over a window (a minute, or a quarter of
/// the time after the warm-up if shorter) at either end of the time after
/// the warm-up: allocators and capped caches make RSS a sawtooth, and one
/// sample at each end would judge its phase.
fn figures(samples: &[(f64, u64)], warmup_s: f64) -> Option<RssFigures> {
    let after: Vec<(f64, u64)> = samples
        .iter()
        .copied()
        .filter(|(t, _)| *t >= warmup_s)
        .collect();
    let &(first_t, _) = after.first()?;
    let &(last_t, _) = after.last()?;
    let window = WINDOW_S.min((last_t - first_t) / 4.0);
    let in_window = |from: f64, to: f64| {
        after
            .iter()
            .filter(|(t, _)| *t >= from && *t <= to)
            .map(|s| s.1)
            .collect::<Vec<u64>>()
    };
    let baseline = median(in_window(first_t, first_t + window))?;
    let end = median(in_window(last_t - window, last_t))?;
    let max = samples.iter().map(|s| s.1).max().unwrap_or(0);
    let n = after.len() as f64;
    let mean_t = after.iter().map(|s| s.0).sum::<f64>() / n;
    let mean_m = after.iter().map(|s| mib(s.1)).sum::<f64>() / n;
    let (mut num, mut den) = (0.0, 0.0);
    for (t, kib) in &after {
        num += (t - mean_t) * (mib(*kib) - mean_m);
        den += (t - mean_t) * (t - mean_t);
    }
    let slope = if den > 0.0 { num / den * 3600.0 } else { 0.0 };
    Some(RssFigures {
        baseline,
        end,
        max,
        growth_pct: (end as f64 - baseline as f64) / baseline.max(1) as f64 * 100.0,
        slope_mib_h: slope,
    })
}

// ---------------------------------------------------------------------------
// Deployment.

struct Deployment {
    /// The router and its files (router topology).
    site: Option<RouterSite>,
    /// Scratch directory of the peer topology (removed at the end).
    scratch: Option<PathBuf>,
    envs: Vec<EnvId>,
    services: Vec<Service>,
    /// Where gym clients connect.
    client: SessionConfig,
    token: String,
}

impl Drop for Deployment {
    fn drop(&mut self) {
        // The processes first (dropping one kills it), then the files; the
        // router's site removes its own directory when it drops.
        self.services.clear();
        if let Some(dir) = self.scratch.take() {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

impl Deployment {
    fn dir(&self) -> &Path {
        match (&self.site, &self.scratch) {
            (Some(site), _) => &site.dir,
            (None, Some(dir)) => dir,
            (None, None) => Path::new("."),
        }
    }
}

fn register_user(db: &Path) -> anyhow::Result<String> {
    Ok(offworld_env_controller::Store::open(db)?.add_user("soak", false)?)
}

fn start(args: &Args) -> anyhow::Result<Deployment> {
    for binary in ["env_controller", "sim_twin", "monitor"] {
        let path = binary_dir().join(binary);
        anyhow::ensure!(
            path.exists(),
            "{} is missing: `source .ci/env && cargo build --release --bins` first",
            path.display()
        );
    }
    let envs: Vec<EnvId> = (0..2)
        .map(|i| EnvId::sim(&format!("soak-{i}")))
        .collect::<Result<_, _>>()?;
    let (site, scratch) = match args.topology {
        Topology::Router => {
            let site = RouterSite::start("soak").context(
                "starting zenohd (on PATH after `source .ci/env`, installed by .ci/setup)",
            )?;
            (Some(site), None)
        }
        Topology::Peer => {
            let dir = std::env::temp_dir().join(format!(
                "offworld-soak-{}-{}",
                std::process::id(),
                offworld_runtime::keys::random_id()
            ));
            std::fs::create_dir_all(&dir)?;
            (None, Some(dir))
        }
    };
    let peer_endpoint = loopback_endpoint()?;
    let mut deployment = Deployment {
        client: match &site {
            Some(site) => site.session(Role::Trainer),
            None => SessionConfig::connecting(&peer_endpoint),
        },
        site,
        scratch,
        envs,
        services: Vec::new(),
        token: String::new(),
    };
    let zenoh_args = |role: Role| -> Vec<String> {
        match &deployment.site {
            Some(site) => site.role_args(role),
            None if role == Role::Controller => vec!["--listen".into(), peer_endpoint.clone()],
            // Peers (not the connecting programs' default, clients) that
            // listen too (any loopback port): the monitor reaches the
            // twins' frames and poses directly, as on a robot's network.
            None => vec![
                "--mode".into(),
                "peer".into(),
                "--connect".into(),
                peer_endpoint.clone(),
                "--listen".into(),
                "tcp/127.0.0.1:0".into(),
            ],
        }
    };
    if let Some(site) = &deployment.site {
        for pid in child_pids("zenohd") {
            deployment.services.push(Service {
                name: "zenohd".into(),
                pid,
                process: None,
                judged: true,
                logs: None,
                samples: Vec::new(),
                exited: None,
            });
        }
        anyhow::ensure!(
            !deployment.services.is_empty(),
            "zenohd started ({}) but its process was not found",
            site.trainer_endpoint
        );
    }
    let db = deployment.dir().join("gym.db");
    if args.registered {
        deployment.token = register_user(&db)?;
    }
    // The controller first: in the peer topology the others connect to it.
    let mut serve = vec![
        "--db".to_owned(),
        db.to_string_lossy().into_owned(),
        "serve".to_owned(),
    ];
    for env in &deployment.envs {
        serve.push("--env".into());
        serve.push(format!("{env}={}", args.task));
    }
    serve.extend(zenoh_args(Role::Controller));
    let controller = spawn_service(
        "env_controller",
        "env_controller",
        &serve,
        "warn",
        args.echo_logs,
    )?;
    deployment.services.push(controller);
    if args.topology == Topology::Peer {
        wait_listening(&peer_endpoint, Duration::from_secs(30))?;
    }
    let world = if args.task.starts_with("MonolithObstacle") {
        "monolith_obstacle"
    } else {
        "monolith"
    };
    for (i, env) in deployment.envs.clone().iter().enumerate() {
        let mut twin = vec![
            "--env".to_owned(),
            env.to_string(),
            "--world".into(),
            world.into(),
            "--resolution".into(),
            "84x84".into(),
            "--seed".into(),
            (args.seed + i as u64).to_string(),
        ];
        twin.extend(zenoh_args(Role::SimTwin));
        let name = format!("sim_twin-{i}");
        deployment.services.push(spawn_service(
            &name,
            "sim_twin",
            &twin,
            "warn",
            args.echo_logs,
        )?);
    }
    if !args.no_monitor {
        let mut monitor = vec!["--all".to_owned()];
        match args.monitor_sink.as_str() {
            "serve" => {
                let port = free_loopback_port("127.0.0.1")?;
                monitor.extend([
                    "--serve".into(),
                    format!("127.0.0.1:{port}"),
                    "--serve-memory-mib".into(),
                    args.monitor_memory_mib.to_string(),
                ]);
            }
            "null" => monitor.extend(["--save".into(), "/dev/null".into()]),
            path => monitor.extend(["--save".into(), path.to_owned()]),
        }
        monitor.extend(zenoh_args(Role::Operator));
        deployment.services.push(spawn_service(
            "monitor",
            "monitor",
            &monitor,
            "warn,monitor=info",
            args.echo_logs,
        )?);
    }
    Ok(deployment)
}

fn wait_listening(endpoint: &str, limit: Duration) -> anyhow::Result<()> {
    let addr: std::net::SocketAddr = endpoint.trim_start_matches("tcp/").parse()?;
    let deadline = Instant::now() + limit;
    while std::net::TcpStream::connect_timeout(&addr, Duration::from_millis(200)).is_err() {
        anyhow::ensure!(Instant::now() < deadline, "nothing listens at {endpoint}");
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(())
}

/// Waits until the controller answers for every env and each has its twin.
async fn ready(deployment: &Deployment, limit: Duration) -> anyhow::Result<()> {
    let session = deployment
        .client
        .open()
        .await
        .map_err(|e| anyhow::anyhow!("client session: {e}"))?;
    let deadline = Instant::now() + limit;
    for env in &deployment.envs {
        loop {
            let status = client::status(&session, env, Duration::from_secs(2)).await;
            match status {
                Ok(s) if !matches!(s.state, EnvState::Offline { .. }) => break,
                other => anyhow::ensure!(
                    Instant::now() < deadline,
                    "{env} did not come up within {limit:?}: {other:?}"
                ),
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }
    let _ = session.close().await;
    Ok(())
}

// ---------------------------------------------------------------------------
// Sampling and the report.

fn sample(services: &mut [Service], me: &mut Service, t: f64, shared: &Shared) {
    for s in services.iter_mut().chain(std::iter::once(me)) {
        if s.exited.is_some() {
            continue;
        }
        if let Some(process) = &mut s.process {
            if let Ok(Some(status)) = process.0.try_wait() {
                let why = format!("exited during the run: {status}");
                shared.error("service", &s.name, &why, false);
                s.exited = Some(why);
                continue;
            }
        }
        match rss_kib(s.pid) {
            Some(kib) => s.samples.push((t, kib)),
            None => {
                let why = "vanished during the run".to_owned();
                shared.error("service", &s.name, &why, false);
                s.exited = Some(why);
            }
        }
    }
}

fn progress(shared: &Shared, services: &[Service], me: &Service, warmup: Duration) {
    let elapsed = shared.start.elapsed();
    let mut line = format!("[{:>8}]", hms(elapsed));
    if elapsed < warmup {
        line.push_str(" (warm-up)");
    }
    let steps: Vec<String> = shared
        .steps
        .iter()
        .map(|c| c.load(Ordering::Relaxed).to_string())
        .collect();
    let episodes: Vec<String> = shared
        .episodes
        .iter()
        .map(|c| c.load(Ordering::Relaxed).to_string())
        .collect();
    let _ = write!(
        line,
        " steps {} ({:.1}/s) | episodes {} | flood {} ok, {} busy | disconnects {}",
        steps.join("+"),
        Shared::total(&shared.steps) as f64 / elapsed.as_secs_f64().max(1e-3),
        episodes.join("+"),
        shared.flood_ok.load(Ordering::Relaxed),
        shared.flood_busy.load(Ordering::Relaxed),
        shared.disconnects.load(Ordering::Relaxed),
    );
    let errors = lock(&shared.errors);
    let _ = write!(line, " | unexpected {}", errors.unexpected);
    if !errors.by_kind.is_empty() {
        let kinds: Vec<String> = errors
            .by_kind
            .iter()
            .map(|((kind, _), n)| format!("{kind}={n}"))
            .collect();
        let _ = write!(line, " [{}]", kinds.join(", "));
    }
    drop(errors);
    line.push_str(" | RSS MiB");
    for s in services.iter().chain(std::iter::once(me)) {
        match (s.samples.last(), &s.exited) {
            (_, Some(_)) => {
                let _ = write!(line, " {} gone", s.name);
            }
            (Some((_, kib)), None) => {
                let _ = write!(line, " {} {:.1}", s.name, mib(*kib));
            }
            (None, None) => {}
        }
    }
    eprintln!("{line}");
}

/// SIGINT and SIGTERM to this process: the run stops early and reports.
struct Signals {
    interrupt: tokio::signal::unix::Signal,
    terminate: tokio::signal::unix::Signal,
}

impl Signals {
    fn install() -> std::io::Result<Self> {
        use tokio::signal::unix::{signal, SignalKind};
        Ok(Self {
            interrupt: signal(SignalKind::interrupt())?,
            terminate: signal(SignalKind::terminate())?,
        })
    }

    /// The next one's name.
    async fn recv(&mut self) -> &'static str {
        tokio::select! {
            _ = self.interrupt.recv() => "SIGINT",
            _ = self.terminate.recv() => "SIGTERM",
        }
    }
}

/// SIGTERM, then up to `limit` for a clean exit; killed otherwise.
fn stop(service: &mut Service, limit: Duration) -> String {
    let Some(process) = &mut service.process else {
        return "-".into();
    };
    if let Some(why) = &service.exited {
        return why.clone();
    }
    process.signal("TERM");
    let signalled = Instant::now();
    let deadline = signalled + limit;
    loop {
        let took = signalled.elapsed().as_secs_f64();
        match process.0.try_wait() {
            Ok(Some(status)) if status.success() => return format!("clean, {took:.1} s"),
            Ok(Some(status)) => return format!("{status}, {took:.1} s"),
            Ok(None) if Instant::now() < deadline => std::thread::sleep(Duration::from_millis(50)),
            _ => return format!("still running {limit:?} after SIGTERM: killed"),
        }
    }
}

struct Report<'a> {
    args: &'a Args,
    shared: &'a Shared,
    services: &'a [Service],
    me: &'a Service,
    exits: &'a [(String, String)],
    ran_for: Duration,
    /// The signal that stopped the run early.
    interrupted: Option<&'static str>,
}

impl Report<'_> {
    /// The Markdown report and whether the run passed.
    fn render(&self) -> (String, bool) {
        let a = self.args;
        let sh = self.shared;
        let warmup_s = a.warmup.as_secs_f64();
        let mut out = String::new();
        let mut failures: Vec<String> = Vec::new();
        let topology = match a.topology {
            Topology::Router => "through zenohd (deploy/ files: QUIC + TLS, mTLS, passwords, ACL)",
            Topology::Peer => "peer to peer (TCP on loopback)",
        };
        let _ = writeln!(
            out,
            "## Soak: {} for {} (warm-up {}), seed {}\n",
            a.task,
            hms(self.ran_for),
            hms(a.warmup),
            a.seed
        );
        if let Some(which) = self.interrupted {
            let _ = writeln!(
                out,
                "**Stopped early by {which}** after {} of {}: the figures are those of the \
                 time that ran.\n",
                hms(self.ran_for),
                hms(a.duration)
            );
        }
        let _ = writeln!(
            out,
            "Two sim envs (`sim_twin` processes, 84×84) served by one `env_controller`, {topology}, \
             stepped {}; monitor: {}; flood: {}; disconnects: {}; gym sessions {}. RSS sampled \
             every {}. {} cores.\n",
            if a.step_rate > 0.0 {
                format!("at most {} steps/s each", a.step_rate)
            } else {
                "as fast as they answer".to_owned()
            },
            match (a.no_monitor, a.monitor_sink.as_str()) {
                (true, _) => "none".to_owned(),
                (false, "serve") => format!(
                    "`monitor --all --serve` (no viewer, {} MiB of history)",
                    a.monitor_memory_mib
                ),
                (false, "null") => "`monitor --all --save /dev/null`".to_owned(),
                (false, path) => format!("`monitor --all --save {path}`"),
            },
            if a.flood_rate == 0 {
                "none".to_owned()
            } else {
                format!(
                    "{} status + booking-list queries/s in bursts of {}",
                    a.flood_rate, a.flood_burst
                )
            },
            if a.no_disconnects {
                "none".to_owned()
            } else {
                format!("every {}–{}", hms(a.disconnect_min), hms(a.disconnect_max))
            },
            if a.registered { "registered" } else { "anonymous" },
            hms(a.sample_every),
            std::thread::available_parallelism().map_or(0, |n| n.get()),
        );
        let judged_s = (self.ran_for.as_secs_f64() - warmup_s).max(0.0);
        let window = Duration::from_secs_f64(WINDOW_S.min(judged_s / 4.0));
        let _ = writeln!(
            out,
            "RSS after warm-up and at end: medians of the samples in the first and the last {} \
             after the warm-up; growth: between the two (limit {} %); trend: least-squares slope \
             after the warm-up; max: over the whole run.\n",
            hms(window),
            a.max_growth_pct
        );
        let _ = writeln!(
            out,
            "| process | RSS after warm-up (MiB) | RSS at end (MiB) | growth | max (MiB) | trend after warm-up (MiB/h) | stopped | verdict |"
        );
        let _ = writeln!(out, "|---|---:|---:|---:|---:|---:|---|---|");
        for s in self.services.iter().chain(std::iter::once(self.me)) {
            let exit = self
                .exits
                .iter()
                .find(|(name, _)| *name == s.name)
                .map_or("-", |(_, e)| e.as_str());
            let verdict;
            let row = match figures(&s.samples, warmup_s) {
                Some(f) => {
                    let over = f.growth_pct > a.max_growth_pct;
                    verdict = match (s.judged, over, &s.exited) {
                        (_, _, Some(_)) => "**died**",
                        (false, _, None) => "not judged",
                        (true, true, None) => "**grew**",
                        (true, false, None) => "flat",
                    };
                    if s.judged && over {
                        failures.push(format!(
                            "{} RSS grew {:+.1} % after the warm-up (limit {} %)",
                            s.name, f.growth_pct, a.max_growth_pct
                        ));
                    }
                    format!(
                        "{:.1} | {:.1} | {:+.1} % | {:.1} | {:+.1}",
                        mib(f.baseline),
                        mib(f.end),
                        f.growth_pct,
                        mib(f.max),
                        f.slope_mib_h
                    )
                }
                None => {
                    verdict = if s.exited.is_some() {
                        "**died**"
                    } else {
                        "no sample after the warm-up"
                    };
                    "- | - | - | - | -".into()
                }
            };
            if let Some(why) = &s.exited {
                failures.push(format!("{} {why}", s.name));
            }
            let name = if s.judged {
                s.name.clone()
            } else {
                format!("{} (this program: the clients)", s.name)
            };
            let _ = writeln!(out, "| {name} | {row} | {exit} | {verdict} |");
        }
        // Load.
        let secs = self.ran_for.as_secs_f64().max(1e-3);
        let _ = writeln!(out, "\n| load | figure |\n|---|---:|");
        for (i, env) in ["env 0", "env 1"].iter().enumerate() {
            let steps = sh.steps.get(i).map_or(0, |c| c.load(Ordering::Relaxed));
            let episodes = sh.episodes.get(i).map_or(0, |c| c.load(Ordering::Relaxed));
            let ended = sh.ended.get(i).map_or(0, |c| c.load(Ordering::Relaxed));
            let _ = writeln!(
                out,
                "| {env}: steps ({:.1}/s) | {steps} |\n| {env}: episodes started (ended by the task or the step limit) | {episodes} ({ended}) |",
                steps as f64 / secs
            );
        }
        let flood_sent = sh.flood_sent.load(Ordering::Relaxed);
        let _ = writeln!(
            out,
            "| flood: queries sent ({:.0}/s) | {flood_sent} |\n| flood: answered | {} |\n| flood: `Busy` answers (expected) | {} |\n| flood: bursts skipped (4 bursts still in flight) | {} |",
            flood_sent as f64 / secs,
            sh.flood_ok.load(Ordering::Relaxed),
            sh.flood_busy.load(Ordering::Relaxed),
            sh.flood_skipped.load(Ordering::Relaxed),
        );
        let mut recoveries = lock(&sh.recoveries).clone();
        recoveries.sort();
        let disconnects = sh.disconnects.load(Ordering::Relaxed);
        let recovery = if recoveries.is_empty() {
            "-".to_owned()
        } else {
            let median = recoveries[recoveries.len() / 2];
            let max = recoveries[recoveries.len() - 1];
            format!(
                "{} ({} ms median, {} ms max)",
                recoveries.len(),
                median.as_millis(),
                max.as_millis()
            )
        };
        let _ = writeln!(
            out,
            "| disconnects done | {disconnects} |\n| new sessions holding the lease again (time from the drop) | {recovery} |"
        );
        for s in self.services {
            if !s.name.starts_with("monitor") {
                continue;
            }
            if let Some(logs) = &s.logs {
                let stats = &lock(logs).monitor_stats;
                let get = |k: &str| stats.get(k).map_or("-".into(), |v| v.to_string());
                let _ = writeln!(
                    out,
                    "| monitor: frames / poses / rewards received (last report) | {} / {} / {} |\n| monitor: frames / messages dropped, decode errors | {} / {} / {} |",
                    get("frames"),
                    get("poses"),
                    get("rewards"),
                    get("dropped_frames"),
                    get("dropped_messages"),
                    get("decode_errors")
                );
            }
        }
        // Errors.
        let errors = lock(&sh.errors);
        let _ = writeln!(out, "\n| answer | count | expected |\n|---|---:|---|");
        if errors.by_kind.is_empty() {
            let _ = writeln!(out, "| (no error answer) | 0 | - |");
        }
        for ((kind, expected), n) in &errors.by_kind {
            let _ = writeln!(
                out,
                "| {kind} | {n} | {} |",
                if *expected { "yes" } else { "**no**" }
            );
        }
        let _ = writeln!(out, "\nUnexpected errors: {}.", errors.unexpected);
        for line in &errors.first {
            let _ = writeln!(out, "- `{}`", line.replace('`', "'"));
        }
        if errors.unexpected > 0 {
            failures.push(format!("{} unexpected errors", errors.unexpected));
        }
        drop(errors);
        // What the services logged.
        let _ = writeln!(
            out,
            "\n| service log | WARN lines | ERROR lines (ours) | ERROR lines (dependencies, not judged) |\n|---|---:|---:|---:|"
        );
        let mut logged_errors = Vec::new();
        for s in self.services {
            if let Some(logs) = &s.logs {
                let logs = lock(logs);
                let _ = writeln!(
                    out,
                    "| {} | {} | {} | {} |",
                    s.name, logs.warn, logs.error, logs.error_deps
                );
                for line in &logs.first_errors {
                    logged_errors.push(format!("{}: {line}", s.name));
                }
                if logs.error > 0 {
                    failures.push(format!("{} logged {} ERROR lines", s.name, logs.error));
                }
            }
        }
        for line in &logged_errors {
            let _ = writeln!(out, "- `{}`", line.replace('`', "'"));
        }
        let passed = failures.is_empty();
        let _ = writeln!(
            out,
            "\n**{}**{}",
            if passed { "PASS" } else { "FAIL" },
            if passed {
                format!(
                    ": every service within {} % RSS growth after the warm-up, no unexpected error.",
                    a.max_growth_pct
                )
            } else {
                format!(": {}.", failures.join("; "))
            }
        );
        (out, passed)
    }
}

// ---------------------------------------------------------------------------

fn main() -> anyhow::Result<ExitCode> {
    let args = Args::parse();
    // Zenoh logs an ERROR for each reply that arrives after its query was
    // abandoned (a step in flight when a session is dropped, or at the
    // deadline): expected here, so not shown unless RUST_LOG asks.
    if std::env::var_os("RUST_LOG").is_none() {
        std::env::set_var("RUST_LOG", "info,zenoh=warn,zenoh::api::handlers::fifo=off");
    }
    offworld_program::init_logging();
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(run(args))
}

async fn run(args: Args) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        args.warmup < args.duration,
        "the warm-up ({}) must end before the run does ({})",
        hms(args.warmup),
        hms(args.duration)
    );
    anyhow::ensure!(!args.sample_every.is_zero(), "--sample-every must be > 0");
    anyhow::ensure!(
        args.step_rate.is_finite() && args.step_rate >= 0.0,
        "--step-rate must be ≥ 0"
    );
    anyhow::ensure!(
        matches!(args.monitor_sink.as_str(), "serve" | "null")
            || args.monitor_sink.ends_with(".rrd"),
        "--monitor-sink is `serve`, `null` or a path ending in .rrd, got `{}`",
        args.monitor_sink
    );
    anyhow::ensure!(
        args.disconnect_min <= args.disconnect_max && !args.disconnect_max.is_zero(),
        "--disconnect-min must be ≤ --disconnect-max, and the latter > 0"
    );
    eprintln!("soak: starting the deployment ({:?}) …", args.topology);
    let mut signals = Signals::install()?;
    let deployment = start(&args)?;
    tokio::select! {
        r = ready(&deployment, Duration::from_secs(120)) => r.context("waiting for the envs")?,
        which = signals.recv() => {
            eprintln!("soak: {which} while starting: stopped");
            return Ok(ExitCode::from(130));
        }
    }
    let mut deployment = deployment;
    let pids: Vec<String> = deployment
        .services
        .iter()
        .map(|s| format!("{} {}", s.name, s.pid))
        .collect();
    eprintln!(
        "soak: up ({}); running for {} (warm-up {}), seed {}",
        pids.join(", "),
        hms(args.duration),
        hms(args.warmup),
        args.seed
    );

    let deadline = TokioInstant::now() + args.duration;
    let shared = Arc::new(Shared::new(
        deployment.envs.len(),
        deadline,
        args.keep_errors,
    ));
    let mut request = OpenRequest::anonymous(ObsOptions {
        channels: Channels::DepthOnly,
        height: 84,
        width: 84,
        depth_format: DepthFormat::Uint8,
    });
    request.token = deployment.token.clone();
    request.experiment_name = "soak".into();
    let setup = ClientSetup {
        session: deployment.client.clone(),
        request,
        recover_within: args.recover_within,
        step_period: (args.step_rate > 0.0).then(|| Duration::from_secs_f64(1.0 / args.step_rate)),
    };
    let mut tasks = Vec::new();
    let mut kicks = Vec::new();
    for (i, env) in deployment.envs.iter().enumerate() {
        let (tx, rx) = mpsc::channel(1);
        kicks.push(tx);
        tasks.push(tokio::spawn(stepper(
            shared.clone(),
            i,
            env.clone(),
            setup.clone(),
            rx,
            args.seed,
        )));
    }
    if args.flood_rate > 0 {
        tasks.push(tokio::spawn(flood(
            shared.clone(),
            deployment.client.clone(),
            deployment.envs.clone(),
            args.flood_rate,
            args.flood_burst,
            args.flood_timeout,
        )));
    }
    if !args.no_disconnects {
        tasks.push(tokio::spawn(disconnects(
            shared.clone(),
            kicks.clone(),
            args.disconnect_min,
            args.disconnect_max,
            args.seed,
        )));
    }

    // Sample at every period, at the end of the warm-up and at the end.
    let mut me = Service {
        name: "soak".into(),
        pid: std::process::id(),
        process: None,
        judged: false,
        logs: None,
        samples: Vec::new(),
        exited: None,
    };
    let mut times: Vec<Duration> = Vec::new();
    let mut t = Duration::ZERO;
    while t < args.duration {
        times.push(t);
        t += args.sample_every;
    }
    times.push(args.warmup);
    times.push(args.duration);
    times.sort();
    times.dedup();
    let origin = TokioInstant::now() - shared.start.elapsed();
    let mut interrupted = None;
    for at in times {
        tokio::select! {
            _ = tokio::time::sleep_until((origin + at).min(deadline)) => {}
            which = signals.recv() => {
                eprintln!("soak: {which}: stopping early, reporting what ran");
                shared.stop.send_replace(true);
                interrupted = Some(which);
                break;
            }
        }
        let t = shared.start.elapsed().as_secs_f64();
        sample(&mut deployment.services, &mut me, t, &shared);
        progress(&shared, &deployment.services, &me, args.warmup);
    }
    let ran_for = shared.start.elapsed();
    // Every task ends at the deadline by itself; bounded anyway.
    for task in tasks {
        if tokio::time::timeout(Duration::from_secs(30), task)
            .await
            .is_err()
        {
            shared.error(
                "soak",
                "task",
                "a load task did not stop within 30 s",
                false,
            );
        }
    }
    drop(kicks);
    // Stop the services (monitor first: it completes its recording).
    let mut exits = Vec::new();
    let mut order: Vec<usize> = (0..deployment.services.len()).collect();
    order.sort_by_key(|&i| match deployment.services[i].name.as_str() {
        "monitor" => 0,
        "env_controller" => 1,
        "zenohd" => 3,
        _ => 2,
    });
    for i in order {
        let service = &mut deployment.services[i];
        let exit = stop(service, Duration::from_secs(10));
        exits.push((service.name.clone(), exit));
    }
    let (report, passed) = Report {
        args: &args,
        shared: &shared,
        services: &deployment.services,
        me: &me,
        exits: &exits,
        ran_for,
        interrupted,
    }
    .render();
    println!("{report}");
    // What is left of the processes is killed, the files removed.
    drop(deployment);
    Ok(match (interrupted, passed) {
        (Some(_), _) => ExitCode::from(130),
        (None, true) => ExitCode::SUCCESS,
        (None, false) => ExitCode::FAILURE,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn durations_parse() {
        let d = |s: &str| parse_duration(s).expect(s);
        assert_eq!(d("90"), Duration::from_secs(90));
        assert_eq!(d("90s"), Duration::from_secs(90));
        assert_eq!(d("4m"), Duration::from_secs(240));
        assert_eq!(d("1h"), Duration::from_secs(3600));
        assert_eq!(d("1h30m"), Duration::from_secs(5400));
        assert_eq!(d("500ms"), Duration::from_millis(500));
        assert!(parse_duration("4x").is_err());
        assert!(parse_duration("").is_err());
    }

    #[test]
    fn figures_after_the_warmup() {
        let samples = [(0.0, 100), (60.0, 1000), (120.0, 1020), (180.0, 1040)];
        let f = figures(&samples, 60.0).expect("figures");
        assert_eq!((f.baseline, f.end, f.max), (1000, 1040, 1040));
        assert!((f.growth_pct - 4.0).abs() < 1e-9);
        assert!(f.slope_mib_h > 0.0);
        // A sawtooth: medians of the first and last minute, not its phase.
        let saw: Vec<(f64, u64)> = (0..=60)
            .map(|i| (f64::from(i) * 10.0, if i % 2 == 0 { 1000 } else { 1100 }))
            .collect();
        let f = figures(&saw, 0.0).expect("figures");
        assert_eq!((f.baseline, f.end, f.max), (1000, 1000, 1100));
        assert!(f.slope_mib_h.abs() < 1.0);
    }

    #[test]
    fn log_levels_without_colours() {
        let line = "\u{1b}[2m2025-01-01T00:00:00Z\u{1b}[0m \u{1b}[31mERROR\u{1b}[0m x: boom";
        assert_eq!(level_of(&strip_ansi(line)), Some("ERROR"));
        assert_eq!(level_of("2025-01-01T00:00:00Z  WARN x: hm"), Some("WARN"));
        assert_eq!(level_of("2025-01-01T00:00:00Z  INFO x: ERROR"), None);
        assert!(ours("t ERROR offworld_env_controller::env: boom"));
        assert!(ours("t ERROR monitor: boom"));
        assert!(!ours(
            "t ERROR zenoh::api::session: Received Data for unknown expr_id: 22"
        ));
    }
}
