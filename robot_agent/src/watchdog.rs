//! The dead-man switch: the robot may move only while the controller is
//! demonstrably there. Pure state, driven by the agent's clock so it can be
//! tested without time passing.

use std::time::{Duration, Instant};

/// What changed at a check.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Transition {
    /// Just disarmed: stop now.
    Tripped(String),
    /// Signs of life are back: new commands may move the robot again.
    Rearmed,
}

/// Trips when neither a command nor a heartbeat arrived within the window
/// or the controller's liveliness token disappeared; re-arms once both are
/// back. Starts disarmed.
#[derive(Debug, Clone)]
pub struct Watchdog {
    window: Duration,
    last_sign_of_life: Option<Instant>,
    controller_present: bool,
    /// `None`: no base guard required; else whether one is there.
    guard_present: Option<bool>,
    armed: bool,
}

impl Watchdog {
    /// A disarmed watchdog with `window`.
    pub fn new(window: Duration) -> Self {
        Self {
            window,
            last_sign_of_life: None,
            controller_present: false,
            guard_present: None,
            armed: false,
        }
    }

    /// Motion also needs the robot's base guard to be there.
    pub fn require_guard(mut self) -> Self {
        self.guard_present = Some(false);
        self
    }

    /// The base guard's liveliness token appeared or vanished.
    pub fn guard_present(&mut self, present: bool) {
        if self.guard_present.is_some() {
            self.guard_present = Some(present);
        }
    }

    /// A command or heartbeat arrived.
    pub fn sign_of_life(&mut self, now: Instant) {
        self.last_sign_of_life = Some(now);
    }

    /// The controller's liveliness token appeared or vanished.
    pub fn controller_present(&mut self, present: bool) {
        self.controller_present = present;
    }

    /// Whether the controller's liveliness token is there (a trip without
    /// it means the controller is gone, not merely late).
    pub fn controller_is_present(&self) -> bool {
        self.controller_present
    }

    /// Whether motion is allowed.
    pub fn armed(&self) -> bool {
        self.armed
    }

    /// Why motion is not allowed now, if it is not.
    pub fn fault(&self, now: Instant) -> Option<String> {
        if self.guard_present == Some(false) {
            return Some(
                "no base guard on the robot: start it for this env (`offworld guard --env …`, or set \
                 require_base_guard = false for a base with a verified command timeout)"
                    .into(),
            );
        }
        if !self.controller_present {
            return Some("the controller's liveliness token is gone".into());
        }
        match self.last_sign_of_life {
            None => Some("no controller heartbeat yet".into()),
            Some(t) if now.saturating_duration_since(t) > self.window => Some(format!(
                "no command or controller heartbeat for {} ms (window {} ms)",
                now.saturating_duration_since(t).as_millis(),
                self.window.as_millis()
            )),
            Some(_) => None,
        }
    }

    /// Updates the state; reports a trip or a re-arm once.
    pub fn check(&mut self, now: Instant) -> Option<Transition> {
        match (self.armed, self.fault(now)) {
            (true, Some(reason)) => {
                self.armed = false;
                Some(Transition::Tripped(reason))
            }
            (false, None) => {
                self.armed = true;
                Some(Transition::Rearmed)
            }
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn arms_on_heartbeat_and_presence_and_trips_on_silence() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut dog = Watchdog::new(ms(200));
        assert_eq!(dog.check(t0), None);
        assert!(!dog.armed());
        dog.sign_of_life(t0);
        assert_eq!(dog.check(t0), None, "no controller token yet");
        dog.controller_present(true);
        assert_eq!(dog.check(t0), Some(Transition::Rearmed));
        assert_eq!(dog.check(t0 + ms(200)), None, "still inside the window");
        assert!(matches!(
            dog.check(t0 + ms(201)),
            Some(Transition::Tripped(_))
        ));
        assert!(!dog.armed());
        assert_eq!(dog.check(t0 + ms(300)), None, "trips once");
        dog.sign_of_life(t0 + ms(400));
        assert_eq!(dog.check(t0 + ms(400)), Some(Transition::Rearmed));
    }

    #[test]
    fn a_required_guard_gates_arming_and_its_loss_trips() {
        let t0 = Instant::now();
        let mut dog = Watchdog::new(Duration::from_millis(200)).require_guard();
        dog.sign_of_life(t0);
        dog.controller_present(true);
        assert_eq!(dog.check(t0), None, "no guard yet: stays disarmed");
        assert!(dog.fault(t0).is_some_and(|f| f.contains("base_guard")));
        dog.guard_present(true);
        assert_eq!(dog.check(t0), Some(Transition::Rearmed));
        dog.guard_present(false);
        assert!(matches!(dog.check(t0), Some(Transition::Tripped(r)) if r.contains("base guard")));
    }

    #[test]
    fn trips_at_once_when_the_controller_token_vanishes() {
        let t0 = Instant::now();
        let mut dog = Watchdog::new(Duration::from_millis(200));
        dog.sign_of_life(t0);
        dog.controller_present(true);
        dog.check(t0);
        dog.controller_present(false);
        match dog.check(t0) {
            Some(Transition::Tripped(reason)) => assert!(reason.contains("liveliness")),
            other => panic!("expected a trip, got {other:?}"),
        }
    }
}
