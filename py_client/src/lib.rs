//! PyO3 bindings of the `offworld_gym` package: type conversion and GIL
//! handling only. Deployment selection, the gym protocol and vector
//! stepping live in the Rust library crates.

mod convert;
mod errors;
mod live_monitor;

use std::sync::OnceLock;

use offworld_client::{ClientTimeouts, EnvClient, VecEnvClient};
use offworld_deploy::{Connection, Target, TwinProfile};
use offworld_runtime::msg::{ActionSpace, Channels, OpenRequest, Seed};
use offworld_runtime::pool::BufferPool;
use offworld_runtime::{EnvId, Resolution, SessionConfig, WireError};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};

/// One tokio runtime for every env of the process.
fn runtime() -> PyResult<&'static tokio::runtime::Runtime> {
    static RUNTIME: OnceLock<std::io::Result<tokio::runtime::Runtime>> = OnceLock::new();
    RUNTIME
        .get_or_init(|| {
            tokio::runtime::Builder::new_multi_thread()
                .worker_threads(2)
                .thread_name("offworld-gym")
                .enable_all()
                .build()
        })
        .as_ref()
        .map_err(|e| errors::local(format!("cannot start the runtime: {e}")))
}

/// How often a blocking call looks for a pending signal (Ctrl-C): the
/// latency of `KeyboardInterrupt`, and one brief GIL hold per period.
const SIGNAL_POLL: std::time::Duration = std::time::Duration::from_millis(50);

/// Runs `work` on the runtime with the GIL released, waking every
/// [`SIGNAL_POLL`] to run Python's signal handlers. When one raises (Ctrl-C:
/// `KeyboardInterrupt`), `work` is dropped, which cancels it, and that error
/// is returned. Dropping abandons the client's wait only; [`NativeEnvs`]
/// says what state that leaves the envs in.
///
/// Python runs signal handlers on the main thread only; called from another
/// thread this waits for `work` like a plain `block_on`.
fn block_on_interruptibly<F>(py: Python<'_>, work: F) -> PyResult<F::Output>
where
    F: std::future::Future + Send,
    F::Output: Send,
{
    let rt = runtime()?;
    // Boxed so it can be polled in slices and dropped before it completes.
    let mut work = Box::pin(work);
    loop {
        // The timer is made inside `block_on`: it needs the runtime's context.
        let slice = py.detach(|| {
            rt.block_on(async { tokio::time::timeout(SIGNAL_POLL, work.as_mut()).await })
        });
        if let Ok(done) = slice {
            return Ok(done);
        }
        if let Err(interrupted) = py.check_signals() {
            // Without the GIL, in case dropping waits (work that owns a
            // session goes through `spawn_interruptibly`, which does not).
            py.detach(move || drop(work));
            return Err(interrupted);
        }
    }
}

/// [`block_on_interruptibly`] for work that owns what it uses, such as a
/// session it opens: it runs as a task of the runtime, which an interrupt
/// aborts there, so closing that session (Zenoh waits for a handshake in
/// progress up to its open timeout, 10 s) does not delay the interrupt.
fn spawn_interruptibly<F>(py: Python<'_>, work: F) -> PyResult<F::Output>
where
    F: std::future::Future + Send + 'static,
    F::Output: Send + 'static,
{
    let task = runtime()?.spawn(work);
    let abort = task.abort_handle();
    joined(block_on_interruptibly(py, task).inspect_err(|_| abort.abort())?)
}

/// Runs a blocking library call (the monitor's start and shutdown) on the
/// runtime's blocking pool, waited for by [`block_on_interruptibly`]; an
/// interrupted call goes on in the background to its end.
fn block_on_pool<T: Send + 'static>(
    py: Python<'_>,
    call: impl FnOnce() -> T + Send + 'static,
) -> PyResult<T> {
    let call = runtime()?.spawn_blocking(call);
    joined(block_on_interruptibly(py, call)?)
}

/// A task's result; its panic goes on here, as if it had run on this thread.
fn joined<T>(result: Result<T, tokio::task::JoinError>) -> PyResult<T> {
    result.map_err(|e| match e.try_into_panic() {
        Ok(panic) => std::panic::resume_unwind(panic),
        Err(e) => errors::local(format!("background task: {e}")),
    })
}

/// Drops `value` on the runtime's blocking pool, not in the caller's way.
fn drop_in_background<T: Send + 'static>(value: T) {
    if let Ok(rt) = runtime() {
        rt.spawn_blocking(move || drop(value));
    }
}

fn controller_error(e: offworld_env_controller::ControllerError) -> PyErr {
    errors::to_py(WireError::from(e))
}

/// N envs of one task (N = 1 for a plain env), opened on a deployment.
///
/// Interrupted calls (Ctrl-C: [`block_on_interruptibly`]) leave the envs
/// open and usable, not closed: a request goes out on the call's first
/// poll, before any signal check, so a reachable controller has it and runs
/// it to its end; `EnvClient` keeps no per-request state a dropped wait
/// could break (the step counter it sends is echoed, never checked); and
/// the controller runs an env's requests one at a time, so the next call
/// waits for the abandoned one, then runs or is refused with a typed error
/// (`InvalidState` if the abandoned step ended the episode). Its
/// observation is lost: reset next. An interrupted `close` still releases
/// the leases (the Python envs count as closed); an interrupted
/// constructor drops what it opened, in the background.
#[pyclass(module = "offworld_gym._native")]
struct NativeEnvs {
    envs: VecEnvClient,
    space: ActionSpace,
    /// The access token the envs were opened with (for `experiments`).
    token: String,
    /// Buffers of the stacked observations of all envs (see `convert::stacked`).
    batches: BufferPool,
    // Closed after the clients so the recording sees the last episode end.
    monitor: Option<live_monitor::Handle>,
    // Dropped after the clients: keeps an embedded deployment alive.
    connection: Connection,
}

/// What `NativeEnvs(options)` reads from the Python layer's
/// `NativeOptions` (`_config.py`), by attribute name: one typed value
/// instead of a long positional list that could drift between the layers.
#[derive(FromPyObject)]
struct OpenOptions {
    task: String,
    realm: String,
    num_envs: usize,
    connect: Option<String>,
    env_ids: Option<Vec<String>>,
    token: String,
    experiment_name: String,
    resume_experiment: bool,
    learning_type: String,
    algorithm_mode: String,
    #[pyo3(from_py_with = convert::channels)]
    channels: Channels,
    height: i64,
    width: i64,
    depth_format: String,
    rerun: Option<String>,
    record: Option<String>,
    twin_profile: Option<String>,
    wait_s: f64,
}

impl NativeEnvs {
    /// Where env `index`'s observations go back when numpy drops them.
    fn buffers(&self, index: usize) -> PyResult<&BufferPool> {
        self.envs
            .get(index)
            .map(EnvClient::observation_buffers)
            .ok_or_else(|| PyValueError::new_err("no envs"))
    }
}

#[pymethods]
impl NativeEnvs {
    #[new]
    fn new(py: Python<'_>, options: OpenOptions) -> PyResult<Self> {
        let OpenOptions {
            task,
            realm,
            num_envs,
            connect,
            env_ids,
            token,
            experiment_name,
            resume_experiment,
            learning_type,
            algorithm_mode,
            channels,
            height,
            width,
            depth_format,
            rerun,
            record,
            twin_profile,
            wait_s,
        } = options;
        if num_envs == 0 {
            return Err(PyValueError::new_err("num_envs must be at least 1"));
        }
        let obs = convert::obs_options(channels, height, width, &depth_format)?;
        let wait = convert::wait(wait_s)?;
        let sink = rerun.as_deref().map(live_monitor::parse_sink).transpose()?;
        let request = OpenRequest {
            token: token.clone(),
            client_id: String::new(),
            experiment_name: experiment_name.clone(),
            resume_experiment,
            learning_type: convert::learning_type(&learning_type)?,
            algorithm_mode: convert::algorithm_mode(&algorithm_mode)?,
            obs,
        };
        let embedded = connect.is_none() && env_ids.is_none() && realm == "sim";
        // A bad file is the caller's: BadRequest naming the file and field.
        let twin_profile = match twin_profile {
            Some(_) if !embedded => {
                return Err(errors::raise_bad_request(
                    "twin_profile= shapes embedded sim twins; a deployment's twins take `sim_twin --profile`".into(),
                ))
            }
            Some(path) => TwinProfile::load(std::path::Path::new(&path))
                .map_err(|e| errors::to_py(WireError::from(e)))?,
            None => TwinProfile::default(),
        };
        let target = match (connect, env_ids) {
            (None, None) if embedded => Target::Embedded {
                task: task.clone(),
                resolution: Resolution::new(obs.width, obs.height),
                count: num_envs,
                record: record.map(std::path::PathBuf::from),
                twin_profile,
            },
            (connect, None) => Target::Discover {
                session: remote_session(connect)?,
                realm: realm
                    .parse()
                    .map_err(|e: offworld_runtime::ContractError| {
                        PyValueError::new_err(e.to_string())
                    })?,
                count: num_envs,
            },
            (connect, Some(env_ids)) => {
                let envs: Vec<EnvId> = env_ids
                    .iter()
                    .map(|e| {
                        e.parse::<EnvId>()
                            .map_err(|e| PyValueError::new_err(e.to_string()))
                    })
                    .collect::<PyResult<_>>()?;
                Target::Remote {
                    session: remote_session(connect)?,
                    envs,
                }
            }
        };
        let connection =
            spawn_interruptibly(
                py,
                async move { offworld_deploy::connect(target, &task).await },
            )?
            .map_err(controller_error)?;
        // Watching starts before the envs open, so the recording holds every episode.
        let monitor = sink
            .map(|sink| {
                let (session, envs) = (connection.session.clone(), connection.envs.clone());
                block_on_pool(py, move || live_monitor::start(&session, envs, sink))
            })
            .transpose()
            .and_then(Option::transpose);
        // On a failure (or Ctrl-C) from here on, what is open is dropped in
        // the background: closing a session or a recording waits on the network.
        let monitor = match monitor {
            Ok(monitor) => monitor,
            Err(e) => {
                drop_in_background(connection);
                return Err(e);
            }
        };
        let opened = block_on_interruptibly(py, async {
            let mut clients = Vec::new();
            for (i, env) in connection.envs.iter().enumerate() {
                let mut request = request.clone();
                if connection.envs.len() > 1 && !experiment_name.is_empty() {
                    request.experiment_name = format!("{experiment_name}-{i}");
                }
                // Said once per place in line (the holder's lease end,
                // also in the message, moves at each of their steps).
                let mut said = String::new();
                let client = EnvClient::open_waiting(
                    &connection.session,
                    env,
                    request,
                    ClientTimeouts::default(),
                    wait,
                    |refused| {
                        let place = refused
                            .message
                            .rsplit_once("; ")
                            .map_or(refused.message.as_str(), |(_, place)| place);
                        if place != said {
                            eprintln!(
                                "offworld_gym: {}; waiting (up to {} s)",
                                refused.message,
                                wait.as_secs_f64()
                            );
                            place.clone_into(&mut said);
                        }
                    },
                )
                .await
                .map_err(errors::to_py)?;
                clients.push(client);
            }
            Ok::<_, PyErr>(clients)
        });
        let clients = match opened.and_then(|opened| opened) {
            Ok(clients) => clients,
            Err(e) => {
                drop_in_background((monitor, connection));
                return Err(e);
            }
        };
        let space = clients
            .first()
            .map(|c| c.spec().action_space.clone())
            .ok_or_else(|| PyValueError::new_err("no envs"))?;
        Ok(Self {
            envs: VecEnvClient::new(clients),
            space,
            token,
            batches: BufferPool::new(),
            monitor,
            connection,
        })
    }

    /// The env spec as a dict.
    #[getter]
    fn spec<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let spec = self
            .envs
            .spec()
            .ok_or_else(|| PyValueError::new_err("no envs"))?;
        let dict = PyDict::new(py);
        dict.set_item("env_id", &spec.env_id)?;
        dict.set_item("task", &spec.task)?;
        dict.set_item("world", &spec.world)?;
        match &spec.action_space {
            ActionSpace::Discrete { n, names } => {
                dict.set_item("action_kind", "discrete")?;
                dict.set_item("action_n", n)?;
                dict.set_item("action_names", names)?;
            }
            ActionSpace::Box { low, high } => {
                dict.set_item("action_kind", "box")?;
                dict.set_item("action_low", low)?;
                dict.set_item("action_high", high)?;
            }
        }
        dict.set_item("depth_max_m", spec.depth_max_m)?;
        dict.set_item("max_episode_steps", spec.max_episode_steps)?;
        let experiment = self.envs.get(0).map(|e| &e.opened().experiment);
        dict.set_item("experiment", experiment.map(|e| e.name.clone()))?;
        dict.set_item("experiment_id", experiment.map(|e| e.id))?;
        Ok(dict)
    }

    /// Env `index`'s experiment and all its episodes so far:
    /// (experiment dict, [episode dict]).
    #[pyo3(signature = (index=0, timeout_s=5.0))]
    fn experiment_episodes<'py>(
        &self,
        py: Python<'py>,
        index: usize,
        timeout_s: f64,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let env = self
            .envs
            .get(index)
            .ok_or_else(|| PyValueError::new_err(format!("no env {index}")))?;
        let timeout = convert::timeout(timeout_s)?;
        let session = &self.connection.session;
        let id = env.opened().experiment.id;
        let asked =
            offworld_client::experiment_episodes(session, env.env(), &self.token, id, timeout);
        let (experiment, episodes) = block_on_interruptibly(py, asked)?.map_err(errors::to_py)?;
        convert::experiment_with_episodes(py, &experiment, &episodes)
    }

    /// Number of envs.
    fn __len__(&self) -> usize {
        self.envs.len()
    }

    /// Resets every env; `seeds[i]` None continues env i's stream.
    /// Returns (observations as one array, first axis the env; infos).
    fn reset<'py>(
        &mut self,
        py: Python<'py>,
        seeds: Vec<Option<u64>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let seeds: Vec<Seed> = seeds
            .into_iter()
            .map(|s| s.map_or(Seed::Continue, Seed::Fixed))
            .collect();
        let envs = &mut self.envs;
        let mut batch = self.batches.take(envs.batch_len());
        let replies = block_on_interruptibly(py, envs.reset_into(&seeds, &mut batch))?
            .map_err(errors::to_py)?;
        let infos = PyList::empty(py);
        for r in &replies {
            infos.append(convert::info(py, &r.info)?)?;
        }
        let first = replies.first().map(|r| &r.observation);
        let first = first.ok_or_else(|| PyValueError::new_err("no envs"))?;
        let observations = convert::stacked(py, batch, &self.batches, first, replies.len())?;
        PyTuple::new(py, [observations, infos.into_any()])
    }

    /// Steps the first env alone, as a `gymnasium.Env` does: an ended
    /// episode waits for `reset()`. Returns (obs, reward, terminated,
    /// truncated, info).
    fn step_without_autoreset<'py>(
        &mut self,
        py: Python<'py>,
        action: &Bound<'py, PyAny>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let action = convert::action(&self.space, action)?;
        let env = self
            .envs
            .get_mut(0)
            .ok_or_else(|| PyValueError::new_err("no envs"))?;
        let r = block_on_interruptibly(py, env.step(action))?.map_err(errors::to_py)?;
        let info = convert::info(py, &r.info)?;
        PyTuple::new(
            py,
            [
                convert::observation(py, r.observation, self.buffers(0)?)?,
                r.reward.into_pyobject(py)?.into_any(),
                pyo3::types::PyBool::new(py, r.terminated)
                    .to_owned()
                    .into_any(),
                pyo3::types::PyBool::new(py, r.truncated)
                    .to_owned()
                    .into_any(),
                info.into_any(),
            ],
        )
    }

    /// Steps every env concurrently with gymnasium's next-step autoreset.
    /// Returns (observations as one array, first axis the env; a list of
    /// (reward, terminated, truncated, info, autoreset)).
    fn step_with_autoreset<'py>(
        &mut self,
        py: Python<'py>,
        actions: Vec<Bound<'py, PyAny>>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let actions = actions
            .iter()
            .map(|a| convert::action(&self.space, a))
            .collect::<PyResult<Vec<_>>>()?;
        let envs = &mut self.envs;
        let mut batch = self.batches.take(envs.batch_len());
        let steps = block_on_interruptibly(py, envs.step_into(actions, &mut batch))?
            .map_err(errors::to_py)?;
        let out = PyList::empty(py);
        for s in &steps {
            let info = convert::info(py, &s.reply.info)?;
            out.append(PyTuple::new(
                py,
                [
                    s.reply.reward.into_pyobject(py)?.into_any(),
                    pyo3::types::PyBool::new(py, s.reply.terminated)
                        .to_owned()
                        .into_any(),
                    pyo3::types::PyBool::new(py, s.reply.truncated)
                        .to_owned()
                        .into_any(),
                    info.into_any(),
                    pyo3::types::PyBool::new(py, s.autoreset)
                        .to_owned()
                        .into_any(),
                ],
            )?)?;
        }
        let first = steps.first().map(|s| &s.reply.observation);
        let first = first.ok_or_else(|| PyValueError::new_err("no envs"))?;
        let observations = convert::stacked(py, batch, &self.batches, first, steps.len())?;
        PyTuple::new(py, [observations, out.into_any()])
    }

    /// Releases every lease and completes the monitor's recording
    /// (idempotent).
    fn close(&mut self, py: Python<'_>) -> PyResult<()> {
        let envs = &mut self.envs;
        let closed = block_on_interruptibly(py, envs.close())?.map_err(errors::to_py);
        if let Some(monitor) = self.monitor.take() {
            block_on_pool(py, move || live_monitor::finish(monitor))??;
        }
        closed
    }
}

/// The session config of a remote deployment: the `OFFWORLD_ZENOH_*`
/// environment (a client unless it names a mode), with `connect` replacing
/// its endpoints.
fn remote_session(connect: Option<String>) -> PyResult<SessionConfig> {
    offworld_client::deployment_session(connect).map_err(|e| PyValueError::new_err(e.to_string()))
}

/// Opens a session on a remote deployment (`connect`, else the
/// `OFFWORLD_ZENOH_*` environment), runs `work` on it with the GIL released,
/// and closes it.
fn on_deployment<T, Fut>(
    py: Python<'_>,
    connect: Option<String>,
    work: impl FnOnce(zenoh::Session) -> Fut + Send + 'static,
) -> PyResult<T>
where
    T: Send + 'static,
    Fut: std::future::Future<Output = Result<T, WireError>> + Send + 'static,
{
    // A config mistake is a ValueError before anything is tried.
    remote_session(connect.clone())?;
    // An unreachable endpoint is an error naming it, not an empty deployment.
    spawn_interruptibly(py, offworld_client::on_deployment(connect, work))?.map_err(errors::to_py)
}

fn parse_env(env_id: &str) -> PyResult<EnvId> {
    env_id
        .parse()
        .map_err(|e: offworld_runtime::ContractError| PyValueError::new_err(e.to_string()))
}

/// Envs reachable through a deployment, as dicts (env_id, task, state,
/// until_unix_ms, message, components).
#[pyfunction]
#[pyo3(signature = (connect=None, timeout_s=2.0))]
fn list_envs<'py>(
    py: Python<'py>,
    connect: Option<String>,
    timeout_s: f64,
) -> PyResult<Bound<'py, PyList>> {
    let timeout = convert::timeout(timeout_s)?;
    let listings = on_deployment(py, connect, move |session| async move {
        offworld_client::discover(&session, timeout).await
    })?;
    let out = PyList::empty(py);
    for listing in &listings {
        out.append(convert::listing(py, listing)?)?;
    }
    Ok(out)
}

/// Runs one booking request against `env_id`; returns the bookings as
/// dicts (id, env_id, user, start_unix_ms, end_unix_ms).
fn booking_request<'py>(
    py: Python<'py>,
    connect: Option<String>,
    env_id: &str,
    request: offworld_runtime::msg::BookingRequest,
    timeout_s: f64,
) -> PyResult<Bound<'py, PyList>> {
    let env = parse_env(env_id)?;
    let timeout = convert::timeout(timeout_s)?;
    let bookings = on_deployment(py, connect, move |session| async move {
        offworld_client::book(&session, &env, &request, timeout).await
    })?;
    let out = PyList::empty(py);
    for b in &bookings.bookings {
        out.append(convert::booking(py, b)?)?;
    }
    Ok(out)
}

/// The caller's experiments on an env (operators: everyone's), as dicts.
#[pyfunction]
#[pyo3(signature = (env_id, token, connect=None, timeout_s=5.0))]
fn experiments<'py>(
    py: Python<'py>,
    env_id: &str,
    token: String,
    connect: Option<String>,
    timeout_s: f64,
) -> PyResult<Bound<'py, PyList>> {
    let env = parse_env(env_id)?;
    let timeout = convert::timeout(timeout_s)?;
    let answer = on_deployment(py, connect, move |session| async move {
        let request = offworld_runtime::msg::ExperimentsRequest::List { token };
        offworld_client::experiments(&session, &env, &request, timeout).await
    })?;
    convert::experiments(py, &answer.experiments)
}

/// One experiment and all its episodes: (experiment dict, [episode dict]).
#[pyfunction]
#[pyo3(signature = (env_id, experiment_id, token, connect=None, timeout_s=5.0))]
fn experiment_episodes<'py>(
    py: Python<'py>,
    env_id: &str,
    experiment_id: i64,
    token: String,
    connect: Option<String>,
    timeout_s: f64,
) -> PyResult<Bound<'py, PyTuple>> {
    let env = parse_env(env_id)?;
    let timeout = convert::timeout(timeout_s)?;
    let (experiment, episodes) = on_deployment(py, connect, move |session| async move {
        offworld_client::experiment_episodes(&session, &env, &token, experiment_id, timeout).await
    })?;
    convert::experiment_with_episodes(py, &experiment, &episodes)
}

/// The leaderboard of an env (test-mode experiments, best first), as dicts.
#[pyfunction]
#[pyo3(signature = (env_id, connect=None, timeout_s=5.0))]
fn leaderboard<'py>(
    py: Python<'py>,
    env_id: &str,
    connect: Option<String>,
    timeout_s: f64,
) -> PyResult<Bound<'py, PyList>> {
    let env = parse_env(env_id)?;
    let timeout = convert::timeout(timeout_s)?;
    let board = on_deployment(py, connect, move |session| async move {
        offworld_client::leaderboard(&session, &env, timeout).await
    })?;
    convert::leaderboard(py, &board)
}

/// Reserves `[start_unix_ms, end_unix_ms)` on an env; returns [the booking].
#[pyfunction]
#[pyo3(signature = (env_id, start_unix_ms, end_unix_ms, token, connect=None, timeout_s=5.0))]
fn book<'py>(
    py: Python<'py>,
    env_id: &str,
    start_unix_ms: i64,
    end_unix_ms: i64,
    token: String,
    connect: Option<String>,
    timeout_s: f64,
) -> PyResult<Bound<'py, PyList>> {
    let request = offworld_runtime::msg::BookingRequest::Make {
        token,
        start_unix_ms,
        end_unix_ms,
    };
    booking_request(py, connect, env_id, request, timeout_s)
}

/// Slots of an env ending after `from_unix_ms`.
#[pyfunction]
#[pyo3(signature = (env_id, from_unix_ms, connect=None, timeout_s=5.0))]
fn bookings<'py>(
    py: Python<'py>,
    env_id: &str,
    from_unix_ms: i64,
    connect: Option<String>,
    timeout_s: f64,
) -> PyResult<Bound<'py, PyList>> {
    let request = offworld_runtime::msg::BookingRequest::List { from_unix_ms };
    booking_request(py, connect, env_id, request, timeout_s)
}

/// Cancels a slot; returns the remaining ones.
#[pyfunction]
#[pyo3(signature = (env_id, booking_id, token, connect=None, timeout_s=5.0))]
fn cancel_booking<'py>(
    py: Python<'py>,
    env_id: &str,
    booking_id: i64,
    token: String,
    connect: Option<String>,
    timeout_s: f64,
) -> PyResult<Bound<'py, PyList>> {
    let request = offworld_runtime::msg::BookingRequest::Cancel {
        token,
        id: booking_id,
    };
    booking_request(py, connect, env_id, request, timeout_s)
}

/// Who `token` is, as `env_id`'s controller says (default: a real env's,
/// else any env's): `{user, operator}`.
#[pyfunction]
#[pyo3(signature = (env_id, token, connect=None, timeout_s=5.0))]
fn whoami<'py>(
    py: Python<'py>,
    env_id: Option<&str>,
    token: String,
    connect: Option<String>,
    timeout_s: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let env = env_id.map(parse_env).transpose()?;
    let timeout = convert::timeout(timeout_s)?;
    let reply = on_deployment(py, connect, move |session| async move {
        offworld_client::whoami(&session, env.as_ref(), &token, timeout).await
    })?;
    let dict = PyDict::new(py);
    dict.set_item("user", &reply.user)?;
    dict.set_item("operator", reply.operator)?;
    Ok(dict)
}

/// Every slot booked with `token` on any env that has not ended, earliest
/// first, as dicts.
#[pyfunction]
#[pyo3(signature = (token, connect=None, timeout_s=5.0))]
fn my_bookings<'py>(
    py: Python<'py>,
    token: String,
    connect: Option<String>,
    timeout_s: f64,
) -> PyResult<Bound<'py, PyList>> {
    let timeout = convert::timeout(timeout_s)?;
    let mine = on_deployment(py, connect, move |session| async move {
        offworld_client::my_bookings(&session, &token, timeout).await
    })?;
    let out = PyList::empty(py);
    for b in &mine {
        out.append(convert::booking(py, b)?)?;
    }
    Ok(out)
}

/// `python -m offworld_gym`: runs the trainer's commands (`argv` as
/// `sys.argv`) with the GIL released; returns the exit status.
#[pyfunction]
fn run_command_line(py: Python<'_>, argv: Vec<String>) -> u8 {
    py.detach(move || offworld_client::cli::run_from(argv))
}

/// The names of the tasks the controller serves (`env_controller/tasks.toml`),
/// from which the gymnasium ids are made.
#[pyfunction]
fn task_names() -> Vec<String> {
    offworld_env_controller::Task::names()
}

/// The native half of `offworld_gym`.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<NativeEnvs>()?;
    m.add_function(wrap_pyfunction!(task_names, m)?)?;
    m.add_function(wrap_pyfunction!(list_envs, m)?)?;
    m.add_function(wrap_pyfunction!(book, m)?)?;
    m.add_function(wrap_pyfunction!(bookings, m)?)?;
    m.add_function(wrap_pyfunction!(cancel_booking, m)?)?;
    m.add_function(wrap_pyfunction!(whoami, m)?)?;
    m.add_function(wrap_pyfunction!(my_bookings, m)?)?;
    m.add_function(wrap_pyfunction!(run_command_line, m)?)?;
    m.add_function(wrap_pyfunction!(experiments, m)?)?;
    m.add_function(wrap_pyfunction!(experiment_episodes, m)?)?;
    m.add_function(wrap_pyfunction!(leaderboard, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
