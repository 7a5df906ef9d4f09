//! `monitor`: streams OffWorld Gym envs to the rerun viewer or an `.rrd`
//! file until interrupted; `monitor replay` plays recorded episodes the
//! same way.
//!
//! ```text
//! monitor --all --viewer rerun+http://127.0.0.1:9876/proxy
//! monitor --env real/monolith-0 --serve            # viewers: rerun --connect
//! monitor --env sim/monolith-0 --save run.rrd -e tcp/127.0.0.1:7447
//! monitor replay runs/sim/monolith-0 --save episodes.rrd
//! monitor replay runs/real/monolith-0/exp-000003/ep-000042.mcap --viewer rerun+http://127.0.0.1:9876/proxy
//! ```

use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::Ordering;
use std::time::Duration;

use crate::replay::{episode_files, FileReport, Replay, ReplayConfig, ReplayError};
use crate::{Monitor, MonitorConfig, Scope, Sink};
use clap::{ArgGroup, Parser, Subcommand};
use offworld_program::CommonArgs;
use offworld_runtime::EnvId;

/// Streams OffWorld Gym envs (world, robot, camera, rewards, events) to rerun.
#[derive(Debug, Parser)]
#[command(name = "monitor", version)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
#[command(group(ArgGroup::new("scope").args(["env", "all", "key"])))]
#[command(group(ArgGroup::new("sink").required(true).args(["save", "viewer", "serve"])))]
pub struct Args {
    #[command(subcommand)]
    command: Option<Command>,
    /// Watch this env, e.g. `sim/monolith-0` or `real/monolith-0`
    /// (repeat for several).
    #[arg(long)]
    env: Vec<EnvId>,
    /// Watch every env (the default).
    #[arg(long)]
    all: bool,
    /// Watch a key expression under `offworld/@v1/`, e.g. `offworld/@v1/sim/**`.
    #[arg(long)]
    key: Option<String>,
    #[command(flatten)]
    sink: SinkArgs,
    /// Draw this built-in world for every env instead of asking each controller.
    #[arg(long)]
    world: Option<String>,
    /// Camera frames queued for the worker at most (older ones are dropped).
    #[arg(long, default_value_t = 32)]
    frame_queue: usize,
    /// Other messages queued for the worker at most.
    #[arg(long, default_value_t = 4096)]
    message_queue: usize,
    /// Log every camera frame (`obs`), command, pose and odometry message
    /// to a viewer or server too (default there: their viewers' copies —
    /// the env's preview, at most one frame every 20 ms — dropped rather
    /// than waited for, so a fast sim env's monitor costs its steps little
    /// and a stalled one holds up no step; `--save` keeps every message).
    /// They are then delivered as the controller's are: a viewer too slow
    /// for them, or frozen, holds up the env.
    #[arg(long)]
    every_frame: bool,
    /// Do not send the default viewer layout.
    #[arg(long)]
    no_blueprint: bool,
    /// Stop after this many seconds (default: run until Ctrl-C).
    #[arg(long, value_name = "SECS")]
    duration: Option<f64>,
    #[command(flatten)]
    common: CommonArgs,
}

/// Where the recording goes: the same flags live and for a replay.
#[derive(Debug, clap::Args)]
struct SinkArgs {
    /// Write the recording to this `.rrd` file (complete once the monitor stops).
    #[arg(long, value_name = "FILE")]
    save: Option<PathBuf>,
    /// Stream to a running viewer, e.g. `rerun+http://127.0.0.1:9876/proxy`
    /// (the live mode's `--connect`/`-e` are the Zenoh endpoints).
    #[arg(long, value_name = "URL")]
    viewer: Option<String>,
    /// Host a gRPC server for viewers (`rerun --connect rerun+http://ADDR/proxy`).
    #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "0.0.0.0:9876")]
    serve: Option<SocketAddr>,
    /// History a `--serve` server keeps for late viewers, MiB (default: a quarter of RAM).
    #[arg(long, value_name = "MIB", requires = "serve")]
    serve_memory_mib: Option<u64>,
}

impl SinkArgs {
    fn sink(&self) -> anyhow::Result<Sink> {
        Ok(if let Some(path) = &self.save {
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
        })
    }
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Plays recorded episodes (the MCAP files of `env_controller serve
    /// --record`) into rerun as the live monitor shows them: same entities,
    /// same timelines, stamped with the recorded times.
    Replay(ReplayArgs),
}

/// `monitor replay FILE_OR_DIR… (--save FILE | --viewer URL | --serve [ADDR])`
#[derive(Debug, clap::Args)]
#[command(group(ArgGroup::new("sink").required(true).args(["save", "viewer", "serve"])))]
struct ReplayArgs {
    /// Episode files (`ep-*.mcap`, `ep-*.mcap.partial`: read up to its cut)
    /// or directories of them (every episode below, sorted).
    #[arg(required = true, value_name = "FILE_OR_DIR")]
    paths: Vec<PathBuf>,
    #[command(flatten)]
    sink: SinkArgs,
    /// Play at X times the recorded pace; 0: as fast as possible (default:
    /// as fast as possible into a file, real time to a viewer or server).
    #[arg(long, value_name = "X")]
    speed: Option<f64>,
    /// Do not send the default viewer layout.
    #[arg(long)]
    no_blueprint: bool,
}

impl ReplayArgs {
    fn config(&self) -> anyhow::Result<ReplayConfig> {
        let sink = self.sink.sink()?;
        let speed = match self.speed {
            Some(x) if !(x.is_finite() && x >= 0.0) => {
                anyhow::bail!("--speed {x}: expected a positive number, or 0")
            }
            // 0: as fast as possible.
            Some(x) => (x > 0.0).then_some(x),
            None if matches!(sink, Sink::File(_)) => None,
            None => Some(1.0),
        };
        let name = match &self.paths[..] {
            [one] => format!("replay of {}", one.display()),
            many => format!("replay of {} paths", many.len()),
        };
        Ok(ReplayConfig {
            speed,
            blueprint: !self.no_blueprint,
            recording_name: Some(name),
            ..ReplayConfig::new(sink)
        })
    }
}

impl Args {
    fn config(&self) -> anyhow::Result<MonitorConfig> {
        let sink = self.sink.sink()?;
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
        config.every_frame |= self.every_frame;
        Ok(config)
    }
}

/// Runs `monitor` (also `offworld monitor`) with these arguments.
pub fn run(args: Args) -> ExitCode {
    offworld_program::run(main_async(args))
}

async fn main_async(mut args: Args) -> anyhow::Result<ExitCode> {
    if let Some(Command::Replay(replay_args)) = args.command.take() {
        return Ok(match replay(replay_args).await {
            Ok(()) => ExitCode::SUCCESS,
            Err(e) => {
                // Our errors name the file and say why; no cause chain.
                eprintln!("monitor replay: {e}");
                ExitCode::FAILURE
            }
        });
    }
    live(args).await?;
    Ok(ExitCode::SUCCESS)
}

async fn live(args: Args) -> anyhow::Result<()> {
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
                    dropped_frames = s.dropped_frames, superseded_frames = s.superseded_frames,
                    dropped_messages = s.dropped_messages,
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

/// One line on stderr about a file.
fn describe(report: &FileReport) -> String {
    let env = report
        .env
        .as_ref()
        .map_or_else(|| "?".to_owned(), ToString::to_string);
    let episode = report
        .episode_id
        .map_or_else(|| "?".to_owned(), |id| id.to_string());
    let mut line = format!(
        "{}: {env} episode {episode}, {} steps",
        report.path.display(),
        report.steps
    );
    match &report.ended {
        Some(reason) => line.push_str(&format!(", ended: {reason}")),
        None if report.cut => line.push_str(", cut (a crashed episode's .partial)"),
        None => line.push_str(", no end recorded"),
    }
    if report.incomplete > 0 {
        line.push_str(&format!(
            "; {} messages of an unfinished step left out",
            report.incomplete
        ));
    }
    if report.unknown > 0 {
        line.push_str(&format!(
            "; {} messages of other topics left out",
            report.unknown
        ));
    }
    if report.messages == 0 {
        line.push_str("; nothing readable");
    }
    line
}

async fn replay(args: ReplayArgs) -> anyhow::Result<()> {
    let files = episode_files(&args.paths)?;
    let config = args.config()?;
    let serving = matches!(config.sink, Sink::Serve { .. });
    let target = format!("{:?}", config.sink);
    let mut replay = Replay::open(config)?;
    let stop = replay.stopper();
    let interrupted = stop.clone();
    let signalled = tokio::spawn(async move {
        let _ = offworld_runtime::shutdown::signalled().await;
        interrupted.store(true, Ordering::Relaxed);
    });
    let total = files.len();
    let (replay, played) = tokio::task::spawn_blocking(move || {
        let mut played: Result<(), ReplayError> = Ok(());
        for (i, file) in files.iter().enumerate() {
            let n = i + 1;
            let report = replay.play(file, &mut |so_far| {
                eprintln!(
                    "monitor replay: [{n}/{total}] {}: {} steps so far",
                    so_far.path.display(),
                    so_far.steps
                );
            });
            match report {
                Ok(report) => {
                    eprintln!("monitor replay: [{n}/{total}] {}", describe(&report));
                    if report.stopped {
                        break;
                    }
                }
                Err(e) => {
                    played = Err(e);
                    break;
                }
            }
        }
        (replay, played)
    })
    .await?;
    if played.is_ok() && serving && !stop.load(Ordering::Relaxed) {
        eprintln!("monitor replay: done; serving until Ctrl-C");
        let _ = signalled.await;
    } else {
        signalled.abort();
    }
    // Whatever was played is kept, even after an error.
    let finished = tokio::task::spawn_blocking(move || replay.finish()).await?;
    played?;
    let stats = finished?;
    let s = &stats.logged;
    eprintln!(
        "monitor replay: {} files ({} cut), {} steps: {} frames, {} poses, {} odometry, {} commands → {target}",
        stats.files, stats.cut_files, stats.steps, s.frames, s.poses, s.odometry, s.commands
    );
    if s.decode_errors + s.log_errors > 0 {
        eprintln!(
            "monitor replay: {} messages could not be drawn, {} refused by rerun",
            s.decode_errors, s.log_errors
        );
    }
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
            "real/monolith-0",
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

    #[test]
    fn replay_takes_the_live_sink_flags_and_paces_for_viewers() {
        let parse = |argv: &[&str]| Args::try_parse_from(argv);
        let replay = |argv: &[&str]| match parse(argv).expect("parse").command {
            Some(Command::Replay(r)) => r,
            None => panic!("not a replay: {argv:?}"),
        };
        let file = replay(&["monitor", "replay", "runs", "ep.mcap", "--save", "out.rrd"]);
        assert_eq!(
            file.paths,
            [PathBuf::from("runs"), PathBuf::from("ep.mcap")]
        );
        let config = file.config().expect("config");
        assert_eq!(config.sink, Sink::File("out.rrd".into()));
        assert_eq!(config.speed, None, "a file: as fast as possible");
        let viewer = replay(&[
            "monitor",
            "replay",
            "runs",
            "--viewer",
            "rerun+http://127.0.0.1:9876/proxy",
        ]);
        let config = viewer.config().expect("config");
        assert_eq!(config.sink, Sink::connect_local());
        assert_eq!(config.speed, Some(1.0), "a viewer: real time");
        let served = replay(&["monitor", "replay", "runs", "--serve", "--speed", "4"]);
        let config = served.config().expect("config");
        assert_eq!(
            (config.sink, config.speed),
            (Sink::serve_default(), Some(4.0))
        );
        let fast = replay(&["monitor", "replay", "runs", "--serve", "--speed", "0"]);
        assert_eq!(fast.config().expect("config").speed, None);
        let negative = replay(&["monitor", "replay", "runs", "--save", "a.rrd", "--speed=-1"]);
        assert!(negative.config().is_err());
        assert!(
            parse(&["monitor", "replay", "runs"]).is_err(),
            "a sink is required"
        );
        assert!(
            parse(&["monitor", "replay", "--save", "a.rrd"]).is_err(),
            "a path is required"
        );
        assert!(
            parse(&["monitor", "replay", "runs", "--save", "a.rrd", "--serve"]).is_err(),
            "one sink"
        );
        assert!(
            parse(&[
                "monitor",
                "replay",
                "runs",
                "--save",
                "a.rrd",
                "-e",
                "tcp/1.2.3.4:7447"
            ])
            .is_err(),
            "no Zenoh"
        );
        assert!(
            parse(&["monitor", "--all", "--save", "a.rrd", "replay", "runs"]).is_err(),
            "live flags or replay"
        );
    }
}
