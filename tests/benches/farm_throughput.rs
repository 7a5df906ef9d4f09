//! Sim-farm throughput: total steps/s a trainer gets from N sim envs
//! stepped together with `VecEnvClient` (one concurrent fan-out per step),
//! for N = 1, 2, 4 — through the `zenohd` router with the repository's
//! deployment files (QUIC with TLS 1.3, mTLS, passwords, ACL) against plain TCP peer to
//! peer, in one run, in two layouts:
//! - "twin processes": N `sim_twin` processes (84×84, lockstep) behind one
//!   `env_controller` process — camera frames cross the router; the farm on
//!   the router's local socket, the trainer over QUIC (what `offworld farm`
//!   runs);
//! - "controller per twin": N `offworld serve --embedded-twins` processes —
//!   only the gym's queries and replies cross the router.
//!
//! A third table takes the router's cost apart for the twin-process layout
//! at N = 1: peer to peer, a bare `zenohd` on plain TCP (no TLS, no
//! passwords, no ACL), the site's router with the farm reached over TLS on
//! TCP, over QUIC (a farm on another host), and over the router's local
//! socket (what the first table measures).
//!
//! `cargo bench --bench farm_throughput`
//! (`FARM_SECONDS` per measurement, default 8; `FARM_SIZES`, default `1,2,4`;
//! `FARM_TABLES`, default `layouts,router`).

use std::time::{Duration, Instant};

use offworld_client::{ClientTimeouts, EnvClient, VecEnvClient};
use offworld_deploy::farm::SimFarm;
use offworld_deploy::site::{Link, Role, RouterSite};
use offworld_runtime::msg::*;
use offworld_runtime::session::loopback_endpoint;
use offworld_runtime::{EnvId, SessionConfig};
use offworld_tests::{Process, Spawn};
use zenoh::Session;

fn seconds() -> f64 {
    std::env::var("FARM_SECONDS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(8.0)
}

fn sizes() -> Vec<usize> {
    std::env::var("FARM_SIZES")
        .ok()
        .map(|v| v.split(',').filter_map(|s| s.trim().parse().ok()).collect())
        .unwrap_or_else(|| vec![1, 2, 4])
}

fn envs(n: usize, tag: &str) -> anyhow::Result<Vec<EnvId>> {
    (0..n)
        .map(|i| Ok(EnvId::sim(&format!("farm-{tag}-{n}-{i}"))?))
        .collect()
}

fn serve_args(db: &str, envs: &[EnvId]) -> Vec<String> {
    let mut args = vec!["--db".into(), db.into(), "serve".into()];
    for env in envs {
        args.push("--env".into());
        args.push(format!("{env}=MonolithDiscrete"));
    }
    args
}

fn twin_args(env: &EnvId) -> Vec<String> {
    vec![
        "--env".into(),
        env.to_string(),
        "--resolution".into(),
        "84x84".into(),
    ]
}

async fn open_all(session: &Session, envs: &[EnvId], token: &str) -> anyhow::Result<VecEnvClient> {
    let request = OpenRequest {
        token: token.to_owned(),
        ..OpenRequest::anonymous(ObsOptions {
            channels: Channels::DepthOnly,
            height: 84,
            width: 84,
            depth_format: DepthFormat::Uint8,
        })
    };
    let mut clients = Vec::new();
    for env in envs {
        let client = EnvClient::open_when_ready(
            session,
            env,
            request.clone(),
            ClientTimeouts::default(),
            Duration::from_secs(30),
        )
        .await
        .map_err(|e| anyhow::anyhow!("open {env}: {e}"))?;
        clients.push(client);
    }
    Ok(VecEnvClient::new(clients))
}

/// Total steps/s over `seconds()` after a warm-up.
async fn measure(vec: &mut VecEnvClient) -> anyhow::Result<f64> {
    let n = vec.len();
    let seeds: Vec<Seed> = (0..n as u64).map(Seed::Fixed).collect();
    vec.reset(&seeds)
        .await
        .map_err(|e| anyhow::anyhow!("reset: {e}"))?;
    let actions = |i: usize| {
        (0..n)
            .map(|k| Action::Discrete(((i + k) % 4) as i64))
            .collect()
    };
    for i in 0..20 {
        vec.step(actions(i))
            .await
            .map_err(|e| anyhow::anyhow!("warm-up step {i}: {e}"))?;
    }
    let start = Instant::now();
    let mut rounds = 0usize;
    while start.elapsed().as_secs_f64() < seconds() {
        vec.step(actions(rounds))
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
        rounds += 1;
    }
    let rate = (rounds * n) as f64 / start.elapsed().as_secs_f64();
    vec.close().await.map_err(|e| anyhow::anyhow!(e))?;
    Ok(rate)
}

fn spawn(binary: &str, args: &[String]) -> anyhow::Result<Process> {
    let refs: Vec<&str> = args.iter().map(String::as_str).collect();
    Ok(Process::spawn_logged(binary, &refs, "warn")?)
}

/// What `offworld farm` runs: the farm on the router's local socket, the
/// trainer over QUIC.
async fn through_router(n: usize) -> anyhow::Result<f64> {
    through_site(n, Link::LocalSocket, false, true).await
}

/// Twin processes behind the site's router (the repository's files), the
/// farm's processes reaching it over `link`, the network's over QUIC or,
/// with `tls_over_tcp`, over its TLS-on-TCP listeners; without `acl`, the
/// router's access control is off (to measure what it costs).
async fn through_site(n: usize, link: Link, tls_over_tcp: bool, acl: bool) -> anyhow::Result<f64> {
    let mut site = RouterSite::start(&format!("router-{n}"))?;
    if tls_over_tcp {
        site.use_tls_over_tcp();
    }
    if !acl {
        site.restart_router_with(&["access_control/enabled:false"])?;
    }
    let farm = SimFarm::start_on(site, &format!("router-{n}"), n, "MonolithDiscrete", link)?;
    farm.ready(Duration::from_secs(60)).await?;
    let trainer = farm.site.session(Role::Trainer).open().await?;
    let mut vec = open_all(&trainer, &farm.envs, &farm.token).await?;
    measure(&mut vec).await
}

async fn peer_to_peer(dir: &std::path::Path, n: usize) -> anyhow::Result<f64> {
    let envs = envs(n, "p2p")?;
    let endpoint = loopback_endpoint()?;
    let db = dir.join(format!("p2p-{n}.db"));
    let mut processes = Vec::new();
    let mut args = serve_args(&db.to_string_lossy(), &envs);
    args.extend(["--listen".into(), endpoint.clone()]);
    processes.push(spawn("env_controller", &args)?);
    for env in &envs {
        let mut args = twin_args(env);
        args.extend(["--connect".into(), endpoint.clone()]);
        processes.push(spawn("sim_twin", &args)?);
    }
    let trainer = SessionConfig::connecting(&endpoint).open().await?;
    let mut vec = open_all(&trainer, &envs, "").await?;
    let rate = measure(&mut vec).await;
    drop(processes);
    rate
}

/// Twin processes behind a bare `zenohd` on plain TCP: every process a
/// client of it, no TLS, no passwords, no access control.
async fn through_bare_router(dir: &std::path::Path, n: usize) -> anyhow::Result<f64> {
    let envs = envs(n, "bare")?;
    let endpoint = loopback_endpoint()?;
    let router = Process::spawn_from_path(
        "zenohd",
        &["--no-multicast-scouting", "-l", &endpoint],
        "warn",
    )?;
    let client = |mut args: Vec<String>| {
        args.extend([
            "--connect".into(),
            endpoint.clone(),
            "--mode".into(),
            "client".into(),
        ]);
        args
    };
    let db = dir.join(format!("bare-{n}.db"));
    let mut processes = vec![router];
    for env in &envs {
        processes.push(spawn("sim_twin", &client(twin_args(env)))?);
    }
    processes.push(spawn(
        "env_controller",
        &client(serve_args(&db.to_string_lossy(), &envs)),
    )?);
    let trainer = SessionConfig {
        mode: offworld_runtime::session::Mode::Client,
        ..SessionConfig::connecting(&endpoint)
    }
    .open()
    .await?;
    let mut vec = open_all(&trainer, &envs, "").await?;
    let rate = measure(&mut vec).await;
    drop(processes);
    rate
}

/// Where the router's cost goes, one twin process behind one controller.
async fn router_breakdown(dir: &std::path::Path) {
    println!("  where the router's cost goes (1 twin process, 84x84 render):");
    println!("  path                                     | steps/s | vs peer to peer");
    let direct = peer_to_peer(dir, 1).await;
    let rows = [
        ("peer to peer, TCP", None),
        (
            "bare zenohd, TCP (no TLS, auth, ACL)",
            Some(through_bare_router(dir, 1).await),
        ),
        (
            "site zenohd, TLS over TCP + ACL",
            Some(through_site(1, Link::Network, true, true).await),
        ),
        (
            "site zenohd, QUIC, ACL off",
            Some(through_site(1, Link::Network, false, false).await),
        ),
        (
            "site zenohd, QUIC + ACL",
            Some(through_site(1, Link::Network, false, true).await),
        ),
        (
            "site zenohd, farm on its socket + ACL",
            Some(through_router(1).await),
        ),
    ];
    for (path, rate) in rows {
        let rate = rate.as_ref().unwrap_or(&direct);
        let (shown, ratio) = match (rate, &direct) {
            (Ok(r), Ok(d)) => (format!("{r:7.0}"), format!("{:.2}", r / d)),
            (Ok(r), Err(_)) => (format!("{r:7.0}"), "-".into()),
            (Err(e), _) => (format!("failed: {e}"), "-".into()),
        };
        println!("  {path:<40} | {shown} | {ratio:>6}");
    }
}

fn tables() -> Vec<String> {
    std::env::var("FARM_TABLES")
        .unwrap_or_else(|_| "layouts,router".into())
        .split(',')
        .map(|t| t.trim().to_owned())
        .collect()
}

fn print_header() {
    println!(
        "  twins | {:>24} | {:>18} | router/p2p",
        "through the site router", "peer to peer (TCP)"
    );
}

/// One table row; a failed measurement shows its error.
fn print_row(n: usize, routed: &anyhow::Result<f64>, direct: &anyhow::Result<f64>) {
    let show = |r: &anyhow::Result<f64>| match r {
        Ok(rate) => format!("{rate:>10.0} steps/s"),
        Err(e) => format!("failed: {e}"),
    };
    let ratio = match (routed, direct) {
        (Ok(a), Ok(b)) => format!("{:.2}", a / b),
        _ => "-".into(),
    };
    println!(
        "  {n:>5} | {:>24} | {:>18} | {ratio:>9}",
        show(routed),
        show(direct)
    );
}

/// N `offworld serve --embedded-twins` processes, one env each.
async fn per_twin(
    site: Option<&RouterSite>,
    dir: &std::path::Path,
    n: usize,
) -> anyhow::Result<f64> {
    let tag = if site.is_some() { "erouter" } else { "ep2p" };
    let envs = envs(n, tag)?;
    let mut processes = Vec::new();
    let mut endpoints = Vec::new();
    for (i, env) in envs.iter().enumerate() {
        let db = dir.join(format!("{tag}-{n}-{i}.db"));
        let mut args = serve_args(&db.to_string_lossy(), std::slice::from_ref(env));
        args.push("--embedded-twins".into());
        match site {
            Some(site) => args.extend(site.role_args(Role::Controller)),
            None => {
                let endpoint = loopback_endpoint()?;
                args.extend(["--listen".into(), endpoint.clone()]);
                endpoints.push(endpoint);
            }
        }
        processes.push(spawn("offworld", &args)?);
    }
    let trainer = match site {
        Some(site) => site.session(Role::Trainer).open().await?,
        None => {
            SessionConfig {
                connect: endpoints,
                ..SessionConfig::default()
            }
            .open()
            .await?
        }
    };
    let mut vec = open_all(&trainer, &envs, "").await?;
    let rate = measure(&mut vec).await;
    drop(processes);
    rate
}

/// The two layouts, N = each of `sizes()`, routed vs peer to peer.
async fn layouts(scratch: &std::path::Path) -> anyhow::Result<()> {
    println!(
        "  twin processes behind one controller (84x84 render; the farm on the router's socket, the trainer over QUIC, ACL):"
    );
    print_header();
    for n in sizes() {
        let routed = through_router(n).await;
        let direct = peer_to_peer(scratch, n).await;
        print_row(n, &routed, &direct);
    }
    println!("  controller per twin (embedded, 320x240 render, 84x84 obs; QUIC + ACL):");
    print_header();
    let site = RouterSite::start("bench")?;
    for n in sizes() {
        let routed = per_twin(Some(&site), scratch, n).await;
        let direct = per_twin(None, scratch, n).await;
        print_row(n, &routed, &direct);
    }
    Ok(())
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> anyhow::Result<()> {
    offworld_program::init_logging();
    let scratch = std::env::temp_dir().join(format!("offworld-farm-bench-{}", std::process::id()));
    std::fs::create_dir_all(&scratch)?;
    println!(
        "sim farm throughput, 84x84 depth, lockstep twins, {} s per point, {} cores:",
        seconds(),
        std::thread::available_parallelism().map_or(0, |n| n.get())
    );
    let tables = tables();
    if tables.iter().any(|t| t == "layouts") {
        layouts(&scratch).await?;
    }
    if tables.iter().any(|t| t == "router") {
        router_breakdown(&scratch).await;
    }
    std::fs::remove_dir_all(&scratch).ok();
    Ok(())
}
