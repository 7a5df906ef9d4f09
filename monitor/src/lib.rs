//! The OffWorld Gym monitor: watches the Zenoh key space of one env or of
//! all envs and streams it to the [rerun](https://rerun.io) viewer (rerun
//! SDK 0.36.3) — live over gRPC, as a server viewers connect to, or into an
//! `.rrd` file.
//!
//! It draws, per env under `envs/<realm>/<name>`: the static world (ground,
//! walls, monolith, boulders, task boundary, success radius), the robot at
//! its tracker pose with its body box and this episode's trajectory, the
//! odometry pose beside it, the RGBD camera as a pinhole with its colour and
//! depth images, every overhead camera, commanded velocities, rewards,
//! returns, successes and episode lengths as time series, and episode
//! boundaries, tracking, status and e-stops as events. The full entity tree
//! and the timelines are in [`paths`]. Recorded episodes (the recorder's
//! MCAP files) play into the same entities with [`replay`].
//!
//! # Never in the way
//!
//! Zenoh callbacks only push the received sample into a bounded queue (one
//! short mutex, no decoding, no waiting). Camera frames have a few slots and
//! the oldest is evicted when full; other messages are refused when their
//! (large) lane is full. Either way the loss is counted in
//! [`MonitorStats`] and the publisher — the robot, the twin, the controller
//! — never waits for the viewer. One named thread (`offworld-monitor`)
//! wakes at most every [`MonitorConfig::batch_interval`], decodes what
//! gathered and logs it (every row with a time as columns: one chunk per
//! entity per 100 ms); malformed messages are counted and skipped.
//!
//! # Embedding
//!
//! ```no_run
//! # fn demo(session: &zenoh::Session) -> Result<(), offworld_monitor::MonitorError> {
//! use offworld_monitor::{Monitor, MonitorConfig, Scope, Sink};
//! let env: offworld_runtime::EnvId = "sim/monolith-0".parse().expect("env id");
//! let monitor = Monitor::spawn(
//!     session,
//!     MonitorConfig::new(Sink::File("run.rrd".into())).scope(Scope::env(env)),
//! )?;
//! // … step the env …
//! let stats = monitor.shutdown()?; // flushes and completes run.rrd
//! println!("{} frames, {} dropped", stats.frames, stats.dropped_frames);
//! # Ok(()) }
//! ```
//!
//! [`Monitor::spawn`] is synchronous and cheap, callable from plain threads,
//! from async code and from Python bindings alike; dropping the
//! [`MonitorHandle`] shuts down as [`MonitorHandle::shutdown`] does. A sink
//! can also be given as one string (see [`Sink`]'s `FromStr`), which suits
//! a `monitor="run.rrd"` option.

pub mod cli;
mod columns;
pub mod layout;
pub mod paths;
mod queue;
pub mod replay;
mod scene;
mod worker;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::str::FromStr;
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use offworld_runtime::keys::{
    clients_alive_selector, components_alive_selector, global_estop_key, overhead_on_all_envs,
    topic_on_all_envs,
};
use offworld_runtime::{Component, EnvId, Topic};
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber;
use zenoh::sample::{Sample, SampleKind};
use zenoh::{Session, Wait};

pub use rerun;

use crate::queue::{Lane, Queue};
use crate::worker::{lane_of, topic_of, Event, Shared, Worker, WorkerConfig};

/// The rerun application id of every recording the monitor makes.
pub const APPLICATION_ID: &str = "offworld_gym";
/// The port a rerun viewer or server listens on by default.
pub const DEFAULT_RERUN_PORT: u16 = 9876;

/// Where the recording goes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Sink {
    /// Write an `.rrd` file (completed when the monitor shuts down).
    File(PathBuf),
    /// Stream to a running viewer or server, e.g.
    /// `rerun+http://127.0.0.1:9876/proxy`.
    Connect(String),
    /// Host a gRPC server that viewers connect to
    /// (`rerun --connect rerun+http://<addr>/proxy`). It keeps recent data in
    /// memory so late viewers see history.
    Serve {
        /// Where to listen.
        addr: SocketAddr,
        /// History kept for late viewers, bytes; `None`: a quarter of RAM.
        memory_limit_bytes: Option<u64>,
    },
}

impl Sink {
    /// Serve on all interfaces on the default port, like `rerun` does.
    pub fn serve_default() -> Self {
        Sink::Serve {
            addr: SocketAddr::from(([0, 0, 0, 0], DEFAULT_RERUN_PORT)),
            memory_limit_bytes: None,
        }
    }

    /// Connect to a viewer on this machine's default port.
    pub fn connect_local() -> Self {
        Sink::Connect(format!("rerun+http://127.0.0.1:{DEFAULT_RERUN_PORT}/proxy"))
    }
}

impl FromStr for Sink {
    type Err = MonitorError;

    /// `path/to/file.rrd` → [`Sink::File`]; `rerun+http://…` (or
    /// `rerun://`, `rerun+https://`) → [`Sink::Connect`]; `serve` or
    /// `serve:<ip>:<port>` → [`Sink::Serve`].
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim();
        if s.starts_with("rerun://") || s.starts_with("rerun+http") {
            return Ok(Sink::Connect(s.to_owned()));
        }
        if s == "serve" {
            return Ok(Sink::serve_default());
        }
        if let Some(addr) = s.strip_prefix("serve:") {
            let addr = addr
                .parse()
                .map_err(|e| MonitorError::InvalidSink(format!("`{addr}`: {e}")))?;
            return Ok(Sink::Serve {
                addr,
                memory_limit_bytes: None,
            });
        }
        if s.ends_with(".rrd") {
            return Ok(Sink::File(PathBuf::from(s)));
        }
        Err(MonitorError::InvalidSink(format!(
            "`{s}`: expected a .rrd path, a rerun+http://…/proxy URL, `serve` or `serve:<ip>:<port>`"
        )))
    }
}

/// The per-env topics a monitor draws after the overhead views
/// (`overhead/*`), in the order subscribed: `status` last, so a publisher
/// that has heard the monitor's `status` subscription has heard the others
/// (one session's declarations travel in order). A live view subscribes
/// to the viewers' copy of those that have one ([`Topic::viewers_copy`]).
const DRAWN_TOPICS: [Topic; 8] = [
    Topic::Obs,
    Topic::Cmd,
    Topic::Pose,
    Topic::Odom,
    Topic::Reward,
    Topic::Tracking,
    Topic::EStop,
    Topic::Status,
];

/// Which part of the key space to watch.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum Scope {
    /// Every env (`offworld/@v1/*/*/<topic>` for each topic drawn), plus
    /// the site-wide e-stop.
    #[default]
    All,
    /// These envs (`offworld/@v1/<realm>/<name>/<topic>` for each topic
    /// drawn), plus the site-wide e-stop; the monitor declares
    /// `alive/monitor` on each.
    Envs(Vec<EnvId>),
    /// Any key expression under `offworld/@v1/`, e.g. `offworld/@v1/sim/**`:
    /// what it names is delivered (every `obs` frame, command, pose and
    /// odometry message too, if it names them, even to a live view, which
    /// ignores them for their viewers' copies). Liveliness is not followed.
    KeyExpr(String),
}

impl Scope {
    /// One env.
    pub fn env(env: EnvId) -> Self {
        Scope::Envs(vec![env])
    }

    /// The key expressions of the data subscriptions: each drawn topic of
    /// each env (for a live view, its viewers' copy if it has one, unless
    /// `every_message`), and the site-wide e-stop; a [`Scope::KeyExpr`] as
    /// given.
    fn data_keys(&self, every_message: bool) -> Vec<String> {
        let topics = DRAWN_TOPICS.map(|topic| match topic.viewers_copy() {
            Some(copy) if !every_message => copy,
            _ => topic,
        });
        match self {
            Scope::All => [overhead_on_all_envs()]
                .into_iter()
                .chain(topics.map(topic_on_all_envs))
                .chain([global_estop_key()])
                .collect(),
            Scope::Envs(envs) => envs
                .iter()
                .flat_map(|env| {
                    [env.overhead_selector()]
                        .into_iter()
                        .chain(topics.map(|topic| env.key(topic)))
                })
                .chain([global_estop_key()])
                .collect(),
            Scope::KeyExpr(k) => vec![k.clone()],
        }
    }

    /// The key expressions of the liveliness subscriptions: components'
    /// tokens, and apart clients' (through a site's router only an
    /// operator may hear those; a trainer's monitor, denied them, still
    /// hears the components).
    fn alive_keys(&self) -> Vec<String> {
        match self {
            Scope::All => vec![components_alive_selector(), clients_alive_selector()],
            Scope::Envs(envs) => envs
                .iter()
                .flat_map(|env| {
                    [
                        env.components_alive_selector(),
                        env.clients_alive_selector(),
                    ]
                })
                .collect(),
            Scope::KeyExpr(_) => Vec::new(),
        }
    }

    /// The envs this monitor announces itself on.
    fn watched_envs(&self) -> &[EnvId] {
        match self {
            Scope::Envs(envs) => envs,
            Scope::All | Scope::KeyExpr(_) => &[],
        }
    }
}

/// How to run a monitor. [`MonitorConfig::new`] gives the defaults.
#[derive(Debug, Clone)]
pub struct MonitorConfig {
    /// Where the recording goes.
    pub sink: Sink,
    /// What to watch.
    pub scope: Scope,
    /// Draw this built-in world for every env instead of asking each env's
    /// controller (`spec`); `None` asks and falls back to `monolith`.
    pub world: Option<String>,
    /// How long a `spec` query may take.
    pub spec_timeout: Duration,
    /// Camera frames (colour + depth, overhead) waiting for the worker at
    /// most; the oldest is dropped beyond.
    pub frame_queue: usize,
    /// Other messages waiting for the worker at most; new ones are dropped
    /// beyond.
    pub message_queue: usize,
    /// Send the default layout (one tab per env).
    pub blueprint: bool,
    /// The worker lets messages gather this long before logging them as a
    /// batch, so it (and rerun's threads) wake a few hundred times a second
    /// at most, not once per message.
    pub batch_interval: Duration,
    /// The recording's name in the viewer.
    pub recording_name: Option<String>,
    /// How long shutdown waits for the sink to take the last data.
    pub flush_timeout: Duration,
    /// Log every camera frame (`obs`), command, pose and odometry message:
    /// the default for a file (a record of the run). Off (the default for a
    /// viewer or server), the monitor takes their viewers' copies (the
    /// env's `preview`, at most one frame every 20 ms, `preview_cmd`,
    /// `preview_pose`, `preview_odom`: sent only while someone watches and
    /// dropped rather than waited for, see `offworld_runtime::preview`), and
    /// a camera's frame waiting for the worker is replaced by its next one
    /// (counted as superseded): what a viewer shows, while a sim env steps
    /// thousands a second, and a stalled viewer holds up no step.
    pub every_frame: bool,
}

impl MonitorConfig {
    /// Defaults: every env, worlds from the controllers' specs, 32 frames and
    /// 4096 messages of queue, the default layout; every frame into a file,
    /// each camera's newest to a viewer or server.
    pub fn new(sink: Sink) -> Self {
        let every_frame = matches!(sink, Sink::File(_));
        Self {
            sink,
            scope: Scope::All,
            world: None,
            spec_timeout: Duration::from_secs(3),
            frame_queue: 32,
            message_queue: 4096,
            blueprint: true,
            batch_interval: Duration::from_millis(20),
            recording_name: None,
            flush_timeout: Duration::from_secs(10),
            every_frame,
        }
    }

    /// Log every camera frame, command, pose and odometry message, as the
    /// controller receives them (a stall of this monitor then holds their
    /// publishers up), not the viewers' copies.
    pub fn every_frame(mut self) -> Self {
        self.every_frame = true;
        self
    }

    /// Log what a live view logs, whatever the sink: the viewers' copies
    /// (frames thinned, commands, poses and odometry droppable), of the
    /// frames each camera's newest.
    pub fn newest_frames(mut self) -> Self {
        self.every_frame = false;
        self
    }

    /// Watch `scope` instead of every env.
    pub fn scope(mut self, scope: Scope) -> Self {
        self.scope = scope;
        self
    }

    /// Draw this built-in world for every env.
    pub fn world(mut self, name: impl Into<String>) -> Self {
        self.world = Some(name.into());
        self
    }

    /// Queue sizes: frames, other messages.
    pub fn queues(mut self, frames: usize, messages: usize) -> Self {
        self.frame_queue = frames;
        self.message_queue = messages;
        self
    }
}

/// Why a monitor could not start or finish.
#[derive(Debug, thiserror::Error)]
pub enum MonitorError {
    /// The sink string is not understood.
    #[error("invalid sink {0}")]
    InvalidSink(String),
    /// rerun refused the sink (bad URL, unwritable file, port in use, …).
    #[error("rerun: {0}")]
    Rerun(#[from] rerun::RecordingStreamError),
    /// Zenoh refused a subscription.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// The worker thread could not start or died.
    #[error("monitor worker: {0}")]
    Worker(String),
    /// The sink did not take the last data in time.
    #[error("flushing the recording: {0}")]
    Flush(String),
}

/// What a monitor has seen and done so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MonitorStats {
    /// Samples the callbacks received.
    pub received: u64,
    /// Camera frames dropped for the viewer (queue full: the monitor could
    /// not keep up).
    pub dropped_frames: u64,
    /// Other messages dropped (queue full).
    pub dropped_messages: u64,
    /// Messages skipped as malformed.
    pub decode_errors: u64,
    /// Log calls rerun refused.
    pub log_errors: u64,
    /// Camera frames not logged because a newer frame of the same camera
    /// replaced them while they waited for the worker (a live view; see
    /// [`MonitorConfig::every_frame`]).
    pub superseded_frames: u64,
    /// Camera frames logged (`obs`, or `preview` in a live view).
    pub frames: u64,
    /// Tracker poses logged.
    pub poses: u64,
    /// Odometry messages logged.
    pub odometry: u64,
    /// Motion commands logged.
    pub commands: u64,
    /// Episode events (rewards) logged.
    pub rewards: u64,
    /// Env status messages seen.
    pub statuses: u64,
    /// Overhead camera images logged.
    pub overhead_frames: u64,
    /// Envs seen.
    pub envs: u64,
}

/// Starts monitors.
pub struct Monitor;

impl Monitor {
    /// Opens the sink, subscribes on `session` and starts the worker. Returns
    /// once subscribed; data published from then on is recorded.
    pub fn spawn(session: &Session, config: MonitorConfig) -> Result<MonitorHandle, MonitorError> {
        let shared = Arc::new(Shared {
            queue: Queue::new(config.frame_queue, config.message_queue),
            counters: Default::default(),
        });
        let worker_config = WorkerConfig {
            world: config.world.clone(),
            spec_timeout: config.spec_timeout,
            blueprint: config.blueprint,
            batch_interval: config.batch_interval,
        };
        // The sink is opened on the worker thread, after it lowered its
        // priority, so rerun's own threads (batcher, encoder, sink) inherit
        // the lower priority too: on a loaded machine the step path runs
        // first and the viewer waits.
        let (opened_tx, opened_rx) = std::sync::mpsc::sync_channel(1);
        let thread = {
            let shared = shared.clone();
            let session = session.clone();
            let config = config.clone();
            std::thread::Builder::new()
                .name("offworld-monitor".into())
                .spawn(move || {
                    offworld_program::priority::lower_current_thread();
                    let rec = match open_sink(&config.sink, config.recording_name.as_deref()) {
                        Ok(rec) => rec,
                        Err(e) => {
                            let _ = opened_tx.send(Err(e));
                            return;
                        }
                    };
                    let _ = opened_tx.send(Ok(rec.clone()));
                    Worker::new(rec, shared, Some(session), worker_config).run();
                })
                .map_err(|e| MonitorError::Worker(e.to_string()))?
        };
        let rec = match opened_rx.recv() {
            Ok(Ok(rec)) => rec,
            Ok(Err(e)) => {
                let _ = thread.join();
                return Err(e);
            }
            Err(_) => {
                let _ = thread.join();
                return Err(MonitorError::Worker(
                    "the worker died while opening the sink".into(),
                ));
            }
        };
        let callbacks = Arc::new(());
        let mut handle = MonitorHandle {
            inner: Some(Inner {
                callbacks: callbacks.clone(),
                subscribers: Vec::new(),
                tokens: Vec::new(),
                shared: shared.clone(),
                thread,
                rec,
                flush_timeout: config.flush_timeout,
            }),
        };
        // From here on, an error drops `handle`, which stops the worker.
        let mut subscribers = Vec::new();
        let newest_frames = !config.every_frame;
        let every_message = config.every_frame;
        // A file takes every `obs` frame, command, pose and odometry
        // message; a live view their viewers' copies (the frames thinned),
        // which Zenoh drops rather than wait for: it never receives the
        // thousands of frames a second a sim env's controller takes, nor
        // holds up their publishers when it stalls. A `Scope::KeyExpr` may
        // name both an original and its copy: the other is ignored.
        let mut ignored = Vec::new();
        if let Scope::KeyExpr(key) = &config.scope {
            ignored = ignored_topics(key, every_message);
            if !every_message && names_an_original(key) {
                tracing::warn!(
                    "`{key}` names `obs`, `cmd`, `pose` or `odom`: Zenoh delivers each of their \
                     messages to this live view, and a stall of it holds up their publishers \
                     (name their viewers' copies `preview`, `preview_cmd`, `preview_pose`, \
                     `preview_odom` instead, or use `--env`)"
                );
            }
        }
        for key in config.scope.data_keys(every_message) {
            let (shared, running, ignored) = (shared.clone(), callbacks.clone(), ignored.clone());
            let sub = session
                .declare_subscriber(key.as_str())
                .callback(move |sample: Sample| {
                    let _running = &running;
                    let key = sample.key_expr().as_str();
                    if ignored.contains(&topic_of(key).unwrap_or_default()) {
                        return;
                    }
                    let lane = lane_of(key);
                    let event = Event::Sample {
                        sample,
                        wall: SystemTime::now(),
                    };
                    if newest_frames && lane == Lane::Frame {
                        shared.queue.push_newest(event, Event::supersedes);
                    } else {
                        shared.queue.push(lane, event);
                    }
                })
                .wait()
                .map_err(|e| MonitorError::Zenoh(format!("subscribing to `{key}`: {e}")))?;
            subscribers.push(sub);
        }
        for key in config.scope.alive_keys() {
            let (shared, running) = (shared.clone(), callbacks.clone());
            let sub = session
                .liveliness()
                .declare_subscriber(key.as_str())
                .history(true)
                .callback(move |sample: Sample| {
                    let _running = &running;
                    shared.queue.push(
                        Lane::Message,
                        Event::Alive {
                            key: sample.key_expr().as_str().to_owned(),
                            online: sample.kind() == SampleKind::Put,
                            wall: SystemTime::now(),
                        },
                    );
                })
                .wait()
                .map_err(|e| MonitorError::Zenoh(format!("liveliness `{key}`: {e}")))?;
            subscribers.push(sub);
        }
        // Others can see that this env is being watched.
        let mut tokens = Vec::new();
        for env in config.scope.watched_envs() {
            tokens.push(
                session
                    .liveliness()
                    .declare_token(env.alive_key(Component::Monitor))
                    .wait()
                    .map_err(|e| MonitorError::Zenoh(format!("liveliness token: {e}")))?,
            );
        }
        if let Some(inner) = handle.inner.as_mut() {
            inner.subscribers = subscribers;
            inner.tokens = tokens;
        }
        Ok(handle)
    }
}

/// Whether a key expression names some env's `obs`, `cmd`, `pose` or
/// `odom`, which a live view reads from their viewers' copies.
fn names_an_original(key: &str) -> bool {
    let names = names_on_some_env(key);
    DRAWN_TOPICS
        .iter()
        .any(|&topic| topic.viewers_copy().is_some() && names(topic))
}

/// Whether key expression `key` names `topic` of some env (never, for a
/// malformed `key`).
fn names_on_some_env(key: &str) -> impl Fn(Topic) -> bool {
    let key = zenoh::key_expr::OwnedKeyExpr::try_from(key.to_owned()).ok();
    move |topic| {
        let all = zenoh::key_expr::OwnedKeyExpr::try_from(topic_on_all_envs(topic));
        matches!((&key, all), (Some(key), Ok(all)) if key.intersects(&all))
    }
}

/// The topics a monitor on key expression `key` ignores: of each original
/// and viewers' copy it names both of, the one it does not log (the copy
/// when taking `every_message`, else the original).
fn ignored_topics(key: &str, every_message: bool) -> Vec<&'static str> {
    let names = names_on_some_env(key);
    DRAWN_TOPICS
        .iter()
        .filter_map(|&original| Some((original, original.viewers_copy()?)))
        .filter(|&(original, copy)| names(original) && names(copy))
        .map(|(original, copy)| {
            if every_message {
                copy.as_str()
            } else {
                original.as_str()
            }
        })
        .collect()
}

/// How long shutdown waits for callbacks still running after their
/// subscriber was undeclared.
const CALLBACKS_FINISH: Duration = Duration::from_secs(1);

fn open_sink(
    sink: &Sink,
    recording_name: Option<&str>,
) -> Result<rerun::RecordingStream, MonitorError> {
    let mut builder = rerun::RecordingStreamBuilder::new(APPLICATION_ID);
    if let Some(name) = recording_name {
        builder = builder.recording_name(name);
    }
    // `wall_time` (when the sample arrived) replaces rerun's `log_time`.
    let rec = match sink {
        Sink::File(path) => builder.save(path)?,
        Sink::Connect(url) => builder.connect_grpc_opts(url.clone())?,
        Sink::Serve {
            addr,
            memory_limit_bytes,
        } => builder.serve_grpc_opts(
            match addr {
                SocketAddr::V4(a) => a.ip().to_string(),
                SocketAddr::V6(a) => format!("[{}]", a.ip()),
            },
            addr.port(),
            rerun::ServerOptions {
                memory_limit: match memory_limit_bytes {
                    Some(bytes) => rerun::MemoryLimit::from_bytes(*bytes),
                    None => rerun::MemoryLimit::from_fraction_of_total(0.25),
                },
                ..Default::default()
            },
        )?,
    };
    rec.set_log_time_enabled(false);
    Ok(rec)
}

/// Waits up to `timeout` for the sink to take everything logged, then
/// closes it: a file sink writes its footer, a server stops.
fn close_sink(rec: &rerun::RecordingStream, timeout: Duration) -> Result<(), MonitorError> {
    let flushed = rec
        .flush_with_timeout(timeout)
        .map_err(|e| MonitorError::Flush(e.to_string()));
    // Replacing the sink drops it.
    rec.disconnect();
    flushed
}

struct Inner {
    /// Held by every subscriber callback: Zenoh drops a callback once it
    /// is undeclared and no longer running.
    callbacks: Arc<()>,
    subscribers: Vec<Subscriber<()>>,
    /// `alive/monitor` of each watched env.
    tokens: Vec<LivelinessToken>,
    shared: Arc<Shared>,
    thread: std::thread::JoinHandle<()>,
    rec: rerun::RecordingStream,
    flush_timeout: Duration,
}

/// A running monitor. Shut it down (or drop it) to complete the recording.
pub struct MonitorHandle {
    inner: Option<Inner>,
}

impl MonitorHandle {
    /// Counters so far.
    pub fn stats(&self) -> MonitorStats {
        self.inner
            .as_ref()
            .map(|i| i.shared.stats())
            .unwrap_or_default()
    }

    /// The recording, to log extra data next to the monitor's.
    pub fn recording(&self) -> Option<&rerun::RecordingStream> {
        self.inner.as_ref().map(|i| &i.rec)
    }

    /// Stops listening, logs everything already queued, flushes the sink and
    /// closes it (an `.rrd` file is complete afterwards). Blocks up to the
    /// configured flush timeout once the queue is drained.
    pub fn shutdown(mut self) -> Result<MonitorStats, MonitorError> {
        self.stop()
    }

    fn stop(&mut self) -> Result<MonitorStats, MonitorError> {
        let Some(inner) = self.inner.take() else {
            return Ok(MonitorStats::default());
        };
        let mut first_error = None;
        for sub in inner.subscribers {
            if let Err(e) = sub.undeclare().wait() {
                first_error.get_or_insert(MonitorError::Zenoh(e.to_string()));
            }
        }
        for token in inner.tokens {
            if let Err(e) = token.undeclare().wait() {
                first_error.get_or_insert(MonitorError::Zenoh(e.to_string()));
            }
        }
        // A publisher's thread may be delivering a sample to a callback
        // right now (say, a frame whose step the client has already been
        // answered for): wait for it, so that sample is recorded too.
        let deadline = Instant::now() + CALLBACKS_FINISH;
        while Arc::strong_count(&inner.callbacks) > 1 && Instant::now() < deadline {
            std::thread::sleep(Duration::from_micros(200));
        }
        inner.shared.queue.close();
        if inner.thread.join().is_err() {
            first_error.get_or_insert(MonitorError::Worker("the worker panicked".into()));
        }
        if let Err(e) = close_sink(&inner.rec, inner.flush_timeout) {
            first_error.get_or_insert(e);
        }
        let stats = inner.shared.stats();
        match first_error {
            Some(e) => Err(e),
            None => Ok(stats),
        }
    }
}

impl Drop for MonitorHandle {
    fn drop(&mut self) {
        if let Err(e) = self.stop() {
            tracing::warn!("monitor shutdown: {e}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sinks_parse_from_one_string() {
        assert_eq!(
            "out/run.rrd".parse::<Sink>().expect("file"),
            Sink::File("out/run.rrd".into())
        );
        assert_eq!(
            "rerun+http://127.0.0.1:9876/proxy"
                .parse::<Sink>()
                .expect("url"),
            Sink::connect_local()
        );
        assert_eq!(
            "serve".parse::<Sink>().expect("serve"),
            Sink::serve_default()
        );
        assert_eq!(
            "serve:127.0.0.1:9000".parse::<Sink>().expect("serve addr"),
            Sink::Serve {
                addr: SocketAddr::from(([127, 0, 0, 1], 9000)),
                memory_limit_bytes: None
            }
        );
        assert!("serve:nowhere".parse::<Sink>().is_err());
        assert!("out.txt".parse::<Sink>().is_err());
    }

    #[test]
    fn scopes_subscribe_below_the_verbatim_version_chunk() {
        let env: EnvId = "real/enclosure-a".parse().expect("env");
        let drawn = |cmd: &str, pose: &str, odom: &str, frames: &str| {
            [
                "overhead/*",
                frames,
                cmd,
                pose,
                odom,
                "reward",
                "tracking",
                "estop",
                "status",
            ]
            .map(str::to_owned)
        };
        let live = drawn("preview_cmd", "preview_pose", "preview_odom", "preview");
        let every = drawn("cmd", "pose", "odom", "obs");
        let expected = |prefix: &str, chunks: &[String]| -> Vec<String> {
            chunks
                .iter()
                .map(|chunk| format!("{prefix}/{chunk}"))
                .chain(["offworld/@v1/estop".to_owned()])
                .collect()
        };
        assert_eq!(
            Scope::All.data_keys(false),
            expected("offworld/@v1/*/*", &live)
        );
        assert_eq!(
            Scope::env(env.clone()).data_keys(true),
            expected("offworld/@v1/real/enclosure-a", &every)
        );
        assert_eq!(
            Scope::KeyExpr("offworld/@v1/sim/**".into()).data_keys(true),
            ["offworld/@v1/sim/**"]
        );
        assert_eq!(
            Scope::env(env).alive_keys(),
            [
                "offworld/@v1/real/enclosure-a/alive/*",
                "offworld/@v1/real/enclosure-a/alive/client/*"
            ]
        );
        assert!(names_an_original("offworld/@v1/sim/**"));
        assert!(names_an_original("offworld/@v1/*/farm-0/obs"));
        assert!(names_an_original("offworld/@v1/*/farm-0/pose"));
        assert!(!names_an_original("offworld/@v1/*/*/preview"));
        assert!(!names_an_original("offworld/@v1/*/*/preview_cmd"));
        assert!(!names_an_original("offworld/@v1/*/*/reward"));
        for every_message in [false, true] {
            for key in Scope::All.data_keys(every_message) {
                zenoh::key_expr::KeyExpr::try_from(key).expect("valid key expression");
            }
        }
    }

    /// A key expression naming an original and its viewers' copy logs
    /// each message once: a live view the copy, a file the original. One
    /// naming only an original or only a copy logs what it names.
    #[test]
    fn a_monitor_logs_either_the_originals_or_their_copies() {
        let every = "offworld/@v1/sim/farm-0/**";
        assert_eq!(
            ignored_topics(every, false),
            ["obs", "cmd", "pose", "odom"],
            "a live view"
        );
        assert_eq!(
            ignored_topics(every, true),
            ["preview", "preview_cmd", "preview_pose", "preview_odom"],
            "a file"
        );
        for only in ["offworld/@v1/*/*/pose", "offworld/@v1/*/*/preview_pose"] {
            for every_message in [false, true] {
                assert!(ignored_topics(only, every_message).is_empty(), "{only}");
            }
        }
        assert!(ignored_topics("offworld/@v1/*/*/reward", false).is_empty());
    }
}
