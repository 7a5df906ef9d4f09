//! What an operator does to the enclosure outside the gym protocol: press
//! and release the e-stops (one env's, or the whole site's).

use std::time::Duration;

use offworld_runtime::keys::{global_estop_key, EnvId, Topic};
use offworld_runtime::msg::EStop;
use offworld_runtime::wire::{self, Delivery};
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
}

/// Publishes `stop` on `scope`'s key as soon as something (a robot agent or
/// a twin) subscribes to it, waiting at most `wait` for one: a press nobody
/// hears is an error, not a silent success. The publication waits out a
/// congested link instead of being dropped.
pub async fn press_estop(
    session: &Session,
    scope: &EStopScope,
    stop: &EStop,
    wait: Duration,
) -> Result<(), ControllerError> {
    let zerr = |e: String| ControllerError::Zenoh(e);
    let key = scope.key();
    let publisher = wire::publisher(session, key.clone(), Delivery::Every)
        .await
        .map_err(|e| zerr(e.to_string()))?;
    let deadline = tokio::time::Instant::now() + wait;
    loop {
        let status = publisher
            .matching_status()
            .await
            .map_err(|e| zerr(e.to_string()))?;
        if status.matching() {
            break;
        }
        if tokio::time::Instant::now() >= deadline {
            return Err(ControllerError::NotFound(format!(
                "no robot or twin listens on {key} (waited {:.1} s): the e-stop reached nobody",
                wait.as_secs_f64()
            )));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    wire::publish(&publisher, stop).map_err(|e| zerr(e.to_string()))?;
    tracing::warn!(%key, engaged = stop.engaged, reason = %stop.reason, "e-stop published");
    Ok(())
}
