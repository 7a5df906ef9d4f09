//! One env served: sessions and leases, episodes, and the request handlers
//! behind the `open`/`spec`/`reset`/`step`/`close`/`status`/`admin`/
//! `leaderboard` queryables. Requests to one env are serialised.

use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use offworld_recorder::msg::{EpisodeEnd as RecordedEnd, EpisodeInfo as RecordedEpisode, Step};
use offworld_recorder::{EnvRecorder, RecordTo, StepRecord};
use offworld_runtime::codec::{self, Encoded};
use offworld_runtime::keys::{EnvId, Topic};
use offworld_runtime::msg::{
    AdminReply, AdminRequest, Booking, BookingRequest, Bookings, CloseReply, CloseRequest, EnvSpec,
    EnvState, EnvStatus, EpisodeEvent, EpisodeRecordEntry, ExperimentInfo, ExperimentRecord,
    Experiments, ExperimentsRequest, Header, Leaderboard, MotionCommand, ObsOptions, OpenReply,
    OpenRequest, Pose2D, RecordingFile, ResetAccuracy, ResetReply, ResetRequest, Seed, StepReply,
    StepRequest, Time, Twist, EXPERIMENTS_PER_REPLY, EXPERIMENT_EPISODES_PER_REPLY,
};
use offworld_runtime::wire::{self, Delivery};
use offworld_runtime::WireError;
use rand::Rng;
use tokio::sync::{watch, Mutex as AsyncMutex};
use zenoh::pubsub::Publisher;
use zenoh::query::Query;
use zenoh::Session;

use crate::episode::{judge, step_info, EndReason, Outcome, SpawnSampler};
use crate::estops::EnvEStops;
use crate::link::{
    Answered, LinkSeals, LinkTimeouts, ObservationRequest, ReplyWhereReceived, RobotLink,
};
use crate::observation::{shape, validate_options};
use crate::store::{
    format_unix_ms, lock_store, now_ms, validate_experiment_name, BookingRules, EpisodeRecord,
    SlotAt, Store, User, ANONYMOUS, IN_PROGRESS, LATEST_BOOKABLE_MS,
};
use crate::task::Task;

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
    /// The status last put on `status`; held while putting, so puts go out
    /// in order.
    published: AsyncMutex<Option<EnvStatus>>,
    /// The last booking answer, valid until its `until_ms`: a step never
    /// queries the database. Cleared when this env's bookings change.
    slots: Mutex<Option<SlotAt>>,
    /// Records every episode as an MCAP file, when asked to.
    recorder: Option<EnvRecorder>,
}

fn unix_ms_in(d: Duration) -> i64 {
    now_ms().saturating_add(i64::try_from(d.as_millis()).unwrap_or(i64::MAX))
}

/// Checks the client id of an `open`: empty (no liveliness watch) or one
/// safe key chunk, as `runtime::client` makes them (the liveliness key of
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
        let events = wire::publisher(session, env.key(Topic::Reward), Delivery::Latest)
            .await
            .map_err(|e| crate::ControllerError::Zenoh(e.to_string()))?;
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
            published: AsyncMutex::new(None),
        })
    }

    /// The env served.
    pub fn env(&self) -> &EnvId {
        &self.env
    }

    /// The robot link (tests wait on it).
    pub fn link(&self) -> &RobotLink {
        &self.link
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

    /// The slot in progress at `now` (Unix ms) and its holder's user id.
    fn slot_at(&self, now: i64) -> Result<Option<(Booking, i64)>, WireError> {
        // Only ever replaced whole: a panic cannot leave it half written.
        let mut cache = self.slots.lock().unwrap_or_else(PoisonError::into_inner);
        match cache.as_ref() {
            Some(known) if now < known.until_ms => Ok(known.slot.clone()),
            _ => {
                let env_id = self.env.to_string();
                let fresh = self.store(|s| s.slot_at(&env_id, now))?;
                let slot = fresh.slot.clone();
                *cache = Some(fresh);
                Ok(slot)
            }
        }
    }

    fn forget_slots(&self) {
        *self.slots.lock().unwrap_or_else(PoisonError::into_inner) = None;
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

    fn authenticate(&self, token: &str) -> Result<User, WireError> {
        if token.is_empty() && !self.options.allow_anonymous {
            return Err(WireError::unauthorized(format!(
                "{} needs an access token",
                self.env
            )));
        }
        let user = self.store(|s| s.authenticate(token))?;
        match user {
            Some(u) if u.name == ANONYMOUS && !self.options.allow_anonymous => Err(
                WireError::unauthorized("anonymous access is not allowed here"),
            ),
            Some(u) => Ok(u),
            None => Err(WireError::unauthorized("unknown access token")),
        }
    }

    /// Checks that `session_id` holds the lease and renews it.
    fn holder<'a>(
        &self,
        state: &'a mut State,
        session_id: &str,
    ) -> Result<&'a mut Lease, WireError> {
        let now = Instant::now();
        match state.lease.as_mut() {
            Some(l) if l.session_id == session_id && l.expires > now && !l.disconnected => {
                l.expires = now + self.options.lease_idle;
                l.expires_unix_ms = unix_ms_in(self.options.lease_idle);
                let (expires, until) = (l.expires, l.expires_unix_ms);
                self.posted.send_modify(|p| {
                    if let Some(posted) = p.lease.as_mut() {
                        (posted.expires, posted.until_unix_ms) = (expires, until);
                    }
                });
                Ok(l)
            }
            Some(l) if l.session_id == session_id => Err(WireError::unauthorized(
                "your lease expired; open the env again to continue",
            )),
            _ => match &state.revoked {
                Some(revoked) if revoked.session_id == session_id => {
                    Err(WireError::unauthorized(revoked.reason.clone()))
                }
                _ => Err(WireError::unauthorized(
                    "this session does not hold the env's lease",
                )),
            },
        }
    }

    /// `open`: authenticate, take the lease, create or resume the experiment.
    pub async fn open(&self, req: OpenRequest) -> Result<OpenReply, WireError> {
        // Every input checked before any lock is taken.
        validate_options(&req.obs)?;
        validate_client_id(&self.env, &req.client_id)?;
        let name = if req.experiment_name.is_empty() {
            format!("run-{}", now_ms())
        } else {
            req.experiment_name.clone()
        };
        validate_experiment_name(&name)?;
        let user = self.authenticate(&req.token)?;
        let mut state = self.state.lock().await;
        if let Some(maintenance) = &state.maintenance {
            return Err(maintenance.refusal(&self.env));
        }
        if !self.link.online() {
            return Err(WireError::unavailable(format!(
                "{} is offline: no robot or sim twin",
                self.env
            )));
        }
        let now = Instant::now();
        let env_id = self.env.to_string();
        let slot = self.slot_at(now_ms())?;
        let booked_until_unix_ms = match &slot {
            Some((booking, holder)) if *holder != user.id => {
                return Err(WireError::busy(format!(
                    "{} is booked by {} until {}",
                    self.env,
                    booking.user,
                    format_unix_ms(booking.end_unix_ms)
                )));
            }
            Some((booking, _)) => Some(booking.end_unix_ms),
            None => None,
        };
        if let Some(lease) = &state.lease {
            let live = lease.expires > now;
            // A slot's holder takes the lease over from a first-come user.
            if live && lease.user.id != user.id && booked_until_unix_ms.is_some() {
                tracing::info!(env = %self.env, user = %user.name, "booked slot: lease taken over");
            } else if live && lease.user.id != user.id {
                return Err(WireError::busy(format!(
                    "{} is leased by another user until {}",
                    self.env,
                    format_unix_ms(lease.expires_unix_ms)
                )));
            }
            if live && lease.user.id == user.id && user.name == ANONYMOUS && !lease.disconnected {
                return Err(WireError::busy(format!(
                    "{} is in use by another anonymous session until {}",
                    self.env,
                    format_unix_ms(lease.expires_unix_ms)
                )));
            }
        }
        // The same user reconnecting takes the lease over; the old
        // session's unfinished episode is recorded as aborted.
        self.abort_episode(&mut state, "session replaced").await;
        let experiment = self.store(|s| {
            s.open_experiment(
                &user,
                &env_id,
                &self.task.name,
                &name,
                req.resume_experiment,
                req.learning_type,
                req.algorithm_mode,
            )
        })?;
        let session_id: String = {
            let mut rng = rand::rng();
            (0..24)
                .map(|_| format!("{:x}", rng.random_range(0..16u8)))
                .collect()
        };
        let lease_until_unix_ms = unix_ms_in(self.options.lease_idle);
        tracing::info!(env = %self.env, user = %user.name, experiment = %experiment.name, "lease granted");
        let info = experiment_info(&experiment);
        state.lease = Some(Lease {
            session_id: session_id.clone(),
            client_id: req.client_id.clone(),
            user,
            experiment,
            obs: req.obs,
            expires: now + self.options.lease_idle,
            expires_unix_ms: lease_until_unix_ms,
            disconnected: false,
            booked_until_unix_ms,
        });
        state.episode = None;
        self.publish_status(&mut state).await;
        Ok(OpenReply {
            session_id,
            lease_until_unix_ms,
            spec: self.spec(),
            experiment: info,
        })
    }

    /// `reset`: spawn (seeded), move the robot there, observe.
    pub async fn reset(&self, req: ResetRequest) -> Result<Encoded<ResetReply>, WireError> {
        let began = Instant::now();
        let mut state = self.state.lock().await;
        self.enforce_slots(&mut state, &req.session_id).await?;
        self.holder(&mut state, &req.session_id)?;
        if let Some(maintenance) = &state.maintenance {
            return Err(maintenance.refusal(&self.env));
        }
        if let Err(refused) = self.estops.refuse_motion() {
            self.abort_episode(&mut state, &refused.message).await;
            return Err(refused);
        }
        self.abort_episode(&mut state, "reset before the episode ended")
            .await;
        let seed = match req.seed {
            Seed::Fixed(s) => {
                state.sampler.reseed(s);
                Some(s)
            }
            Seed::Continue => None,
        };
        let target = state
            .sampler
            .sample(&self.task)
            .ok_or_else(|| WireError::internal("no valid spawn pose in this world"))?;
        state.seq += 1;
        let arrived = self.link.goto(state.seq, target).await?;
        state.seq += 1;
        let observe = MotionCommand {
            seq: state.seq,
            linear_x: 0.0,
            angular_z: 0.0,
            duration_s: 0.0,
        };
        let obs = self.holder(&mut state, &req.session_id)?.obs;
        let answer = self
            .link
            .execute(&observe, self.observation_request(obs), None)
            .await?;
        let frame = answer.frame();
        let answered = answer.complete().await?;
        let lease = self.holder(&mut state, &req.session_id)?;
        let index = lease.experiment.episodes;
        let experiment = (lease.experiment.name.clone(), lease.experiment.id);
        let recorded = self.recorder.is_some().then(|| RecordedEpisode {
            header: Header::new(Time::now(), "world"),
            env_id: self.env.to_string(),
            task: self.task.name.clone(),
            world: self.task.world.name.clone(),
            experiment_id: u64::try_from(lease.experiment.id).unwrap_or_default(),
            experiment: lease.experiment.name.clone(),
            learning_type: lease.experiment.learning_type.clone(),
            algorithm_mode: lease.experiment.algorithm_mode.clone(),
            episode_id: index,
            seeded: seed.is_some(),
            seed: seed.unwrap_or_default(),
            embodiment: match self.env.realm() {
                offworld_runtime::Realm::Sim => "twin",
                offworld_runtime::Realm::Real => "robot",
            }
            .to_owned(),
            software_version: env!("CARGO_PKG_VERSION").to_owned(),
            max_episode_steps: self.task.episode.max_steps,
            requested_start: [target.x, target.y, target.yaw],
        });
        let achieved = answered.pose().planar();
        let accuracy =
            ResetAccuracy::measure(target, achieved, began.elapsed().as_secs_f64(), now_ms());
        tracing::debug!(env = %self.env, ?target, reached = ?arrived.achieved, ?accuracy, "reset");
        let episode = Episode {
            index,
            seed,
            steps: 0,
            episode_return: 0.0,
            over: false,
            reset: accuracy,
            started_ms: accuracy.unix_ms,
            saved: Instant::now(),
        };
        // On record from its first moment: a controller killed mid-episode
        // leaves it, closed as aborted at the next start.
        let started = episode.record(lease.experiment.id, None, episode.started_ms);
        lock_store(&self.store)
            .begin_episode(&started)
            .map_err(WireError::from)?;
        lease.experiment.episodes += 1;
        state.episode = Some(episode);
        state.last_reset = accuracy;
        self.publish_status(&mut state).await;
        let event = episode_event(&experiment, index, 0, observe.seq, None, 0.0);
        if let (Some(recorder), Some(info)) = (&self.recorder, recorded) {
            // How well the reset placed the robot, with the episode
            // (`parity replay` reports it).
            // (The achieved pose is the reset step's recorded pose.)
            let notes = std::collections::BTreeMap::from([(
                offworld_recorder::episode_file::RESET_DURATION_NOTE.to_owned(),
                format!("{:.6}", accuracy.duration_s),
            )]);
            recorder.begin_annotated(info, notes).await;
            let step = Step::from_event(&event, None, None);
            self.record_step(frame, &answered, step, None).await;
        }
        let reply = ResetReply {
            info: step_info(&self.task, index, 0, &achieved, None, self.shares_pose()),
            observation: shape(&obs),
        };
        let reply = with_observation(&reply, answered)?
            .ok_or_else(|| WireError::internal("a reset was replied where its frame arrived"))?;
        self.publish_event(&event).await;
        Ok(reply)
    }

    /// Whether `info` carries the robot's ground truth (see
    /// [`EnvOptions::share_real_pose`]).
    fn shares_pose(&self) -> bool {
        self.env.realm() == offworld_runtime::Realm::Sim || self.options.share_real_pose
    }

    /// What to build from the frames answering the lease holder's commands.
    fn observation_request(&self, options: ObsOptions) -> ObservationRequest {
        ObservationRequest {
            options,
            depth_max_m: self.task.episode.depth_max_m,
        }
    }

    /// `step`: act, observe, judge. Given its `query`, the reply is sent
    /// from where the robot's answer is received when it can be (not for
    /// an episode's last step, which is recorded first), and this returns
    /// `None`; otherwise the reply to send.
    pub async fn step(
        &self,
        req: StepRequest,
        query: Option<Query>,
    ) -> Result<Option<Encoded<StepReply>>, WireError> {
        let mut state = self.state.lock().await;
        self.enforce_slots(&mut state, &req.session_id).await?;
        let lease = self.holder(&mut state, &req.session_id)?;
        let obs = lease.obs;
        let experiment = (lease.experiment.name.clone(), lease.experiment.id);
        if let Some(maintenance) = &state.maintenance {
            return Err(maintenance.refusal(&self.env));
        }
        if let Err(refused) = self.estops.refuse_motion() {
            // Whatever stopped the robot may have moved it: the episode
            // cannot go on from here.
            self.abort_episode(&mut state, &refused.message).await;
            return Err(refused);
        }
        let (index, step) = match &state.episode {
            None => return Err(WireError::invalid_state("call reset() before step()")),
            Some(e) if e.over => {
                return Err(WireError::invalid_state(
                    "the episode has ended; call reset()",
                ))
            }
            Some(e) => (e.index, e.steps + 1),
        };
        let motion = self.task.motion(&req.action, state.seq + 1)?;
        state.seq += 1;
        let request = self.observation_request(obs);
        let judged = JudgedStep {
            task: self.task.clone(),
            share_pose: self.shares_pose(),
            seq: req.seq,
            episode_id: index,
            step,
            obs,
        };
        let reply_here = query.map(|query| judged.clone().reply_where_received(query));
        let commanded_at = Time::now();
        let mut frame = None;
        let answered = match self.link.execute(&motion, request, reply_here).await {
            Ok(answer) => {
                frame = answer.frame();
                answer.complete().await
            }
            Err(e) => Err(e),
        };
        let answered = match answered {
            Ok(a) => a,
            Err(e) => {
                // The step cannot be scored, so neither can the episode (a
                // robot that did not answer has been stopped by the link).
                self.abort_episode(&mut state, &format!("aborted: {}", e.message))
                    .await;
                // An e-stop that cut the motion short is the reason to
                // report, whichever message arrived first.
                return Err(self.estops.refuse_motion().err().unwrap_or(e));
            }
        };
        let (outcome, reply) = judged.judge(&answered.pose().planar());
        let Some(episode) = state.episode.as_mut() else {
            return Err(WireError::internal("episode vanished"));
        };
        episode.steps = step;
        episode.episode_return += outcome.reward;
        let (steps, ret) = (episode.steps, episode.episode_return);
        let event = episode_event(&experiment, index, steps, motion.seq, Some(&outcome), ret);
        if self.recorder.is_some() {
            let recorded = Step::from_event(&event, Some(&req.action), Some(&motion));
            let command = Twist::planar(motion.linear_x, motion.angular_z);
            self.record_step(frame, &answered, recorded, Some((command, commanded_at)))
                .await;
        }
        let reply = with_observation(&reply, answered)?;
        self.publish_event(&event).await;
        match &outcome.end {
            Some(end) => self.finish_episode(&mut state, end).await?,
            None => self.save_progress(&mut state),
        }
        Ok(reply)
    }

    /// `close`: record, release the lease.
    pub async fn close(&self, req: CloseRequest) -> Result<CloseReply, WireError> {
        let mut state = self.state.lock().await;
        self.holder(&mut state, &req.session_id)?;
        self.abort_episode(&mut state, "closed").await;
        if let Some(recorder) = &self.recorder {
            // A client that closed its env finds its episodes complete.
            recorder.caught_up().await;
        }
        let lease = state
            .lease
            .take()
            .ok_or_else(|| WireError::internal("lease vanished"))?;
        tracing::info!(env = %self.env, user = %lease.user.name, "lease released");
        self.publish_status(&mut state).await;
        Ok(CloseReply {
            experiment: experiment_info(&lease.experiment),
        })
    }

    /// `admin`: who a token is (anyone's); operators put the env into or
    /// out of maintenance and revoke its lease.
    pub async fn admin(&self, req: AdminRequest) -> Result<AdminReply, WireError> {
        let user = self
            .store(|s| s.authenticate(req.token()))?
            .filter(|u| u.name != ANONYMOUS)
            .ok_or_else(|| WireError::unauthorized("unknown access token"))?;
        let reply = |status| AdminReply {
            user: user.name.clone(),
            operator: user.is_operator(),
            status,
        };
        if let AdminRequest::Identify { .. } = req {
            return Ok(reply(self.status()));
        }
        if !user.is_operator() {
            return Err(WireError::unauthorized(format!(
                "{} is not an operator: only operators change an env's service",
                user.name
            )));
        }
        let mut state = self.state.lock().await;
        match req {
            AdminRequest::SetMaintenance {
                message,
                back_unix_ms,
                ..
            } => {
                validate_operator_text("maintenance message", &message)?;
                if back_unix_ms > LATEST_BOOKABLE_MS {
                    return Err(WireError::bad_request(format!(
                        "the expected return {back_unix_ms} is not a date (Unix ms up to year 9999)"
                    )));
                }
                tracing::warn!(env = %self.env, %message, by = %user.name, "maintenance on");
                self.link.stop().await;
                self.abort_episode(&mut state, "maintenance").await;
                // The lease ends with it: its holder is told why at their
                // next request, and nobody holds the env through it.
                state.episode = None;
                if let Some(lease) = state.lease.take() {
                    state.revoked = Some(Revoked {
                        session_id: lease.session_id,
                        reason: format!(
                            "{} went into maintenance ({message}); your lease ended with it",
                            self.env
                        ),
                    });
                }
                state.maintenance = Some(Maintenance {
                    message,
                    by: user.name.clone(),
                    back_unix_ms: back_unix_ms.max(0),
                });
            }
            AdminRequest::ClearMaintenance { .. } => {
                tracing::warn!(env = %self.env, by = %user.name, "maintenance off");
                state.maintenance = None;
            }
            AdminRequest::RevokeLease { reason, .. } => {
                validate_operator_text("reason", &reason)?;
                if state.lease.is_none() {
                    return Err(WireError::not_found(format!(
                        "{} has no lease to revoke",
                        self.env
                    )));
                }
                self.link.stop().await;
                // Recorded while the lease (its experiment) is still known.
                self.abort_episode(&mut state, "lease revoked").await;
                state.episode = None;
                let Some(lease) = state.lease.take() else {
                    return Err(WireError::internal("lease vanished"));
                };
                tracing::warn!(env = %self.env, holder = %lease.user.name, by = %user.name, %reason, "lease revoked");
                state.revoked = Some(Revoked {
                    session_id: lease.session_id,
                    reason: format!(
                        "your lease on {} was revoked by the operator {}: {reason}",
                        self.env, user.name
                    ),
                });
            }
            AdminRequest::Identify { .. } => {}
        }
        self.publish_status(&mut state).await;
        Ok(reply(self.status_of(&state)))
    }

    /// Ends the lease of `session_id` when its booked slot is over or
    /// someone else's slot began: the robot stops, the episode is recorded
    /// as aborted, and the caller learns why (401).
    async fn enforce_slots(&self, state: &mut State, session_id: &str) -> Result<(), WireError> {
        let Some(lease) = state.lease.as_ref().filter(|l| l.session_id == session_id) else {
            return Ok(());
        };
        let now = now_ms();
        let reason = match lease.booked_until_unix_ms {
            Some(end) if now >= end => Some(format!(
                "your booked slot on {} ended at {}; the lease ended with it",
                self.env,
                format_unix_ms(end)
            )),
            _ => match self.slot_at(now)? {
                Some((booking, holder)) if holder != lease.user.id => Some(format!(
                    "{} is booked by {} from {} to {}; your lease ended",
                    self.env,
                    booking.user,
                    format_unix_ms(booking.start_unix_ms),
                    format_unix_ms(booking.end_unix_ms)
                )),
                _ => None,
            },
        };
        let Some(reason) = reason else {
            return Ok(());
        };
        tracing::info!(env = %self.env, %reason, "lease ended by a booking");
        self.link.stop().await;
        self.abort_episode(state, "booked slot ended").await;
        state.lease = None;
        state.episode = None;
        self.publish_status(state).await;
        Err(WireError::unauthorized(reason))
    }

    /// `book`: make, list or cancel slots.
    pub fn book(&self, req: BookingRequest) -> Result<Bookings, WireError> {
        let env_id = self.env.to_string();
        match req {
            BookingRequest::Make {
                token,
                start_unix_ms,
                end_unix_ms,
            } => {
                let user = self.authenticate(&token)?;
                let rules = self.options.booking_rules;
                // Checked here, before the store is locked (and again by
                // the store, which clamps the start to its own `now`).
                let now = now_ms();
                rules
                    .validate(start_unix_ms, end_unix_ms, now)
                    .map_err(|e| WireError::from(crate::ControllerError::from(e)))?;
                let booking =
                    self.store(|s| s.book(&user, &env_id, start_unix_ms, end_unix_ms, now, rules))?;
                self.forget_slots();
                tracing::info!(env = %self.env, user = %user.name, id = booking.id, "slot booked");
                Ok(Bookings {
                    bookings: vec![booking],
                })
            }
            BookingRequest::List { from_unix_ms } => Ok(Bookings {
                bookings: self.store(|s| s.bookings(&env_id, from_unix_ms))?,
            }),
            BookingRequest::Cancel { token, id } => {
                let user = self.authenticate(&token)?;
                self.store(|s| s.cancel_booking(&user, &env_id, id))?;
                self.forget_slots();
                Ok(Bookings {
                    bookings: self.store(|s| s.bookings(&env_id, now_ms()))?,
                })
            }
        }
    }

    /// `experiments`: the caller's experiments on this env (operators:
    /// everyone's), or one of them with its episodes and recordings. Another
    /// user's experiment is answered as not found, like one that does not exist.
    pub async fn experiments(&self, req: ExperimentsRequest) -> Result<Experiments, WireError> {
        let env_id = self.env.to_string();
        match req {
            ExperimentsRequest::List { token } => {
                let user = self.authenticate(&token)?;
                let owner = (!user.is_operator()).then_some(&user);
                let mut experiments = self.store(|s| s.experiments_on(&env_id, owner))?;
                experiments.truncate(EXPERIMENTS_PER_REPLY as usize);
                Ok(Experiments {
                    experiments,
                    episodes: Vec::new(),
                    more: false,
                })
            }
            ExperimentsRequest::Show {
                token,
                experiment_id,
                from_episode,
            } => {
                let user = self.authenticate(&token)?;
                let not_found = || {
                    WireError::not_found(format!(
                        "no experiment {experiment_id} of yours on {env_id}"
                    ))
                };
                let experiment = self
                    .store(|s| s.experiment_by_id(experiment_id))?
                    .filter(|e| e.env_id == env_id && (user.is_operator() || e.user == user.name))
                    .ok_or_else(not_found)?;
                // One more than a page tells whether another follows.
                let mut episodes = self.store(|s| {
                    s.episodes_from(
                        experiment_id,
                        from_episode,
                        EXPERIMENT_EPISODES_PER_REPLY + 1,
                    )
                })?;
                let more = episodes.len() > EXPERIMENT_EPISODES_PER_REPLY as usize;
                episodes.truncate(EXPERIMENT_EPISODES_PER_REPLY as usize);
                self.attach_recordings(experiment_id, &mut episodes).await;
                Ok(Experiments {
                    experiments: vec![experiment],
                    episodes,
                    more,
                })
            }
        }
    }

    /// Lists each episode's files, when this env records. A directory that
    /// cannot be read leaves the episodes without files (and says so in the
    /// log): the store's record is still worth answering.
    async fn attach_recordings(&self, experiment_id: i64, episodes: &mut [EpisodeRecordEntry]) {
        let Some(recorder) = &self.recorder else {
            return;
        };
        // The files match what the client did: the episodes it ended are
        // finished, the one it began exists.
        recorder.caught_up().await;
        let files = match recorder
            .destination()
            .experiment_files(&self.env, u64::try_from(experiment_id).unwrap_or_default())
        {
            Ok(files) => files,
            Err(e) => {
                tracing::warn!(env = %self.env, experiment_id, "cannot list recordings: {e}");
                return;
            }
        };
        for file in files {
            let Ok(at) = episodes.binary_search_by_key(&file.episode_id, |e| e.index) else {
                continue;
            };
            let path = file
                .relative_path
                .iter()
                .map(|part| part.to_string_lossy())
                .collect::<Vec<_>>()
                .join("/");
            episodes[at].recordings.push(RecordingFile {
                path,
                bytes: file.bytes,
                complete: file.complete,
            });
        }
    }

    /// `leaderboard`: test-mode experiments ranked.
    pub fn leaderboard(&self) -> Result<Leaderboard, WireError> {
        let env_id = self.env.to_string();
        let entries = self.store(|s| s.leaderboard(&env_id))?;
        Ok(Leaderboard { env_id, entries })
    }

    /// The holder's client vanished: stop the robot, record the episode as
    /// aborted, keep the lease for the reconnect grace period.
    pub async fn client_disconnected(&self, client_id: &str) {
        let mut state = self.state.lock().await;
        let holder = state
            .lease
            .as_ref()
            .is_some_and(|l| l.client_id == client_id && !l.disconnected);
        if !holder {
            return;
        }
        tracing::warn!(env = %self.env, client_id, "lease holder disconnected; robot stopped");
        self.link.stop().await;
        self.abort_episode(&mut state, "client disconnected").await;
        if let Some(lease) = state.lease.as_mut() {
            lease.disconnected = true;
            lease.expires = Instant::now() + self.options.reconnect_grace;
            lease.expires_unix_ms = unix_ms_in(self.options.reconnect_grace);
        }
        self.publish_status(&mut state).await;
    }

    /// The holder's client is back (its liveliness token reappeared, e.g.
    /// after a network flap or a router restart) within the grace period:
    /// the lease is theirs again. The interrupted episode stays aborted; the
    /// client goes on with `reset()` without opening the env again.
    pub async fn client_reconnected(&self, client_id: &str) {
        let mut state = self.state.lock().await;
        let now = Instant::now();
        let Some(lease) = state
            .lease
            .as_mut()
            .filter(|l| l.client_id == client_id && l.disconnected && l.expires > now)
        else {
            return;
        };
        tracing::info!(env = %self.env, client_id, "lease holder reconnected; lease restored");
        lease.disconnected = false;
        lease.expires = now + self.options.lease_idle;
        lease.expires_unix_ms = unix_ms_in(self.options.lease_idle);
        self.publish_status(&mut state).await;
    }

    /// Records an unfinished episode as ended for `reason`.
    /// Stops the robot and records the episode in progress as aborted
    /// (the controller is stopping).
    pub async fn stop_and_record(&self, reason: &str) {
        self.link.close();
        self.link.stop().await;
        let mut state = self.state.lock().await;
        self.abort_episode(&mut state, reason).await;
    }

    async fn abort_episode(&self, state: &mut State, reason: &str) {
        let running = state.episode.as_ref().is_some_and(|e| !e.over);
        if running {
            let end = EndReason::Aborted(reason.to_owned());
            if let Err(e) = self.finish_episode(state, &end).await {
                tracing::error!(env = %self.env, "could not record the aborted episode: {}", e.message);
            }
        }
    }

    /// Saves the running episode's progress when [`PROGRESS_EVERY`] has
    /// passed since the last save (a failure is logged: the step stands).
    fn save_progress(&self, state: &mut State) {
        let (Some(episode), Some(lease)) = (state.episode.as_mut(), state.lease.as_ref()) else {
            return;
        };
        if episode.over || episode.saved.elapsed() < PROGRESS_EVERY {
            return;
        }
        episode.saved = Instant::now();
        let record = episode.record(lease.experiment.id, None, now_ms());
        if let Err(e) = lock_store(&self.store).progress_episode(&record) {
            tracing::error!(env = %self.env, "could not save the episode's progress: {e}");
        }
    }

    async fn finish_episode(&self, state: &mut State, end: &EndReason) -> Result<(), WireError> {
        let (Some(episode), Some(lease)) = (state.episode.as_mut(), state.lease.as_mut()) else {
            return Ok(());
        };
        episode.over = true;
        let record = episode.record(lease.experiment.id, Some(end), now_ms());
        // The recording ends whether or not the database takes the record.
        if let Some(recorder) = &self.recorder {
            recorder
                .end(RecordedEnd {
                    header: Header::new(Time::now(), "world"),
                    episode_id: episode.index,
                    steps: episode.steps,
                    episode_return: episode.episode_return,
                    success: record.success,
                    terminated: matches!(end, EndReason::Success | EndReason::OutOfBounds),
                    truncated: *end == EndReason::StepLimit,
                    end_reason: end.as_str().to_owned(),
                })
                .await;
        }
        lock_store(&self.store)
            .record_episode(&record)
            .map_err(WireError::from)?;
        lease.experiment.steps += u64::from(episode.steps);
        Ok(())
    }

    /// Hands a step to the recorder (which stamps it with its frame's
    /// capture time), when recording and its frame is at hand.
    async fn record_step(
        &self,
        frame: Option<Arc<crate::link::Frame>>,
        answered: &Answered,
        step: Step,
        command: Option<(Twist, Time)>,
    ) {
        let (Some(recorder), Some(frame)) = (&self.recorder, frame) else {
            return;
        };
        recorder
            .step(StepRecord {
                step,
                frame: frame.payload().clone(),
                pose: answered.pose().pose.clone(),
                command,
            })
            .await;
    }

    /// Publishes a step's (or a reset's) event for spectators, monitors
    /// and subscriber-side recorders.
    async fn publish_event(&self, event: &EpisodeEvent) {
        if let Err(e) = wire::publish(&self.events, event) {
            tracing::warn!("reward publish failed: {e}");
        }
    }
}

/// The event of step `step` of episode `episode_id` in `experiment` (name,
/// id), answered by the frame of command `command_seq`: the reset when
/// `outcome` is `None`. The recorded `Step` is built from it
/// ([`Step::from_event`]), so both say the same.
fn episode_event(
    experiment: &(String, i64),
    episode_id: u64,
    step: u32,
    command_seq: u64,
    outcome: Option<&Outcome>,
    episode_return: f64,
) -> EpisodeEvent {
    let end = outcome.and_then(|o| o.end.as_ref());
    EpisodeEvent {
        experiment: experiment.0.clone(),
        episode_id,
        step,
        reward: outcome.map_or(0.0, |o| o.reward),
        episode_return,
        terminated: outcome.is_some_and(|o| o.terminated),
        truncated: outcome.is_some_and(|o| o.truncated),
        success: end == Some(&EndReason::Success),
        end_reason: end.map(|e| e.as_str().to_owned()).unwrap_or_default(),
        experiment_id: experiment.1,
        command_seq,
    }
}

/// Encodes `reply` with the observation as its last field; `None` if the
/// reply was already sent where the frame was received.
fn with_observation<T: serde::Serialize>(
    reply: &T,
    answered: Answered,
) -> Result<Option<Encoded<T>>, WireError> {
    match answered {
        Answered::Observation { data, .. } => codec::encode_with_tail(reply, data)
            .map(Some)
            .map_err(|e| WireError::internal(e.to_string())),
        Answered::Replied { .. } => Ok(None),
    }
}

/// What a step's reply says, given the pose it reached: one definition for
/// the reply sent from the step's task and the one sent where its frame is
/// received.
#[derive(Clone)]
struct JudgedStep {
    task: Arc<Task>,
    /// The client's request number.
    seq: u64,
    episode_id: u64,
    /// This step's number in the episode (1-based).
    step: u32,
    obs: ObsOptions,
    /// Whether `info` carries the robot's ground truth.
    share_pose: bool,
}

impl JudgedStep {
    fn judge(&self, pose: &Pose2D) -> (Outcome, StepReply) {
        let outcome = judge(&self.task, pose.x, pose.y, self.step);
        let info = step_info(
            &self.task,
            self.episode_id,
            self.step,
            pose,
            Some(&outcome),
            self.share_pose,
        );
        let reply = StepReply {
            seq: self.seq,
            reward: outcome.reward,
            terminated: outcome.terminated,
            truncated: outcome.truncated,
            info,
            observation: shape(&self.obs),
        };
        (outcome, reply)
    }

    /// Replies to `query` where the frame is received, unless the episode
    /// ends (its record is written before the reply).
    fn reply_where_received(self, query: Query) -> ReplyWhereReceived {
        Box::new(move |pose, data| {
            let (outcome, reply) = self.judge(&pose.planar());
            if outcome.end.is_some() {
                return Err(data);
            }
            match codec::encode_with_tail(&reply, data.clone()) {
                Ok(encoded) => {
                    if let Err(e) = wire::reply_encoded_now(&query, Ok(encoded)) {
                        tracing::warn!(key = %query.key_expr(), "step reply failed: {e}");
                    }
                    Ok(())
                }
                Err(_) => Err(data),
            }
        })
    }
}

fn experiment_info(e: &ExperimentRecord) -> ExperimentInfo {
    ExperimentInfo {
        id: e.id,
        name: e.name.clone(),
        episodes: e.episodes,
        steps: e.steps,
    }
}

/// Longest operator message (maintenance, revocation reason), characters.
pub const MAX_OPERATOR_TEXT: usize = 500;

/// An operator's `what`: 1 to [`MAX_OPERATOR_TEXT`] characters, no control
/// characters (it is shown on pages and in logs).
fn validate_operator_text(what: &str, text: &str) -> Result<(), WireError> {
    let bad = |why: String| Err(WireError::bad_request(why));
    if text.trim().is_empty() {
        return bad(format!("the {what} must say something"));
    }
    if text.chars().take(MAX_OPERATOR_TEXT + 1).count() > MAX_OPERATOR_TEXT {
        return bad(format!("the {what} is over {MAX_OPERATOR_TEXT} characters"));
    }
    if text.chars().any(char::is_control) {
        return bad(format!("the {what} holds a control character"));
    }
    Ok(())
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
