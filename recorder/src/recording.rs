//! An env's recorder: the controller hands it each episode's start, steps
//! and end; a thread of its own writes the files, so a step never waits
//! for the disk on a real env.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;

use offworld_runtime::codec;
use offworld_runtime::keys::{EnvId, Topic};
use offworld_runtime::msg::{CameraFrameView, Header, Odometry, PoseStamped, Time, Twist};
use tokio::sync::mpsc;
use zenoh::bytes::ZBytes;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;
use zenoh::Session;

use crate::episode_file::{now_ns, stamp_ns, Channel, Compression, EpisodeFile};
use crate::msg::{EpisodeEnd, EpisodeInfo, Step};
use crate::RecordError;

/// Events waiting for the writer, at most; a real env's recording of an
/// episode stops when they are exceeded (its steps never wait).
const QUEUE: usize = 256;

/// The odometry an episode file starts with is at most this old.
const START_ODOM_MAX_AGE_NS: u64 = 2_000_000_000;

/// Where and how an env records.
#[derive(Debug, Clone)]
pub struct RecordTo {
    /// The root of the recordings.
    pub dir: PathBuf,
    /// Steps wait for the writer instead of dropping a recording that
    /// falls behind: for sim envs, where nothing moves while they wait.
    pub lossless: bool,
    /// Each step flushed as its own chunk, so a crash loses none of the
    /// steps already answered, and each finished file synced to disk (with
    /// its directory) before its rename, so a power cut loses none either:
    /// for real robots, whose steps are scarce. Else chunks of about 1 MiB
    /// (a crashed sim loses at most that much of the episode in progress)
    /// and no syncs: a sim step pays far less for its recording.
    pub durable: bool,
}

impl RecordTo {
    /// Checks that `dir` can hold recordings: creates it, writes, syncs and
    /// removes a probe file. A clear error before anything is served.
    pub fn check(dir: &Path) -> Result<(), RecordError> {
        let unwritable = |e: std::io::Error| RecordError::Unwritable {
            dir: dir.to_owned(),
            reason: e.to_string(),
        };
        std::fs::create_dir_all(dir).map_err(unwritable)?;
        let probe = dir.join(format!(".offworld-probe-{}", std::process::id()));
        let written = std::fs::File::create(&probe).and_then(|mut f| {
            use std::io::Write;
            f.write_all(b"offworld recording probe\n")?;
            f.sync_all()
        });
        let removed = std::fs::remove_file(&probe);
        written.map_err(unwritable)?;
        removed.map_err(unwritable)
    }

    /// The file of episode `episode_id` of experiment `experiment_id` on `env`.
    pub fn episode_path(&self, env: &EnvId, experiment_id: u64, episode_id: u64) -> PathBuf {
        self.dir
            .join(experiment_dir(env, experiment_id))
            .join(format!("ep-{episode_id:06}.mcap"))
    }

    /// The episode files of experiment `experiment_id` on `env` (finished and
    /// `.partial`), by episode then name; none if it never recorded here.
    pub fn experiment_files(
        &self,
        env: &EnvId,
        experiment_id: u64,
    ) -> Result<Vec<RecordedFile>, RecordError> {
        let relative_dir = experiment_dir(env, experiment_id);
        let dir = self.dir.join(&relative_dir);
        let entries = match std::fs::read_dir(&dir) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(RecordError::io(&dir, e)),
        };
        let mut found = Vec::new();
        for entry in entries {
            let entry = entry.map_err(|e| RecordError::io(&dir, e))?;
            let name = entry.file_name();
            let Some((episode_id, complete)) = name.to_str().and_then(parse_episode_file_name)
            else {
                continue;
            };
            // Not followed: only files this recorder wrote count.
            let meta = std::fs::symlink_metadata(entry.path())
                .map_err(|e| RecordError::io(&entry.path(), e))?;
            if meta.is_file() {
                found.push(RecordedFile {
                    episode_id,
                    relative_path: relative_dir.join(&name),
                    bytes: meta.len(),
                    complete,
                });
            }
        }
        found.sort_by(|a, b| {
            (a.episode_id, &a.relative_path).cmp(&(b.episode_id, &b.relative_path))
        });
        Ok(found)
    }
}

/// An episode file found by [`RecordTo::experiment_files`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordedFile {
    /// The episode it holds.
    pub episode_id: u64,
    /// Relative to [`RecordTo::dir`].
    pub relative_path: PathBuf,
    /// Size, bytes.
    pub bytes: u64,
    /// False for a `.partial` (its episode was cut short).
    pub complete: bool,
}

/// `<realm>/<env name>/exp-NNNNNN`, relative to the recordings root.
fn experiment_dir(env: &EnvId, experiment_id: u64) -> PathBuf {
    PathBuf::from(env.realm().as_str())
        .join(env.name())
        .join(format!("exp-{experiment_id:06}"))
}

/// `ep-N.mcap`, `ep-N.K.mcap` (a reused episode id) or either + `.partial`
/// → (N, finished).
fn parse_episode_file_name(name: &str) -> Option<(u64, bool)> {
    let (name, complete) = match name.strip_suffix(".partial") {
        Some(stem) => (stem, false),
        None => (name, true),
    };
    let stem = name.strip_prefix("ep-")?.strip_suffix(".mcap")?;
    let episode = stem.split_once('.').map_or(stem, |(n, _)| n);
    if episode.is_empty() || !episode.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    Some((episode.parse().ok()?, complete))
}

/// One step as the controller answered it.
pub struct StepRecord {
    /// The transition (its stamp is set from the frame when written).
    pub step: Step,
    /// The camera frame payload (`CameraFrame` CDR) the observation was built from.
    pub frame: ZBytes,
    /// The pose the step was judged from.
    pub pose: PoseStamped,
    /// What was commanded and when (none for the reset).
    pub command: Option<(Twist, Time)>,
}

enum Event {
    Begin {
        path: PathBuf,
        info: Box<EpisodeInfo>,
        /// Added to the file's metadata record.
        notes: BTreeMap<String, String>,
        /// The odometry last received before the episode began.
        odom: Option<Received>,
    },
    Step(Box<StepRecord>),
    Odom(Received),
    /// With whom to tell once the file is finished.
    End(EpisodeEnd, Option<tokio::sync::oneshot::Sender<()>>),
    /// Told once every event queued before it is handled.
    CaughtUp(tokio::sync::oneshot::Sender<()>),
}

/// An odometry message and when it was received.
#[derive(Clone)]
struct Received {
    odom: Box<Odometry>,
    received_ns: u64,
}

/// An event of the episode with this generation.
struct Queued {
    generation: u64,
    event: Event,
}

/// Records one env's episodes (see `docs/recording.md`). Dropping it ends
/// the episode in progress as `recorder_stopped` and waits for the writer.
pub struct EnvRecorder {
    to: RecordTo,
    env: EnvId,
    queue: Option<mpsc::Sender<Queued>>,
    /// The episode being recorded (0: none yet).
    generation: Arc<AtomicU64>,
    /// Whether an episode is open (odometry is recorded only then).
    open: Arc<AtomicBool>,
    /// The generation whose recording was given up (queue full).
    abandoned: Arc<AtomicU64>,
    /// Set once the writer thread is found gone (logged once).
    writer_gone: AtomicBool,
    /// The odometry last received (an episode's file starts with it).
    last_odom: Arc<std::sync::Mutex<Option<Received>>>,
    writer: Option<JoinHandle<()>>,
    /// Holds a sender of the queue: undeclared before the writer is awaited.
    odom: Option<Subscriber<()>>,
    /// Told when the last ended episode's file is finished (lossless only).
    finishing: std::sync::Mutex<Option<tokio::sync::oneshot::Receiver<()>>>,
}

impl EnvRecorder {
    /// Starts recording `env` (`to.dir` checked already, see
    /// [`RecordTo::check`]): its writer thread and an odometry subscriber.
    pub async fn start(session: &Session, env: &EnvId, to: RecordTo) -> Result<Self, RecordError> {
        let (queue, events) = mpsc::channel(QUEUE);
        let open = Arc::new(AtomicBool::new(false));
        let abandoned = Arc::new(AtomicU64::new(0));
        let generation = Arc::new(AtomicU64::new(0));
        let odom_queue = queue.clone();
        let odom_open = open.clone();
        let odom_generation = generation.clone();
        let last_odom = Arc::new(std::sync::Mutex::new(None));
        let odom_last = last_odom.clone();
        let odom = session
            .declare_subscriber(env.key(Topic::Odom))
            .callback(move |sample: Sample| {
                let Ok(odom) = codec::decode_payload::<Odometry>(sample.payload()) else {
                    return;
                };
                let received = Received {
                    odom: Box::new(odom),
                    received_ns: now_ns(),
                };
                if let Ok(mut last) = odom_last.lock() {
                    *last = Some(received.clone());
                }
                // Odometry streams: dropped rather than waited for, and
                // never allowed more than half the queue (steps come first).
                if !odom_open.load(Ordering::Acquire) || odom_queue.capacity() < QUEUE / 2 {
                    return;
                }
                let _ = odom_queue.try_send(Queued {
                    generation: odom_generation.load(Ordering::Acquire),
                    event: Event::Odom(received),
                });
            })
            .await
            .map_err(|e| RecordError::Zenoh(e.to_string()))?;
        let writer_env = env.clone();
        let writer_abandoned = abandoned.clone();
        let durable = to.durable;
        let writer = std::thread::Builder::new()
            .name(format!("record {}", env.name()))
            .spawn(move || write_episodes(&writer_env, events, &writer_abandoned, durable))
            .map_err(|e| RecordError::io(&to.dir, e))?;
        Ok(Self {
            to,
            env: env.clone(),
            queue: Some(queue),
            generation,
            open,
            abandoned,
            last_odom,
            writer_gone: AtomicBool::new(false),
            writer: Some(writer),
            odom: Some(odom),
            finishing: std::sync::Mutex::new(None),
        })
    }

    /// Where this recorder writes.
    pub fn destination(&self) -> &RecordTo {
        &self.to
    }

    /// The file an episode will be recorded in.
    pub fn episode_path(&self, info: &EpisodeInfo) -> PathBuf {
        self.to
            .episode_path(&self.env, info.experiment_id, info.episode_id)
    }

    /// Starts recording the episode `info` (ends one left open), once the
    /// episodes ended before are finished on disk: a client that reset its
    /// env finds its earlier episodes complete, even if the controller is
    /// killed right after.
    pub async fn begin(&self, info: EpisodeInfo) {
        self.begin_annotated(info, BTreeMap::new()).await;
    }

    /// [`EnvRecorder::begin`] with `notes` added to the file's metadata
    /// record (see [`EpisodeFile::create_annotated`]).
    pub async fn begin_annotated(&self, info: EpisodeInfo, notes: BTreeMap<String, String>) {
        self.ended_episodes_finished().await;
        let generation = self.generation.fetch_add(1, Ordering::AcqRel) + 1;
        let path = self.episode_path(&info);
        // Only a recent one says where the robot starts from.
        let fresh_since = now_ns().saturating_sub(START_ODOM_MAX_AGE_NS);
        let odom = self
            .last_odom
            .lock()
            .ok()
            .and_then(|last| last.clone())
            .filter(|o| o.received_ns >= fresh_since);
        self.open.store(true, Ordering::Release);
        self.send(
            generation,
            Event::Begin {
                path,
                info: Box::new(info),
                notes,
                odom,
            },
        )
        .await;
    }

    /// Records a step of the open episode.
    pub async fn step(&self, record: StepRecord) {
        let generation = self.generation.load(Ordering::Acquire);
        self.send(generation, Event::Step(Box::new(record))).await;
    }

    /// Ends the open episode's file. Returns at once: a lossless (sim)
    /// recorder finishes the file while the client moves on (its next
    /// reset overlaps the finishing), and [`EnvRecorder::begin`] and
    /// [`EnvRecorder::caught_up`] wait for it.
    pub async fn end(&self, end: EpisodeEnd) {
        self.open.store(false, Ordering::Release);
        let generation = self.generation.load(Ordering::Acquire);
        if self.to.lossless {
            let (done, finished) = tokio::sync::oneshot::channel();
            self.send(generation, Event::End(end, Some(done))).await;
            // The writer keeps the queue's order: this end finished means
            // every earlier one is too.
            if let Ok(mut pending) = self.finishing.lock() {
                *pending = Some(finished);
            }
        } else {
            self.send(generation, Event::End(end, None)).await;
        }
    }

    /// Returns once the writer has handled everything handed to it before
    /// (files of ended episodes finished and renamed, the current one
    /// created): listings of the recordings then match what the client did.
    /// A recorder whose writer is gone, or whose queue is full (lossy), does
    /// not wait.
    pub async fn caught_up(&self) {
        let Some(queue) = &self.queue else { return };
        let (done, handled) = tokio::sync::oneshot::channel();
        let queued = Queued {
            generation: self.generation.load(Ordering::Acquire),
            event: Event::CaughtUp(done),
        };
        let sent = if self.to.lossless {
            queue.send(queued).await.is_ok()
        } else {
            queue.try_send(queued).is_ok()
        };
        if sent {
            let _ = handled.await;
        }
    }

    /// Waits for the last ended episode's file to be finished (lossless).
    async fn ended_episodes_finished(&self) {
        let pending = self.finishing.lock().ok().and_then(|mut p| p.take());
        if let Some(finished) = pending {
            let _ = finished.await;
        }
    }

    async fn send(&self, generation: u64, event: Event) {
        let Some(queue) = &self.queue else { return };
        if self.abandoned.load(Ordering::Acquire) == generation {
            return;
        }
        let queued = Queued { generation, event };
        if self.to.lossless {
            // The writer only stops when this recorder is dropped.
            let _ = queue.send(queued).await;
            return;
        }
        match queue.try_send(queued) {
            Ok(()) => {}
            Err(mpsc::error::TrySendError::Full(_)) => {
                tracing::warn!(
                    env = %self.env,
                    "the recorder fell behind ({QUEUE} events queued): this episode's recording stops; \
                     the episode goes on"
                );
                self.abandoned.store(generation, Ordering::Release);
            }
            Err(mpsc::error::TrySendError::Closed(_)) => {
                if !self.writer_gone.swap(true, Ordering::AcqRel) {
                    tracing::error!(env = %self.env, "the recorder's writer has stopped (a bug): episodes are no longer recorded");
                }
            }
        }
    }
}

/// How long a dropped recorder waits for its writer to finish the files.
const WRITER_GRACE: std::time::Duration = std::time::Duration::from_secs(10);

impl Drop for EnvRecorder {
    fn drop(&mut self) {
        // Closing the queue (its last sender is in the odometry callback)
        // ends the writer once it has written what is queued.
        self.queue = None;
        drop(self.odom.take());
        let Some(writer) = self.writer.take() else {
            return;
        };
        let deadline = std::time::Instant::now() + WRITER_GRACE;
        while !writer.is_finished() && std::time::Instant::now() < deadline {
            std::thread::sleep(std::time::Duration::from_millis(5));
        }
        if writer.is_finished() {
            let _ = writer.join();
        } else {
            tracing::warn!(env = %self.env, "the recorder's writer did not finish in time; the episode in progress may stay a .partial");
        }
    }
}

/// The file being written and what its end record needs.
struct Open {
    generation: u64,
    file: EpisodeFile,
    last: Option<Step>,
    episode_id: u64,
}

impl Open {
    /// Ends the file with `end_reason` (the episode's own end unknown).
    fn stop(self, env: &EnvId, durable: bool, end_reason: &str) {
        let end = EpisodeEnd::after(self.episode_id, self.last.as_ref(), end_reason);
        finish(env, self.file, &end, durable);
    }
}

fn finish(env: &EnvId, file: EpisodeFile, end: &EpisodeEnd, durable: bool) {
    let path = file.path().to_owned();
    match file.finish(end, durable) {
        Ok(path) => tracing::debug!(%env, path = %path.display(), "episode recorded"),
        Err(e) => tracing::warn!(
            %env,
            "could not finish the recording {}: {e}; the steps written so far stay in its .partial",
            path.display()
        ),
    }
}

/// The writer thread: writes every queued event until the queue closes.
fn write_episodes(
    env: &EnvId,
    mut events: mpsc::Receiver<Queued>,
    abandoned: &AtomicU64,
    durable: bool,
) {
    // Writing is background work: on a machine whose cores the step path
    // keeps busy (a sim, the robot's computer) it must not take their turn.
    offworld_program::priority::lower_current_thread();
    let mut open: Option<Open> = None;
    while let Some(Queued { generation, event }) = events.blocking_recv() {
        let handled = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            handle(env, &mut open, generation, event, abandoned, durable)
        }));
        if handled.is_err() {
            tracing::error!(%env, "the recorder failed on an event (a bug): this episode's recording stops");
            open = None;
        }
    }
    if let Some(current) = open.take() {
        current.stop(env, durable, "recorder_stopped: the controller stopped");
    }
}

/// Writes one queued event of episode `generation` into `open`.
fn handle(
    env: &EnvId,
    open: &mut Option<Open>,
    generation: u64,
    event: Event,
    abandoned: &AtomicU64,
    durable: bool,
) {
    if let Some(current) = open.take_if(|o| abandoned.load(Ordering::Acquire) == o.generation) {
        current.stop(
            env,
            durable,
            "recorder_stopped: the writer fell behind (its queue was full)",
        );
    }
    match event {
        Event::Begin {
            path,
            info,
            notes,
            odom,
        } => {
            if let Some(current) = open.take() {
                current.stop(env, durable, "recorder_stopped: a new episode began first");
            }
            // Zstd where steps are few and precious; none where a sim
            // steps thousands of times a second and every cycle counts
            // (LZ4's frame checksum alone cost more than its compression).
            let compression = durable.then_some(Compression::Zstd);
            let created = EpisodeFile::create_annotated(&path, &info, &notes, compression)
                .and_then(|mut file| {
                    if let Some(odom) = odom {
                        write_odom(&mut file, &odom)?;
                    }
                    Ok(file)
                });
            match created {
                Ok(file) => {
                    *open = Some(Open {
                        generation,
                        file,
                        last: None,
                        episode_id: info.episode_id,
                    })
                }
                Err(e) => tracing::warn!(
                    %env,
                    episode = info.episode_id,
                    "cannot record this episode: {e}; it goes on unrecorded"
                ),
            }
        }
        Event::Step(mut record) => {
            let Some(current) = open.as_mut().filter(|o| o.generation == generation) else {
                return;
            };
            if let Err(e) = write_step(&mut current.file, &mut record, durable) {
                tracing::warn!(%env, "recording stopped: {e}; the episode goes on");
                if let Some(current) = open.take() {
                    current.stop(env, durable, &format!("recorder_stopped: {e}"));
                }
                return;
            }
            current.last = Some(record.step);
        }
        Event::Odom(odom) => {
            let Some(current) = open.as_mut().filter(|o| o.generation == generation) else {
                return;
            };
            if let Err(e) = write_odom(&mut current.file, &odom) {
                tracing::warn!(%env, "recording stopped: {e}; the episode goes on");
                if let Some(current) = open.take() {
                    current.stop(env, durable, &format!("recorder_stopped: {e}"));
                }
            }
        }
        Event::CaughtUp(done) => {
            let _ = done.send(());
        }
        Event::End(end, done) => {
            if let Some(current) = open.take_if(|o| o.generation == generation) {
                finish(env, current.file, &end, durable);
            }
            if let Some(done) = done {
                let _ = done.send(());
            }
        }
    }
}

fn write_odom(file: &mut EpisodeFile, odom: &Received) -> Result<(), RecordError> {
    let at = stamp_ns(&odom.odom.header.stamp);
    file.write(Channel::Odom, at, odom.received_ns, &*odom.odom)
}

/// Writes a step's messages (and flushes them as one chunk if asked).
fn write_step(
    file: &mut EpisodeFile,
    record: &mut StepRecord,
    flush: bool,
) -> Result<(), RecordError> {
    let received = now_ns();
    let bytes = record.frame.to_bytes();
    let frame = codec::decode_borrowed::<CameraFrameView>(&bytes)
        .map_err(|e| RecordError::Encode(format!("a bad camera frame: {e}")))?;
    // Stamped here, off the step's path: the frame's capture time.
    record.step.header = Header::new(frame.color.header.stamp, "world");
    if let Some((twist, sent)) = &record.command {
        let at = stamp_ns(sent);
        file.write(Channel::CmdVel, at, at, twist)?;
    }
    file.write(
        Channel::Color,
        stamp_ns(&frame.color.header.stamp),
        received,
        &frame.color,
    )?;
    file.write(
        Channel::Depth,
        stamp_ns(&frame.depth.header.stamp),
        received,
        &frame.depth,
    )?;
    file.write(
        Channel::Pose,
        stamp_ns(&record.pose.header.stamp),
        received,
        &record.pose,
    )?;
    file.write(
        Channel::Step,
        stamp_ns(&record.step.header.stamp),
        received,
        &record.step,
    )?;
    if flush {
        file.end_step()?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn episode_file_names_parse_to_their_episode() {
        assert_eq!(parse_episode_file_name("ep-000003.mcap"), Some((3, true)));
        assert_eq!(parse_episode_file_name("ep-000003.2.mcap"), Some((3, true)));
        assert_eq!(
            parse_episode_file_name("ep-000012.mcap.partial"),
            Some((12, false))
        );
        for other in [
            "ep-.mcap",
            "ep-12.txt",
            "ep-1x.mcap",
            "ep-+1.mcap",
            "notes.mcap",
            "ep-99999999999999999999999.mcap",
        ] {
            assert_eq!(parse_episode_file_name(other), None, "{other}");
        }
    }
}
