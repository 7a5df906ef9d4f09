//! The base guard: an independent safety process on the robot's computer
//! that stops the base when the robot agent cannot.
//!
//! The agent's watchdog covers everything upstream of the agent (controller
//! dead, frozen or cut off). Nothing inside the agent can cover the agent
//! itself: killed (`SIGKILL`, OOM), frozen (`SIGSTOP`, a deadlock) or cut
//! from the robot's router, it simply stops publishing, and a base without
//! its own command timeout holds the last velocity forever. The guard runs
//! as a separate process (its own systemd unit), watches the base's
//! velocity topic and the agent's liveliness token, and publishes zero
//! velocity on the same topic when
//!
//! - the base was last told to move and no velocity command followed
//!   within `stale_ms` (the agent streams at `control_hz`, 50 Hz, while it
//!   moves, so a silent stream means a dead or frozen agent), or
//! - the agent's liveliness token disappears (killed: its session closed).
//!
//! It repeats the zero for `zero_for_ms` at `rate_hz`, then stays quiet
//! until the base moves again. It never commands anything but zero.
//! [`BaseGuard`] is the pure decision, driven by the caller's clock; [`spawn`]
//! runs it over Zenoh.

use std::time::{Duration, Instant};

use offworld_runtime::codec;
use offworld_runtime::keys::{Component, EnvId, Topic};
use offworld_runtime::msg::{MotionFault, Twist};
use offworld_runtime::ros2::{RobotTopics, RosGraph, RosType};
use offworld_runtime::wire::{self, Delivery};
use serde::{Deserialize, Serialize};
use tokio::sync::{mpsc, oneshot};
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::sample::{Sample, SampleKind};
use zenoh::Session;

use crate::agent::NodeHandle;
use crate::error::AgentError;
use crate::limiter::Velocity;
use crate::ros2::CmdVelPublisher;

/// The guard's timings.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GuardConfig {
    /// A moving base with no velocity command for this long is stopped, ms.
    pub stale_ms: u64,
    /// How long zero velocity is repeated after a trip, ms.
    pub zero_for_ms: u64,
    /// Zero velocity commands per second while tripped.
    pub rate_hz: f64,
}

impl Default for GuardConfig {
    /// 150 ms: seven missed commands of the agent's 50 Hz stream; with the
    /// guard's 10 ms check and delivery, the base is told zero within the
    /// 200 ms the safety design allows.
    fn default() -> Self {
        Self {
            stale_ms: 150,
            zero_for_ms: 1000,
            rate_hz: 20.0,
        }
    }
}

impl GuardConfig {
    /// Rejects timings that would make the guard useless or a flood.
    pub fn validate(&self) -> Result<(), AgentError> {
        if !(1..=1000).contains(&self.stale_ms) {
            return Err(AgentError::Config(format!(
                "guard stale_ms must be in 1..=1000, got {}",
                self.stale_ms
            )));
        }
        if !(1..=60_000).contains(&self.zero_for_ms) {
            return Err(AgentError::Config(format!(
                "guard zero_for_ms must be in 1..=60000, got {}",
                self.zero_for_ms
            )));
        }
        if !(self.rate_hz.is_finite() && (1.0..=200.0).contains(&self.rate_hz)) {
            return Err(AgentError::Config(format!(
                "guard rate_hz must be in 1..=200, got {}",
                self.rate_hz
            )));
        }
        Ok(())
    }
}

/// The guard's decision, as pure state.
#[derive(Debug, Clone)]
pub struct BaseGuard {
    config: GuardConfig,
    /// The newest velocity command seen on the base's topic: when, and
    /// whether it moves the base.
    last_command: Option<(Instant, bool)>,
    agent_present: bool,
    /// Zeroing until then, and why.
    tripped: Option<(Instant, String)>,
    next_zero: Option<Instant>,
    /// The previous check: a long gap means the guard itself did not run.
    last_check: Option<Instant>,
}

impl BaseGuard {
    /// A quiet guard.
    pub fn new(config: GuardConfig) -> Self {
        Self {
            config,
            last_command: None,
            agent_present: false,
            tripped: None,
            next_zero: None,
            last_check: None,
        }
    }

    /// A velocity command was seen on the base's topic (from anyone,
    /// including the guard's own zeros).
    pub fn command_seen(&mut self, now: Instant, moving: bool) {
        self.last_command = Some((now, moving));
        if moving && self.tripped.is_some() {
            // The agent drives again: it is alive and its own watchdog
            // decides from here.
            tracing::info!("base guard: the agent commands the base again");
            self.tripped = None;
            self.next_zero = None;
        }
    }

    /// The robot agent's liveliness token appeared or vanished. Returns a
    /// trip reason when it vanished.
    pub fn agent_present(&mut self, now: Instant, present: bool) -> Option<String> {
        let was = std::mem::replace(&mut self.agent_present, present);
        if was && !present {
            let reason = "the robot agent's liveliness token is gone".to_owned();
            self.trip(now, reason.clone());
            return Some(reason);
        }
        None
    }

    /// Checks the velocity stream; returns a trip reason once when it fires.
    pub fn check(&mut self, now: Instant) -> Option<String> {
        let stale = Duration::from_millis(self.config.stale_ms);
        let paused = self
            .last_check
            .is_some_and(|t| now.saturating_duration_since(t) > stale / 2);
        self.last_check = Some(now);
        if paused {
            // The guard itself was not running (the whole machine stalled):
            // silence it did not watch is no evidence against the agent,
            // which gets a full window from now.
            if let Some((at, _)) = &mut self.last_command {
                *at = (*at).max(now);
            }
            return None;
        }
        let (at, moving) = self.last_command?;
        let silent = now.saturating_duration_since(at);
        if moving && self.tripped.is_none() && silent > Duration::from_millis(self.config.stale_ms)
        {
            let reason = format!(
                "no velocity command for {} ms while the base moves (limit {} ms): the agent is dead, frozen or cut off",
                silent.as_millis(),
                self.config.stale_ms
            );
            self.trip(now, reason.clone());
            return Some(reason);
        }
        None
    }

    /// Whether a zero velocity is due now (at `rate_hz` while tripped).
    pub fn zero_due(&mut self, now: Instant) -> bool {
        let Some((until, _)) = &self.tripped else {
            return false;
        };
        if now >= *until {
            self.tripped = None;
            self.next_zero = None;
            return false;
        }
        match self.next_zero {
            Some(next) if now < next => false,
            _ => {
                self.next_zero = Some(now + Duration::from_secs_f64(1.0 / self.config.rate_hz));
                true
            }
        }
    }

    /// Why the guard is zeroing the base, if it is.
    pub fn tripped(&self) -> Option<&str> {
        self.tripped.as_ref().map(|(_, reason)| reason.as_str())
    }

    fn trip(&mut self, now: Instant, reason: String) {
        self.tripped = Some((now + Duration::from_millis(self.config.zero_for_ms), reason));
        self.next_zero = None;
    }
}

enum Event {
    Command(bool),
    AgentPresent(bool),
}

/// A running guard; ends when dropped or shut down.
pub type GuardHandle = NodeHandle;

/// Guards the base of `env`'s robot on `session` (a client of the robot
/// computer's router, like the agent).
pub async fn spawn(
    session: &Session,
    env: &EnvId,
    graph: &RosGraph,
    topics: &RobotTopics,
    config: GuardConfig,
) -> Result<GuardHandle, AgentError> {
    config.validate()?;
    let (tx, events) = mpsc::unbounded_channel();
    let commands = tx.clone();
    let cmd_vel: Subscriber<()> = session
        .declare_subscriber(graph.subscription_key(&topics.cmd_vel, RosType::Twist)?)
        .callback(move |s: Sample| {
            // An unreadable command may have set anything: assume motion.
            let moving = codec::decode_payload::<Twist>(s.payload())
                .map(|t| {
                    !Velocity {
                        linear: t.linear.x,
                        angular: t.angular.z,
                    }
                    .is_zero()
                })
                .unwrap_or(true);
            let _ = commands.send(Event::Command(moving));
        })
        .await?;
    let agent: Subscriber<()> = session
        .liveliness()
        .declare_subscriber(env.alive_key(Component::RobotAgent))
        .history(true)
        .callback(move |s: Sample| {
            let _ = tx.send(Event::AgentPresent(s.kind() == SampleKind::Put));
        })
        .await?;
    let token = session
        .liveliness()
        .declare_token(env.alive_key(Component::BaseGuard))
        .await?;
    let node = GuardNode {
        env: env.clone(),
        guard: BaseGuard::new(config),
        base: CmdVelPublisher::new(session, graph, topics)?,
        fault: wire::publisher(session, env.key(Topic::Fault), Delivery::Every).await?,
        _subscribers: [cmd_vel, agent],
        _token: token,
    };
    Ok(NodeHandle::spawn(|stop| node.run(events, stop)))
}

struct GuardNode {
    env: EnvId,
    guard: BaseGuard,
    base: CmdVelPublisher,
    /// Tells the controller the command in flight will not complete.
    fault: Publisher<'static>,
    _subscribers: [Subscriber<()>; 2],
    _token: LivelinessToken,
}

/// How often the stream is checked.
const CHECK_PERIOD: Duration = Duration::from_millis(10);

impl GuardNode {
    async fn run(
        mut self,
        mut events: mpsc::UnboundedReceiver<Event>,
        mut stop: oneshot::Receiver<()>,
    ) {
        tracing::info!(env = %self.env, "base guard watching the robot agent and the base");
        let mut tick = tokio::time::interval(CHECK_PERIOD);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        loop {
            tokio::select! {
                _ = &mut stop => break,
                event = events.recv() => {
                    let now = Instant::now();
                    match event {
                        Some(Event::Command(moving)) => self.guard.command_seen(now, moving),
                        Some(Event::AgentPresent(present)) => {
                            if let Some(reason) = self.guard.agent_present(now, present) {
                                self.tripped(&reason);
                            } else if present {
                                tracing::info!(env = %self.env, "robot agent present");
                            }
                        }
                        None => break,
                    }
                    self.zero_if_due(now).await;
                }
                _ = tick.tick() => {
                    let now = Instant::now();
                    if let Some(reason) = self.guard.check(now) {
                        self.tripped(&reason);
                    }
                    self.zero_if_due(now).await;
                }
            }
        }
        tracing::info!(env = %self.env, "base guard stopped");
    }

    /// Logs a trip and fails the command in flight at the controller (it
    /// may not know yet: a frozen agent's liveliness token stays).
    fn tripped(&self, reason: &str) {
        tracing::error!(env = %self.env, %reason, "BASE GUARD: stopping the base");
        let fault = MotionFault {
            seq: MotionFault::ANY_COMMAND,
            reason: format!("the base guard stopped the base: {reason}"),
        };
        if let Err(e) = wire::publish(&self.fault, &fault) {
            tracing::warn!("base guard cannot report the stop: {e}");
        }
    }

    async fn zero_if_due(&mut self, now: Instant) {
        if self.guard.zero_due(now) {
            if let Err(e) = self.base.send(Velocity::ZERO).await {
                tracing::error!("base guard cannot command the base: {e}");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ms(n: u64) -> Duration {
        Duration::from_millis(n)
    }

    /// Checks every 10 ms (as the node does) from `from` to `to`
    /// inclusive; returns the trips with their times.
    fn run(guard: &mut BaseGuard, t0: Instant, from: u64, to: u64) -> Vec<(u64, String)> {
        (from..=to)
            .step_by(10)
            .filter_map(|t| guard.check(t0 + ms(t)).map(|r| (t, r)))
            .collect()
    }

    #[test]
    fn a_silent_stream_while_moving_trips_once_and_zeroes_at_the_rate() {
        let t0 = Instant::now();
        let mut guard = BaseGuard::new(GuardConfig::default());
        assert_eq!(
            run(&mut guard, t0, 0, 100),
            [],
            "nothing seen: nothing to guard"
        );
        guard.command_seen(t0 + ms(100), true);
        let trips = run(&mut guard, t0, 110, 400);
        assert_eq!(trips.len(), 1, "trips once: {trips:?}");
        assert_eq!(trips[0].0, 260, "first check past 150 ms of silence");
        assert!(trips[0].1.contains("160 ms"), "{}", trips[0].1);
        // Zeros at 20 Hz for a second from the trip, then quiet.
        let due: Vec<u64> = (260..1400)
            .filter(|t| guard.zero_due(t0 + ms(*t)))
            .collect();
        assert_eq!(due.len(), 20, "{due:?}");
        assert_eq!((due[0], due[1]), (260, 310));
        assert!(*due.last().expect("zeros") < 1260);
        assert_eq!(guard.tripped(), None);
    }

    #[test]
    fn a_stall_of_the_guard_itself_gives_the_agent_a_fresh_window() {
        let t0 = Instant::now();
        let mut guard = BaseGuard::new(GuardConfig::default());
        guard.command_seen(t0, true);
        assert_eq!(run(&mut guard, t0, 0, 20), []);
        // The machine stalls 700 ms: nobody ran, the guard neither.
        assert_eq!(
            guard.check(t0 + ms(720)),
            None,
            "no verdict on unwatched silence"
        );
        let trips = run(&mut guard, t0, 730, 1000);
        assert_eq!(trips.len(), 1, "{trips:?}");
        assert_eq!(trips[0].0, 880, "a full window after the stall");
    }

    #[test]
    fn a_base_told_zero_is_left_alone() {
        let t0 = Instant::now();
        let mut guard = BaseGuard::new(GuardConfig::default());
        guard.command_seen(t0, true);
        guard.command_seen(t0 + ms(20), false);
        assert_eq!(guard.check(t0 + ms(5_000)), None);
        assert!(!guard.zero_due(t0 + ms(5_000)));
    }

    #[test]
    fn the_agent_vanishing_trips_at_once_and_its_return_to_driving_clears_it() {
        let t0 = Instant::now();
        let mut guard = BaseGuard::new(GuardConfig::default());
        assert_eq!(guard.agent_present(t0, true), None);
        guard.command_seen(t0, true);
        let reason = guard.agent_present(t0 + ms(1), false).expect("trip");
        assert!(reason.contains("liveliness"), "{reason}");
        assert!(guard.zero_due(t0 + ms(1)));
        guard.agent_present(t0 + ms(50), true);
        guard.command_seen(t0 + ms(60), true);
        assert_eq!(guard.tripped(), None, "the agent drives again");
        assert!(!guard.zero_due(t0 + ms(61)));
    }

    #[test]
    fn timings_out_of_range_are_config_errors() {
        for config in [
            GuardConfig {
                stale_ms: 0,
                ..GuardConfig::default()
            },
            GuardConfig {
                zero_for_ms: 0,
                ..GuardConfig::default()
            },
            GuardConfig {
                rate_hz: f64::NAN,
                ..GuardConfig::default()
            },
        ] {
            assert!(matches!(config.validate(), Err(AgentError::Config(_))));
        }
    }
}
