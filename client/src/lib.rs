//! The OffWorld Gym client library, over the contract
//! (`offworld_runtime`): it knows keys and messages only, so it works
//! against any deployment. Used by the Python package, the CLI, the web
//! page, monitors and the tests.
//!
//! - [`EnvClient`]: open a session on an env, reset, step, close; wait in
//!   an env's line.
//! - [`VecEnvClient`]: several envs stepped at once, with gymnasium's
//!   autoreset.
//! - [`discover`], [`envs_here`]: what a deployment serves.
//! - [`spec`], [`status`], [`leaderboard`], [`book`], [`admin`],
//!   [`experiments`]: one request each, outside a session.
//! - [`open_deployment`], [`whoami`], [`my_bookings`]: a trainer's
//!   requests to a deployment as a whole.
//! - [`operator`]: pressing e-stops and hearing who obeyed.
//! - [`cli`]: the trainer's commands (`offworld gym`, `python -m
//!   offworld_gym`).

use std::time::Duration;

use serde::Serialize;

use offworld_runtime::codec;
use offworld_runtime::keys::{random_id, Component, EnvId, Topic};
use offworld_runtime::msg::{
    Action, ClientTag, CloseReply, CloseRequest, EnvSpec, EnvState, EnvStatus, Leaderboard,
    ObsOptions, OpenReply, OpenRequest, ResetReply, ResetRequest, Seed, StepReply, StepRequest,
};
use offworld_runtime::pool::BufferPool;
use offworld_runtime::wire;
use offworld_runtime::{DecodeError, ErrorCode, WireError};
use zenoh::bytes::ZBytes;
use zenoh::liveliness::LivelinessToken;
use zenoh::Session;

pub mod cli;
mod deployment;
pub mod operator;

pub use deployment::{
    deployment_session, my_bookings, on_deployment, open_deployment, whoami, CONNECT_ENV, TOKEN_ENV,
};

/// Deadlines of client requests.
#[derive(Debug, Clone, Copy)]
pub struct ClientTimeouts {
    /// `open`, `spec`, `close`, `status`.
    pub control: Duration,
    /// `step` (a real action takes up to ~2 s plus the network).
    pub step: Duration,
    /// `reset` (a real reset drives the robot across the enclosure).
    pub reset: Duration,
}

impl Default for ClientTimeouts {
    fn default() -> Self {
        Self {
            control: Duration::from_secs(10),
            step: Duration::from_secs(30),
            reset: Duration::from_secs(120),
        }
    }
}

/// Who this process is to a controller for the requests it sends outside
/// an open session (`spec`, `status`, `leaderboard`, `book`, discovery):
/// one random id per process. An [`EnvClient`] says its own client id.
pub fn process_tag() -> &'static ClientTag {
    static TAG: std::sync::OnceLock<ClientTag> = std::sync::OnceLock::new();
    TAG.get_or_init(|| ClientTag {
        client_id: random_id(),
    })
}

/// How often a client waiting in an env's line asks again
/// ([`EnvClient::open_waiting`]); the controller forgets a waiter that
/// stops asking for a few of these.
pub const WAIT_POLL: Duration = Duration::from_secs(1);

/// [`EnvClient::open_waiting`] waits at most this long (a year).
pub const LONGEST_WAIT: Duration = Duration::from_secs(365 * 86_400);

/// When an `open` is asked again.
struct Retry {
    /// For at most this long.
    within: Duration,
    /// This long after each refusal.
    every: Duration,
    /// After a refusal with one of these codes.
    on: &'static [ErrorCode],
}

/// An open session on one env (holds its lease until closed).
pub struct EnvClient {
    session: Session,
    env: EnvId,
    reply: OpenReply,
    timeouts: ClientTimeouts,
    seq: u64,
    closed: Option<CloseReply>,
    /// This client's id (its liveliness token's), on every request.
    tag: ClientTag,
    /// Where observations are decoded into: see [`EnvClient::observation_buffers`].
    observations: BufferPool,
    /// The observations asked for at `open`.
    obs: ObsOptions,
    _alive: LivelinessToken,
}

impl EnvClient {
    /// Opens a session. `request.client_id` is replaced by a fresh id whose
    /// liveliness token tells the controller this client is alive.
    pub async fn open(
        session: &Session,
        env: &EnvId,
        request: OpenRequest,
        timeouts: ClientTimeouts,
    ) -> Result<Self, WireError> {
        Self::open_waiting(session, env, request, timeouts, Duration::ZERO, |_| {}).await
    }

    /// [`EnvClient::open`], waiting up to `wait` in the env's line while
    /// it is `Busy` (leased or booked by someone else, or held for those
    /// who came first): asks again every [`WAIT_POLL`] with the same client
    /// id (and liveliness token), so the controller keeps its place, and
    /// hands every refusal (a `Busy` says the place) to `on_refusal`. While
    /// waiting, an env that is `Unavailable` (maintenance, robot offline)
    /// or slow to answer (`Timeout`: a real reset holds it) is asked again
    /// too (an `open` that was granted after its reply timed out is
    /// answered with the same lease). The last refusal is returned when
    /// `wait` (at most [`LONGEST_WAIT`]) is over; any other error at once.
    pub async fn open_waiting(
        session: &Session,
        env: &EnvId,
        request: OpenRequest,
        timeouts: ClientTimeouts,
        wait: Duration,
        on_refusal: impl FnMut(&WireError),
    ) -> Result<Self, WireError> {
        let retry = Retry {
            within: wait,
            every: WAIT_POLL,
            on: &[ErrorCode::Busy, ErrorCode::Unavailable, ErrorCode::Timeout],
        };
        Self::open_retrying(session, env, request, timeouts, retry, on_refusal).await
    }

    /// [`EnvClient::open`], asked again (as one client) every 100 ms for up
    /// to `wait` while the deployment is still coming up (the typed "not
    /// yet" answers: `Unavailable`, `NotFound`, `Timeout`). Any other
    /// error, or the last one when `wait` is over, is returned.
    pub async fn open_when_ready(
        session: &Session,
        env: &EnvId,
        request: OpenRequest,
        timeouts: ClientTimeouts,
        wait: Duration,
    ) -> Result<Self, WireError> {
        let retry = Retry {
            within: wait,
            every: Duration::from_millis(100),
            on: &[
                ErrorCode::Unavailable,
                ErrorCode::NotFound,
                ErrorCode::Timeout,
            ],
        };
        Self::open_retrying(session, env, request, timeouts, retry, |_| {}).await
    }

    /// Opens as one client (one id, one liveliness token) however often
    /// `retry` asks again; hands each retried refusal to `on_refusal`.
    async fn open_retrying(
        session: &Session,
        env: &EnvId,
        mut request: OpenRequest,
        timeouts: ClientTimeouts,
        retry: Retry,
        mut on_refusal: impl FnMut(&WireError),
    ) -> Result<Self, WireError> {
        request.client_id = random_id();
        let alive_key = env
            .client_alive_key(&request.client_id)
            .map_err(|e| WireError::bad_request(e.to_string()))?;
        let alive = session
            .liveliness()
            .declare_token(alive_key)
            .await
            .map_err(|e| WireError::internal(format!("zenoh: {e}")))?;
        let tag = ClientTag {
            client_id: request.client_id.clone(),
        };
        // Any wait a person means fits; a larger one would overflow the clock.
        let deadline = tokio::time::Instant::now() + retry.within.min(LONGEST_WAIT);
        let reply: OpenReply = loop {
            let opened = wire::request_as(
                session,
                &env.key(Topic::Open),
                &request,
                timeouts.control,
                &tag,
            )
            .await
            .map_err(wire::RequestError::into_wire);
            match opened {
                Err(e)
                    if retry.on.contains(&e.code)
                        && tokio::time::Instant::now() + retry.every < deadline =>
                {
                    on_refusal(&e);
                    tokio::time::sleep(retry.every).await;
                }
                opened => break opened?,
            }
        };
        Ok(Self {
            session: session.clone(),
            env: env.clone(),
            reply,
            timeouts,
            seq: 0,
            closed: None,
            tag,
            observations: BufferPool::new(),
            obs: request.obs,
            _alive: alive,
        })
    }

    /// The env's spec as returned by `open`.
    pub fn spec(&self) -> &EnvSpec {
        &self.reply.spec
    }

    /// The `open` reply (session id, lease, experiment counters).
    pub fn opened(&self) -> &OpenReply {
        &self.reply
    }

    /// The env.
    pub fn env(&self) -> &EnvId {
        &self.env
    }

    /// Bytes of one observation, as asked for at `open`.
    pub fn observation_len(&self) -> usize {
        usize::try_from(self.obs.shape().shape_len()).unwrap_or(usize::MAX)
    }

    /// The buffers observations are decoded into. Handing a reply's
    /// `observation.data` back ([`BufferPool::recycle`]) once done with it
    /// lets a later reply reuse its memory: without that, every step of a
    /// 320×240 RGBD env allocates, page-faults in and frees 307 KB.
    pub fn observation_buffers(&self) -> &BufferPool {
        &self.observations
    }

    fn ensure_open(&self) -> Result<(), WireError> {
        if self.closed.is_some() {
            return Err(WireError::invalid_state("the env is closed"));
        }
        Ok(())
    }

    /// Starts an episode.
    pub async fn reset(&mut self, seed: Seed) -> Result<ResetReply, WireError> {
        let tail = self.observations.take_empty();
        self.reset_decoded(seed, |reply| codec::decode_payload_tail_into(reply, tail))
            .await
    }

    /// [`EnvClient::reset`] with the observation's pixels written into
    /// `pixels`, which must be [`EnvClient::observation_len`] bytes (the
    /// reply's own `observation.data` is left empty).
    pub async fn reset_into(
        &mut self,
        seed: Seed,
        pixels: &mut [u8],
    ) -> Result<ResetReply, WireError> {
        self.check_fits(pixels)?;
        self.reset_decoded(seed, |reply| codec::decode_payload_tail_to(reply, pixels))
            .await
    }

    /// Refuses, before anything is sent, a buffer of another size than
    /// one observation.
    fn check_fits(&self, pixels: &[u8]) -> Result<(), WireError> {
        if pixels.len() == self.observation_len() {
            return Ok(());
        }
        Err(WireError::bad_request(format!(
            "a buffer of {} bytes for observations of {}",
            pixels.len(),
            self.observation_len()
        )))
    }

    async fn reset_decoded(
        &mut self,
        seed: Seed,
        decode: impl FnOnce(&ZBytes) -> Result<ResetReply, DecodeError>,
    ) -> Result<ResetReply, WireError> {
        self.ensure_open()?;
        let request = ResetRequest {
            session_id: self.reply.session_id.clone(),
            seed,
        };
        self.request(Topic::Reset, &request, self.timeouts.reset, decode)
            .await
    }

    /// Takes one step.
    pub async fn step(&mut self, action: Action) -> Result<StepReply, WireError> {
        let tail = self.observations.take_empty();
        self.step_decoded(action, |reply| codec::decode_payload_tail_into(reply, tail))
            .await
    }

    /// [`EnvClient::step`] with the observation's pixels written into
    /// `pixels`, which must be [`EnvClient::observation_len`] bytes (the
    /// reply's own `observation.data` is left empty): a vector env's
    /// observations land in one batch without another copy.
    pub async fn step_into(
        &mut self,
        action: Action,
        pixels: &mut [u8],
    ) -> Result<StepReply, WireError> {
        self.check_fits(pixels)?;
        self.step_decoded(action, |reply| codec::decode_payload_tail_to(reply, pixels))
            .await
    }

    async fn step_decoded(
        &mut self,
        action: Action,
        decode: impl FnOnce(&ZBytes) -> Result<StepReply, DecodeError>,
    ) -> Result<StepReply, WireError> {
        self.ensure_open()?;
        self.seq += 1;
        let request = StepRequest {
            session_id: self.reply.session_id.clone(),
            seq: self.seq,
            action,
        };
        self.request(Topic::Step, &request, self.timeouts.step, decode)
            .await
    }

    /// Releases the lease; a second call returns the first call's reply.
    pub async fn close(&mut self) -> Result<CloseReply, WireError> {
        if let Some(reply) = &self.closed {
            return Ok(reply.clone());
        }
        let request = CloseRequest {
            session_id: self.reply.session_id.clone(),
        };
        let reply: CloseReply = self
            .request(
                Topic::Close,
                &request,
                self.timeouts.control,
                codec::decode_payload,
            )
            .await?;
        self.closed = Some(reply.clone());
        Ok(reply)
    }

    /// One request of this session on `topic`, its reply read by `decode`.
    async fn request<Req: Serialize, Rep>(
        &self,
        topic: Topic,
        request: &Req,
        timeout: Duration,
        decode: impl FnOnce(&ZBytes) -> Result<Rep, DecodeError>,
    ) -> Result<Rep, WireError> {
        let key = self.env.key(topic);
        wire::request_decoded_as(&self.session, &key, request, timeout, &self.tag, decode)
            .await
            .map_err(|e| self.in_session(e))
    }

    /// A request error within the open session as a typed error. The env
    /// was there: nobody answering now means its controller (or the way to
    /// it) went away, which is transient — the session reconnects by itself
    /// and the lease comes back within the controller's grace period — not
    /// the permanent "no such env" (`NotFound`) that discovery reports.
    fn in_session(&self, e: wire::RequestError) -> WireError {
        match e {
            wire::RequestError::NoResponder(_) => WireError::unavailable(format!(
                "the controller of {} is unreachable (it stopped, restarted or the network to \
                 it is down): retry; the session resumes when it is back",
                self.env
            )),
            e => e.into_wire(),
        }
    }
}

/// One request to an env's queryable from this process (outside a
/// session), every failure as a typed error.
async fn ask<Req: serde::Serialize, Rep: serde::de::DeserializeOwned>(
    session: &Session,
    env: &EnvId,
    topic: Topic,
    request: &Req,
    timeout: Duration,
) -> Result<Rep, WireError> {
    wire::request_as(session, &env.key(topic), request, timeout, process_tag())
        .await
        .map_err(wire::RequestError::into_wire)
}

/// Queries an env's spec without opening a session.
pub async fn spec(session: &Session, env: &EnvId, timeout: Duration) -> Result<EnvSpec, WireError> {
    ask(session, env, Topic::Spec, &(), timeout).await
}

/// Queries an env's availability.
pub async fn status(
    session: &Session,
    env: &EnvId,
    timeout: Duration,
) -> Result<EnvStatus, WireError> {
    ask(session, env, Topic::Status, &(), timeout).await
}

/// Queries an env's leaderboard.
pub async fn leaderboard(
    session: &Session,
    env: &EnvId,
    timeout: Duration,
) -> Result<Leaderboard, WireError> {
    ask(session, env, Topic::Leaderboard, &(), timeout).await
}

/// Makes, lists or cancels bookings of an env.
pub async fn book(
    session: &Session,
    env: &EnvId,
    request: &offworld_runtime::msg::BookingRequest,
    timeout: Duration,
) -> Result<offworld_runtime::msg::Bookings, WireError> {
    ask(session, env, Topic::Book, request, timeout).await
}

/// Asks an env's controller who a token is, or (operators) changes the
/// env's service: maintenance, lease revocation.
pub async fn admin(
    session: &Session,
    env: &EnvId,
    request: &offworld_runtime::msg::AdminRequest,
    timeout: Duration,
) -> Result<offworld_runtime::msg::AdminReply, WireError> {
    ask(session, env, Topic::Admin, request, timeout).await
}

/// Lists an env's experiments or shows one with its episodes.
pub async fn experiments(
    session: &Session,
    env: &EnvId,
    request: &offworld_runtime::msg::ExperimentsRequest,
    timeout: Duration,
) -> Result<offworld_runtime::msg::Experiments, WireError> {
    ask(session, env, Topic::Experiments, request, timeout).await
}

/// Experiment `experiment_id` on `env` with all its episodes (asked for a
/// page at a time), as its owner `token` (or an operator) sees it.
pub async fn experiment_episodes(
    session: &Session,
    env: &EnvId,
    token: &str,
    experiment_id: i64,
    timeout: Duration,
) -> Result<
    (
        offworld_runtime::msg::ExperimentRecord,
        Vec<offworld_runtime::msg::EpisodeRecordEntry>,
    ),
    WireError,
> {
    let mut episodes = Vec::new();
    let mut from_episode = 0;
    loop {
        let request = offworld_runtime::msg::ExperimentsRequest::Show {
            token: token.to_owned(),
            experiment_id,
            from_episode,
        };
        let page = experiments(session, env, &request, timeout).await?;
        let experiment =
            page.experiments.into_iter().next().ok_or_else(|| {
                WireError::internal("the controller answered without the experiment")
            })?;
        let next = page.episodes.last().and_then(|e| e.index.checked_add(1));
        episodes.extend(page.episodes);
        match next {
            // Each page starts after the last: the loop ends.
            Some(next) if page.more && next > from_episode => from_episode = next,
            _ => return Ok((experiment, episodes)),
        }
    }
}

/// One env found by [`discover`].
#[derive(Debug, Clone, PartialEq)]
pub struct EnvListing {
    /// The env.
    pub env: EnvId,
    /// Its task (`MonolithDiscrete`, …); empty when the controller did not
    /// answer `spec`.
    pub task: String,
    /// Availability; `Offline` when no controller is alive for it or it did
    /// not answer.
    pub state: EnvState,
    /// Components alive under the env (`controller`, `sim_twin`,
    /// `robot_agent`, `tracker_agent`, `monitor`), sorted.
    pub components: Vec<String>,
    /// Booked slots in progress or ahead, earliest first (empty when the
    /// controller did not answer).
    pub bookings: Vec<offworld_runtime::msg::Booking>,
    /// The e-stop latches in force as its controller knows them (default,
    /// nothing engaged, when it did not answer).
    pub estop: offworld_runtime::msg::EStopState,
    /// How well its last reset put the robot at its spawn pose (not
    /// measured when the controller did not answer or has not reset it).
    pub last_reset: offworld_runtime::msg::ResetAccuracy,
}

/// Lists the envs reachable through `session`: every env with a liveliness
/// token of a component (controller, twin or agents; a client's or a
/// monitor's only watches it), with its task and availability from
/// its controller's `spec` and `status`. Sorted by env id. Bounded by
/// `timeout` per query; an env whose controller does not answer is listed
/// `Offline`, never dropped. Each listing carries the env's booked slots
/// from now on, so a researcher sees when a real env is reserved.
pub async fn discover(session: &Session, timeout: Duration) -> Result<Vec<EnvListing>, WireError> {
    let replies = session
        .liveliness()
        .get(offworld_runtime::keys::components_alive_selector())
        .timeout(timeout)
        .await
        .map_err(|e| WireError::new(ErrorCode::Unavailable, format!("liveliness query: {e}")))?;
    let mut components: std::collections::BTreeMap<EnvId, std::collections::BTreeSet<String>> =
        Default::default();
    while let Ok(reply) = replies.recv_async().await {
        let Ok(sample) = reply.result() else { continue };
        let key = sample.key_expr().as_str();
        let (Ok(env), Some((_, component))) = (EnvId::from_key(key), key.split_once("/alive/"))
        else {
            continue;
        };
        // Monitors are watchers, not components: an env only watched (an
        // operator's typo in `monitor --env`) is not listed. (Clients'
        // tokens, `alive/client/<id>`, are not asked for.)
        if component != Component::Monitor.as_str() {
            components
                .entry(env)
                .or_default()
                .insert(component.to_owned());
        }
    }
    let listings = components.into_iter().map(|(env, alive)| async move {
        let has_controller = alive.contains(Component::Controller.as_str());
        let (task, state, bookings, estop, last_reset) = if has_controller {
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap_or_default();
            let upcoming = offworld_runtime::msg::BookingRequest::List {
                from_unix_ms: i64::try_from(now.as_millis()).unwrap_or(i64::MAX),
            };
            let (spec, status, booked) = futures::join!(
                spec(session, &env, timeout),
                status(session, &env, timeout),
                book(session, &env, &upcoming, timeout)
            );
            let bookings = booked.map(|b| b.bookings).unwrap_or_default();
            match (spec, status) {
                (Ok(spec), Ok(status)) => (
                    spec.task,
                    status.state,
                    bookings,
                    status.estop,
                    status.last_reset,
                ),
                (_, Err(e)) | (Err(e), _) => (
                    String::new(),
                    EnvState::Offline {
                        reason: format!("the controller does not answer: {}", e.message),
                    },
                    bookings,
                    Default::default(),
                    Default::default(),
                ),
            }
        } else {
            (
                String::new(),
                EnvState::Offline {
                    reason: "no controller serves it".into(),
                },
                Vec::new(),
                Default::default(),
                Default::default(),
            )
        };
        EnvListing {
            env,
            task,
            state,
            components: alive.into_iter().collect(),
            bookings,
            estop,
            last_reset,
        }
    });
    Ok(futures::future::join_all(listings).await)
}

/// [`discover`], looked at again every `interval` until `enough` holds of
/// the listings or `within` has passed; the last listings either way. A
/// session just opened receives the deployment's liveliness tokens over a
/// moment, and envs come up while a client waits for them.
pub async fn discover_until(
    session: &Session,
    timeout: Duration,
    within: Duration,
    interval: Duration,
    enough: impl Fn(&[EnvListing]) -> bool,
) -> Result<Vec<EnvListing>, WireError> {
    let deadline = tokio::time::Instant::now() + within;
    loop {
        let listings = discover(session, timeout).await?;
        if enough(&listings) || tokio::time::Instant::now() >= deadline {
            return Ok(listings);
        }
        tokio::time::sleep(interval).await;
    }
}

/// What an error saying "not found" should add: the envs that *are*
/// reachable through `session` (id, task, state), or that none answered —
/// which, when an env was expected, usually means the endpoint is wrong or
/// nothing runs there.
pub async fn envs_here(session: &Session, timeout: Duration) -> String {
    match discover(session, timeout).await {
        Ok(listings) if listings.is_empty() => {
            "no env answered through this connection: check the endpoint (`--connect`, \
             OFFWORLD_GYM_CONNECT) and that a controller or router runs there"
                .to_owned()
        }
        Ok(listings) => {
            let listed: Vec<String> = listings
                .iter()
                .map(|l| {
                    let state = match &l.state {
                        EnvState::Free => "free",
                        EnvState::Leased { .. } => "leased",
                        EnvState::Maintenance { .. } => "maintenance",
                        EnvState::Offline { .. } => "offline",
                    };
                    if l.task.is_empty() {
                        format!("{} ({state})", l.env)
                    } else {
                        format!("{} ({}, {state})", l.env, l.task)
                    }
                })
                .collect();
            format!("envs reachable here: {}", listed.join(", "))
        }
        Err(e) => format!("the envs reachable here could not be listed: {}", e.message),
    }
}

/// One sub-env's result in a vector step.
#[derive(Debug, Clone)]
pub struct VecStep {
    /// The step's reply (for an autoreset: the reset observation, reward 0,
    /// flags false).
    pub reply: StepReply,
    /// This entry is the reset that followed the previous step's episode end.
    pub autoreset: bool,
}

/// N envs stepped together: every call fans out to all envs at once and
/// waits for all (one round of concurrent requests, not N sequential ones).
/// Gymnasium 1.x "next-step" autoreset: the step after an episode ended
/// resets that env (its action is ignored).
pub struct VecEnvClient {
    envs: Vec<EnvClient>,
    needs_reset: Vec<bool>,
}

impl VecEnvClient {
    /// Wraps opened envs.
    pub fn new(envs: Vec<EnvClient>) -> Self {
        let n = envs.len();
        Self {
            envs,
            needs_reset: vec![false; n],
        }
    }

    /// One env.
    pub fn get(&self, index: usize) -> Option<&EnvClient> {
        self.envs.get(index)
    }

    /// One env, for single-env stepping without autoreset.
    pub fn get_mut(&mut self, index: usize) -> Option<&mut EnvClient> {
        self.envs.get_mut(index)
    }

    /// Number of envs.
    pub fn len(&self) -> usize {
        self.envs.len()
    }

    /// Whether there are no envs.
    pub fn is_empty(&self) -> bool {
        self.envs.is_empty()
    }

    /// The first env's spec (all envs share the task).
    pub fn spec(&self) -> Option<&EnvSpec> {
        self.envs.first().map(EnvClient::spec)
    }

    /// Resets every env (seed `i` for env `i`).
    pub async fn reset(&mut self, seeds: &[Seed]) -> Result<Vec<ResetReply>, WireError> {
        self.reset_each(seeds, None).await
    }

    /// [`VecEnvClient::reset`] with the observations written into `batch`
    /// (see [`VecEnvClient::step_into`]).
    pub async fn reset_into(
        &mut self,
        seeds: &[Seed],
        batch: &mut [u8],
    ) -> Result<Vec<ResetReply>, WireError> {
        self.reset_each(seeds, Some(batch)).await
    }

    async fn reset_each(
        &mut self,
        seeds: &[Seed],
        batch: Option<&mut [u8]>,
    ) -> Result<Vec<ResetReply>, WireError> {
        if seeds.len() != self.envs.len() {
            return Err(WireError::bad_request(format!(
                "{} seeds for {} envs",
                seeds.len(),
                self.envs.len()
            )));
        }
        let slots = self.slots(batch)?;
        let replies = futures::future::join_all(self.envs.iter_mut().zip(seeds).zip(slots).map(
            |((env, seed), slot)| async move {
                match slot {
                    Some(pixels) => env.reset_into(*seed, pixels).await,
                    None => env.reset(*seed).await,
                }
            },
        ))
        .await;
        self.needs_reset.fill(false);
        replies.into_iter().collect()
    }

    /// Steps every env with its action.
    pub async fn step(&mut self, actions: Vec<Action>) -> Result<Vec<VecStep>, WireError> {
        self.step_each(actions, None).await
    }

    /// [`VecEnvClient::step`] with the observations written into `batch`,
    /// env after env, each [`EnvClient::observation_len`] bytes (the
    /// replies' own `observation.data` left empty): one array for all envs
    /// without copying them again.
    pub async fn step_into(
        &mut self,
        actions: Vec<Action>,
        batch: &mut [u8],
    ) -> Result<Vec<VecStep>, WireError> {
        self.step_each(actions, Some(batch)).await
    }

    /// Bytes of all envs' observations together (a batch for the `_into` calls).
    pub fn batch_len(&self) -> usize {
        self.envs.iter().map(EnvClient::observation_len).sum()
    }

    /// `batch` cut into each env's slot, or no slots (each reply keeps its own pixels).
    fn slots<'b>(
        &self,
        batch: Option<&'b mut [u8]>,
    ) -> Result<Vec<Option<&'b mut [u8]>>, WireError> {
        let Some(mut rest) = batch else {
            return Ok(self.envs.iter().map(|_| None).collect());
        };
        if rest.len() != self.batch_len() {
            return Err(WireError::bad_request(format!(
                "a batch of {} bytes for {} bytes of observations",
                rest.len(),
                self.batch_len()
            )));
        }
        let mut slots = Vec::with_capacity(self.envs.len());
        for env in &self.envs {
            let (slot, after) = std::mem::take(&mut rest).split_at_mut(env.observation_len());
            slots.push(Some(slot));
            rest = after;
        }
        Ok(slots)
    }

    async fn step_each(
        &mut self,
        actions: Vec<Action>,
        batch: Option<&mut [u8]>,
    ) -> Result<Vec<VecStep>, WireError> {
        if actions.len() != self.envs.len() {
            return Err(WireError::bad_request(format!(
                "{} actions for {} envs",
                actions.len(),
                self.envs.len()
            )));
        }
        let slots = self.slots(batch)?;
        let work = self
            .envs
            .iter_mut()
            .zip(actions)
            .zip(self.needs_reset.iter().copied())
            .zip(slots)
            .map(|(((env, action), reset), slot)| async move {
                if reset {
                    let r = match slot {
                        Some(pixels) => env.reset_into(Seed::Continue, pixels).await?,
                        None => env.reset(Seed::Continue).await?,
                    };
                    Ok(VecStep {
                        reply: StepReply {
                            seq: 0,
                            observation: r.observation,
                            info: r.info,
                            ..StepReply::default()
                        },
                        autoreset: true,
                    })
                } else {
                    let reply = match slot {
                        Some(pixels) => env.step_into(action, pixels).await?,
                        None => env.step(action).await?,
                    };
                    Ok(VecStep {
                        reply,
                        autoreset: false,
                    })
                }
            });
        let results: Vec<Result<VecStep, WireError>> = futures::future::join_all(work).await;
        let steps: Vec<VecStep> = results.into_iter().collect::<Result<_, _>>()?;
        for (flag, s) in self.needs_reset.iter_mut().zip(&steps) {
            *flag = s.reply.terminated || s.reply.truncated;
        }
        Ok(steps)
    }

    /// Closes every env (idempotent).
    pub async fn close(&mut self) -> Result<(), WireError> {
        let results = futures::future::join_all(self.envs.iter_mut().map(EnvClient::close)).await;
        results.into_iter().try_for_each(|r| r.map(|_| ()))
    }
}
