//! The Zenoh side: which envs exist and what state each is in, kept live.
//!
//! Three sources feed one table of [`EnvView`]s:
//! - a periodic (and on every liveliness change, immediate) sweep with
//!   [`client::discover`], the listing the Python `list_envs` shows: alive
//!   components, task, state, e-stops, last reset, bookings;
//! - every env's `status` publications, so a lease or an e-stop shows up
//!   the moment its controller announces it;
//! - every env's `fault` publications: the last fault's reason.
//!
//! Every change publishes a new [`Snapshot`] on a `watch` channel: the JSON
//! API reads the latest, each event stream waits for the next.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use offworld_client::operator::{press_estop, EStopScope, PressError, PressReport};
use offworld_client::{self as client, EnvListing};
use offworld_runtime::keys::{self, EnvId, Topic};
use offworld_runtime::msg::{
    AdminReply, AdminRequest, BookingRequest, Bookings, EnvStatus, Experiments, ExperimentsRequest,
    Leaderboard, MotionFault, TrackingStatus,
};
use offworld_runtime::{codec, WireError};
use tokio::sync::{watch, Notify};
use zenoh::Session;

use crate::model::{DeploymentView, EnvView, FaultView, Snapshot, TrackingView};

/// How discovery talks to the deployment.
#[derive(Debug, Clone, Copy)]
pub struct DiscoveryConfig {
    /// Deadline of every Zenoh query (liveliness, `spec`, `status`, `book`,
    /// `leaderboard`): a dead controller costs a page at most this long.
    pub query_timeout: Duration,
    /// Time between two sweeps when nothing changes.
    pub sweep_interval: Duration,
}

impl Default for DiscoveryConfig {
    fn default() -> Self {
        Self {
            query_timeout: Duration::from_secs(2),
            sweep_interval: Duration::from_secs(5),
        }
    }
}

/// Wall clock, Unix ms.
pub fn now_unix_ms() -> i64 {
    let since = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .unwrap_or_default();
    i64::try_from(since.as_millis()).unwrap_or(i64::MAX)
}

/// One env as tracked: its view plus when its controller last published a
/// status (a sweep that started before that must not overwrite it).
struct Tracked {
    view: EnvView,
    status_received: Option<Instant>,
}

/// Envs tracked at most: status and fault publications name their env,
/// and a peer publishing under ever new names must not grow the table
/// without bound (the router's ACL lets only controllers and robots
/// publish these; this is the second line).
const MAX_ENVS: usize = 1024;

#[derive(Default)]
struct Table {
    envs: BTreeMap<EnvId, Tracked>,
    deployment: DeploymentView,
}

impl Table {
    /// The env's entry, created if there is room.
    fn entry(&mut self, env: &EnvId) -> Option<&mut Tracked> {
        if !self.envs.contains_key(env) && self.envs.len() >= MAX_ENVS {
            tracing::warn!(%env, "not tracked: {MAX_ENVS} envs are already");
            return None;
        }
        Some(self.envs.entry(env.clone()).or_insert_with(|| Tracked {
            view: EnvView::new(env),
            status_received: None,
        }))
    }
}

/// The live availability of every env reachable through one session.
/// Cloning shares it; the background tasks stop when [`Discovery::stop`]
/// is called or the last clone is dropped.
#[derive(Clone)]
pub struct Discovery {
    inner: Arc<Inner>,
}

/// How long a press from the console waits for a robot or twin to be
/// present under its scope (a page request has 10 s in all).
pub const ESTOP_PRESENCE: Duration = Duration::from_secs(2);
/// How long it waits for each one's acknowledgement (the CLI's: 1 s).
pub const ESTOP_ACK_WITHIN: Duration = Duration::from_secs(2);

struct Inner {
    session: Session,
    config: DiscoveryConfig,
    table: Mutex<Table>,
    snapshot: watch::Sender<Arc<Snapshot>>,
    sweep_now: Notify,
    stopped: watch::Sender<bool>,
}

impl Discovery {
    /// Subscribes to every env's `status`, `fault` and liveliness on
    /// `session` and starts sweeping. Needs a Tokio runtime.
    pub async fn start(session: Session, config: DiscoveryConfig) -> Result<Self, WireError> {
        let (snapshot, _) = watch::channel(Arc::new(Snapshot::default()));
        let (stopped, _) = watch::channel(false);
        let inner = Arc::new(Inner {
            session: session.clone(),
            config,
            table: Mutex::new(Table::default()),
            snapshot,
            sweep_now: Notify::new(),
            stopped,
        });
        // The subscribers hold only a weak reference: dropping the last
        // `Discovery` drops the table.
        let status = follow(
            &session,
            &inner,
            Topic::Status,
            |inner, env, status: EnvStatus| inner.status_received(env, &status),
        )
        .await?;
        let fault = follow(
            &session,
            &inner,
            Topic::Fault,
            |inner, env, fault: MotionFault| inner.fault_received(env, fault.reason),
        )
        .await?;
        let tracking = follow(&session, &inner, Topic::Tracking, Inner::tracking_received).await?;
        let weak = Arc::downgrade(&inner);
        let alive = session
            .liveliness()
            .declare_subscriber(keys::components_alive_selector())
            .callback(move |_| {
                // A component came or went: sweep now rather than at the
                // next tick, so an env vanishing shows offline at once.
                if let Some(inner) = weak.upgrade() {
                    inner.sweep_now.notify_one();
                }
            })
            .await
            .map_err(zenoh_error)?;
        let weak = Arc::downgrade(&inner);
        let mut stop = inner.stopped.subscribe();
        tokio::spawn(async move {
            // Keeps the subscriptions declared while the loop runs.
            let _subscriptions = (status, fault, tracking, alive);
            loop {
                let Some(inner) = weak.upgrade() else { return };
                inner.sweep().await;
                let (interval, wait) = (inner.config.sweep_interval, Arc::clone(&inner));
                drop(inner);
                tokio::select! {
                    _ = tokio::time::sleep(interval) => {}
                    _ = wait.sweep_now.notified() => {
                        // Liveliness changes come in bursts (a deployment
                        // starting declares several tokens): one sweep each
                        // 100 ms is enough.
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                    // The only change is to "stopped" (or the sender is gone).
                    _ = stop.changed() => return,
                }
            }
        });
        Ok(Self { inner })
    }

    /// The latest snapshot.
    pub fn snapshot(&self) -> Arc<Snapshot> {
        self.inner.snapshot.borrow().clone()
    }

    /// A receiver that wakes on every new snapshot.
    pub fn watch(&self) -> watch::Receiver<Arc<Snapshot>> {
        self.inner.snapshot.subscribe()
    }

    /// Stops sweeping and releases the subscriptions.
    pub fn stop(&self) {
        self.inner.stopped.send_replace(true);
    }

    /// One env's leaderboard from its controller, bounded by the query
    /// timeout.
    pub async fn leaderboard(&self, env: &EnvId) -> Result<Leaderboard, WireError> {
        client::leaderboard(&self.inner.session, env, self.inner.config.query_timeout).await
    }

    /// Makes, lists or cancels bookings of `env` (its controller checks
    /// the token and the rules), bounded by the query timeout.
    pub async fn book(&self, env: &EnvId, request: &BookingRequest) -> Result<Bookings, WireError> {
        client::book(
            &self.inner.session,
            env,
            request,
            self.inner.config.query_timeout,
        )
        .await
    }

    /// Presses (`engaged`) or releases the e-stop of `scope` for an
    /// operator, as `env_controller estop` does: waits at most
    /// [`ESTOP_PRESENCE`] for a robot or twin to obey it and
    /// [`ESTOP_ACK_WITHIN`] for each to acknowledge.
    pub async fn press_estop(
        &self,
        scope: &EStopScope,
        engaged: bool,
        reason: &str,
    ) -> Result<PressReport, PressError> {
        press_estop(
            &self.inner.session,
            scope,
            engaged,
            reason,
            ESTOP_PRESENCE,
            ESTOP_ACK_WITHIN,
        )
        .await
    }

    /// Asks `env`'s controller who a token is, or changes the env's
    /// service (operators), bounded by the query timeout.
    /// The status in the reply is shown at once (the same the controller
    /// publishes, which may arrive later).
    pub async fn admin(
        &self,
        env: &EnvId,
        request: &AdminRequest,
    ) -> Result<AdminReply, WireError> {
        let reply = client::admin(
            &self.inner.session,
            env,
            request,
            self.inner.config.query_timeout,
        )
        .await?;
        self.inner.status_received(env.clone(), &reply.status);
        Ok(reply)
    }

    /// Waits (at most `within`) for a snapshot where `settled` holds;
    /// returns whether one did.
    pub async fn settled(&self, within: Duration, settled: impl Fn(&Snapshot) -> bool) -> bool {
        let mut snapshots = self.inner.snapshot.subscribe();
        tokio::time::timeout(within, async {
            loop {
                if settled(&snapshots.borrow_and_update()) {
                    return true;
                }
                if snapshots.changed().await.is_err() {
                    return false;
                }
            }
        })
        .await
        .unwrap_or(false)
    }

    /// Lists the caller's experiments on `env` or shows one, bounded by
    /// the query timeout.
    pub async fn experiments(
        &self,
        env: &EnvId,
        request: &ExperimentsRequest,
    ) -> Result<Experiments, WireError> {
        client::experiments(
            &self.inner.session,
            env,
            request,
            self.inner.config.query_timeout,
        )
        .await
    }
}

/// Subscribes to `topic` on every env: each sample that decodes as `T`
/// goes to `received` with its env (an undecodable one is logged). The
/// subscriber holds only a weak reference: dropping the last `Discovery`
/// drops the table.
async fn follow<T: serde::de::DeserializeOwned>(
    session: &Session,
    inner: &Arc<Inner>,
    topic: Topic,
    received: impl Fn(&Inner, EnvId, T) + Send + Sync + 'static,
) -> Result<zenoh::pubsub::Subscriber<()>, WireError> {
    let weak = Arc::downgrade(inner);
    session
        .declare_subscriber(keys::topic_on_all_envs(topic))
        .callback(move |sample| {
            let Some(inner) = weak.upgrade() else { return };
            let Ok(env) = EnvId::from_key(sample.key_expr().as_str()) else {
                return;
            };
            match codec::decode_payload::<T>(sample.payload()) {
                Ok(value) => received(&inner, env, value),
                Err(e) => tracing::debug!(%env, ?topic, "undecodable sample: {e}"),
            }
        })
        .await
        .map_err(zenoh_error)
}

fn zenoh_error(e: impl std::fmt::Display) -> WireError {
    WireError::internal(format!("zenoh: {e}"))
}

impl Inner {
    fn table(&self) -> MutexGuard<'_, Table> {
        // A panic while holding the lock leaves a table that is still
        // consistent field by field: keep serving it.
        self.table
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    fn publish(&self, table: &Table) {
        let snapshot = Snapshot {
            generated_unix_ms: now_unix_ms(),
            deployment: table.deployment.clone(),
            envs: table.envs.values().map(|t| t.view.clone()).collect(),
        };
        self.snapshot.send_replace(Arc::new(snapshot));
    }

    fn status_received(&self, env: EnvId, status: &EnvStatus) {
        let mut table = self.table();
        let known = table.envs.contains_key(&env);
        let Some(tracked) = table.entry(&env) else {
            return;
        };
        tracked.view.apply_status(status);
        tracked.view.last_seen_unix_ms = Some(now_unix_ms());
        tracked.status_received = Some(Instant::now());
        self.publish(&table);
        if !known {
            // Its task and components come with a sweep.
            self.sweep_now.notify_one();
        }
    }

    fn fault_received(&self, env: EnvId, reason: String) {
        let mut table = self.table();
        let Some(tracked) = table.entry(&env) else {
            return;
        };
        let now = now_unix_ms();
        tracked.view.last_fault = Some(FaultView {
            reason,
            unix_ms: now,
        });
        tracked.view.last_seen_unix_ms = Some(now);
        self.publish(&table);
    }

    fn tracking_received(&self, env: EnvId, status: TrackingStatus) {
        let mut table = self.table();
        let Some(tracked) = table.entry(&env) else {
            return;
        };
        let now = now_unix_ms();
        tracked.view.tracking = Some(TrackingView {
            ok: status.tracking,
            last_pose_age_s: status.last_pose_age_s,
            reason: status.reason,
            unix_ms: now,
        });
        tracked.view.last_seen_unix_ms = Some(now);
        self.publish(&table);
    }

    /// Lists every env and merges the listing into the table.
    async fn sweep(&self) {
        let started = Instant::now();
        let connected = self.connected().await;
        let listed = client::discover(&self.session, self.config.query_timeout).await;
        let mut table = self.table();
        let now = now_unix_ms();
        table.deployment.last_sweep_unix_ms = Some(now);
        let (listings, problem) = match (listed, connected) {
            (_, false) => (
                Vec::new(),
                Some(
                    "not connected to the deployment: no Zenoh router or peer is reachable".into(),
                ),
            ),
            (Err(e), true) => (
                Vec::new(),
                Some(format!("the envs could not be listed: {}", e.message)),
            ),
            (Ok(listings), true) => (listings, None),
        };
        table.deployment.reachable = problem.is_none();
        table.deployment.message = problem;
        let mut seen = std::collections::BTreeSet::new();
        for listing in listings {
            seen.insert(listing.env.clone());
            let Some(tracked) = table.entry(&listing.env) else {
                continue;
            };
            // A status published while this sweep was under way is newer
            // than what the sweep's own `status` query returned.
            let status_is_newer = tracked.status_received.is_some_and(|at| at >= started);
            merge_listing(&mut tracked.view, listing, status_is_newer, now);
        }
        let reason = if connected {
            "no component of this env is alive"
        } else {
            "the deployment is unreachable"
        };
        for (env, tracked) in &mut table.envs {
            if !seen.contains(env) {
                tracked.view.components.clear();
                tracked.view.set_offline(reason);
            }
        }
        self.publish(&table);
    }

    /// Whether the session reaches any router or peer at all (a dead
    /// deployment answers no query; this tells it from an empty one).
    async fn connected(&self) -> bool {
        let info = self.session.info();
        info.routers_zid().await.next().is_some() || info.peers_zid().await.next().is_some()
    }
}

/// What one sweep's listing says about an env, merged into its view.
fn merge_listing(view: &mut EnvView, listing: EnvListing, status_is_newer: bool, now: i64) {
    view.components = listing.components;
    view.last_seen_unix_ms = Some(now);
    view.next_booking = listing
        .bookings
        .iter()
        .find(|b| b.end_unix_ms > now)
        .map(Into::into);
    // `discover` leaves the task empty when the controller did not answer:
    // its state then says why, and the last e-stops and reset are kept.
    let controller_answered = !listing.task.is_empty();
    if controller_answered {
        view.task = Some(listing.task);
        if !status_is_newer {
            view.apply_status(&EnvStatus {
                env_id: view.id.clone(),
                state: listing.state,
                estop: listing.estop,
                last_reset: listing.last_reset,
            });
        }
    } else {
        view.apply_state(&listing.state);
    }
}
