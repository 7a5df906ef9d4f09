//! One env served: its state and status here, the request handlers behind
//! its queryables by job in the modules below. Requests to one env are
//! serialised (the state lock).
//!
//! - [`sessions`]: tokens, leases, `open`/`close`, clients that vanish.
//! - [`waiting`]: the line of clients waiting for a leased env.
//! - [`episodes`]: `reset`/`step`, judged, published and recorded.
//! - [`bookings`]: booked slots and the `book` queryable.
//! - [`admin`]: maintenance and lease revocation.
//! - [`records`]: experiments, episodes and the leaderboard.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use offworld_recorder::msg::{EpisodeEnd as RecordedEnd, EpisodeInfo as RecordedEpisode, Step};
use offworld_recorder::{EnvRecorder, RecordTo, StepRecord};
use offworld_runtime::codec::Encoded;
use offworld_runtime::keys::{EnvId, Topic};
use offworld_runtime::msg::{
    AdminReply, AdminRequest, Booking, BookingRequest, Bookings, CloseReply, CloseRequest, EnvSpec,
    EnvState, EnvStatus, EpisodeEvent, EpisodeRecordEntry, ExperimentInfo, ExperimentRecord,
    Experiments, ExperimentsRequest, Header, Leaderboard, MotionCommand, ObsOptions, OpenReply,
    OpenRequest, RecordingFile, ResetAccuracy, ResetReply, ResetRequest, Seed, StepReply,
    StepRequest, Time, Twist, EXPERIMENTS_PER_REPLY, EXPERIMENT_EPISODES_PER_REPLY,
};
use offworld_runtime::wire::{self, Delivery};
use offworld_runtime::WireError;
use rand::Rng;
use tokio::sync::{watch, Mutex as AsyncMutex};
use zenoh::pubsub::Publisher;
use zenoh::query::Query;
use zenoh::Session;

use crate::episode::{step_info, EndReason, Outcome, SpawnSampler};
use crate::estops::EnvEStops;
use crate::link::{LinkSeals, LinkTimeouts, ObservationRequest, RobotLink};
use crate::observation::validate_options;
use crate::step::{Answered, Plan, StepJudge};
use crate::store::{
    format_unix_ms, lock_store, now_ms, validate_experiment_name, BookingRules, EpisodeRecord,
    SlotAt, Store, User, ANONYMOUS, IN_PROGRESS, LATEST_BOOKABLE_MS,
};
use crate::task::Task;

mod admin;
mod bookings;
mod episodes;
mod records;
mod sessions;
mod waiting;

pub use admin::MAX_OPERATOR_TEXT;
use records::experiment_info;
use waiting::WaitingLine;

/// Per-env policy.
#[derive(Debug, Clone, Copy)]
pub struct EnvOptions {
    /// A lease lapses after this long without a request.
    pub lease_idle: Duration,
    /// After the holder disconnects, the lease waits this long for them.
    pub reconnect_grace: Duration,
    /// Admit clients without a token (sim envs only).
    pub allow_anonymous: bool,
    /// Robot-side timeouts.
    pub timeouts: LinkTimeouts,
    /// Seed of the spawn sampler before any `reset(seed)`.
    pub seed: u64,
    /// Limits on bookings.
    pub booking_rules: BookingRules,
    /// Real envs also put the robot's ground truth (pose, distance to the
    /// monolith) in each step's `info`, as sim envs always do. Off by
    /// default: it is privileged information, the operator's choice.
    pub share_real_pose: bool,
}

/// Longest lease idle timeout and reconnect grace a site may configure.
pub const MAX_LEASE_TIMEOUT: Duration = Duration::from_secs(7 * 24 * 3600);

impl EnvOptions {
    /// Checks the policy itself (a site's configuration): lease timeouts
    /// at most [`MAX_LEASE_TIMEOUT`] (the idle one not zero), sane booking
    /// rules.
    pub fn check(&self) -> Result<(), crate::ControllerError> {
        if self.lease_idle.is_zero() {
            return Err(crate::ControllerError::Config(
                "the lease idle timeout must not be zero".into(),
            ));
        }
        for (what, d) in [
            ("lease idle timeout", self.lease_idle),
            ("reconnect grace", self.reconnect_grace),
        ] {
            if d > MAX_LEASE_TIMEOUT {
                return Err(crate::ControllerError::Config(format!(
                    "the {what} is at most {} s, got {} s",
                    MAX_LEASE_TIMEOUT.as_secs(),
                    d.as_secs_f64()
                )));
            }
        }
        self.booking_rules.check()
    }
}

impl Default for EnvOptions {
    fn default() -> Self {
        Self {
            lease_idle: Duration::from_secs(300),
            reconnect_grace: Duration::from_secs(120),
            allow_anonymous: false,
            timeouts: LinkTimeouts::default(),
            seed: 0,
            booking_rules: BookingRules::default(),
            share_real_pose: false,
        }
    }
}

struct Lease {
    session_id: String,
    client_id: String,
    user: User,
    experiment: ExperimentRecord,
    obs: ObsOptions,
    expires: Instant,
    expires_unix_ms: i64,
    disconnected: bool,
    /// End of the booked slot the lease was taken in, Unix ms.
    booked_until_unix_ms: Option<i64>,
}

struct Episode {
    index: u64,
    seed: Option<u64>,
    steps: u32,
    episode_return: f64,
    over: bool,
    /// Where its reset asked for and put the robot, and how long it took.
    reset: ResetAccuracy,
    started_ms: i64,
    /// When its progress was last saved ([`PROGRESS_EVERY`]).
    saved: Instant,
}

/// How often an episode's progress is saved while it runs: a controller
/// killed mid-episode loses at most this much of its record (a save is a
/// durable write, too slow for every step of a fast twin).
const PROGRESS_EVERY: Duration = Duration::from_secs(1);

impl Episode {
    /// Its record, ended by `end` at `ended_ms` (`None`: in progress).
    fn record(&self, experiment_id: i64, end: Option<&EndReason>, ended_ms: i64) -> EpisodeRecord {
        EpisodeRecord {
            experiment_id,
            episode_index: self.index,
            seed: self.seed,
            steps: self.steps,
            episode_return: self.episode_return,
            success: end == Some(&EndReason::Success),
            end_reason: end.map_or(IN_PROGRESS, EndReason::as_str).to_owned(),
            reset: self.reset,
            started_ms: self.started_ms,
            ended_ms,
        }
    }
}

/// An operator's maintenance: why, by whom, until when.
#[derive(Debug, Clone)]
struct Maintenance {
    message: String,
    by: String,
    /// 0: not said.
    back_unix_ms: i64,
}

impl Maintenance {
    /// The refusal of a request while it lasts.
    fn refusal(&self, env: &EnvId) -> WireError {
        let back = if self.back_unix_ms > 0 {
            format!(" (expected back at {})", format_unix_ms(self.back_unix_ms))
        } else {
            String::new()
        };
        WireError::unavailable(format!("{env} is in maintenance: {}{back}", self.message))
    }
}

/// A lease an operator revoked: its holder's next request is told why.
struct Revoked {
    session_id: String,
    reason: String,
}

struct State {
    lease: Option<Lease>,
    maintenance: Option<Maintenance>,
    /// The last revoked lease.
    revoked: Option<Revoked>,
    episode: Option<Episode>,
    sampler: SpawnSampler,
    seq: u64,
    /// The last reset's accuracy, for `status`.
    last_reset: ResetAccuracy,
}

/// What `status` needs of the state, posted (under the state lock) at
/// every change, so `status` is answered without the lock — a real reset
/// holds it for seconds. The rest of a status (robot present, e-stops,
/// lease lapsed) is read live.
#[derive(Debug, Clone, Default)]
struct Posted {
    maintenance: Option<Maintenance>,
    lease: Option<PostedLease>,
    last_reset: ResetAccuracy,
}

/// The lease as `status` shows it.
#[derive(Debug, Clone)]
struct PostedLease {
    /// When it lapses if left idle.
    expires: Instant,
    /// The same, Unix ms.
    until_unix_ms: i64,
    /// Its holder's user name.
    holder: String,
}

impl Posted {
    fn of(state: &State) -> Self {
        Self {
            maintenance: state.maintenance.clone(),
            lease: state.lease.as_ref().map(|l| PostedLease {
                expires: l.expires,
                until_unix_ms: l.expires_unix_ms,
                holder: l.user.name.clone(),
            }),
            last_reset: state.last_reset,
        }
    }
}

/// One env: its task, robot link, state and store.
pub struct EnvServer {
    env: EnvId,
    /// Shared with the replies sent where a step's frame is received.
    task: Arc<Task>,
    options: EnvOptions,
    session: Session,
    /// Episode events for spectators, published on every step.
    events: Publisher<'static>,
    link: RobotLink,
    /// The site and env e-stop latches: motion refused while engaged.
    estops: EnvEStops,
    store: Arc<Mutex<Store>>,
    state: AsyncMutex<State>,
    /// The state as `status` shows it (see [`Posted`]).
    posted: watch::Sender<Posted>,
    /// The lease holder's client id, whose presence token is watched.
    holder: watch::Sender<Option<String>>,
    /// The status last put on `status`; held while putting, so puts go out
    /// in order.
    published: AsyncMutex<Option<EnvStatus>>,
    /// The last booking answer, valid until its `until_ms`: a step never
    /// queries the database. Cleared when this env's bookings change.
    slots: Mutex<Option<SlotAt>>,
    /// Clients waiting for the env, in order: kept apart from the state,
    /// so a request waiting for the state still counts as its sender there.
    line: Mutex<WaitingLine>,
    /// Records every episode as an MCAP file, when asked to.
    recorder: Option<EnvRecorder>,
}

fn unix_ms_in(d: Duration) -> i64 {
    now_ms().saturating_add(i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// Checks the client id of an `open`: empty (no liveliness watch) or one
/// safe key chunk, as `offworld_client` makes them (the liveliness key of
/// the client is built from it).
pub fn validate_client_id(env: &EnvId, client_id: &str) -> Result<(), WireError> {
    if client_id.is_empty() {
        return Ok(());
    }
    env.client_alive_key(client_id).map(drop).map_err(|_| {
        WireError::bad_request("client ids are 1 to 64 characters of A-Z a-z 0-9 _ - (or empty)")
    })
}

impl EnvServer {
    /// Connects to the env's robot side and prepares the state.
    pub async fn new(
        session: &Session,
        env: EnvId,
        task: Task,
        options: EnvOptions,
        seals: &LinkSeals,
        store: Arc<Mutex<Store>>,
        record: Option<&std::path::Path>,
    ) -> Result<Self, crate::ControllerError> {
        options.check()?;
        let abandoned = lock_store(&store).abandon_in_progress(
            &env.to_string(),
            "aborted: the controller stopped before the episode ended (killed or power cut)",
        )?;
        if abandoned > 0 {
            tracing::warn!(%env, abandoned, "episodes left in progress by the previous run recorded as aborted");
        }
        let link = RobotLink::connect(session, &env, options.timeouts, seals).await?;
        let estops = EnvEStops::follow(session, &env).await?;
        // Spectators' view: a slow one must never stall a step.
        let events = wire::publisher(session, env.key(Topic::Reward), Delivery::Latest).await?;
        let recorder = match record {
            Some(dir) => {
                let sim = env.realm() == offworld_runtime::Realm::Sim;
                let to = RecordTo {
                    dir: dir.to_owned(),
                    // Nothing moves while a sim step waits for the disk.
                    lossless: sim,
                    durable: !sim,
                };
                Some(EnvRecorder::start(session, &env, to).await?)
            }
            None => None,
        };
        Ok(Self {
            recorder,
            env,
            task: Arc::new(task),
            options,
            events,
            session: session.clone(),
            link,
            estops,
            store,
            slots: Mutex::new(None),
            line: Mutex::new(WaitingLine::default()),
            state: AsyncMutex::new(State {
                lease: None,
                maintenance: None,
                revoked: None,
                episode: None,
                sampler: SpawnSampler::new(options.seed),
                seq: 0,
                last_reset: ResetAccuracy::default(),
            }),
            posted: watch::Sender::new(Posted::default()),
            holder: watch::Sender::new(None),
            published: AsyncMutex::new(None),
        })
    }

    /// The env's waiting line (never held across an await).
    fn line(&self) -> std::sync::MutexGuard<'_, WaitingLine> {
        self.line.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The env served.
    pub fn env(&self) -> &EnvId {
        &self.env
    }

    /// The robot link (tests wait on it).
    pub fn link(&self) -> &RobotLink {
        &self.link
    }

    /// The client id of the lease holder, as it changes: its presence
    /// token is the one the controller watches (`alive/client/<id>`).
    pub fn lease_holder(&self) -> watch::Receiver<Option<String>> {
        self.holder.subscribe()
    }

    /// The env's spec.
    pub fn spec(&self) -> EnvSpec {
        EnvSpec {
            env_id: self.env.to_string(),
            task: self.task.name.clone(),
            world: self.task.world.name.clone(),
            action_space: self.task.action_space(),
            native_height: self.task.world.camera.height,
            native_width: self.task.world.camera.width,
            depth_max_m: self.task.episode.depth_max_m,
            max_episode_steps: self.task.episode.max_steps,
        }
    }

    fn store<T>(
        &self,
        f: impl FnOnce(&mut Store) -> Result<T, crate::ControllerError>,
    ) -> Result<T, WireError> {
        f(&mut lock_store(&self.store)).map_err(WireError::from)
    }

    fn state_from(&self, posted: &Posted) -> EnvState {
        if let Some(maintenance) = &posted.maintenance {
            return EnvState::Maintenance {
                message: maintenance.message.clone(),
                by: maintenance.by.clone(),
                back_unix_ms: maintenance.back_unix_ms,
            };
        }
        if !self.link.online() {
            return EnvState::Offline {
                reason: "no robot or sim twin is serving this env".into(),
            };
        }
        match &posted.lease {
            Some(lease) if lease.expires > Instant::now() => EnvState::Leased {
                until_unix_ms: lease.until_unix_ms,
                holder: lease.holder.clone(),
            },
            _ => EnvState::Free,
        }
    }

    fn status_from(&self, posted: &Posted) -> EnvStatus {
        EnvStatus {
            env_id: self.env.to_string(),
            state: self.state_from(posted),
            estop: self.estops.state(),
            last_reset: posted.last_reset,
        }
    }

    fn status_of(&self, state: &State) -> EnvStatus {
        self.status_from(&Posted::of(state))
    }

    /// Current status, without waiting for a request in progress (from
    /// what the state last posted, the robot's presence and the e-stops).
    pub fn status(&self) -> EnvStatus {
        self.status_from(&self.posted.borrow())
    }

    /// Posts the state for `status` and publishes the status if it changed.
    async fn publish_status(&self, state: &mut State) {
        self.posted.send_replace(Posted::of(state));
        let holder = state.lease.as_ref().map(|l| &l.client_id);
        self.holder.send_if_modified(|watched| {
            let changed = watched.as_ref() != holder;
            if changed {
                *watched = holder.cloned();
            }
            changed
        });
        self.refresh_status().await;
    }

    /// Publishes the status if it changed (liveliness of the robot side,
    /// e-stops, a lapsed lease). Never waits for a request in progress (a
    /// real reset takes seconds and the caller also drives the robot's
    /// heartbeat): the status comes from what the state last posted.
    pub async fn refresh_status(&self) {
        let mut published = self.published.lock().await;
        let status = self.status();
        if published.as_ref() == Some(&status) {
            return;
        }
        if let Err(e) = wire::put(&self.session, &self.env.key(Topic::Status), &status).await {
            tracing::warn!("status publish failed: {e}");
        }
        *published = Some(status);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_strategies::{any_text, text};
    use offworld_runtime::ErrorCode;
    use proptest::prelude::*;

    const CHUNK: &[char] = &['A', 'z', 'q', '0', '9', '_', '-'];

    #[test]
    fn site_policy_is_checked() {
        EnvOptions::default().check().expect("defaults are sane");
        for bad in [
            EnvOptions {
                lease_idle: Duration::ZERO,
                ..EnvOptions::default()
            },
            EnvOptions {
                lease_idle: Duration::from_secs(u64::MAX),
                ..EnvOptions::default()
            },
            EnvOptions {
                reconnect_grace: MAX_LEASE_TIMEOUT + Duration::from_secs(1),
                ..EnvOptions::default()
            },
            EnvOptions {
                booking_rules: BookingRules {
                    max_slot_ms: 0,
                    ..BookingRules::default()
                },
                ..EnvOptions::default()
            },
        ] {
            assert!(bad.check().is_err(), "{bad:?}");
        }
        // Far-future lease ends are computed without overflow.
        assert_eq!(unix_ms_in(Duration::MAX), i64::MAX);
    }

    proptest! {
        /// Client ids: empty, or a key chunk the liveliness key can be made
        /// of; anything else is a 400, never a panic.
        #[test]
        fn client_ids(
            good in text(CHUNK, 1..=64),
            any_id in any_text(),
        ) {
            let env = EnvId::sim("a").expect("env");
            prop_assert!(validate_client_id(&env, &good).is_ok());
            prop_assert!(validate_client_id(&env, "").is_ok());
            match validate_client_id(&env, &any_id) {
                Ok(()) => prop_assert!(
                    any_id.is_empty() || env.client_alive_key(&any_id).is_ok()
                ),
                Err(e) => prop_assert_eq!(e.code, ErrorCode::BadRequest),
            }
        }
    }
}
