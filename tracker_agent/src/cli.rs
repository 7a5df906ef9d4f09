//! `tracker_agent`: publish the robot's tracked pose, or calibrate.
//!
//! ```text
//! tracker_agent run --env real/monolith-0 --source tcp://127.0.0.1:6969 --calibration tracker.toml
//! python3 pysurvive_source.py | offworld tracker run --env real/monolith-0 --source stdin --calibration tracker.toml
//! tracker_agent calibrate --reference marks.toml --source tcp://127.0.0.1:6969 --out tracker.toml
//! tracker_agent calibrate --samples measured.toml --out tracker.toml
//! ```
//!
//! `run` connects to tcp/127.0.0.1:7447 unless Zenoh endpoints are given.

use std::path::PathBuf;
use std::process::ExitCode;
use std::str::FromStr;
use std::time::Duration;

use crate::calibration::{
    self, average_poses, position_spread, rosbot_mount, unit_quaternion, vector, ReferenceFile,
    ReferencePoint,
};
use crate::{
    AgentConfig, Calibration, FilterConfig, PoseSource, SourceError, SourceSpec, TrackerSample,
};
use anyhow::{bail, ensure, Context};
use clap::{Parser, Subcommand};
use nalgebra::{Isometry3, Translation3, UnitQuaternion};
use offworld_program::CommonArgs;
use offworld_runtime::seal::SealKey;
use offworld_runtime::EnvId;
use tokio::io::AsyncBufReadExt;

/// Vive tracker localization for an OffWorld enclosure.
#[derive(Parser)]
#[command(name = "tracker_agent", version)]
pub struct Args {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Publish base_link's world pose and the tracking status of an env.
    Run(RunArgs),
    /// Solve tracker→world from the robot at ≥ 3 surveyed marks and write
    /// the calibration file.
    Calibrate(CalibrateArgs),
}

#[derive(clap::Args)]
struct RunArgs {
    /// Env id to serve, e.g. real/monolith-0.
    #[arg(long)]
    env: EnvId,
    /// stdin | tcp://HOST:PORT | udp://BIND:PORT | replay:PATH[?rate=R].
    #[arg(long)]
    source: SourceSpec,
    /// Calibration TOML (world_from_tracking, tracker_in_base_link).
    #[arg(long)]
    calibration: PathBuf,
    /// Only use this device id (default: the first device seen).
    #[arg(long)]
    device: Option<String>,
    /// Tracking is lost when no pose was accepted for this long, ms.
    #[arg(long, default_value_t = 300)]
    lost_after_ms: u64,
    /// Fastest plausible robot speed, m/s (faster jumps are outliers).
    #[arg(long, default_value_t = 2.0)]
    max_speed: f64,
    /// Fastest plausible yaw rate, rad/s.
    #[arg(long, default_value_t = 10.0)]
    max_yaw_rate: f64,
    /// Accept the newest pose after rejecting poses for this long, ms.
    #[arg(long, default_value_t = 500)]
    relock_after_ms: u64,
    /// The site's tracker key file (64 hex digits, mode 600): poses and
    /// tracking reports are sealed with it; the controller and robot agent
    /// given the same key believe no other pose.
    #[arg(long, value_name = "FILE", env = "OFFWORLD_TRACKER_KEY")]
    tracker_key: Option<PathBuf>,
    #[command(flatten)]
    common: CommonArgs,
}

/// `x,y,z`.
#[derive(Debug, Clone, Copy)]
struct Vec3Arg([f64; 3]);

impl FromStr for Vec3Arg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let v = parse_numbers::<3>(s)?;
        vector(v, "mount").map_err(|e| e.to_string())?;
        Ok(Self(v))
    }
}

/// `qx,qy,qz,qw`.
#[derive(Debug, Clone, Copy)]
struct QuatArg(UnitQuaternion<f64>);

impl FromStr for QuatArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let q = parse_numbers::<4>(s)?;
        Ok(Self(
            unit_quaternion(q, "mount rotation").map_err(|e| e.to_string())?,
        ))
    }
}

fn parse_numbers<const N: usize>(s: &str) -> Result<[f64; N], String> {
    let values: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("`{s}`: {e}"))?;
    values
        .try_into()
        .map_err(|_| format!("`{s}`: expected {N} comma-separated numbers"))
}

#[derive(clap::Args)]
struct CalibrateArgs {
    /// Reference marks: `[[point]] world = [x, y, z]` (base_link origin's
    /// surveyed world position); optional `name = "…"`.
    #[arg(long, required_unless_present = "samples")]
    reference: Option<PathBuf>,
    /// Live: measure the tracker at each mark from this source
    /// (tcp://, udp:// or replay:; stdin is taken by the prompts).
    #[arg(long, conflicts_with = "samples", required_unless_present = "samples")]
    source: Option<SourceSpec>,
    /// Offline: a reference file whose points also carry
    /// `device_translation` and `device_rotation` (tracking frame).
    #[arg(long)]
    samples: Option<PathBuf>,
    /// Where to write the calibration TOML.
    #[arg(long)]
    out: PathBuf,
    /// Tracker position in base_link, m (default: ROSbot, -0.03,0,0.14).
    #[arg(long, allow_hyphen_values = true)]
    mount: Option<Vec3Arg>,
    /// Tracker orientation in base_link, qx,qy,qz,qw (default identity).
    #[arg(long, allow_hyphen_values = true)]
    mount_rotation: Option<QuatArg>,
    /// Live: seconds of poses averaged at each mark.
    #[arg(long, default_value_t = 1.0)]
    average: f64,
    /// Live: only use this device id (default: the first device seen).
    #[arg(long)]
    device: Option<String>,
    /// Live: also write the measured poses as a samples file (re-run
    /// offline with --samples).
    #[arg(long)]
    save_samples: Option<PathBuf>,
}

/// Runs `tracker_agent` (also `offworld tracker`) with these arguments.
pub fn run(args: Args) -> ExitCode {
    offworld_program::run(async move {
        match args.command {
            Command::Run(args) => run_tracker(args).await,
            Command::Calibrate(args) => calibrate(args).await,
        }
    })
}

async fn run_tracker(args: RunArgs) -> anyhow::Result<()> {
    let calibration = Calibration::load(&args.calibration)?;
    ensure!(
        args.max_speed.is_finite() && args.max_speed > 0.0,
        "--max-speed must be > 0"
    );
    ensure!(
        args.max_yaw_rate.is_finite() && args.max_yaw_rate > 0.0,
        "--max-yaw-rate must be > 0"
    );
    ensure!(args.lost_after_ms > 0, "--lost-after-ms must be > 0");
    let config = AgentConfig {
        filter: FilterConfig {
            max_speed_mps: args.max_speed,
            max_yaw_rate_rps: args.max_yaw_rate,
            relock_after_s: args.relock_after_ms as f64 / 1000.0,
        },
        lost_after: Duration::from_millis(args.lost_after_ms),
        device: args.device,
        seal_key: args.tracker_key.as_deref().map(SealKey::load).transpose()?,
        ..AgentConfig::default()
    };
    let source = args
        .source
        .open()
        .await
        .with_context(|| format!("opening {}", args.source))?;
    let session = args.common.client_config().open().await?;
    let stats = crate::run(&session, args.env, calibration, source, config, async {
        let _ = offworld_runtime::shutdown::signalled().await;
    })
    .await?;
    tracing::info!(?stats, "done");
    Ok(())
}

async fn calibrate(args: CalibrateArgs) -> anyhow::Result<()> {
    let mount = Isometry3::from_parts(
        Translation3::from(
            args.mount
                .map(|m| m.0)
                .unwrap_or_else(|| rosbot_mount().translation.vector.into()),
        ),
        args.mount_rotation
            .map(|q| q.0)
            .unwrap_or_else(UnitQuaternion::identity),
    );
    let reference = args
        .reference
        .as_deref()
        .map(ReferenceFile::load)
        .transpose()?;
    let samples = match (&args.samples, &args.source) {
        (Some(path), _) => {
            let samples = ReferenceFile::load(path)?;
            if let Some(reference) = &reference {
                check_same_marks(reference, &samples)?;
            }
            samples
        }
        (None, Some(spec)) => {
            let reference = reference.context("live calibration needs --reference")?;
            ensure!(
                *spec != SourceSpec::Stdin,
                "live calibration reads Enter on stdin: stream poses over tcp://, udp:// or replay:"
            );
            ensure!(
                args.average.is_finite() && args.average > 0.0,
                "--average must be > 0"
            );
            let source = spec
                .open()
                .await
                .with_context(|| format!("opening {spec}"))?;
            let measured = measure(
                reference,
                source,
                Duration::from_secs_f64(args.average),
                args.device,
            )
            .await?;
            if let Some(path) = &args.save_samples {
                measured.save(path)?;
                eprintln!("measured poses written to {}", path.display());
            }
            measured
        }
        (None, None) => bail!("give --source (live) or --samples (offline)"),
    };
    let solution = calibration::calibrate_from_samples(&samples, &mount)?;
    for (i, (point, residual)) in samples.point.iter().zip(&solution.residuals_m).enumerate() {
        eprintln!("{}: residual {:.1} mm", point.label(i), residual * 1000.0);
    }
    eprintln!(
        "RMS residual {:.1} mm, max {:.1} mm over {} points",
        solution.rms_residual_m * 1000.0,
        solution.max_residual_m * 1000.0,
        samples.point.len()
    );
    if solution.rms_residual_m > 0.01 {
        eprintln!(
            "warning: RMS residual above 1 cm: check the order of the marks, the survey and the mount"
        );
    }
    let result = Calibration {
        world_from_tracking: solution.world_from_tracking,
        tracker_in_base_link: mount,
    };
    result.save(
        &args.out,
        &format!(
            "written by `tracker_agent calibrate` from {} reference points\n\
             RMS residual {:.2} mm, max {:.2} mm",
            samples.point.len(),
            solution.rms_residual_m * 1000.0,
            solution.max_residual_m * 1000.0
        ),
    )?;
    eprintln!("calibration written to {}", args.out.display());
    Ok(())
}

fn check_same_marks(reference: &ReferenceFile, samples: &ReferenceFile) -> anyhow::Result<()> {
    ensure!(
        reference.point.len() == samples.point.len(),
        "--reference has {} points, --samples {}",
        reference.point.len(),
        samples.point.len()
    );
    for (i, (r, s)) in reference.point.iter().zip(&samples.point).enumerate() {
        let same = r
            .world
            .iter()
            .zip(&s.world)
            .all(|(a, b)| (a - b).abs() < 1e-9);
        ensure!(
            same,
            "{}: world {:?} in --reference but {:?} in --samples",
            r.label(i),
            r.world,
            s.world
        );
    }
    Ok(())
}

/// Prompts for each mark and averages the tracker's poses there.
async fn measure(
    reference: ReferenceFile,
    source: Box<dyn PoseSource>,
    average: Duration,
    device: Option<String>,
) -> anyhow::Result<ReferenceFile> {
    let (tx, mut rx) = tokio::sync::mpsc::channel::<TrackerSample>(4096);
    let name = source.describe();
    let pump = tokio::spawn(pump(source, tx));
    let mut stdin = tokio::io::BufReader::new(tokio::io::stdin()).lines();
    let mut locked = device;
    let mut measured = ReferenceFile::default();
    for (i, point) in reference.point.iter().enumerate() {
        let [x, y, z] = point.world;
        let pose = loop {
            eprintln!(
                "place the robot at {} (world {x:.3}, {y:.3}, {z:.3}) and press Enter",
                point.label(i)
            );
            if stdin.next_line().await?.is_none() {
                pump.abort();
                bail!("stdin closed before every mark was measured");
            }
            // Poses queued while waiting are stale.
            while rx.try_recv().is_ok() {}
            let deadline = tokio::time::Instant::now() + average;
            let mut poses = Vec::new();
            while let Ok(Some(sample)) = tokio::time::timeout_at(deadline, rx.recv()).await {
                let chosen = locked.get_or_insert_with(|| {
                    let id = sample.device.clone().unwrap_or_default();
                    eprintln!("using device `{id}` (pass --device to choose)");
                    id
                });
                if sample.device.as_deref().unwrap_or_default() == chosen.as_str() {
                    poses.push(sample.pose);
                }
            }
            if pump.is_finished() && poses.is_empty() {
                bail!("{name} ended or failed before every mark was measured");
            }
            match average_poses(&poses) {
                Some(pose) => {
                    let spread = position_spread(&poses);
                    eprintln!("  {} poses, spread {:.1} mm", poses.len(), spread * 1000.0);
                    if spread > 0.005 {
                        eprintln!("  warning: the tracker moved while measuring");
                    }
                    break pose;
                }
                None => eprintln!("  no tracker pose from {name} within {average:?}; try again"),
            }
        };
        let t = pose.translation.vector;
        let q = pose.rotation.quaternion();
        measured.point.push(ReferencePoint {
            name: point.name.clone(),
            world: point.world,
            device_translation: Some([t.x, t.y, t.z]),
            device_rotation: Some([q.i, q.j, q.k, q.w]),
        });
    }
    pump.abort();
    Ok(measured)
}

async fn pump(mut source: Box<dyn PoseSource>, tx: tokio::sync::mpsc::Sender<TrackerSample>) {
    loop {
        match source.next().await {
            Ok(Some(sample)) => {
                // Full queue: nobody is measuring; drop.
                if let Err(tokio::sync::mpsc::error::TrySendError::Closed(_)) = tx.try_send(sample)
                {
                    return;
                }
            }
            Err(SourceError::Malformed(e)) => tracing::warn!("skipped {e}"),
            Ok(None) => return,
            Err(e) => {
                tracing::error!("{e}");
                return;
            }
        }
    }
}
