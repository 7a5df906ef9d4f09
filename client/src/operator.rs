//! What an operator does to the enclosure outside the gym protocol: press
//! and release the e-stops (one env's, or the whole site's), and learn who
//! obeyed.
//!
//! A press is published (never dropped, at control priority; again while
//! someone is silent); every robot agent and twin that receives it stops
//! first, then acknowledges on its env's `estop_ack` with the press's id
//! and the latches now in force.
//! The operator waits for an acknowledgement from every robot agent and
//! twin that declared itself under the scope, and a press that one of them
//! did not acknowledge in time (dropped by a router's ACL, a cut link, a
//! frozen agent) is an error, never a silent success.

use std::collections::BTreeSet;
use std::time::{Duration, Instant};

use tokio::sync::mpsc;
use zenoh::bytes::Encoding;
use zenoh::sample::Sample;
use zenoh::Session;

use offworld_runtime::codec;
use offworld_runtime::estop::{self, Latch};
use offworld_runtime::keys::{
    components_alive_selector, global_estop_key, topic_on_all_envs, Component, EnvId, Topic,
};
use offworld_runtime::msg::{EStop, EStopAck, EStopState};
use offworld_runtime::wire::{self, Delivery};
use offworld_runtime::WireError;

/// Why a press did not reach every robot it should have.
#[derive(Debug, thiserror::Error)]
pub enum PressError {
    /// No robot agent or twin declares itself under the scope.
    #[error("{0}")]
    NotFound(String),
    /// Zenoh refused the subscription, the query or the publication.
    #[error("zenoh: {0}")]
    Zenoh(String),
    /// Some present robot or twin did not acknowledge in time.
    #[error("{message}")]
    Unacknowledged {
        /// What to tell the operator.
        message: String,
        /// Who did acknowledge, and who not.
        report: PressReport,
    },
    /// A press every obeyer acknowledged, but some hold the latch the other
    /// way: a release whose latch was engaged again after it was pressed
    /// (by someone else's press that arrived first), or an engage released
    /// since by a later press.
    #[error("{message}")]
    Overtaken {
        /// What to tell the operator.
        message: String,
        /// Who acknowledged, with the latches they hold.
        report: PressReport,
    },
}

impl From<PressError> for WireError {
    fn from(e: PressError) -> Self {
        match e {
            PressError::NotFound(m) => WireError::not_found(m),
            PressError::Zenoh(m) => WireError::internal(format!("zenoh: {m}")),
            PressError::Unacknowledged { message, .. } => WireError::unavailable(message),
            PressError::Overtaken { message, .. } => WireError::invalid_state(message),
        }
    }
}

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
            Self::Env(env) => env.components_alive_selector(),
            Self::Site => components_alive_selector(),
        }
    }

    /// The latch this scope's e-stop sets.
    fn latch(&self) -> Latch {
        match self {
            Self::Env(_) => Latch::Env,
            Self::Site => Latch::Site,
        }
    }

    /// Where the obeying components acknowledge.
    fn acks(&self) -> String {
        match self {
            Self::Env(env) => env.key(Topic::EStopAck),
            Self::Site => topic_on_all_envs(Topic::EStopAck),
        }
    }
}

/// A component that obeys e-stops: `(env, component)`, e.g.
/// `("real/enclosure-a", "robot_agent")`.
pub type Obeyer = (String, String);

/// One component's acknowledgement of a press.
#[derive(Debug, Clone, PartialEq)]
pub struct Acknowledgement {
    /// The env it serves.
    pub env: String,
    /// `robot_agent` or `sim_twin`.
    pub component: String,
    /// From the publication to the acknowledgement's arrival.
    pub after: Duration,
    /// The latches in force there after the press.
    pub state: EStopState,
}

/// Who obeyed a press, and who did not answer in time.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct PressReport {
    /// Acknowledgements, in arrival order.
    pub acknowledged: Vec<Acknowledgement>,
    /// Components present under the scope that did not acknowledge.
    pub silent: Vec<Obeyer>,
}

/// Publishes an engage (`engaged`) or release of `scope` once a robot agent
/// or a twin is present there (its liveliness token; waits at most
/// `presence` for one: a press nobody obeys is `NotFound`), then waits at
/// most `ack_within` for every one of them to acknowledge. Returns the
/// report when all did; `Unacknowledged` naming the silent ones otherwise,
/// and `Overtaken` when some of them hold the latch the other way (a
/// release pressed before an engage that reached them first).
pub async fn press_estop(
    session: &Session,
    scope: &EStopScope,
    engaged: bool,
    reason: &str,
    presence: Duration,
    ack_within: Duration,
) -> Result<PressReport, PressError> {
    let zerr = |e: String| PressError::Zenoh(e);
    let key = scope.key();
    let deadline = tokio::time::Instant::now() + presence;
    let expected = loop {
        let found = obeyers(session, scope, deadline).await?;
        if !found.is_empty() {
            break found;
        }
        if tokio::time::Instant::now() >= deadline {
            return Err(PressError::NotFound(format!(
                "no robot or twin listens on {key} (waited {:.1} s): the e-stop reached nobody",
                presence.as_secs_f64()
            )));
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    };
    // The press's time: obeyers order releases by it.
    let press_id = estop::new_press_id();
    let (tx, mut acks) = mpsc::unbounded_channel();
    let _ack_sub = session
        .declare_subscriber(scope.acks())
        .callback(
            move |s: Sample| match codec::decode_payload::<EStopAck>(s.payload()) {
                Ok(ack) if ack.press_id == press_id => {
                    let _ = tx.send((Instant::now(), ack));
                }
                Ok(_) => {}
                Err(e) => tracing::warn!("ignored a malformed e-stop acknowledgement: {e}"),
            },
        )
        .await
        .map_err(|e| zerr(e.to_string()))?;
    let stop = EStop {
        engaged,
        reason: reason.to_owned(),
        press_id,
    };
    let bytes = codec::encode(&stop).map_err(|e| zerr(e.to_string()))?;
    let publisher = session
        .declare_publisher(key.clone())
        .encoding(Encoding::APPLICATION_CDR)
        .congestion_control(Delivery::Every.congestion_control())
        .priority(wire::CONTROL_PRIORITY)
        .await
        .map_err(|e| zerr(e.to_string()))?;
    let ack_deadline = tokio::time::Instant::now() + ack_within;
    // A new session learns the robots' subscriptions from the router a
    // moment after it sees their presence, and a client drops a put that
    // matches no subscription it knows of: wait (within the time for the
    // acknowledgements, whatever the presence wait took) until one
    // matches, then publish (regardless: the acknowledgements tell the
    // truth).
    while !publisher
        .matching_status()
        .await
        .map_err(|e| zerr(e.to_string()))?
        .matching()
        && tokio::time::Instant::now() < ack_deadline
    {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let sent = Instant::now();
    let mut waiting: BTreeSet<Obeyer> = expected.into_iter().collect();
    let mut report = PressReport::default();
    // A press is published again while someone is still silent: a put or
    // an acknowledgement can be lost while the sessions learn each other's
    // subscriptions through the router (the acknowledgement's subscriber
    // above is moments old). Every copy is safe: an obeyer applies a press
    // once and acknowledges every copy, and applies a release only when it
    // was pressed after the latch's last change, so a late copy never
    // undoes an engage pressed in between ([`estop::RecentPresses`]); each
    // obeyer counts once here.
    let mut republish_in = Duration::from_millis(250);
    loop {
        publisher
            .put(bytes.clone())
            .await
            .map_err(|e| zerr(e.to_string()))?;
        tracing::warn!(%key, engaged, %reason, "e-stop published");
        let next_publish = (tokio::time::Instant::now() + republish_in).min(ack_deadline);
        republish_in = republish_in.saturating_mul(2).min(Duration::from_secs(1));
        while !waiting.is_empty() {
            let Ok(Some((at, ack))) = tokio::time::timeout_at(next_publish, acks.recv()).await
            else {
                break;
            };
            let obeyer = (ack.env.clone(), ack.component.clone());
            let first = waiting.remove(&obeyer)
                || !report
                    .acknowledged
                    .iter()
                    .any(|a| a.env == obeyer.0 && a.component == obeyer.1);
            if first {
                report.acknowledged.push(Acknowledgement {
                    env: ack.env,
                    component: ack.component,
                    after: at.saturating_duration_since(sent),
                    state: ack.state,
                });
            }
        }
        // Published at least once, whatever the deadline.
        if waiting.is_empty() || tokio::time::Instant::now() >= ack_deadline {
            break;
        }
    }
    report.silent = waiting.into_iter().collect();
    let latch = scope.latch();
    let holding: Vec<String> = report
        .acknowledged
        .iter()
        .filter(|a| a.state.latch(latch).engaged != engaged)
        .map(|a| {
            format!(
                "{} of {} ({})",
                a.component,
                a.env,
                a.state.latch(latch).reason
            )
        })
        .collect();
    if report.silent.is_empty() && holding.is_empty() {
        Ok(report)
    } else if report.silent.is_empty() {
        let message = if engaged {
            format!(
                "the e-stop on {key} is not in force at {}: a later press released the {} latch",
                holding.join(", "),
                latch.as_str()
            )
        } else {
            format!(
                "the release on {key} was refused: the {} latch was engaged again after it \
                 was pressed, and holds at {}",
                latch.as_str(),
                holding.join(", ")
            )
        };
        Err(PressError::Overtaken { message, report })
    } else {
        let names: Vec<String> = report
            .silent
            .iter()
            .map(|(env, component)| format!("{component} of {env}"))
            .collect();
        Err(PressError::Unacknowledged {
            message: format!(
                "the e-stop on {key} was not acknowledged within {} ms by {} (dropped by the \
                 router's access control, a cut link, or a frozen component): check them in person",
                ack_within.as_millis(),
                names.join(", ")
            ),
            report,
        })
    }
}

/// The robot agents and twins that declare themselves under `scope`.
async fn obeyers(
    session: &Session,
    scope: &EStopScope,
    deadline: tokio::time::Instant,
) -> Result<Vec<Obeyer>, PressError> {
    let left = deadline.saturating_duration_since(tokio::time::Instant::now());
    let replies = session
        .liveliness()
        .get(scope.obeyed_by())
        .timeout(left.max(Duration::from_millis(100)))
        .await
        .map_err(|e| PressError::Zenoh(e.to_string()))?;
    let obeying = [Component::RobotAgent, Component::SimTwin];
    let mut found = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        let Ok(sample) = reply.result() else { continue };
        let token = sample.key_expr().as_str();
        let Ok(env) = EnvId::from_key(token) else {
            continue;
        };
        for component in obeying {
            if token == env.alive_key(component) {
                found.push((env.to_string(), component.as_str().to_owned()));
            }
        }
    }
    found.sort();
    found.dedup();
    Ok(found)
}
