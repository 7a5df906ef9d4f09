//! The e-stops as the controller sees them, per env: the site latch and the
//! env's own ([`offworld_runtime::estop`]). The controller refuses resets
//! and steps while either is engaged — the same `InvalidState` for a sim
//! env and a real one — shows them in the env's status, answers
//! `estop_state` for its envs (so a restarted robot agent or twin learns
//! them from the network), and on start learns them the same way (asking
//! again for a few seconds: a fresh session may not reach everyone yet).

use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use offworld_runtime::estop::{self, Latch, Pressed, RecentPresses};
use offworld_runtime::keys::{global_estop_key, EnvId, Topic};
use offworld_runtime::msg::{EStopState, Time};
use offworld_runtime::WireError;
use tokio::sync::watch;
use zenoh::pubsub::Subscriber;
use zenoh::query::Queryable;
use zenoh::sample::Sample;
use zenoh::Session;

use crate::error::ControllerError;

/// How long a starting controller asks the network for the latches.
const RECALL: Duration = Duration::from_millis(500);

/// One env's e-stop latches, followed live.
pub struct EnvEStops {
    state: watch::Receiver<EStopState>,
    _subscribers: [Subscriber<()>; 2],
    _queryable: Queryable<()>,
}

impl EnvEStops {
    /// Learns the latches from the network, then follows both e-stop keys.
    pub async fn follow(session: &Session, env: &EnvId) -> Result<Self, ControllerError> {
        let recalled = estop::recall(session, env, RECALL).await;
        if let Some(reason) = recalled.refusal() {
            tracing::warn!(%env, %reason, "e-stop in force at start (from the network)");
        }
        let (tx, state) = watch::channel(recalled);
        // Answers that were not routable yet come in later.
        tokio::spawn(estop::keep_recalling(
            session.clone(),
            env.clone(),
            tx.clone(),
            RECALL,
        ));
        // One record of presses for both latches, as an obeyer keeps: the
        // controller applies each press by the same rule.
        let presses = Arc::new(Mutex::new(RecentPresses::default()));
        let subscribe = |key: String, latch: Latch| {
            let (tx, env, presses) = (tx.clone(), env.clone(), presses.clone());
            session.declare_subscriber(key).callback(move |s: Sample| {
                let stop = estop::decode(s.payload());
                let mut pressed = Pressed::Repeated;
                tx.send_if_modified(|state| {
                    let mut presses = presses.lock().unwrap_or_else(PoisonError::into_inner);
                    pressed = presses.apply(state, latch, &stop, Time::now());
                    pressed == Pressed::Applied
                });
                if pressed == Pressed::Applied {
                    tracing::warn!(%env, latch = latch.as_str(), engaged = stop.engaged, reason = %stop.reason, "e-stop");
                }
            })
        };
        let env_sub = subscribe(env.key(Topic::EStop), Latch::Env).await?;
        let site_sub = subscribe(global_estop_key(), Latch::Site).await?;
        let queryable = session
            .declare_queryable(env.key(Topic::EStopState))
            .callback(estop::state_replier(env, state.clone()))
            .await?;
        Ok(Self {
            state,
            _subscribers: [env_sub, site_sub],
            _queryable: queryable,
        })
    }

    /// The latches now.
    pub fn state(&self) -> EStopState {
        self.state.borrow().clone()
    }

    /// `InvalidState` naming every engaged latch, if motion is refused.
    pub fn refuse_motion(&self) -> Result<(), WireError> {
        match self.state.borrow().refusal() {
            Some(reason) => Err(WireError::invalid_state(reason)),
            None => Ok(()),
        }
    }
}
