//! Recorded episodes played into rerun: the MCAP files `offworld-recorder`
//! writes (one per episode, `docs/recording.md`) logged with the live
//! monitor's own logging code, under the same entity paths and on the same
//! timelines, so a replay looks like the live view of those episodes.
//!
//! | recorded | logged as (live source) |
//! |---|---|
//! | `/offworld/episode` | the env's world (`spec`) |
//! | `/cmd_vel` | `metrics/linear_x`, `metrics/angular_z` (`cmd`) |
//! | `/camera/color/image_raw` + `/camera/depth/image_raw` | `robot/camera/{color,depth}` (`obs`) |
//! | `/tracker/pose` | `robot`, `trajectory` (`pose`) |
//! | `/odom` | `odom/robot` (`odom`) |
//! | `/offworld/step` | `metrics/{reward,return,success,episode_length}`, episode events (`reward`) |
//! | `/offworld/episode_end` | an episode that ended without a terminal step: its end event |
//!
//! Timelines: `step` is the step's `command_seq` (a step's messages are
//! the ones between the previous `Step` and its own), `sim_time` the
//! messages' header stamps (the capture times), `wall_time` when the
//! recorder received each message (its `publish_time`), as the live
//! monitor's `wall_time` is when it received it.
//!
//! ```no_run
//! # fn demo() -> Result<(), offworld_monitor::replay::ReplayError> {
//! use offworld_monitor::replay::{episode_files, Replay, ReplayConfig};
//! use offworld_monitor::Sink;
//! let files = episode_files(&["runs/sim/monolith-0".into()])?;
//! let mut replay = Replay::open(ReplayConfig::new(Sink::File("episodes.rrd".into())))?;
//! for file in &files {
//!     let report = replay.play(file, &mut |_| {})?;
//!     eprintln!("{}: {} steps", file.display(), report.steps);
//! }
//! let stats = replay.finish()?; // episodes.rrd is complete
//! # Ok(()) }
//! ```

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use offworld_recorder::msg::{EpisodeEnd, EpisodeInfo, Step};
use offworld_recorder::read::{self, EpisodeData, RecordedMessage};
use offworld_recorder::{Channel, RecordError};
use offworld_runtime::msg::{EpisodeEvent, Image, Odometry, PoseStamped, Twist};
use offworld_runtime::world::WorldSpec;
use offworld_runtime::EnvId;

use crate::queue::Queue;
use crate::worker::{fallback_world, Shared, Worker, WorkerConfig, WorldSource};
use crate::{close_sink, open_sink, MonitorError, MonitorStats, Sink};

/// How to replay. [`ReplayConfig::new`] gives the defaults.
#[derive(Debug, Clone)]
pub struct ReplayConfig {
    /// Where the recording goes.
    pub sink: Sink,
    /// Play at this multiple of the recorded pace (1.0: real time); `None`:
    /// as fast as possible.
    pub speed: Option<f64>,
    /// Send the default viewer layout.
    pub blueprint: bool,
    /// The recording's name in the viewer.
    pub recording_name: Option<String>,
    /// How long finishing waits for the sink to take the last data.
    pub flush_timeout: Duration,
}

impl ReplayConfig {
    /// As fast as possible, with the default layout.
    pub fn new(sink: Sink) -> Self {
        Self {
            sink,
            speed: None,
            blueprint: true,
            recording_name: None,
            flush_timeout: Duration::from_secs(10),
        }
    }
}

/// Why a replay failed. Every error about a file names it.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// A file is missing, unreadable, not MCAP, cut (a complete `.mcap`)
    /// or holds a message that does not decode.
    #[error(transparent)]
    Record(#[from] RecordError),
    /// A file is MCAP but not an episode as the recorder writes it.
    #[error("{}: {reason}", path.display())]
    Episode {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A directory holds no episode files.
    #[error("no episode files (ep-*.mcap, ep-*.mcap.partial) under {}", .0.display())]
    NoFiles(PathBuf),
    /// The speed is not a positive number.
    #[error("replay speed {0}: expected a positive number")]
    Speed(f64),
    /// The sink could not be opened or flushed.
    #[error(transparent)]
    Monitor(#[from] MonitorError),
}

/// What one file held, as replayed.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct FileReport {
    /// The file.
    pub path: PathBuf,
    /// Its env (from `/offworld/episode`).
    pub env: Option<EnvId>,
    /// Its episode id.
    pub episode_id: Option<u64>,
    /// Messages read.
    pub messages: u64,
    /// Steps (`/offworld/step`, the reset included) logged.
    pub steps: u64,
    /// How the episode ended (`/offworld/episode_end`), if recorded.
    pub ended: Option<String>,
    /// The file ended in a cut: a `.partial` read up to its last complete
    /// chunk.
    pub cut: bool,
    /// Messages of an unfinished last step (no `Step` record after them)
    /// left out.
    pub incomplete: u64,
    /// Messages of topics the monitor does not draw, left out.
    pub unknown: u64,
    /// The replay was stopped ([`Replay::stopper`]) before the file's end.
    pub stopped: bool,
}

/// What a replay did so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ReplayStats {
    /// Files played.
    pub files: u64,
    /// Files that ended in a cut.
    pub cut_files: u64,
    /// Steps logged.
    pub steps: u64,
    /// What was logged (`frames`, `poses`, `odometry`, `commands`,
    /// `rewards`, `envs`; `decode_errors` counts messages that decoded but
    /// could not be drawn, e.g. a non-finite pose, as the live monitor does).
    pub logged: MonitorStats,
}

/// A replay into one rerun recording. [`Replay::finish`] (or dropping it)
/// completes the recording.
pub struct Replay {
    worker: Worker,
    shared: Arc<Shared>,
    rec: rerun::RecordingStream,
    config: ReplayConfig,
    stop: Arc<AtomicBool>,
    stats: ReplayStats,
    closed: bool,
}

/// The longest sleep between checks of the stop flag while pacing.
const PACE_SLICE: Duration = Duration::from_millis(50);
/// A progress report at most this often while a file plays.
const PROGRESS_PERIOD: Duration = Duration::from_secs(1);

fn wall(ns: u64) -> SystemTime {
    SystemTime::UNIX_EPOCH + Duration::from_nanos(ns)
}

impl Replay {
    /// Opens the sink and sends the layout.
    pub fn open(config: ReplayConfig) -> Result<Self, ReplayError> {
        if let Some(speed) = config.speed {
            if !(speed.is_finite() && speed > 0.0) {
                return Err(ReplayError::Speed(speed));
            }
        }
        let rec = open_sink(&config.sink, config.recording_name.as_deref())?;
        // The live monitor's worker without its queue and Zenoh session:
        // worlds come from the recordings.
        let shared = Arc::new(Shared {
            queue: Queue::new(1, 1),
            counters: Default::default(),
        });
        let worker = Worker::new(
            rec.clone(),
            shared.clone(),
            None,
            WorkerConfig {
                world: None,
                spec_timeout: Duration::ZERO,
                blueprint: config.blueprint,
                batch_interval: Duration::ZERO,
            },
        );
        worker.start();
        Ok(Self {
            worker,
            shared,
            rec,
            config,
            stop: Arc::new(AtomicBool::new(false)),
            stats: ReplayStats::default(),
            closed: false,
        })
    }

    /// Set it to stop the replay: the file playing ends where it is
    /// ([`FileReport::stopped`]).
    pub fn stopper(&self) -> Arc<AtomicBool> {
        self.stop.clone()
    }

    /// The recording, to log extra data next to the replay's.
    pub fn recording(&self) -> &rerun::RecordingStream {
        &self.rec
    }

    /// Counters so far.
    pub fn stats(&self) -> ReplayStats {
        ReplayStats {
            logged: self.shared.stats(),
            ..self.stats
        }
    }

    /// Plays one episode file (paced as configured); `progress` hears how
    /// far it got about once a second while it plays. Its data is logged once this
    /// returns. An error names the file; what was logged before it stays
    /// in the recording.
    pub fn play(
        &mut self,
        path: &Path,
        progress: &mut dyn FnMut(&FileReport),
    ) -> Result<FileReport, ReplayError> {
        let data = EpisodeData::read(path)?;
        let mut messages = data.messages()?;
        let mut report = FileReport {
            path: path.to_owned(),
            ..FileReport::default()
        };
        let mut episode = Episode::default();
        let mut pace: Option<(u64, Instant)> = None;
        let mut reported = Instant::now();
        let played = (|| -> Result<(), ReplayError> {
            for message in messages.by_ref() {
                let message = message?;
                report.messages += 1;
                if !self.pace(&mut pace, message.publish_time_ns) {
                    report.stopped = true;
                    break;
                }
                self.on_message(&data, &mut episode, message, &mut report)?;
                self.worker.flush_columns_if_due();
                if reported.elapsed() >= PROGRESS_PERIOD {
                    progress(&report);
                    reported = Instant::now();
                }
            }
            // Odometry after the last step; an unfinished step is left out.
            if let Some(env) = episode.env.clone() {
                self.log_pending(&data, &env, &mut episode, None, &mut report)?;
            } else if report.messages > 0 {
                return Err(no_episode(path));
            }
            Ok(())
        })();
        report.cut = messages.cut();
        self.worker.flush_columns();
        played?;
        self.stats.files += 1;
        self.stats.cut_files += u64::from(report.cut);
        self.stats.steps += report.steps;
        Ok(report)
    }

    /// Waits until the message received at `publish_ns` is due (its delay
    /// since the file's first message, at the configured speed). False:
    /// stopped.
    fn pace(&mut self, origin: &mut Option<(u64, Instant)>, publish_ns: u64) -> bool {
        if self.stop.load(Ordering::Relaxed) {
            return false;
        }
        let Some(speed) = self.config.speed else {
            return true;
        };
        let (first_ns, started) = *origin.get_or_insert((publish_ns, Instant::now()));
        let recorded = Duration::from_nanos(publish_ns.saturating_sub(first_ns));
        let Some(due) = Duration::try_from_secs_f64(recorded.as_secs_f64() / speed)
            .ok()
            .and_then(|offset| started.checked_add(offset))
        else {
            // Beyond any clock: not worth waiting for.
            return true;
        };
        if due > Instant::now() {
            // What gathered is shown before the pause, not after it.
            self.worker.flush_columns();
        }
        while let Some(left) = due.checked_duration_since(Instant::now()) {
            if left.is_zero() {
                break;
            }
            if self.stop.load(Ordering::Relaxed) {
                return false;
            }
            std::thread::sleep(left.min(PACE_SLICE));
        }
        true
    }

    fn on_message(
        &mut self,
        data: &EpisodeData,
        episode: &mut Episode,
        message: RecordedMessage,
        report: &mut FileReport,
    ) -> Result<(), ReplayError> {
        let at = wall(message.publish_time_ns);
        match message.channel {
            Some(Channel::Episode) => {
                let info: EpisodeInfo = data.decode(&message)?;
                let env: EnvId = info.env_id.parse().map_err(|e| ReplayError::Episode {
                    path: data.path().to_owned(),
                    reason: format!("env id `{}`: {e}", info.env_id),
                })?;
                let (world, source) = match WorldSpec::builtin(&info.world) {
                    Ok(world) => (Some(world), WorldSource::Recording),
                    Err(e) => (
                        fallback_world(),
                        WorldSource::Fallback(format!("the recorded world: {e}")),
                    ),
                };
                if let Some(world) = world {
                    self.worker.apply_world(&env, world, source, at);
                }
                report.env = Some(env.clone());
                report.episode_id = Some(info.episode_id);
                episode.env = Some(env);
                episode.experiment = info.experiment;
                episode.experiment_id = i64::try_from(info.experiment_id).unwrap_or(i64::MAX);
            }
            Some(Channel::Step) => {
                let step: Step = data.decode(&message)?;
                let env = episode.env(data.path())?;
                self.worker.set_seq(&env, step.command_seq);
                episode.command_seq = step.command_seq;
                self.log_pending(data, &env, episode, Some(step.command_seq), report)?;
                let event = EpisodeEvent {
                    experiment: episode.experiment.clone(),
                    episode_id: step.episode_id,
                    step: step.step,
                    reward: step.reward,
                    episode_return: step.episode_return,
                    terminated: step.terminated,
                    truncated: step.truncated,
                    success: step.success,
                    end_reason: step.end_reason,
                    experiment_id: episode.experiment_id,
                    command_seq: step.command_seq,
                };
                let logged =
                    self.worker
                        .log_episode_event(&env, &event, Some(&step.header.stamp), at);
                self.worker.account(logged);
                report.steps += 1;
            }
            Some(Channel::EpisodeEnd) => {
                let end: EpisodeEnd = data.decode(&message)?;
                let env = episode.env(data.path())?;
                self.log_pending(data, &env, episode, None, report)?;
                // A terminal step has logged the episode's end already.
                if !(end.terminated || end.truncated) {
                    let last = EpisodeEvent {
                        experiment: episode.experiment.clone(),
                        episode_id: end.episode_id,
                        step: end.steps,
                        reward: 0.0,
                        episode_return: end.episode_return,
                        terminated: false,
                        truncated: false,
                        success: end.success,
                        end_reason: end.end_reason.clone(),
                        experiment_id: episode.experiment_id,
                        // No command of its own: the episode's last.
                        command_seq: episode.command_seq,
                    };
                    let logged = self
                        .worker
                        .log_episode_stopped(&env, &last, &end.end_reason, at);
                    self.worker.account(logged);
                }
                report.ended = Some(end.end_reason);
            }
            Some(_) => episode.pending.push(message),
            None => report.unknown += 1,
        }
        Ok(())
    }

    /// Logs the messages gathered since the last step: as the step at
    /// `seq` when its `Step` came, else (the file's end) only its odometry,
    /// at the env's current step.
    fn log_pending(
        &mut self,
        data: &EpisodeData,
        env: &EnvId,
        episode: &mut Episode,
        seq: Option<u64>,
        report: &mut FileReport,
    ) -> Result<(), ReplayError> {
        let complete = seq.is_some();
        // Colour waiting for its depth image (recorded one after the other).
        let mut color: Option<(Image, SystemTime)> = None;
        for message in episode.pending.drain(..) {
            let at = wall(message.publish_time_ns);
            let logged = match message.channel {
                Some(Channel::Odom) => {
                    let odom: Odometry = data.decode(&message)?;
                    self.worker.log_odom(env, &odom, seq, at)
                }
                _ if !complete => {
                    report.incomplete += 1;
                    Ok(())
                }
                Some(Channel::CmdVel) => {
                    let twist: Twist = data.decode(&message)?;
                    self.worker
                        .log_command(env, seq, twist.linear.x, twist.angular.z, at);
                    Ok(())
                }
                Some(Channel::Color) => {
                    let image: Image = data.decode(&message)?;
                    match color.replace((image, at)) {
                        Some((alone, at)) => {
                            self.worker.log_frame(env, seq, alone, Image::default(), at)
                        }
                        None => Ok(()),
                    }
                }
                Some(Channel::Depth) => {
                    let depth: Image = data.decode(&message)?;
                    let (color, at) = color.take().unwrap_or((Image::default(), at));
                    self.worker.log_frame(env, seq, color, depth, at)
                }
                Some(Channel::Pose) => {
                    let pose: PoseStamped = data.decode(&message)?;
                    self.worker.log_pose(env, &pose, seq, at)
                }
                // Never gathered.
                Some(Channel::Episode | Channel::Step | Channel::EpisodeEnd) | None => Ok(()),
            };
            self.worker.account(logged);
        }
        if let Some((alone, at)) = color {
            let logged = self.worker.log_frame(env, seq, alone, Image::default(), at);
            self.worker.account(logged);
        }
        Ok(())
    }

    /// Logs what is pending and completes the recording (an `.rrd` file is
    /// whole afterwards; a server stops).
    pub fn finish(mut self) -> Result<ReplayStats, ReplayError> {
        self.close()?;
        Ok(self.stats())
    }

    fn close(&mut self) -> Result<(), ReplayError> {
        if std::mem::replace(&mut self.closed, true) {
            return Ok(());
        }
        self.worker.finish();
        close_sink(&self.rec, self.config.flush_timeout)?;
        Ok(())
    }
}

impl Drop for Replay {
    fn drop(&mut self) {
        if let Err(e) = self.close() {
            tracing::warn!("replay: {e}");
        }
    }
}

/// The file being played.
#[derive(Default)]
struct Episode {
    /// Its env, once `/offworld/episode` was read.
    env: Option<EnvId>,
    /// Its experiment's name.
    experiment: String,
    /// Its experiment's id.
    experiment_id: i64,
    /// The last step's command.
    command_seq: u64,
    /// The messages since the last `Step`: the next step's.
    pending: Vec<RecordedMessage>,
}

impl Episode {
    fn env(&self, path: &Path) -> Result<EnvId, ReplayError> {
        self.env.clone().ok_or_else(|| no_episode(path))
    }
}

fn no_episode(path: &Path) -> ReplayError {
    ReplayError::Episode {
        path: path.to_owned(),
        reason: "not an episode file: no /offworld/episode record before its steps".into(),
    }
}

/// The files to replay for `paths`: a file as given; for a directory,
/// every `ep-*.mcap` and `ep-*.mcap.partial` in it and below it, sorted.
pub fn episode_files(paths: &[PathBuf]) -> Result<Vec<PathBuf>, ReplayError> {
    let mut files = Vec::new();
    for path in paths {
        let is_dir = std::fs::metadata(path)
            .map_err(|e| RecordError::Io {
                path: path.clone(),
                source: e,
            })?
            .is_dir();
        if !is_dir {
            files.push(path.clone());
            continue;
        }
        let found: Vec<PathBuf> = read::episode_files(path)?
            .into_iter()
            .filter(|f| {
                f.file_name()
                    .is_some_and(|n| n.to_string_lossy().starts_with("ep-"))
            })
            .collect();
        if found.is_empty() {
            return Err(ReplayError::NoFiles(path.clone()));
        }
        files.extend(found);
    }
    Ok(files)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_directory_without_episodes_is_an_error_naming_it() {
        let dir =
            std::env::temp_dir().join(format!("offworld-replay-empty-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("dir");
        std::fs::write(dir.join("notes.txt"), b"x").expect("file");
        let err = episode_files(std::slice::from_ref(&dir)).expect_err("no episodes");
        assert!(
            err.to_string().contains(&dir.display().to_string()),
            "{err}"
        );
        let missing = dir.join("missing.mcap");
        let err = episode_files(std::slice::from_ref(&missing)).expect_err("missing");
        assert!(err.to_string().contains("missing.mcap"), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn speeds_must_be_positive() {
        let path = std::env::temp_dir().join("offworld-replay-never-written.rrd");
        for speed in [0.0, -1.0, f64::NAN] {
            let config = ReplayConfig {
                speed: Some(speed),
                ..ReplayConfig::new(Sink::File(path.clone()))
            };
            assert!(Replay::open(config).is_err(), "{speed}");
        }
    }
}
