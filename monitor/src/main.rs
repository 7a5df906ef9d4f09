//! `monitor`: streams OffWorld Gym envs to the rerun viewer or an `.rrd`
//! file until interrupted.
//!
//! ```text
//! monitor --all --viewer rerun+http://127.0.0.1:9876/proxy
//! monitor --env real/enclosure-a --serve            # viewers: rerun --connect
//! monitor --env sim/monolith-0 --save run.rrd -e tcp/127.0.0.1:7447
//! ```

use std::net::SocketAddr;
use std::path::PathBuf;
use std::time::Duration;

use clap::{ArgGroup, Parser};
use offworld_monitor::{Monitor, MonitorConfig, Scope, Sink};
use offworld_runtime::{CommonArgs, EnvId};

/// Streams OffWorld Gym envs (world, robot, camera, rewards, events) to rerun.
#[derive(Debug, Parser)]
#[command(name = "monitor", version)]
#[command(group(ArgGroup::new("scope").args(["env", "all", "key"])))]
#[command(group(ArgGroup::new("sink").required(true).args(["save", "viewer", "serve"])))]
struct Args {
    /// Watch this env, e.g. `sim/monolith-0` or `real/enclosure-a`
    /// (repeat for several).
    #[arg(long)]
    env: Vec<EnvId>,
    /// Watch every env (the default).
    #[arg(long)]
    all: bool,
    /// Watch a key expression under `offworld/@v1/`, e.g. `offworld/@v1/sim/**`.
    #[arg(long)]
    key: Option<String>,
    /// Write the recording to this `.rrd` file (complete once the monitor stops).
    #[arg(long, value_name = "FILE")]
    save: Option<PathBuf>,
    /// Stream to a running viewer, e.g. `rerun+http://127.0.0.1:9876/proxy`
    /// (`--connect`/`-e` are the Zenoh endpoints).
    #[arg(long, value_name = "URL")]
    viewer: Option<String>,
    /// Host a gRPC server for viewers (`rerun --connect rerun+http://ADDR/proxy`).
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "0.0.0.0:9876")]
    serve: Option<SocketAddr>,
    /// History a `--serve` server keeps for late viewers, MiB (default: a quarter of RAM).
    #[arg(long, value_name = "MIB", requires = "serve")]
    serve_memory_mib: Option<u64>,
    /// Draw this built-in world for every env instead of asking each controller.
    #[arg(long)]
    world: Option<String>,
    /// Camera frames queued for the worker at most (older ones are dropped).
    #[arg(long, default_value_t = 32)]
    frame_queue: usize,
    /// Other messages queued for the worker at most.
    #[arg(long, default_value_t = 4096)]
    message_queue: usize,
    /// Do not send the default viewer layout.
    #[arg(long)]
    no_blueprint: bool,
    /// Stop after this many seconds (default: run until Ctrl-C).
    #[arg(long, value_name = "SECS")]
    duration: Option<f64>,
    #[command(flatten)]
    common: CommonArgs,
}

impl Args {
    fn config(&self) -> anyhow::Result<MonitorConfig> {
        let sink = if let Some(path) = &self.save {
            Sink::File(path.clone())
        } else if let Some(url) = &self.viewer {
            Sink::Connect(url.clone())
        } else if let Some(addr) = self.serve {
            Sink::Serve {
                addr,
                memory_limit_bytes: self.serve_memory_mib.map(|m| m * 1024 * 1024),
            }
        } else {
            anyhow::bail!("one of --save, --viewer or --serve is required");
        };
        let scope = match (&self.env[..], &self.key) {
            ([], Some(key)) => Scope::KeyExpr(key.clone()),
            ([], None) => Scope::All,
            (envs, _) => Scope::Envs(envs.to_vec()),
        };
        let mut config = MonitorConfig::new(sink)
            .scope(scope)
            .queues(self.frame_queue, self.message_queue);
        config.world = self.world.clone();
        config.blueprint = !self.no_blueprint;
        Ok(config)
    }
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    offworld_runtime::session::init_logging();
    let args = Args::parse();
    let config = args.config()?;
    let session = args.common.clone().client_config().open().await?;
    let sink = format!("{:?}", config.sink);
    let monitor = Monitor::spawn(&session, config)?;
    tracing::info!(sink, "monitor running");
    let stop = async {
        match args.duration {
            Some(secs) if secs.is_finite() && secs >= 0.0 => {
                tokio::time::sleep(Duration::from_secs_f64(secs)).await;
            }
            _ => {
                let _ = offworld_runtime::shutdown::signalled().await;
            }
        }
    };
    tokio::pin!(stop);
    let mut report = tokio::time::interval(Duration::from_secs(10));
    report.tick().await;
    loop {
        tokio::select! {
            _ = &mut stop => break,
            _ = report.tick() => {
                let s = monitor.stats();
                tracing::info!(
                    envs = s.envs, frames = s.frames, poses = s.poses, rewards = s.rewards,
                    dropped_frames = s.dropped_frames, dropped_messages = s.dropped_messages,
                    decode_errors = s.decode_errors, "monitor"
                );
            }
        }
    }
    let stats = tokio::task::spawn_blocking(move || monitor.shutdown()).await??;
    tracing::info!(?stats, "monitor stopped");
    let _ = session.close().await;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::CommandFactory;

    #[test]
    fn flags_are_consistent_with_the_common_zenoh_flags() {
        Args::command().debug_assert();
        let args = Args::try_parse_from([
            "monitor",
            "--env",
            "real/enclosure-a",
            "--viewer",
            "rerun+http://127.0.0.1:9876/proxy",
            "-e",
            "tcp/10.0.0.2:7447",
        ])
        .expect("parse");
        let config = args.config().expect("config");
        assert_eq!(config.sink, Sink::connect_local());
        assert_eq!(args.common.connect, ["tcp/10.0.0.2:7447"]);
        let serve = Args::try_parse_from(["monitor", "--all", "--serve"]).expect("parse");
        assert_eq!(serve.config().expect("config").sink, Sink::serve_default());
        assert!(
            Args::try_parse_from(["monitor", "--all"]).is_err(),
            "a sink is required"
        );
        assert!(
            Args::try_parse_from(["monitor", "--save", "a.rrd", "--serve"]).is_err(),
            "one sink"
        );
    }
}
