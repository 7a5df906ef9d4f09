//! An in-process deployment: sim twins and the controller on one Zenoh
//! session, on the same code path as a distributed deployment (the twins
//! and the controller still talk only through Zenoh keys).

use std::time::Duration;

use offworld_runtime::keys::EnvId;
use offworld_runtime::Resolution;
/// Where an embedded twin simulates a command (re-exported likewise).
pub use offworld_sim_twin::Stepping;
/// The twin profile an embedded env's twin is built with (re-exported so
/// front ends need not depend on the twin crate).
pub use offworld_sim_twin::TwinProfile;
use offworld_sim_twin::{NodeOptions, SimTwin, TwinConfig, TwinNode, RENDER_THREADS_LIMIT};
use zenoh::Session;

use offworld_env_controller::{
    Controller, ControllerError, EnvOptions, EnvServer, RequestLimits, Store, Task,
};

/// One simulated env to start.
#[derive(Debug, Clone)]
pub struct SimEnv {
    /// Its id (under `sim/`).
    pub env: EnvId,
    /// Task name (`MonolithDiscrete`, …).
    pub task: String,
    /// Rendered resolution (render at the observation size: fastest).
    pub resolution: Option<Resolution>,
    /// Spawn sampler seed before any `reset(seed)`.
    pub seed: u64,
    /// The physical robot the twin behaves like (`docs/twin-profile.md`);
    /// the default is the nominal twin.
    pub profile: TwinProfile,
    /// Threads each frame is rendered on ([`render_threads_for`] shares the
    /// machine's cores among a process's twins).
    pub render_threads: usize,
    /// Where its twin simulates a command: [`Stepping::OnArrival`] for the
    /// one env of a trainer's own process (its steps then run on the
    /// trainer's thread), [`Stepping::OwnThread`] where several envs or
    /// remote clients share the deployment.
    pub stepping: Stepping,
}

/// The most threads [`render_threads_for`] gives one twin by default: a
/// twin should not take every core of a large machine (measured here up
/// to two cores).
pub const DEFAULT_RENDER_THREADS_CAP: usize = 4;

/// Overrides [`render_threads_for`]: the threads each twin of this process
/// renders on (as `OMP_NUM_THREADS` does for OpenMP), e.g. 1 when every
/// core already runs a process of its own (gymnasium's `AsyncVectorEnv`).
pub const RENDER_THREADS_VAR: &str = "OFFWORLD_RENDER_THREADS";

/// Render threads per twin when `twins` twins of one embedded deployment
/// (one `gymnasium.make` or `make_vec`) share the machine:
/// [`RENDER_THREADS_VAR`] if set (empty = unset), else the cores divided
/// among them (at least one each, at most [`DEFAULT_RENDER_THREADS_CAP`]).
/// One env on two cores renders on both; two envs on two cores on one each.
/// Deployments do not know of each other: a process making several, or
/// several processes each making one, divide nothing (set the variable).
pub fn render_threads_for(twins: usize) -> Result<usize, ControllerError> {
    let limit = usize::from(RENDER_THREADS_LIMIT);
    if let Some(value) = std::env::var_os(RENDER_THREADS_VAR).filter(|v| !v.is_empty()) {
        let value = value.to_string_lossy();
        return match value.trim().parse::<usize>() {
            Ok(n) if (1..=limit).contains(&n) => Ok(n),
            _ => Err(ControllerError::Config(format!(
                "{RENDER_THREADS_VAR}={value:?}: give a whole number of threads from 1 to {limit}"
            ))),
        };
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    Ok((cores / twins.max(1)).clamp(1, DEFAULT_RENDER_THREADS_CAP))
}

/// Overrides [`stepping_for`]: `own-thread` gives even a lone embedded twin
/// a thread of its own (its steps then cost a thread wake-up, and a hung
/// simulation times out instead of holding the trainer's call), or
/// `on-arrival` (for every twin: a vector env's then take turns on the
/// trainer's thread).
pub const TWIN_STEPPING_VAR: &str = "OFFWORLD_TWIN_STEPPING";

/// Where the twins of one embedded deployment of `twins` envs simulate:
/// [`TWIN_STEPPING_VAR`] if set (empty = unset), else one env on the
/// trainer's thread ([`Stepping::OnArrival`]: a vector env's requests go out
/// from one thread, so several envs each keep a thread, to progress in
/// parallel).
pub fn stepping_for(twins: usize) -> Result<Stepping, ControllerError> {
    if let Some(value) = std::env::var_os(TWIN_STEPPING_VAR).filter(|v| !v.is_empty()) {
        return match value.to_string_lossy().trim() {
            "own-thread" => Ok(Stepping::OwnThread),
            "on-arrival" => Ok(Stepping::OnArrival),
            other => Err(ControllerError::Config(format!(
                "{TWIN_STEPPING_VAR}={other:?}: give `own-thread` or `on-arrival`"
            ))),
        };
    }
    Ok(if twins == 1 {
        Stepping::OnArrival
    } else {
        Stepping::OwnThread
    })
}

/// A running in-process deployment; stops when dropped.
pub struct Embedded {
    /// The controller serving every env.
    pub controller: Controller,
    /// One twin per env.
    pub twins: Vec<TwinNode>,
}

/// How long to wait for an embedded twin to appear (it is in-process).
const ONLINE_TIMEOUT: Duration = Duration::from_secs(10);

impl Embedded {
    /// Starts a twin and a controller env per `SimEnv` on `session`.
    pub async fn start(
        session: &Session,
        envs: &[SimEnv],
        store: Store,
    ) -> Result<Self, ControllerError> {
        Self::start_with(
            session,
            envs,
            store,
            EnvOptions::default(),
            RequestLimits::default(),
            None,
        )
        .await
    }

    /// [`Embedded::start`] with a site's policy (`options`; anonymous
    /// access is always allowed and the seed is each `SimEnv`'s) and
    /// request limits, recording every episode under `record` if given.
    pub async fn start_with(
        session: &Session,
        envs: &[SimEnv],
        store: Store,
        options: EnvOptions,
        limits: RequestLimits,
        record: Option<&std::path::Path>,
    ) -> Result<Self, ControllerError> {
        let mut controller = Controller::with_limits(session.clone(), store, limits)?;
        if let Some(dir) = record {
            controller.record_into(dir)?;
        }
        let mut twins = Vec::new();
        for sim in envs {
            if sim.env.realm() != offworld_runtime::Realm::Sim {
                return Err(ControllerError::Config(format!(
                    "{} is not a sim env",
                    sim.env
                )));
            }
            let task = Task::by_name(&sim.task)?;
            let mut config = TwinConfig::builtin(&task.world.name)
                .map_err(|e| ControllerError::Config(e.to_string()))?;
            config.resolution = sim.resolution;
            config.profile = sim.profile;
            config.render_threads = sim.render_threads;
            let twin = SimTwin::new(config).map_err(|e| ControllerError::Config(e.to_string()))?;
            let node_options = NodeOptions {
                stepping: sim.stepping,
                ..NodeOptions::default()
            };
            twins.push(
                TwinNode::spawn_with(session, sim.env.clone(), twin, node_options).map_err(
                    |e| {
                        ControllerError::Offline(format!(
                            "the twin of {} could not start: {e}",
                            sim.env
                        ))
                    },
                )?,
            );
            let options = EnvOptions {
                allow_anonymous: true,
                seed: sim.seed,
                ..options
            };
            let server: std::sync::Arc<EnvServer> =
                controller.serve(sim.env.clone(), task, options).await?;
            if !server.link().wait_online(ONLINE_TIMEOUT).await {
                return Err(ControllerError::Offline(format!(
                    "the twin of {} never came online",
                    sim.env
                )));
            }
        }
        Ok(Self { controller, twins })
    }

    /// Stops cleanly: see [`Controller::shutdown`].
    pub async fn shutdown(self, reason: &str) {
        self.controller.shutdown(reason).await;
    }
}
