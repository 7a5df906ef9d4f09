//! The controller: serves any number of envs from one process on one Zenoh
//! session. Per env: its queryables, a watcher of client liveliness tokens,
//! a heartbeat for the robot's watchdog, and status publication.
//!
//! A query is taken in Zenoh's callback, which never waits for a worker:
//! there it is admitted ([`crate::admission`]: size, client rate, a place
//! in the env's bounded queue) or refused at once (`BadRequest`, `Busy`);
//! `status` and `spec` are answered there and then from a snapshot. An
//! admitted request runs on its own task (requests to an env are
//! serialised by its state lock), except that a sim env's step starts in
//! the callback and goes to a task when woken after its first wait,
//! usually for its frame (`start`). A handler that panics (a bug) answers
//! `Internal` and serving goes on ([`answer_supervised`]).

use std::any::Any;
use std::future::Future;
use std::panic::AssertUnwindSafe;
use std::pin::{pin, Pin};
use std::sync::{Arc, Mutex};
use std::task::Poll;
use std::time::Duration;

use offworld_runtime::codec::Encoded;
use offworld_runtime::keys::{Component, EnvId, Realm, Topic};
use offworld_runtime::msg::{
    AdminRequest, BookingRequest, CloseRequest, ExperimentsRequest, Heartbeat, OpenRequest,
    ResetRequest, StepRequest, Time,
};
use offworld_runtime::{wire, WireError};
use tokio::sync::watch;
use tokio::task::JoinHandle;
use zenoh::handlers::FifoChannelHandler;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Sample, SampleKind};
use zenoh::Session;

use crate::admission::{self, ClientRates, Gate, RequestLimits};
use crate::env::{EnvOptions, EnvServer};
use crate::error::ControllerError;
use crate::link::LinkSeals;
use crate::start::start_here;
use crate::store::Store;
use crate::task::Task;

/// How often the controller's heartbeat reaches each robot.
pub const HEARTBEAT_PERIOD: Duration = Duration::from_millis(50);

/// A running controller; stops serving when dropped.
pub struct Controller {
    session: Session,
    store: Arc<Mutex<Store>>,
    envs: Vec<ServedEnv>,
    limits: RequestLimits,
    rates: Arc<ClientRates>,
    seals: LinkSeals,
    /// Where episodes are recorded (`docs/recording.md`), if anywhere.
    record: Option<std::path::PathBuf>,
}

struct ServedEnv {
    server: Arc<EnvServer>,
    tasks: Vec<JoinHandle<()>>,
    /// Undeclared on drop: no new request is taken.
    _queryables: Vec<Queryable<()>>,
    /// Dropped with the env: the requests still running end with it.
    _serving: watch::Sender<()>,
    _token: LivelinessToken,
}

impl Drop for ServedEnv {
    fn drop(&mut self) {
        for task in &self.tasks {
            task.abort();
        }
    }
}

/// What an env's queryable does with a request once admitted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Lane {
    /// Answered in Zenoh's callback from a snapshot (`status`, `spec`).
    Now,
    /// Queued for the env's state (`open`, `reset`, `step`, `close`, `admin`).
    State,
    /// Queued for the store (`leaderboard`, `book`, `experiments`).
    Store,
}

fn lane(topic: Topic) -> Lane {
    match topic {
        Topic::Status | Topic::Spec => Lane::Now,
        Topic::Leaderboard | Topic::Book | Topic::Experiments => Lane::Store,
        _ => Lane::State,
    }
}

/// Everything one env's queryable callbacks share.
struct Admission {
    server: Arc<EnvServer>,
    limits: RequestLimits,
    rates: Arc<ClientRates>,
    state: Arc<Gate>,
    store: Arc<Gate>,
    /// Where admitted requests run (the callback runs on Zenoh's threads;
    /// a sim step's first stretch too).
    runtime: tokio::runtime::Handle,
    serving: watch::Receiver<()>,
}

impl Admission {
    /// [`Admission::take`]; should it panic (a bug), the query is answered
    /// `Internal` and Zenoh's receive path goes on.
    fn take_supervised(self: &Arc<Self>, topic: Topic, query: Query) {
        let kept = query.clone();
        let taken = std::panic::catch_unwind(AssertUnwindSafe(|| self.take(topic, query)));
        if let Err(panic) = taken {
            tracing::error!(
                key = %kept.key_expr(),
                "request admission panicked (a bug): {}",
                panic_message(panic.as_ref())
            );
            refuse(
                &kept,
                WireError::internal(
                    "the controller failed on this request (a bug, logged); it goes on serving",
                ),
            );
        }
    }

    /// Takes `query` on `topic` without waiting for a worker: refused,
    /// answered, started here (a sim step), or handed to a task with its
    /// place in the queue.
    fn take(self: &Arc<Self>, topic: Topic, query: Query) {
        let admitted = self
            .limits
            .check_size(admission::request_size(&query))
            .and_then(|()| admission::client_of(self.server.env(), &query))
            .and_then(|client| self.rates.check(&client).map(|()| client));
        let client = match admitted {
            Ok(client) => client,
            Err(refused) => return refuse(&query, refused),
        };
        let gate = match lane(topic) {
            Lane::Now => return answer_now(&self.server, topic, &query),
            Lane::State => &self.state,
            Lane::Store => &self.store,
        };
        let ticket = match gate.enter(&client) {
            Ok(ticket) => ticket,
            Err(refused) => return refuse(&query, refused),
        };
        let (server, mut serving) = (self.server.clone(), self.serving.clone());
        let work = async move {
            let _place = ticket;
            tokio::select! {
                () = answer_supervised(&query, handle(&server, topic, &query)) => {}
                // The env stopped serving (the controller was dropped).
                _ = serving.changed() => {}
            }
        };
        if topic == Topic::Step && self.server.env().realm() == Realm::Sim {
            // Up to the command it puts on `cmd`, a sim step needs no
            // worker: it starts here, sparing a hand-off (`crate::start`).
            // A real robot's steps last a second; its link's receive thread
            // is never held by a command put to a congested robot link.
            start_here(&self.runtime, work);
        } else {
            self.runtime.spawn(work);
        }
    }
}

/// Answers `query` with `refused`, from Zenoh's callback.
fn refuse(query: &Query, refused: WireError) {
    tracing::debug!(key = %query.key_expr(), "request refused: {refused}");
    if let Err(e) = wire::reply_encoded_now::<()>(query, Err(refused)) {
        tracing::warn!(key = %query.key_expr(), "reply failed: {e}");
    }
}

/// Answers `status` or `spec` from Zenoh's callback: neither waits for
/// anything (see [`EnvServer::status`]).
fn answer_now(server: &EnvServer, topic: Topic, query: &Query) {
    let sent = match topic {
        Topic::Status => wire::reply_now(query, Ok(&server.status())),
        _ => wire::reply_now(query, Ok(&server.spec())),
    };
    if let Err(e) = sent {
        tracing::warn!(env = %server.env(), ?topic, "reply failed: {e}");
    }
}

impl Controller {
    /// A controller on `session` recording into `store`, with the default
    /// [`RequestLimits`].
    pub fn new(session: Session, store: Store) -> Self {
        let limits = RequestLimits::default();
        Self {
            session,
            store: Arc::new(Mutex::new(store)),
            envs: Vec::new(),
            rates: Arc::new(ClientRates::new(&limits)),
            limits,
            seals: LinkSeals::default(),
            record: None,
        }
    }

    /// Seals what moves real robots, and believes only sealed tracker
    /// reports, for the envs served from now on ([`LinkSeals`]).
    pub fn seal_with(&mut self, seals: LinkSeals) {
        self.seals = seals;
    }

    /// Records every episode of the envs served from now on under `dir`
    /// (checked now: an unwritable directory is an error before anything
    /// is served).
    pub fn record_into(&mut self, dir: &std::path::Path) -> Result<(), ControllerError> {
        offworld_recorder::RecordTo::check(dir)?;
        self.record = Some(dir.to_owned());
        Ok(())
    }

    /// [`Controller::new`] with a site's request limits (checked).
    pub fn with_limits(
        session: Session,
        store: Store,
        limits: RequestLimits,
    ) -> Result<Self, ControllerError> {
        limits.check()?;
        Ok(Self {
            rates: Arc::new(ClientRates::new(&limits)),
            limits,
            ..Self::new(session, store)
        })
    }

    /// The request limits in force.
    pub fn limits(&self) -> &RequestLimits {
        &self.limits
    }

    /// The shared store.
    pub fn store(&self) -> Arc<Mutex<Store>> {
        self.store.clone()
    }

    /// Starts serving `env` with `task`. Must be called inside a tokio runtime.
    pub async fn serve(
        &mut self,
        env: EnvId,
        task: Task,
        options: EnvOptions,
    ) -> Result<Arc<EnvServer>, ControllerError> {
        if self.envs.iter().any(|e| e.server.env() == &env) {
            return Err(ControllerError::Conflict(format!(
                "{env} is already served"
            )));
        }
        let server = Arc::new(
            EnvServer::new(
                &self.session,
                env.clone(),
                task,
                options,
                &self.seals,
                self.store.clone(),
                self.record.as_deref(),
            )
            .await?,
        );
        let mut tasks = Vec::new();
        let (serving, serving_rx) = watch::channel(());
        let admission = Arc::new(Admission {
            server: server.clone(),
            limits: self.limits,
            rates: self.rates.clone(),
            state: Gate::new(env.clone(), "its state", &self.limits),
            store: Gate::new(env.clone(), "the store", &self.limits),
            runtime: tokio::runtime::Handle::current(),
            serving: serving_rx,
        });
        let mut queryables = Vec::new();
        for topic in [
            Topic::Open,
            Topic::Spec,
            Topic::Reset,
            Topic::Step,
            Topic::Close,
            Topic::Status,
            Topic::Admin,
            Topic::Leaderboard,
            Topic::Book,
            Topic::Experiments,
        ] {
            let admission = admission.clone();
            queryables.push(
                self.session
                    .declare_queryable(env.key(topic))
                    .callback(move |query| admission.take_supervised(topic, query))
                    .await?,
            );
        }
        tasks.push(tokio::spawn(watch_lease_holder(
            self.session.clone(),
            server.clone(),
        )));
        // Heartbeat for the robot's watchdog, and status on change.
        let session = self.session.clone();
        let beat_server = server.clone();
        let heartbeat_key = env.key(Topic::Heartbeat);
        let sealer = self.seals.command.clone();
        tasks.push(tokio::spawn(async move {
            let mut interval = tokio::time::interval(HEARTBEAT_PERIOD);
            let mut counter = 0u64;
            loop {
                interval.tick().await;
                counter += 1;
                let beat = Heartbeat {
                    stamp: Time::now(),
                    counter,
                };
                let sent =
                    wire::put_control_sealed(&session, &heartbeat_key, &beat, sealer.as_deref());
                if let Err(e) = sent.await {
                    tracing::warn!("heartbeat failed: {e}");
                }
                if counter.is_multiple_of(10) {
                    beat_server.refresh_status().await;
                }
            }
        }));
        let token = self
            .session
            .liveliness()
            .declare_token(env.alive_key(Component::Controller))
            .await?;
        tracing::info!(%env, task = %server.spec().task, "serving");
        self.envs.push(ServedEnv {
            server: server.clone(),
            tasks,
            _queryables: queryables,
            _serving: serving,
            _token: token,
        });
        Ok(server)
    }

    /// The envs served.
    pub fn envs(&self) -> impl Iterator<Item = &Arc<EnvServer>> {
        self.envs.iter().map(|e| &e.server)
    }

    /// Stops cleanly (SIGTERM, Ctrl-C): every robot is told to stop and
    /// every episode in progress is recorded as aborted with `reason`, then
    /// serving ends (liveliness tokens undeclared on drop).
    pub async fn shutdown(self, reason: &str) {
        for env in &self.envs {
            env.server.stop_and_record(reason).await;
        }
    }
}

/// Follows the lease holder's presence: a vanished holder stops the robot;
/// one back within the grace period gets its lease back. Only the holder's
/// own token is heard (a subscriber on its exact key, declared again when
/// the lease changes hands), not `alive/client/*`: a trainer may declare
/// tokens there by the ten thousand, and Zenoh matches each new key
/// against every key a subscriber's session knows (ARCHITECTURE.md,
/// "Backpressure and fairness").
async fn watch_lease_holder(session: Session, server: Arc<EnvServer>) {
    let mut holder = server.lease_holder();
    loop {
        let client_id = holder.borrow_and_update().clone();
        let presence = match &client_id {
            Some(id) => watch_presence(&session, &server, id).await,
            None => None,
        };
        // Until the lease changes hands, its holder's token comes and goes.
        loop {
            let sample = tokio::select! {
                changed = holder.changed() => match changed {
                    Ok(()) => break,
                    // Never while `server`, which holds the sender, lives.
                    Err(_) => return,
                },
                sample = async {
                    match &presence {
                        Some(presence) => presence.recv_async().await.ok(),
                        None => None,
                    }
                } => sample,
            };
            let (Some(sample), Some(client_id)) = (sample, client_id.as_deref()) else {
                // No holder, or the session closed: wait for a change.
                if holder.changed().await.is_err() {
                    return;
                }
                break;
            };
            on_presence(&server, client_id, sample.kind()).await;
        }
    }
}

/// A subscriber to `client_id`'s token, its current state included: the
/// token was declared before `open`, and this session must know it to
/// hear it go when its own link to the router drops. A holder gone before
/// this is declared (a router's round trip after `open`) is not heard: its
/// lease lapses idle, as a client's that opened and never stepped (a
/// client may also send an id and declare no token). `None` for an empty
/// id (a client without a token) or a closed session.
async fn watch_presence(
    session: &Session,
    server: &EnvServer,
    client_id: &str,
) -> Option<Subscriber<FifoChannelHandler<Sample>>> {
    let key = server.env().client_alive_key(client_id).ok()?;
    session
        .liveliness()
        .declare_subscriber(&key)
        .history(true)
        .await
        .inspect_err(|e| tracing::warn!(env = %server.env(), "cannot watch the lease holder: {e}"))
        .ok()
}

/// The holder's token came (`Put`) or went (`Delete`).
async fn on_presence(server: &EnvServer, client_id: &str, kind: SampleKind) {
    let handled = supervised(async {
        match kind {
            SampleKind::Delete => server.client_disconnected(client_id).await,
            SampleKind::Put => server.client_reconnected(client_id).await,
        }
    })
    .await;
    if let Err(panic) = handled {
        tracing::error!(
            env = %server.env(),
            client_id,
            "client liveliness handler panicked (a bug): {}",
            panic_message(panic.as_ref())
        );
    }
}

/// Runs `work` to completion, catching a panic in any of its polls: the
/// panic's payload instead of unwinding into the caller (a queryable's
/// serving loop, which would die with it).
pub async fn supervised<F: Future>(work: F) -> Result<F::Output, Box<dyn Any + Send>> {
    let mut work = pin!(work);
    std::future::poll_fn(move |cx| {
        // The future is not polled again after a panic: whatever state it
        // broke is dropped with it.
        match std::panic::catch_unwind(AssertUnwindSafe(|| work.as_mut().poll(cx))) {
            Ok(Poll::Ready(output)) => Poll::Ready(Ok(output)),
            Ok(Poll::Pending) => Poll::Pending,
            Err(panic) => Poll::Ready(Err(panic)),
        }
    })
    .await
}

/// What a panic said, for the log.
pub fn panic_message(panic: &(dyn Any + Send)) -> &str {
    panic
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| panic.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
}

/// Answers `query` with `work`; should `work` panic, the query is answered
/// `Internal` instead and the caller goes on serving.
pub async fn answer_supervised(query: &Query, work: impl Future<Output = ()>) {
    let Err(panic) = supervised(work).await else {
        return;
    };
    tracing::error!(
        key = %query.key_expr(),
        "request handler panicked (a bug): {}",
        panic_message(panic.as_ref())
    );
    let refused = WireError::internal(
        "the controller failed on this request (a bug, logged); it goes on serving",
    );
    if let Err(e) = wire::reply_encoded::<()>(query, Err(refused)).await {
        tracing::warn!(key = %query.key_expr(), "reply failed: {e}");
    }
}

async fn handle(server: &EnvServer, topic: Topic, query: &Query) {
    let sent = match topic {
        Topic::Open => {
            respond(
                query,
                Box::pin(async { server.open(wire::decode_query::<OpenRequest>(query)?).await }),
            )
            .await
        }
        Topic::Reset => {
            respond_encoded(
                query,
                Box::pin(async {
                    server
                        .reset(wire::decode_query::<ResetRequest>(query)?)
                        .await
                }),
            )
            .await
        }
        Topic::Step => {
            respond_unless_sent(
                query,
                Box::pin(async {
                    let req = wire::decode_query::<StepRequest>(query)?;
                    server.step(req, query.clone()).await
                }),
            )
            .await
        }
        Topic::Close => {
            respond(
                query,
                Box::pin(async {
                    server
                        .close(wire::decode_query::<CloseRequest>(query)?)
                        .await
                }),
            )
            .await
        }
        Topic::Admin => {
            respond(
                query,
                Box::pin(async {
                    server
                        .admin(wire::decode_query::<AdminRequest>(query)?)
                        .await
                }),
            )
            .await
        }
        Topic::Leaderboard => respond(query, Box::pin(async { server.leaderboard() })).await,
        Topic::Book => {
            respond(
                query,
                Box::pin(async { server.book(wire::decode_query::<BookingRequest>(query)?) }),
            )
            .await
        }
        Topic::Experiments => {
            respond(
                query,
                Box::pin(async {
                    server
                        .experiments(wire::decode_query::<ExperimentsRequest>(query)?)
                        .await
                }),
            )
            .await
        }
        other => {
            tracing::error!(?other, "no handler");
            Ok(())
        }
    };
    if let Err(e) = sent {
        tracing::warn!(env = %server.env(), ?topic, "reply failed: {e}");
    }
}

/// A handler's work, boxed where [`handle`] starts it. Each layer of
/// `respond*` and [`answer_supervised`] keeps the future it wraps in its own
/// state, so an unboxed handler's state machine is copied into every layer:
/// the request task grew to ~48 KB, memcpy'd on each spawn and poll of a
/// step (a tenth of a step's instructions outside the twin). Boxed once,
/// each layer holds a pointer.
type Work<'a, T> = Pin<Box<dyn Future<Output = Result<T, WireError>> + Send + 'a>>;

async fn respond<T: serde::Serialize>(
    query: &Query,
    work: Work<'_, T>,
) -> Result<(), offworld_runtime::RequestError> {
    respond_encoded(query, Box::pin(async { Ok(Encoded::new(&work.await?)?) })).await
}

/// Replies with the handler's encoded reply or its typed error.
async fn respond_encoded<T>(
    query: &Query,
    work: Work<'_, Encoded<T>>,
) -> Result<(), offworld_runtime::RequestError> {
    respond_unless_sent(query, Box::pin(async { work.await.map(Some) })).await
}

/// [`respond_encoded`] for a handler that may have replied itself (`None`).
async fn respond_unless_sent<T>(
    query: &Query,
    work: Work<'_, Option<Encoded<T>>>,
) -> Result<(), offworld_runtime::RequestError> {
    let result = match work.await {
        Ok(None) => return Ok(()),
        Ok(Some(reply)) => Ok(reply),
        Err(e) => {
            tracing::debug!(key = %query.key_expr(), "request refused: {e}");
            Err(e)
        }
    };
    wire::reply_encoded(query, result).await
}

#[cfg(test)]
mod tests {
    use super::*;
    use offworld_runtime::{ErrorCode, RequestError, SessionConfig};

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_panicking_handler_answers_internal_and_serving_goes_on() {
        let session = SessionConfig::isolated().open().await.expect("session");
        let key = "offworld/@v1/sim/supervised/ask";
        let queryable = session.declare_queryable(key).await.expect("queryable");
        let serving = tokio::spawn(async move {
            while let Ok(query) = queryable.recv_async().await {
                answer_supervised(&query, async {
                    let n: u32 = wire::decode_query(&query).unwrap_or(0);
                    tokio::task::yield_now().await;
                    assert!(n != 13, "unlucky request");
                    let _ = wire::reply(&query, Ok(&(n * 2))).await;
                })
                .await;
            }
        });
        let ask = |n: u32| {
            let session = session.clone();
            async move { wire::request::<u32, u32>(&session, key, &n, Duration::from_secs(5)).await }
        };
        assert_eq!(ask(1).await.expect("answer"), 2);
        match ask(13).await {
            Err(RequestError::Remote(e)) => assert_eq!(e.code, ErrorCode::Internal, "{e}"),
            other => panic!("expected Internal, got {other:?}"),
        }
        // The same queryable goes on answering.
        assert_eq!(ask(21).await.expect("answer after the panic"), 42);
        assert!(!serving.is_finished());
        serving.abort();
    }

    #[tokio::test]
    async fn supervised_returns_the_panic() {
        let caught = supervised(async { panic!("boom {}", 7) }).await;
        let panic = caught.expect_err("caught");
        assert_eq!(panic_message(panic.as_ref()), "boom 7");
        assert_eq!(supervised(async { 5 }).await.expect("no panic"), 5);
    }
}
