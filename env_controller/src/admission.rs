//! Admission: what every query to the controller passes before it is
//! handled, decided in Zenoh's callback without waiting on anything (a
//! handler that waited there — on an env's state lock through a real
//! reset drive, say — would stall Zenoh's receive path, and with it every
//! other client of the controller).
//!
//! In order: the request's size ([`RequestLimits::max_request_bytes`],
//! checked before anything is decoded: `BadRequest`); who asks (the
//! [`ClientTag`] attachment `offworld_client` puts on every request;
//! untagged requests share one client, [`UNTAGGED`]); that client's rate
//! ([`ClientRates`], across the controller); then, for a request that needs
//! the env's state or the store, a place in the env's bounded queue
//! ([`Gate`]: so many requests queued or running per env, fewer per client
//! and env). Whatever does not fit is answered `Busy` at once, with a
//! message saying which limit and what to do; nothing is ever left
//! unanswered.

use std::collections::HashMap;
use std::num::NonZeroU32;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use governor::clock::{Clock, DefaultClock};
use governor::{DefaultKeyedRateLimiter, Quota, RateLimiter};
use offworld_runtime::keys::EnvId;
use offworld_runtime::msg::ClientTag;
use offworld_runtime::{codec, WireError};
use zenoh::bytes::ZBytes;
use zenoh::query::Query;

use crate::env::validate_client_id;
use crate::error::ControllerError;

/// The client of every request without a [`ClientTag`] (not a valid client
/// id, so no tagged client shares its quota).
pub const UNTAGGED: &str = "(untagged)";

/// Smallest request size limit a site may set, bytes: an `open` with a
/// token, a 64-character experiment name and its options fits many times.
pub const MIN_REQUEST_BYTES: usize = 1024;
/// Largest request size limit a site may set, bytes; Zenoh's own limit on a
/// message (`transport/link/rx/max_message_size`, 1 GiB by default) is far
/// above it, so the controller's typed refusal always comes first.
pub const MAX_REQUEST_BYTES: usize = 16 << 20;

/// A site's limits on requests (`env_controller serve` flags).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct RequestLimits {
    /// Requests queued or running on one env (waiting for its state or the
    /// store), beyond which requests to it are answered `Busy`.
    /// `status` and `spec` are answered at once from a snapshot and never
    /// queue.
    pub env_queue: usize,
    /// Requests one client may have queued or running on one env (an
    /// honest client has one: it waits for each answer).
    pub client_queue: usize,
    /// Requests per second one client may send to the controller, sustained.
    pub client_rate_per_s: u32,
    /// Requests one client may send at once above that rate.
    pub client_burst: u32,
    /// Largest request accepted (payload plus client tag), bytes.
    pub max_request_bytes: usize,
}

impl Default for RequestLimits {
    fn default() -> Self {
        Self {
            env_queue: 64,
            client_queue: 8,
            client_rate_per_s: 2000,
            client_burst: 1000,
            max_request_bytes: 64 * 1024,
        }
    }
}

impl RequestLimits {
    /// The limits of a controller that serves only the process that
    /// started it (`gymnasium.make` of a sim env, on a private session):
    /// no rate a client can reach (a million requests a second), since a
    /// limit would only cap the researcher's own training (a twin steps up
    /// to ~3,800 times a second at 84×84); the queue and size limits stay.
    pub fn in_process() -> Self {
        Self {
            client_rate_per_s: 1_000_000,
            client_burst: 1_000_000,
            ..Self::default()
        }
    }

    /// Checks the limits themselves (a site's configuration).
    pub fn check(&self) -> Result<(), ControllerError> {
        let bad = |why: String| Err(ControllerError::Config(why));
        if self.env_queue == 0 || self.client_queue == 0 {
            return bad("the env queue and the client queue must not be zero".into());
        }
        if self.client_queue > self.env_queue {
            return bad(format!(
                "the client queue ({}) must not exceed the env queue ({}): one client \
                 could fill an env's queue",
                self.client_queue, self.env_queue
            ));
        }
        if self.client_rate_per_s == 0 || self.client_burst == 0 {
            return bad("the client rate and burst must not be zero".into());
        }
        if !(MIN_REQUEST_BYTES..=MAX_REQUEST_BYTES).contains(&self.max_request_bytes) {
            return bad(format!(
                "the request size limit is {MIN_REQUEST_BYTES} to {MAX_REQUEST_BYTES} bytes, \
                 got {}",
                self.max_request_bytes
            ));
        }
        Ok(())
    }

    /// Refuses a request of `size` bytes (`BadRequest`) over the limit.
    pub fn check_size(&self, size: usize) -> Result<(), WireError> {
        if size <= self.max_request_bytes {
            return Ok(());
        }
        Err(WireError::bad_request(format!(
            "a request of {size} bytes is over this controller's limit of {} bytes \
             (env_controller serve --max-request-bytes); gym requests are a few hundred bytes",
            self.max_request_bytes
        )))
    }
}

/// The size of `query`'s request: payload plus attachment, bytes.
pub fn request_size(query: &Query) -> usize {
    let len = |b: Option<&ZBytes>| b.map_or(0, ZBytes::len);
    len(query.payload()).saturating_add(len(query.attachment()))
}

/// Who sent `query`: its [`ClientTag`]'s id, or [`UNTAGGED`]. A tag that
/// is not one is a `BadRequest`.
pub fn client_of(env: &EnvId, query: &Query) -> Result<String, WireError> {
    let Some(attachment) = query.attachment() else {
        return Ok(UNTAGGED.to_owned());
    };
    let tag: ClientTag = codec::decode(&attachment.to_bytes())
        .map_err(|e| WireError::bad_request(format!("undecodable client tag: {e}")))?;
    if tag.client_id.is_empty() {
        return Err(WireError::bad_request("the client tag's id is empty"));
    }
    validate_client_id(env, &tag.client_id)?;
    Ok(tag.client_id)
}

/// How a client is named in a refusal.
fn named(client: &str) -> String {
    if client == UNTAGGED {
        "requests without a client tag (they share one quota)".to_owned()
    } else {
        format!("client {client}")
    }
}

/// Per-client request rates across the controller (GCRA token buckets,
/// `governor`).
pub struct ClientRates {
    limiter: DefaultKeyedRateLimiter<String>,
    clock: DefaultClock,
    rate_per_s: u32,
    burst: u32,
    /// The bucket count above which idle buckets are dropped.
    next_sweep: AtomicUsize,
}

/// Buckets kept before idle ones are swept.
const SWEEP_FROM: usize = 4096;

impl ClientRates {
    /// Rates for `limits` (checked: zero rates are refused there).
    pub fn new(limits: &RequestLimits) -> Self {
        let one = NonZeroU32::MIN;
        let rate = NonZeroU32::new(limits.client_rate_per_s).unwrap_or(one);
        let burst = NonZeroU32::new(limits.client_burst).unwrap_or(one);
        let clock = DefaultClock::default();
        Self {
            limiter: RateLimiter::keyed(Quota::per_second(rate).allow_burst(burst)),
            clock,
            rate_per_s: rate.get(),
            burst: burst.get(),
            next_sweep: AtomicUsize::new(SWEEP_FROM),
        }
    }

    /// Counts one request of `client`: `Busy` (saying when to retry) when
    /// it comes faster than allowed.
    pub fn check(&self, client: &str) -> Result<(), WireError> {
        let checked = self.limiter.check_key(&client.to_owned());
        self.sweep();
        checked.map_err(|not_until| {
            let wait = not_until.wait_time_from(self.clock.now());
            WireError::busy(format!(
                "{} sent more than this controller allows ({} requests/s, bursts of {}; \
                 env_controller serve --client-rate, --client-burst): nothing was done, \
                 retry in {} ms",
                named(client),
                self.rate_per_s,
                self.burst,
                wait.as_millis().max(1)
            ))
        })
    }

    /// Drops the buckets of clients idle long enough to be full again, once
    /// there are many: memory stays bounded by the clients of the last
    /// moments, however many ids a flood makes up.
    fn sweep(&self) {
        let due = self.next_sweep.load(Ordering::Relaxed);
        if self.limiter.len() <= due {
            return;
        }
        self.limiter.retain_recent();
        self.limiter.shrink_to_fit();
        let next = (self.limiter.len() * 2).max(SWEEP_FROM);
        self.next_sweep.store(next, Ordering::Relaxed);
    }

    /// Clients with a bucket (tests).
    pub fn tracked(&self) -> usize {
        self.limiter.len()
    }
}

/// One env's bounded queue for one kind of work (its state, or the store):
/// at most `capacity` requests queued or running, at most `per_client` of
/// them from one client. Entered without waiting; a [`Ticket`] holds the
/// place until the request is answered.
pub struct Gate {
    env: EnvId,
    /// What waits behind this gate, for messages ("its state", "the store").
    what: &'static str,
    capacity: usize,
    per_client: usize,
    places: Mutex<Places>,
}

#[derive(Default)]
struct Places {
    taken: usize,
    by_client: HashMap<String, usize>,
}

/// A place in a [`Gate`]'s queue, given back when dropped.
pub struct Ticket {
    gate: Arc<Gate>,
    client: String,
}

impl Gate {
    /// A gate for `env`'s requests that wait for `what`.
    pub fn new(env: EnvId, what: &'static str, limits: &RequestLimits) -> Arc<Self> {
        Arc::new(Self {
            env,
            what,
            capacity: limits.env_queue,
            per_client: limits.client_queue,
            places: Mutex::new(Places::default()),
        })
    }

    fn places(&self) -> std::sync::MutexGuard<'_, Places> {
        // Counters only, updated whole: a panic cannot leave them half done.
        self.places.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// A place for one request of `client`, or `Busy` saying which bound
    /// is reached.
    pub fn enter(self: &Arc<Self>, client: &str) -> Result<Ticket, WireError> {
        let mut places = self.places();
        let mine = places.by_client.get(client).copied().unwrap_or(0);
        if mine >= self.per_client {
            return Err(WireError::busy(format!(
                "{} already has {mine} requests queued or running on {}, this controller's \
                 limit per client (env_controller serve --client-queue): nothing was done; \
                 wait for their answers before sending more",
                named(client),
                self.env
            )));
        }
        if places.taken >= self.capacity {
            return Err(WireError::busy(format!(
                "{} has {} requests waiting for {}, this controller's limit per env \
                 (env_controller serve --env-queue; a real reset holds it for seconds): \
                 nothing was done; retry in a moment",
                self.env, places.taken, self.what
            )));
        }
        places.taken += 1;
        *places.by_client.entry(client.to_owned()).or_insert(0) += 1;
        Ok(Ticket {
            gate: self.clone(),
            client: client.to_owned(),
        })
    }

    /// Requests queued or running.
    pub fn taken(&self) -> usize {
        self.places().taken
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        let mut places = self.gate.places();
        places.taken = places.taken.saturating_sub(1);
        if let Some(n) = places.by_client.get_mut(&self.client) {
            *n = n.saturating_sub(1);
            if *n == 0 {
                places.by_client.remove(&self.client);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use offworld_runtime::ErrorCode;

    fn limits() -> RequestLimits {
        RequestLimits {
            env_queue: 3,
            client_queue: 2,
            client_rate_per_s: 1,
            client_burst: 4,
            ..RequestLimits::default()
        }
    }

    #[test]
    fn site_limits_are_checked() {
        RequestLimits::default().check().expect("defaults are sane");
        limits().check().expect("small limits are fine");
        for bad in [
            RequestLimits {
                env_queue: 0,
                ..limits()
            },
            RequestLimits {
                client_queue: 0,
                ..limits()
            },
            RequestLimits {
                client_queue: 4,
                ..limits()
            },
            RequestLimits {
                client_rate_per_s: 0,
                ..limits()
            },
            RequestLimits {
                client_burst: 0,
                ..limits()
            },
            RequestLimits {
                max_request_bytes: 10,
                ..limits()
            },
            RequestLimits {
                max_request_bytes: usize::MAX,
                ..limits()
            },
        ] {
            assert!(bad.check().is_err(), "{bad:?}");
        }
    }

    #[test]
    fn oversized_requests_are_bad_requests() {
        let limits = RequestLimits::default();
        assert!(limits.check_size(limits.max_request_bytes).is_ok());
        let e = limits
            .check_size(limits.max_request_bytes + 1)
            .expect_err("over");
        assert_eq!(e.code, ErrorCode::BadRequest);
        assert!(e.message.contains("--max-request-bytes"), "{e}");
    }

    #[test]
    fn a_gate_bounds_the_env_and_each_client_and_gives_places_back() {
        let gate = Gate::new(EnvId::sim("gate").expect("env"), "its state", &limits());
        let a1 = gate.enter("a").expect("a's first");
        let a2 = gate.enter("a").expect("a's second");
        let refused = gate.enter("a").err().expect("a's third");
        assert_eq!(refused.code, ErrorCode::Busy);
        assert!(
            refused.message.contains("client a already has 2"),
            "{refused}"
        );
        assert!(refused.message.contains("--client-queue"), "{refused}");
        let b1 = gate.enter("b").expect("b's first");
        // The env's bound (3) before b's own (2).
        let full = gate.enter("c").err().expect("env full");
        assert_eq!(full.code, ErrorCode::Busy);
        assert!(full.message.contains("3 requests waiting"), "{full}");
        assert!(full.message.contains("--env-queue"), "{full}");
        assert_eq!(gate.taken(), 3);
        drop(a1);
        let c1 = gate.enter("c").expect("a place was given back");
        drop((a2, b1, c1));
        assert_eq!(gate.taken(), 0);
        assert!(gate.places().by_client.is_empty(), "no client left behind");
    }

    #[test]
    fn rates_are_per_client_and_say_when_to_retry() {
        let rates = ClientRates::new(&limits());
        for _ in 0..4 {
            rates.check("a").expect("within the burst");
        }
        let e = rates.check("a").expect_err("over the burst");
        assert_eq!(e.code, ErrorCode::Busy);
        assert!(e.message.contains("client a sent more"), "{e}");
        assert!(e.message.contains("retry in"), "{e}");
        // Another client has its own bucket; untagged ones share one.
        rates.check("b").expect("b's own bucket");
        for _ in 0..4 {
            rates.check(UNTAGGED).expect("within the burst");
        }
        let e = rates.check(UNTAGGED).expect_err("shared bucket");
        assert!(e.message.contains("without a client tag"), "{e}");
        assert_eq!(rates.tracked(), 3);
    }

    #[test]
    fn an_in_process_controller_never_throttles_its_own_trainer() {
        let limits = RequestLimits::in_process();
        limits.check().expect("valid limits");
        let rates = ClientRates::new(&limits);
        // Ten times the default burst at once: a tight training loop.
        for i in 0..10 * RequestLimits::default().client_burst {
            rates
                .check("trainer")
                .unwrap_or_else(|e| panic!("request {i}: {e}"));
        }
        assert_eq!(
            limits.max_request_bytes,
            RequestLimits::default().max_request_bytes
        );
    }
}
