//! E-stop semantics, defined once for every component that obeys or shows
//! them (robot agent, twin, controller, operator CLI).
//!
//! Two latches apply to every env: the site-wide one
//! (`offworld/@v1/estop`) and the env's own (`<env>/estop`). They are
//! independent: engaging or releasing one never touches the other, and
//! motion is refused while either is engaged. Every change is stamped with
//! the wall clock, so a component that restarts merges what it kept on disk
//! with what the network remembers ([`crate::keys::Topic::EStopState`]) by
//! taking, per latch, the newer report.

use std::time::Duration;

use tokio::sync::watch;
use zenoh::bytes::ZBytes;
use zenoh::query::{ConsolidationMode, Query, QueryTarget, Reply};
use zenoh::{Session, Wait};

use crate::codec;
use crate::keys::{topic_on_all_envs, EnvId, Topic};
use crate::msg::{EStop, EStopState, LatchState, Time};

/// Which latch an e-stop publication sets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, strum::IntoStaticStr)]
#[strum(serialize_all = "snake_case")]
pub enum Latch {
    /// Every robot of the site.
    Site,
    /// One env's robot or twin.
    Env,
}

impl Latch {
    /// `site` or `env`, for logs and messages.
    pub fn as_str(self) -> &'static str {
        self.into()
    }
}

fn newer(a: &Time, b: &Time) -> bool {
    (a.sec, a.nanosec) > (b.sec, b.nanosec)
}

impl EStopState {
    /// The latch `latch`.
    pub fn latch(&self, latch: Latch) -> &LatchState {
        match latch {
            Latch::Site => &self.site,
            Latch::Env => &self.env,
        }
    }

    /// Applies `stop` to `latch` at `now`; returns whether it changed
    /// whether that latch is engaged.
    pub fn apply(&mut self, latch: Latch, stop: &EStop, now: Time) -> bool {
        let slot = match latch {
            Latch::Site => &mut self.site,
            Latch::Env => &mut self.env,
        };
        let changed = slot.engaged != stop.engaged;
        *slot = LatchState {
            engaged: stop.engaged,
            reason: stop.reason.clone(),
            changed: now,
        };
        changed
    }

    /// Takes, per latch, `other`'s report where it is newer than ours:
    /// how a component merges what the network or its disk remembers into
    /// the latches it acts on. Returns whether anything engaged or
    /// released. A report stamped in this host's future (another host's
    /// clock ahead) counts as made now: it must not outrank every press
    /// this host applies later.
    pub fn merge(&mut self, other: &EStopState) -> bool {
        let now = Time::now();
        let mut changed = false;
        for (ours, theirs) in [(&mut self.site, &other.site), (&mut self.env, &other.env)] {
            if newer(&theirs.changed, &ours.changed) {
                changed |= ours.engaged != theirs.engaged;
                *ours = theirs.clone();
                if newer(&ours.changed, &now) {
                    ours.changed = now;
                }
            }
        }
        changed
    }

    /// Whether any latch refuses motion.
    pub fn engaged(&self) -> bool {
        self.site.engaged || self.env.engaged
    }

    /// Why motion is refused, naming every engaged latch, if it is.
    pub fn refusal(&self) -> Option<String> {
        let engaged: Vec<String> = [Latch::Site, Latch::Env]
            .into_iter()
            .filter(|l| self.latch(*l).engaged)
            .map(|l| format!("{} ({})", l.as_str(), self.latch(l).reason))
            .collect();
        (!engaged.is_empty()).then(|| format!("e-stop engaged: {}", engaged.join(", ")))
    }

    /// The engaged latches as `site`, `env`, `site+env` or `none`.
    pub fn summary(&self) -> &'static str {
        match (self.site.engaged, self.env.engaged) {
            (true, true) => "site+env",
            (true, false) => "site",
            (false, true) => "env",
            (false, false) => "none",
        }
    }
}

/// What an obeyer did with one e-stop publication ([`RecentPresses::apply`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Pressed {
    /// Applied to its latch.
    Applied,
    /// A copy of a press applied already: acknowledged, not applied again.
    Repeated,
    /// A release pressed before the latch's last change (a late copy of
    /// it, or an operator's clock behind): refused, the latch stands.
    Outdated,
}

/// How far a latch's stamp may run ahead of this host's clock before it
/// counts as this clock having stepped back (and no longer orders presses).
pub const CLOCK_STEP: Duration = Duration::from_secs(60);

/// A new press id: the operator's wall clock in nanoseconds since the
/// epoch, strictly increasing within this process (a clock before the
/// epoch gives a random id: ids must still differ). Obeyers order releases
/// by it ([`RecentPresses::apply`]), so an operator can publish a press
/// again, engage or release, while an obeyer is silent.
pub fn new_press_id() -> u64 {
    use std::sync::atomic::{AtomicU64, Ordering};
    static LAST: AtomicU64 = AtomicU64::new(0);
    let now = match Time::now_unix_nanos() {
        0 => rand::random_range(1..u64::MAX / 2),
        now => now,
    };
    let previous = LAST
        .fetch_update(Ordering::AcqRel, Ordering::Acquire, |last| {
            Some(now.max(last.saturating_add(1)))
        })
        .unwrap_or(0);
    now.max(previous.saturating_add(1))
}

/// The presses an obeyer applied lately, and the rule every obeyer (robot
/// agent, twin) and the controller apply a press by. An operator publishes
/// a press again while an obeyer is silent (`operator::press_estop`):
/// every copy is acknowledged, only the first applied, so a late copy of
/// an engage does not re-engage a latch released since; a release applies
/// only when pressed after the latch's last change, so a late copy of a
/// release never undoes an engage pressed in between.
#[derive(Debug, Default)]
pub struct RecentPresses(std::collections::VecDeque<u64>);

impl RecentPresses {
    /// How many press ids are remembered: far more than can be in flight.
    const KEPT: usize = 64;

    /// Applies `stop` to `latch` of `state`, this host's clock reading
    /// `now`. An engage always applies (safety first, whatever the clocks
    /// say), stamped when it arrived here (after the latch's last change):
    /// the latch's newest report. A release applies only when pressed after
    /// the latch's last change, its press time read from its id and never
    /// later than `now` — so a late copy of a release pressed before an
    /// engage arrived never undoes it (up to how far the releaser's clock
    /// runs ahead of this one: sites keep clocks in sync). A latch stamped
    /// more than [`CLOCK_STEP`] in this host's future (its clock stepped
    /// back; merged reports are never stamped ahead) cannot order presses:
    /// a release then applies, as a publication naming no press (id 0)
    /// always does; a smaller step holds releases until the clock passes
    /// the stamp.
    pub fn apply(
        &mut self,
        state: &mut EStopState,
        latch: Latch,
        stop: &EStop,
        now: Time,
    ) -> Pressed {
        if !self.first_time(stop.press_id) {
            return Pressed::Repeated;
        }
        let (last, now) = (
            state.latch(latch).changed.as_unix_nanos(),
            now.as_unix_nanos(),
        );
        let clock_stepped_back = last > now.saturating_add(CLOCK_STEP.as_nanos() as u64);
        let stamp = if stop.engaged || stop.press_id == 0 || clock_stepped_back {
            now.max(last.saturating_add(1))
        } else {
            let pressed = stop.press_id.min(now);
            if pressed <= last {
                return Pressed::Outdated;
            }
            pressed
        };
        state.apply(latch, stop, Time::from_unix_nanos(stamp));
        Pressed::Applied
    }

    /// Whether the press `press_id` is new here (remembering it). Id 0 (a
    /// publication that names no press) is always new.
    fn first_time(&mut self, press_id: u64) -> bool {
        if press_id == 0 {
            return true;
        }
        if self.0.contains(&press_id) {
            return false;
        }
        if self.0.len() == Self::KEPT {
            self.0.pop_front();
        }
        self.0.push_back(press_id);
        true
    }
}

/// An e-stop publication as every obeying component reads it: one that
/// does not decode engages (safety first), naming why.
pub fn decode(payload: &ZBytes) -> EStop {
    codec::decode_payload::<EStop>(payload)
        .unwrap_or_else(|e| EStop::new(true, format!("malformed e-stop ({e})")))
}

/// The callback of `env`'s `estop_state` queryable answering `state`'s
/// current value (robot agents, twins and the controller declare one per
/// env). The reply carries the env's own key, not the asker's selector: a
/// starting component asks every env at once and takes the env latch only
/// from its own env's answers.
pub fn state_replier(
    env: &EnvId,
    state: watch::Receiver<EStopState>,
) -> impl Fn(Query) + Send + Sync + 'static {
    let key = env.key(Topic::EStopState);
    move |query: Query| {
        let current = state.borrow().clone();
        let sent = codec::encode(&current)
            .map_err(|e| e.to_string())
            .and_then(|bytes| {
                query
                    .reply(key.as_str(), bytes)
                    .encoding(zenoh::bytes::Encoding::APPLICATION_CDR)
                    .wait()
                    .map_err(|e| e.to_string())
            });
        if let Err(e) = sent {
            tracing::warn!("e-stop state reply failed: {e}");
        }
    }
}

/// What the network remembers of the e-stops that apply to `env`: asks
/// every `estop_state` queryable of the site (robot agents, twins,
/// controllers) for at most `timeout` and merges the newest report per
/// latch: the site latch from any env's answer, the env latch only from
/// answers for `env`. Nobody answering gives the default (released, never
/// changed), which loses to anything kept on disk.
pub async fn recall(session: &Session, env: &EnvId, timeout: Duration) -> EStopState {
    let mut recalled = Recalled::default();
    match recall_query(session, timeout).await {
        Ok(replies) => {
            while let Ok(reply) = replies.recv_async().await {
                recalled.fold(env, &reply);
            }
        }
        Err(e) => tracing::warn!("cannot ask the network for e-stop state: {e}"),
    }
    recalled.stamped_by_arrival()
}

/// When a starting component asks the network again, after its first
/// [`recall`]: a session that has just connected may not have heard of
/// every `estop_state` queryable yet (a router still exchanging
/// declarations), and a latch learnt late must still be learnt.
pub const RECALL_AGAIN: [Duration; 4] = [
    Duration::from_millis(300),
    Duration::from_secs(1),
    Duration::from_secs(2),
    Duration::from_secs(4),
];

/// Asks the network again at each of [`RECALL_AGAIN`] (each ask bounded by
/// `timeout`) and merges what it remembers into `state` (the newer report
/// per latch wins, so a change heard live since is never undone). Returns
/// when done or when every receiver of `state` is gone.
pub async fn keep_recalling(
    session: Session,
    env: EnvId,
    state: watch::Sender<EStopState>,
    timeout: Duration,
) {
    for delay in RECALL_AGAIN {
        tokio::time::sleep(delay).await;
        if state.is_closed() {
            return;
        }
        let network = recall(&session, &env, timeout).await;
        let mut merged = false;
        state.send_if_modified(|s| {
            merged = s.merge(&network);
            merged
        });
        if merged {
            tracing::warn!(%env, now = state.borrow().summary(), "e-stop latches learnt late from the network");
        }
    }
}

/// [`recall`] for a caller that is not async (a simulation thread's setup).
pub fn recall_wait(session: &Session, env: &EnvId, timeout: Duration) -> EStopState {
    let mut recalled = Recalled::default();
    match recall_query(session, timeout).wait() {
        Ok(replies) => {
            while let Ok(reply) = replies.recv() {
                recalled.fold(env, &reply);
            }
        }
        Err(e) => tracing::warn!("cannot ask the network for e-stop state: {e}"),
    }
    recalled.stamped_by_arrival()
}

fn recall_query(
    session: &Session,
    timeout: Duration,
) -> zenoh::session::SessionGetBuilder<'_, '_, zenoh::handlers::DefaultHandler> {
    session
        .get(topic_on_all_envs(Topic::EStopState))
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
}

/// The replies of one recall, combined: per latch the newest report as
/// stamped (the newest wins whatever order the replies arrive in), and when
/// that reply arrived here.
#[derive(Debug, Default)]
struct Recalled {
    state: EStopState,
    /// When the winning reply of the site and the env latch arrived.
    arrived: [Time; 2],
}

impl Recalled {
    /// Takes `reply`: the site latch from any env's answer, the env latch
    /// only from answers for `env`.
    fn fold(&mut self, env: &EnvId, reply: &Reply) {
        let Ok(sample) = reply.result() else { return };
        let Ok(theirs) = codec::decode_payload::<EStopState>(sample.payload()) else {
            tracing::warn!(key = %sample.key_expr(), "ignored a malformed e-stop state");
            return;
        };
        let same_env = EnvId::from_key(sample.key_expr().as_str()).is_ok_and(|e| &e == env);
        let report = EStopState {
            site: theirs.site,
            env: if same_env {
                theirs.env
            } else {
                LatchState::default()
            },
        };
        self.take(&report, Time::now());
    }

    fn take(&mut self, report: &EStopState, arrived: Time) {
        let latches = [
            (&mut self.state.site, &report.site),
            (&mut self.state.env, &report.env),
        ];
        for (i, (ours, theirs)) in latches.into_iter().enumerate() {
            if newer(&theirs.changed, &ours.changed) {
                *ours = theirs.clone();
                self.arrived[i] = arrived;
            }
        }
    }

    /// The latches, each stamped no later than its reply arrived: a report
    /// stamped ahead of this host's clock never outranks a press applied
    /// here after it arrived (see [`EStopState::merge`]).
    fn stamped_by_arrival(self) -> EStopState {
        let mut state = self.state;
        for (latch, arrived) in [
            (&mut state.site, self.arrived[0]),
            (&mut state.env, self.arrived[1]),
        ] {
            if newer(&latch.changed, &arrived) {
                latch.changed = arrived;
            }
        }
        state
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn at(sec: i32) -> Time {
        Time { sec, nanosec: 0 }
    }

    fn press(engaged: bool, press_id: u64) -> EStop {
        EStop {
            engaged,
            reason: format!("press {press_id}"),
            press_id,
        }
    }

    const SECOND: u64 = 1_000_000_000;

    fn millis(ms: u64) -> Time {
        Time::from_unix_nanos(ms * 1_000_000)
    }

    /// A press is applied once however often it arrives; id 0 always
    /// applies; the oldest ids are forgotten past the bound.
    #[test]
    fn a_repeated_press_is_applied_once() {
        let (mut recent, mut state) = (RecentPresses::default(), EStopState::default());
        let mut apply = |stop, now| recent.apply(&mut state, Latch::Env, &stop, now);
        assert_eq!(apply(press(true, 7 * SECOND), at(100)), Pressed::Applied);
        assert_eq!(apply(press(false, 103 * SECOND), at(102)), Pressed::Applied);
        assert_eq!(
            apply(press(true, 7 * SECOND), at(104)),
            Pressed::Repeated,
            "a late copy"
        );
        assert_eq!(apply(EStop::new(true, "no id"), at(90)), Pressed::Applied);
        assert_eq!(apply(EStop::new(false, "no id"), at(90)), Pressed::Applied);
        assert!(!state.engaged());
        // An engage is stamped on arrival, a release never ahead of the
        // clock, and each change after the last.
        assert_eq!(state.env.changed, Time::from_unix_nanos(102 * SECOND + 2));
        let now = at(100);
        for id in 1000..1000 + RecentPresses::KEPT as u64 {
            recent.apply(&mut state, Latch::Site, &press(true, id), now);
        }
        assert!(recent.first_time(7 * SECOND), "forgotten past the bound");
    }

    /// A release applies only when pressed after the latch's last change: a
    /// late copy of one never undoes an engage that arrived in between,
    /// even from an operator whose clock is behind. An engage always
    /// applies.
    #[test]
    fn a_release_applies_only_after_the_latchs_last_change() {
        let (mut recent, mut state) = (RecentPresses::default(), EStopState::default());
        // Bob's clock is 2 s behind: his engage pressed at 100.5 reads
        // 98.5, and arrives at 100.6.
        assert_eq!(
            recent.apply(
                &mut state,
                Latch::Env,
                &press(true, 98_500_000_000),
                millis(100_600)
            ),
            Pressed::Applied
        );
        // Alice pressed a release at 100.0; its first copies were lost and
        // a later copy arrives at 100.75.
        assert_eq!(
            recent.apply(
                &mut state,
                Latch::Env,
                &press(false, 100 * SECOND),
                millis(100_750)
            ),
            Pressed::Outdated
        );
        assert!(state.env.engaged, "Bob's engage stands");
        assert_eq!(state.env.reason, "press 98500000000");
        // A release pressed after it applies; the other latch is another story.
        assert_eq!(
            recent.apply(
                &mut state,
                Latch::Env,
                &press(false, 101 * SECOND),
                millis(101_010)
            ),
            Pressed::Applied
        );
        assert_eq!(state.env.changed, at(101));
        assert_eq!(
            recent.apply(&mut state, Latch::Site, &press(false, 16 * SECOND), at(200)),
            Pressed::Applied
        );
        // A release stamped far ahead counts as pressed now.
        recent.apply(&mut state, Latch::Env, &press(true, 0x7000), at(300));
        assert_eq!(
            recent.apply(&mut state, Latch::Env, &press(false, u64::MAX), at(300)),
            Pressed::Outdated,
            "not after the engage that arrived at 300"
        );
        assert_eq!(
            recent.apply(&mut state, Latch::Env, &press(false, u64::MAX - 1), at(301)),
            Pressed::Applied
        );
        assert_eq!(state.env.changed, at(301));
        // This host's clock stepped back by 10 s: releases wait until it
        // passes the latch's stamp; by more than a minute: time cannot
        // order presses, a release applies.
        recent.apply(&mut state, Latch::Env, &press(true, 0x7001), at(400));
        assert_eq!(
            recent.apply(&mut state, Latch::Env, &press(false, 390 * SECOND), at(390)),
            Pressed::Outdated
        );
        assert_eq!(
            recent.apply(&mut state, Latch::Env, &press(false, 339 * SECOND), at(339)),
            Pressed::Applied
        );
        assert_eq!(state.env.changed, Time::from_unix_nanos(400 * SECOND + 1));
    }

    /// The replies of one recall are combined as reported (the newest wins
    /// whatever their order), each latch then stamped no later than its
    /// winning reply arrived.
    #[test]
    fn one_recall_keeps_the_newest_report_whatever_the_order() {
        let report = |engaged: bool, reason: &str, stamp: u64| {
            let mut state = EStopState::default();
            state.apply(Latch::Env, &EStop::new(engaged, reason), at(stamp as i32));
            state
        };
        let mut recalled = Recalled::default();
        // Stamped by a clock 10 s ahead of this one: the newest arrives first.
        recalled.take(&report(true, "newest", 105), at(95));
        recalled.take(&report(false, "staler", 102), at(96));
        recalled.take(&report(false, "oldest", 50), at(97));
        let live = recalled.stamped_by_arrival();
        assert!(live.env.engaged);
        assert_eq!(live.env.reason, "newest");
        assert_eq!(live.env.changed, at(95), "capped at its arrival");
        assert_eq!(
            live.site,
            LatchState::default(),
            "nobody reported the site latch"
        );
        // A report stamped in the past keeps its stamp.
        let mut recalled = Recalled::default();
        recalled.take(&report(true, "past", 40), at(95));
        assert_eq!(recalled.stamped_by_arrival().env.changed, at(40));
    }

    /// Press ids are the wall clock in nanoseconds, strictly increasing.
    #[test]
    fn press_ids_are_times_that_only_grow() {
        let before = Time::now_unix_nanos();
        let ids: Vec<u64> = (0..1000).map(|_| new_press_id()).collect();
        assert!(ids.windows(2).all(|w| w[0] < w[1]), "strictly increasing");
        assert!(ids[0] >= before);
        assert!(ids[999] - ids[0] < 60 * SECOND);
    }

    #[test]
    fn times_convert_to_nanoseconds_exactly() {
        let t = Time::from_unix_nanos(1_764_211_200_123_456_789);
        assert_eq!((t.sec, t.nanosec), (1_764_211_200, 123_456_789));
        assert_eq!(t.as_unix_nanos(), 1_764_211_200_123_456_789);
        assert_eq!(Time::from_unix_nanos(u64::MAX).sec, i32::MAX);
        assert_eq!(
            Time {
                sec: -1,
                nanosec: 5
            }
            .as_unix_nanos(),
            5
        );
    }

    #[test]
    fn site_and_env_latches_are_independent() {
        let mut state = EStopState::default();
        assert!(state.apply(Latch::Site, &EStop::new(true, "fire alarm"), at(1)));
        assert!(state.apply(Latch::Env, &EStop::new(true, "person inside"), at(2)));
        assert_eq!(
            state.refusal().as_deref(),
            Some("e-stop engaged: site (fire alarm), env (person inside)")
        );
        assert!(state.apply(Latch::Env, &EStop::new(false, "clear"), at(3)));
        assert!(state.engaged(), "the env release leaves the site latch");
        assert_eq!(state.summary(), "site");
        assert!(!state.apply(Latch::Env, &EStop::new(false, "again"), at(4)));
        assert!(state.apply(Latch::Site, &EStop::new(false, "all clear"), at(5)));
        assert_eq!(state.refusal(), None);
    }

    #[test]
    fn a_merge_takes_the_newer_report_per_latch() {
        // Kept on disk: site engaged at t=10, env released at t=0.
        let mut ours = EStopState::default();
        ours.apply(Latch::Site, &EStop::new(true, "drill"), at(10));
        // The network: site released at t=20 (while we were down), env
        // engaged at t=15.
        let mut theirs = EStopState::default();
        theirs.apply(Latch::Site, &EStop::new(false, "drill over"), at(20));
        theirs.apply(Latch::Env, &EStop::new(true, "maintenance"), at(15));
        assert!(ours.merge(&theirs));
        assert!(!ours.site.engaged);
        assert_eq!(ours.env.reason, "maintenance");
        // A report stamped in this host's future counts as made now.
        let mut ahead = EStopState::default();
        let far = Time::from_unix_nanos(Time::now_unix_nanos() + 3600 * SECOND);
        ahead.apply(Latch::Site, &EStop::new(true, "clock ahead"), far);
        let mut here = EStopState::default();
        assert!(here.merge(&ahead));
        assert!(here.site.engaged);
        assert!(here.site.changed.as_unix_nanos() <= Time::now_unix_nanos());
        // An older report changes nothing.
        let mut stale = EStopState::default();
        stale.apply(Latch::Env, &EStop::new(false, "old"), at(5));
        assert!(!ours.merge(&stale));
        assert!(ours.env.engaged);
    }
}
