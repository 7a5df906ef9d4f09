//! A trainer's requests to a deployment as a whole rather than to one env:
//! its session (the process environment's endpoint), who an access token
//! is, and the token's bookings on every env.

use std::time::Duration;

use offworld_runtime::keys::{Component, EnvId, Realm};
use offworld_runtime::msg::{AdminReply, AdminRequest, Booking};
use offworld_runtime::session::{SessionConfig, REACH_WITHIN};
use offworld_runtime::{ContractError, ErrorCode, WireError};
use zenoh::Session;

use crate::{admin, discover_until, EnvListing};

/// The variable naming a deployment's endpoint for trainers (`--connect`
/// overrides it), read by the Python package and `offworld gym` alike.
pub const CONNECT_ENV: &str = "OFFWORLD_GYM_CONNECT";

/// The variable holding a trainer's access token.
pub const TOKEN_ENV: &str = "OFFWORLD_GYM_ACCESS_TOKEN";

/// The session of a trainer's process on a remote deployment: the
/// `OFFWORLD_ZENOH_*` environment (a client unless it names a mode; its
/// config file supplies TLS and credentials), `connect` replacing its
/// endpoints when given.
pub fn deployment_session(connect: Option<String>) -> Result<SessionConfig, ContractError> {
    let mut session = SessionConfig::connecting_from_env()?;
    if let Some(endpoint) = connect {
        session.connect = vec![endpoint];
    }
    Ok(session)
}

/// Opens [`deployment_session`]: an endpoint where nothing answers is an
/// error naming it within [`REACH_WITHIN`], not an empty deployment.
pub async fn open_deployment(connect: Option<String>) -> Result<Session, WireError> {
    Ok(deployment_session(connect)?
        .open_reaching(REACH_WITHIN)
        .await?)
}

/// Opens a session on the deployment ([`open_deployment`]), runs `work`
/// on it and closes it: one request or a few, outside an env's session.
pub async fn on_deployment<T, Fut>(
    connect: Option<String>,
    work: impl FnOnce(Session) -> Fut,
) -> Result<T, WireError>
where
    Fut: std::future::Future<Output = Result<T, WireError>>,
{
    let session = open_deployment(connect).await?;
    let answer = work(session.clone()).await;
    let _ = session.close().await;
    answer
}

/// Who `token` is (`user`, `operator`), as `env`'s controller says; without
/// an env, as a real env's controller says, else any env's: the first
/// three served envs are asked in turn while one is away.
pub async fn whoami(
    session: &Session,
    env: Option<&EnvId>,
    token: &str,
    timeout: Duration,
) -> Result<AdminReply, WireError> {
    match env {
        Some(env) => identify(session, std::slice::from_ref(env), token, timeout).await,
        None => {
            let listings = discover_served(session, timeout).await?;
            identify(session, &served_real_first(&listings), token, timeout).await
        }
    }
}

/// Every slot booked with `token` on any env of the deployment that has not
/// ended, earliest first.
pub async fn my_bookings(
    session: &Session,
    token: &str,
    timeout: Duration,
) -> Result<Vec<Booking>, WireError> {
    let listings = discover_served(session, timeout).await?;
    let me = identify(session, &served_real_first(&listings), token, timeout)
        .await?
        .user;
    let mut mine: Vec<Booking> = listings
        .into_iter()
        .flat_map(|listing| listing.bookings)
        .filter(|booking| booking.user == me)
        .collect();
    mine.sort_by(|a, b| (a.start_unix_ms, &a.env_id).cmp(&(b.start_unix_ms, &b.env_id)));
    Ok(mine)
}

/// How long a session just opened looks again for a controller's liveliness
/// token ([`discover_until`]): a first look may miss the controller a
/// command is about to ask.
const TOKENS_SETTLE: Duration = Duration::from_secs(2);

/// The deployment's listings once an env with a live controller is among
/// them (or [`TOKENS_SETTLE`] has passed).
async fn discover_served(
    session: &Session,
    timeout: Duration,
) -> Result<Vec<EnvListing>, WireError> {
    let served = |listings: &[EnvListing]| !served_real_first(listings).is_empty();
    discover_until(
        session,
        timeout,
        TOKENS_SETTLE,
        Duration::from_millis(100),
        served,
    )
    .await
}

/// Envs with a live controller, real ones first, at most three: the ones
/// asked who a token is.
fn served_real_first(listings: &[EnvListing]) -> Vec<EnvId> {
    let mut served: Vec<EnvId> = listings
        .iter()
        .filter(|l| {
            l.components
                .iter()
                .any(|c| c == Component::Controller.as_str())
        })
        .map(|l| l.env.clone())
        .collect();
    // Real envs' controllers know the site's users; stable within a realm.
    served.sort_by_key(|env| env.realm() != Realm::Real);
    served.truncate(3);
    served
}

/// Asks each env's controller in turn until one answers who `token` is.
async fn identify(
    session: &Session,
    envs: &[EnvId],
    token: &str,
    timeout: Duration,
) -> Result<AdminReply, WireError> {
    let mut last = WireError::new(
        ErrorCode::NotFound,
        "no controller is reachable to say who this token is (is the deployment up?)",
    );
    for env in envs {
        let request = AdminRequest::Identify {
            token: token.to_owned(),
        };
        match admin(session, env, &request, timeout).await {
            // That controller is away: ask the next.
            Err(e) if is_away(&e) => last = e,
            answer => return answer,
        }
    }
    Err(last)
}

fn is_away(e: &WireError) -> bool {
    matches!(
        e.code,
        ErrorCode::Timeout | ErrorCode::Unavailable | ErrorCode::NotFound
    )
}
