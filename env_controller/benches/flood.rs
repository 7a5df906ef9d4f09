//! Backpressure under a flood, through a `zenohd` router (issue 22): 10,000
//! queries (`status`, `step`, `reset`, a third each, from 100 made-up
//! clients) sent at once to env A while A's state is held by reset drives
//! (A's robot, played here, takes `FLOOD_DRIVE_MS` per drive; a holder
//! resets A again and again), and a trainer steps env B (an embedded twin,
//! 84×84 depth) throughout. Every session is a Zenoh client of the router,
//! so every query and reply crosses it.
//!
//! Reports B's step latency idle and under the flood (while its immediate
//! answers come back, then while the queued requests wait), how the flood was
//! answered (ok, `Busy`, other typed errors, no answer) and whether
//! anything crashed (the router, the controller, a failed step of B).
//!
//! ```text
//! source .ci/env   # zenohd on PATH
//! cargo bench --bench flood
//! ```
//! `FLOOD_QUERIES` (10000), `FLOOD_CLIENTS` (100), `FLOOD_DRIVE_MS` (3000),
//! `FLOOD_IDLE_STEPS` (300); `ZENOHD` names the router binary.

use offworld_runtime::Resolution;
use std::collections::BTreeMap;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::embedded::{Embedded, SimEnv, Stepping, TwinProfile};
use offworld_env_controller::{EnvOptions, RequestLimits, Store, Task};
use offworld_runtime::msg::*;
use offworld_runtime::session::{loopback_endpoint, Mode};
use offworld_runtime::wire::{self, RequestError};
use offworld_runtime::{Component, EnvId, ErrorCode, SessionConfig, Topic, WireError};
use zenoh::query::Query;
use zenoh::Session;

fn setting(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// The router, killed when dropped.
struct Router(Child);

impl Drop for Router {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn start_router(endpoint: &str) -> anyhow::Result<Router> {
    let binary = std::env::var_os("ZENOHD").unwrap_or_else(|| "zenohd".into());
    let child = Command::new(&binary)
        .args(["--listen", endpoint, "--no-multicast-scouting"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .with_context(|| format!("{binary:?} (source .ci/env: it installs zenohd)"))?;
    let router = Router(child);
    let addr = endpoint.trim_start_matches("tcp/");
    let deadline = Instant::now() + Duration::from_secs(20);
    while std::net::TcpStream::connect(addr).is_err() {
        anyhow::ensure!(Instant::now() < deadline, "zenohd not listening on {addr}");
        std::thread::sleep(Duration::from_millis(50));
    }
    Ok(router)
}

async fn client_of_router(endpoint: &str) -> anyhow::Result<Session> {
    Ok(SessionConfig {
        mode: Mode::Client,
        connect: vec![endpoint.to_owned()],
        ..SessionConfig::default()
    }
    .open()
    .await?)
}

/// How one flood query was answered.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
enum Outcome {
    Ok,
    /// A typed error's code.
    Refused(u16),
    NoAnswer(String),
}

fn outcome<T>(result: Result<T, RequestError>) -> Outcome {
    match result {
        Ok(_) => Outcome::Ok,
        Err(RequestError::Remote(e)) => Outcome::Refused(e.code as u16),
        Err(RequestError::Timeout { .. }) => Outcome::NoAnswer("timeout".into()),
        Err(RequestError::NoResponder(_)) => Outcome::NoAnswer("no responder".into()),
        Err(other) => Outcome::NoAnswer(other.to_string()),
    }
}

/// The `q`-quantile (0..=1) of `v`, ms.
fn quantile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// One step of B, ms; resets (not timed) when the episode ends.
async fn timed_step(b: &mut EnvClient, i: usize) -> Result<f64, WireError> {
    let start = Instant::now();
    let r = b.step(Action::Discrete((i % 3) as i64)).await?;
    let ms = start.elapsed().as_secs_f64() * 1e3;
    if r.terminated || r.truncated {
        b.reset(Seed::Continue).await?;
    }
    Ok(ms)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    let queries = setting("FLOOD_QUERIES", 10_000) as usize;
    let clients = setting("FLOOD_CLIENTS", 100).max(1) as usize;
    let drive = Duration::from_millis(setting("FLOOD_DRIVE_MS", 3000));
    let idle_steps = setting("FLOOD_IDLE_STEPS", 300) as usize;

    let endpoint = loopback_endpoint()?;
    let mut router = start_router(&endpoint)?;
    let limits = RequestLimits::default();

    // The controller: B with its twin embedded, A with a robot played here.
    let controller = client_of_router(&endpoint).await?;
    let env_a = EnvId::sim("flood-bench-a")?;
    let env_b = EnvId::sim("flood-bench-b")?;
    let sim = SimEnv {
        env: env_b.clone(),
        task: "MonolithDiscrete".into(),
        resolution: Some(Resolution::new(84, 84)),
        seed: 0,
        profile: TwinProfile::default(),
        render_threads: 1,
        stepping: Stepping::OwnThread,
    };
    let mut embedded = Embedded::start_with(
        &controller,
        &[sim],
        Store::in_memory()?,
        EnvOptions::default(),
        limits,
        None,
    )
    .await?;
    let robot = client_of_router(&endpoint).await?;
    let runtime = tokio::runtime::Handle::current();
    let drives = Arc::new(AtomicUsize::new(0));
    let driven = drives.clone();
    let _goto = robot
        .declare_queryable(env_a.key(Topic::Goto))
        .callback(move |query: Query| {
            driven.fetch_add(1, Ordering::SeqCst);
            runtime.spawn(async move {
                tokio::time::sleep(drive).await;
                let over = WireError::unavailable("the bench's robot ends every drive short");
                let _ = wire::reply_now::<GotoReply>(&query, Err(over));
            });
        })
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let _robot_alive = robot
        .liveliness()
        .declare_token(env_a.alive_key(Component::SimTwin))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let served_a = embedded
        .controller
        .serve(
            env_a.clone(),
            Task::by_name("MonolithDiscrete")?,
            EnvOptions {
                allow_anonymous: true,
                ..EnvOptions::default()
            },
        )
        .await?;
    anyhow::ensure!(
        served_a.link().wait_online(Duration::from_secs(10)).await,
        "A's robot never came online"
    );

    let obs = ObsOptions {
        channels: Channels::DepthOnly,
        height: 84,
        width: 84,
        depth_format: DepthFormat::Uint8,
    };
    let open = |session: Session, env: EnvId| async move {
        EnvClient::open_when_ready(
            &session,
            &env,
            OpenRequest::anonymous(obs),
            ClientTimeouts::default(),
            Duration::from_secs(20),
        )
        .await
    };

    // B's trainer: idle figures first.
    let trainer = client_of_router(&endpoint).await?;
    let mut b = open(trainer.clone(), env_b.clone()).await?;
    b.reset(Seed::Fixed(1)).await?;
    for i in 0..20 {
        timed_step(&mut b, i).await?;
    }
    let mut idle = Vec::with_capacity(idle_steps);
    for i in 0..idle_steps {
        idle.push(timed_step(&mut b, i).await?);
    }

    // A's holder: reset after reset, each holding A's state for a drive.
    let holder_session = client_of_router(&endpoint).await?;
    let mut holder = open(holder_session.clone(), env_a.clone()).await?;
    let stop = Arc::new(AtomicBool::new(false));
    let holding = {
        let stop = stop.clone();
        tokio::spawn(async move {
            let mut resets = 0usize;
            while !stop.load(Ordering::SeqCst) {
                let _ = holder.reset(Seed::Continue).await;
                resets += 1;
            }
            let _ = holder.close().await;
            resets
        })
    };
    while drives.load(Ordering::SeqCst) == 0 {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }

    // The flood, all sent at once; B steps until every query is answered.
    let flooder = client_of_router(&endpoint).await?;
    let answered = Arc::new(AtomicUsize::new(0));
    let flood_start = Instant::now();
    let flood: Vec<_> = (0..queries)
        .map(|i| {
            let (s, env, answered) = (flooder.clone(), env_a.clone(), answered.clone());
            let tag = ClientTag {
                client_id: format!("flooder-{}", i % clients),
            };
            tokio::spawn(async move {
                let key = |t: Topic| env.key(t);
                let deadline = Duration::from_secs(30);
                let got = match i % 3 {
                    0 => outcome(
                        wire::request_as::<(), EnvStatus>(
                            &s,
                            &key(Topic::Status),
                            &(),
                            deadline,
                            &tag,
                        )
                        .await,
                    ),
                    1 => {
                        let forged = StepRequest {
                            session_id: format!("forged-{i}"),
                            seq: 1,
                            action: Action::Discrete(0),
                        };
                        outcome(
                            wire::request_tail_as::<_, StepReply>(
                                &s,
                                &key(Topic::Step),
                                &forged,
                                deadline,
                                &tag,
                                Vec::new(),
                            )
                            .await,
                        )
                    }
                    _ => {
                        let forged = ResetRequest {
                            session_id: format!("forged-{i}"),
                            seed: Seed::Continue,
                        };
                        outcome(
                            wire::request_tail_as::<_, ResetReply>(
                                &s,
                                &key(Topic::Reset),
                                &forged,
                                deadline,
                                &tag,
                                Vec::new(),
                            )
                            .await,
                        )
                    }
                };
                answered.fetch_add(1, Ordering::SeqCst);
                (i % 3, got)
            })
        })
        .collect();
    // Steps taken while the flood's immediate answers (status, Busy) are
    // still coming back, and while only the queued ones wait for A's state.
    let (mut burst, mut queued) = (Vec::new(), Vec::new());
    let immediate = queries.saturating_sub(limits.env_queue);
    let mut b_failures = Vec::new();
    let mut i = 0;
    while answered.load(Ordering::SeqCst) < queries || burst.len() + queued.len() < 30 {
        let in_burst = answered.load(Ordering::SeqCst) < immediate;
        match timed_step(&mut b, i).await {
            Ok(ms) if in_burst => burst.push(ms),
            Ok(ms) => queued.push(ms),
            Err(e) => b_failures.push(e.to_string()),
        }
        i += 1;
        if flood_start.elapsed() > Duration::from_secs(120) {
            break;
        }
    }
    let flood_took = flood_start.elapsed();
    let flooded: Vec<f64> = burst.iter().chain(&queued).copied().collect();
    let mut tally: BTreeMap<(usize, Outcome), usize> = BTreeMap::new();
    for query in flood {
        let (kind, got) = query.await?;
        *tally.entry((kind, got)).or_default() += 1;
    }
    stop.store(true, Ordering::SeqCst);
    let resets = holding.await?;

    // After: both envs still answer, B still steps, the router is up.
    let mut after = Vec::new();
    for i in 0..50 {
        after.push(timed_step(&mut b, i).await?);
    }
    b.close().await?;
    let status_a = offworld_client::status(&trainer, &env_a, Duration::from_secs(5)).await;
    let router_alive = router.0.try_wait()?.is_none();

    let kinds = ["status", "step", "reset"];
    println!("flood: {queries} queries to {env_a} ({clients} client ids, a third each of status/step/reset), sent at once");
    println!(
        "       while A's state is held by reset drives of {} ms ({resets} resets by A's holder); \
         limits: {limits:?}",
        drive.as_millis()
    );
    println!(
        "       every session a Zenoh client of zenohd on {endpoint}; all answered within {:.2} s",
        flood_took.as_secs_f64()
    );
    println!("{:<8} {:<28} {:>7}", "query", "answer", "count");
    let mut busy = 0;
    let mut unanswered = 0;
    for ((kind, got), n) in &tally {
        let shown = match got {
            Outcome::Ok => "ok".to_owned(),
            Outcome::Refused(code) => match ErrorCode::try_from(*code) {
                Ok(known) => format!("{} ({code})", known.name()),
                Err(_) => format!("code {code}"),
            },
            Outcome::NoAnswer(why) => format!("NO ANSWER: {why}"),
        };
        match got {
            Outcome::Refused(code) if *code == ErrorCode::Busy as u16 => busy += n,
            Outcome::NoAnswer(_) => unanswered += n,
            _ => {}
        }
        println!("{:<8} {:<28} {:>7}", kinds[*kind], shown, n);
    }
    println!("Busy answers: {busy}; unanswered: {unanswered}");
    println!();
    println!(
        "B's step (84x84 depth, via the router), ms: {:>6} {:>8} {:>8} {:>8}",
        "steps", "p50", "p99", "max"
    );
    for (what, v) in [
        ("idle", &idle),
        ("under the flood (all)", &flooded),
        ("  while the burst is answered", &burst),
        ("  while the queued wait for A", &queued),
        ("after", &after),
    ] {
        println!(
            "  {:<40} {:>6} {:>8.2} {:>8.2} {:>8.2}",
            what,
            v.len(),
            quantile(v, 0.5),
            quantile(v, 0.99),
            quantile(v, 1.0)
        );
    }
    println!(
        "crashes: router {}, controller {} (A's status after: {}), B's failed steps: {}",
        if router_alive { "alive" } else { "DIED" },
        if status_a.is_ok() {
            "serving"
        } else {
            "NOT ANSWERING"
        },
        match &status_a {
            Ok(s) => format!("{:?}", s.state),
            Err(e) => e.to_string(),
        },
        b_failures.len()
    );
    for failure in b_failures.iter().take(5) {
        println!("  B failed: {failure}");
    }
    embedded.shutdown("bench over").await;
    Ok(())
}
