//! `lab_web`: the lab's web page for an OffWorld Gym deployment.
//!
//! ```text
//! lab_web                                      # deployment on tcp/127.0.0.1:7447, page on 127.0.0.1:8080
//! lab_web --http 0.0.0.0:8080 -e tcp/router.lab:7447
//! lab_web -c deploy/roles/web.json5            # TLS, credentials from a role file
//! ```

use std::net::SocketAddr;
use std::num::NonZeroU32;
use std::process::ExitCode;
use std::time::Duration;

use crate::{DiscoveryConfig, LabWeb, Limits, WebOptions};
use clap::Parser;
use offworld_program::CommonArgs;

/// Serves the lab's web page: live availability of every env (real and
/// sim), each env's leaderboard, bookings and (signed in with a gym access
/// token) a user's experiments, from the deployment over Zenoh.
#[derive(Debug, Parser)]
#[command(name = "lab_web", version)]
pub struct Args {
    /// HTTP address to serve on (behind a TLS reverse proxy for the world).
    #[arg(
        long = "http",
        value_name = "ADDR",
        default_value = "127.0.0.1:8080",
        env = "OFFWORLD_WEB_HTTP"
    )]
    http_listen: SocketAddr,
    /// Deadline of each Zenoh query (listing, status, leaderboard), ms: a
    /// dead deployment shows as offline after this long, never hangs a page.
    #[arg(long, value_name = "MS", default_value_t = 2000)]
    query_timeout_ms: u64,
    /// Time between two listings of the envs when nothing changes, ms
    /// (status changes and components coming or going show at once).
    #[arg(long, value_name = "MS", default_value_t = 5000)]
    sweep_interval_ms: u64,
    /// Open HTTP connections at most.
    #[arg(long, default_value_t = Limits::default().max_connections)]
    max_connections: usize,
    /// Requests answered at once at most (more: 503).
    #[arg(long, default_value_t = Limits::default().max_in_flight)]
    max_in_flight: usize,
    /// Open live-update streams at most (more: 503).
    #[arg(long, default_value_t = Limits::default().max_event_streams)]
    max_event_streams: usize,
    /// Requests per second one client address may send, sustained (more: 429).
    #[arg(long, default_value_t = Limits::default().rate_per_client)]
    rate_per_client: NonZeroU32,
    /// Requests one client address may send at once above the rate.
    #[arg(long, default_value_t = Limits::default().burst_per_client)]
    burst_per_client: NonZeroU32,
    /// Signed-in sessions kept at most (the least recently used is signed
    /// out first).
    #[arg(long, default_value_t = Limits::default().max_sessions)]
    max_sessions: usize,
    /// A signed-in session lapses after this many minutes without a request.
    #[arg(long, value_name = "MIN", default_value_t = 720)]
    session_idle_min: u64,
    /// Mark cookies `Secure` (set it when users reach the page through a
    /// TLS reverse proxy).
    #[arg(long, env = "OFFWORLD_WEB_SECURE_COOKIES")]
    secure_cookies: bool,
    /// Show the lab's state to signed-in users only (any gym user's
    /// token): every page and the JSON answer 401 to others.
    #[arg(long, env = "OFFWORLD_WEB_MEMBERS_ONLY")]
    members_only: bool,
    /// Where the rerun viewer watches the deployment live (a monitor's
    /// `--serve` stream, e.g. `rerun+http://lab.example:9876/proxy`):
    /// linked from each env's page.
    #[arg(long, value_name = "URL", env = "OFFWORLD_WEB_RERUN_URL")]
    rerun_url: Option<String>,
    #[command(flatten)]
    common: CommonArgs,
}

/// Runs `lab_web` (also `offworld web`) with these arguments.
pub fn run(args: Args) -> ExitCode {
    offworld_program::run(serve(args))
}

async fn serve(args: Args) -> anyhow::Result<()> {
    let options = WebOptions {
        discovery: DiscoveryConfig {
            query_timeout: Duration::from_millis(args.query_timeout_ms.max(1)),
            sweep_interval: Duration::from_millis(args.sweep_interval_ms.max(100)),
        },
        limits: Limits {
            max_connections: args.max_connections.max(1),
            max_in_flight: args.max_in_flight.max(1),
            max_event_streams: args.max_event_streams,
            rate_per_client: args.rate_per_client,
            burst_per_client: args.burst_per_client,
            max_sessions: args.max_sessions.max(1),
            session_idle: Duration::from_secs(args.session_idle_min.max(1).saturating_mul(60)),
            ..Limits::default()
        },
        secure_cookies: args.secure_cookies,
        members_only: args.members_only,
        rerun_url: args.rerun_url.clone(),
    };
    let session = args.common.clone().client_config().open().await?;
    let web = LabWeb::start(session.clone(), args.http_listen, options).await?;
    tracing::info!("lab web page on http://{}", web.local_addr());
    let signal = offworld_runtime::shutdown::signalled().await?;
    tracing::info!("stopping ({signal:?})");
    web.stop().await;
    let _ = session.close().await;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn the_command_line_is_consistent() {
        Args::command().debug_assert();
        let args = Args::try_parse_from([
            "lab_web",
            "--http",
            "0.0.0.0:9000",
            "--listen",
            "tcp/127.0.0.1:7000",
        ])
        .expect("parse");
        assert_eq!(args.http_listen, "0.0.0.0:9000".parse().expect("addr"));
        assert_eq!(args.common.listen, ["tcp/127.0.0.1:7000"]);
    }
}
