//! What an operator does to the enclosure outside the gym protocol: press
//! and release the e-stops (one env's, or the whole site's).

use std::time::Duration;

use offworld_runtime::codec;
use offworld_runtime::keys::{all_alive_selector, global_estop_key, Component, EnvId, Topic};
use offworld_runtime::msg::EStop;
use offworld_runtime::wire::{self, Delivery};
use offworld_runtime::zenoh::bytes::Encoding;
use offworld_runtime::zenoh::Session;

use crate::error::ControllerError;

/// Which e-stop.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum EStopScope {
    /// One env's robot (or twin).
    Env(EnvId),
    /// Every robot of the site.
    Site,
}

impl EStopScope {
    /// The key the robots listen on.
    pub fn key(&self) -> String {
        match self {
            Self::Env(env) => env.key(Topic::EStop),
            Self::Site => global_estop_key(),
        }
    }

    /// The liveliness tokens of whatever obeys this e-stop.
    fn obeyed_by(&self) -> String {
        match self {
            Self::Env(env) => format!("{}/alive/*", env.prefix()),
            Self::Site => all_alive_selector(),
        }
    }
}

/// Publishes `stop` on `scope`'s key once a robot agent or a twin is
/// present there (its liveliness token), waiting at most `wait` for one: a
/// press nobody obeys is an error, not a silent success. The publication
/// waits out a congested link instead of being dropped.
pub async fn press_estop(
    session: &Session,
    scope: &EStopScope,
    stop: &EStop,
    wait: Duration,
) -> Result<(), ControllerError> {
    let zerr = |e: String| ControllerError::Zenoh(e);
    let key = scope.key();
    let deadline = tokio::time::Instant::now() + wait;
    while !embodiment_present(session, scope, deadline).await? {
        if tokio::time::Instant::now() >= deadline {
            return Err(ControllerError::NotFound(format!(
                "no robot or twin listens on {key} (waited {:.1} s): the e-stop reached nobody",
                wait.as_secs_f64()
            )));
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let bytes = codec::encode(stop).map_err(|e| zerr(e.to_string()))?;
    session
        .put(&key, bytes)
        .encoding(Encoding::APPLICATION_CDR)
        .congestion_control(Delivery::Every.congestion_control())
        .priority(wire::CONTROL_PRIORITY)
        .await
        .map_err(|e| zerr(e.to_string()))?;
    tracing::warn!(%key, engaged = stop.engaged, reason = %stop.reason, "e-stop published");
    Ok(())
}

/// Whether a robot agent or twin under `scope` declares itself alive.
async fn embodiment_present(
    session: &Session,
    scope: &EStopScope,
    deadline: tokio::time::Instant,
) -> Result<bool, ControllerError> {
    let left = deadline.saturating_duration_since(tokio::time::Instant::now());
    let replies = session
        .liveliness()
        .get(scope.obeyed_by())
        .timeout(left.max(Duration::from_millis(100)))
        .await
        .map_err(|e| ControllerError::Zenoh(e.to_string()))?;
    let obeys =
        [Component::RobotAgent, Component::SimTwin].map(|c| format!("/alive/{}", c.as_str()));
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            let token = sample.key_expr().as_str();
            if obeys.iter().any(|suffix| token.ends_with(suffix.as_str())) {
                return Ok(true);
            }
        }
    }
    Ok(false)
}
