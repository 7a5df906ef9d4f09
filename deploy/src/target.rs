//! Where a client's envs live: an embedded in-process sim deployment (the
//! default: no router, no robot) or a remote deployment reached through
//! Zenoh. Shared by the Python package and any other front end.

use offworld_client as client;
use offworld_runtime::keys::EnvId;
use offworld_runtime::{Resolution, SessionConfig};
use zenoh::Session;

use offworld_env_controller::{ControllerError, EnvOptions, RequestLimits, Store};

use crate::embedded::{render_threads_for, stepping_for, Embedded, SimEnv, TwinProfile};

/// What to connect to.
#[derive(Debug, Clone)]
pub enum Target {
    /// Start `count` sim twins and a controller inside this process.
    Embedded {
        /// Task name.
        task: String,
        /// Observation (and render) resolution (width, height).
        resolution: Resolution,
        /// Number of envs.
        count: usize,
        /// Record every episode under this directory (`docs/recording.md`).
        record: Option<std::path::PathBuf>,
        /// Every twin's profile (`docs/twin-profile.md`).
        twin_profile: TwinProfile,
    },
    /// Use envs served elsewhere.
    Remote {
        /// How to reach the deployment.
        session: SessionConfig,
        /// Which envs.
        envs: Vec<EnvId>,
    },
    /// Use `count` free envs of the expected task in `realm`, found by
    /// discovery (liveliness + `spec` + `status`), on any host.
    Discover {
        /// How to reach the deployment.
        session: SessionConfig,
        /// `sim` or `real`.
        realm: offworld_runtime::Realm,
        /// Number of envs.
        count: usize,
    },
}

/// An open connection; keeps an embedded deployment alive.
pub struct Connection {
    /// The Zenoh session to talk through.
    pub session: Session,
    /// The envs to open.
    pub envs: Vec<EnvId>,
    _embedded: Option<Embedded>,
}

/// How long a remote env may take to answer its first `spec` query.
const DISCOVERY: std::time::Duration = std::time::Duration::from_secs(10);

/// Connects to `target`. Remote envs must answer `spec` for the expected
/// task, so a wrong namespace fails here with a clear message.
pub async fn connect(target: Target, expected_task: &str) -> Result<Connection, ControllerError> {
    match target {
        Target::Embedded {
            task,
            resolution,
            count,
            record,
            twin_profile,
        } => {
            let session = SessionConfig::isolated().open().await?;
            let prefix = offworld_runtime::keys::random_id();
            let envs: Vec<EnvId> = (0..count.max(1))
                .map(|i| EnvId::sim(&format!("embedded-{}-{i}", &prefix[..8])))
                .collect::<Result<_, _>>()
                .map_err(|e| ControllerError::Config(e.to_string()))?;
            let render_threads = render_threads_for(envs.len())?;
            let stepping = stepping_for(envs.len())?;
            let sims: Vec<SimEnv> = envs
                .iter()
                .enumerate()
                .map(|(i, env)| SimEnv {
                    env: env.clone(),
                    task: task.clone(),
                    resolution: Some(resolution),
                    seed: i as u64,
                    profile: twin_profile,
                    render_threads,
                    stepping,
                })
                .collect();
            let embedded = Embedded::start_with(
                &session,
                &sims,
                Store::in_memory()?,
                EnvOptions::default(),
                RequestLimits::in_process(),
                record.as_deref(),
            )
            .await?;
            Ok(Connection {
                session,
                envs,
                _embedded: Some(embedded),
            })
        }
        Target::Discover {
            session,
            realm,
            count,
        } => {
            let session = open_remote(&session).await?;
            let envs = pick_free(&session, realm, expected_task, count).await?;
            Ok(Connection {
                session,
                envs,
                _embedded: None,
            })
        }
        Target::Remote { session, envs } => {
            let session = open_remote(&session).await?;
            for env in &envs {
                let spec = wait_for_spec(&session, env).await?;
                if spec.task != expected_task {
                    return Err(ControllerError::Config(format!(
                        "{env} serves task {}, not {expected_task}",
                        spec.task
                    )));
                }
            }
            Ok(Connection {
                session,
                envs,
                _embedded: None,
            })
        }
    }
}

async fn open_remote(config: &SessionConfig) -> Result<Session, ControllerError> {
    // An unreachable endpoint is an error naming it, not an empty deployment.
    Ok(config
        .open_reaching(offworld_runtime::session::REACH_WITHIN)
        .await?)
}

/// `count` free envs of `task` in `realm`, in env id order. Waits up to
/// [`DISCOVERY`] for enough of them to show up.
async fn pick_free(
    session: &Session,
    realm: offworld_runtime::Realm,
    task: &str,
    count: usize,
) -> Result<Vec<EnvId>, ControllerError> {
    let wanted = count.max(1);
    let free = |listings: &[client::EnvListing]| -> Vec<EnvId> {
        listings
            .iter()
            .filter(|l| {
                l.env.realm() == realm
                    && l.task == task
                    && l.state == offworld_runtime::msg::EnvState::Free
            })
            .map(|l| l.env.clone())
            .take(wanted)
            .collect()
    };
    let timeout = std::time::Duration::from_secs(2);
    let listings = client::discover_until(
        session,
        timeout,
        DISCOVERY,
        std::time::Duration::from_millis(200),
        |listings| free(listings).len() == wanted,
    )
    .await?;
    let free = free(&listings);
    if free.len() == wanted {
        return Ok(free);
    }
    let here = client::envs_here(session, timeout).await;
    Err(ControllerError::NotFound(format!(
        "{count} free {realm:?} envs of task {task} wanted, {} found; {here}",
        free.len(),
    )))
}

async fn wait_for_spec(
    session: &Session,
    env: &EnvId,
) -> Result<offworld_runtime::msg::EnvSpec, ControllerError> {
    let deadline = tokio::time::Instant::now() + DISCOVERY;
    loop {
        match client::spec(session, env, std::time::Duration::from_secs(2)).await {
            Ok(spec) => return Ok(spec),
            Err(e) if tokio::time::Instant::now() >= deadline => {
                let here = client::envs_here(session, std::time::Duration::from_secs(2)).await;
                return Err(ControllerError::NotFound(format!(
                    "no deployment serves {env} ({}); {here}",
                    e.message
                )));
            }
            Err(_) => tokio::time::sleep(std::time::Duration::from_millis(100)).await,
        }
    }
}
