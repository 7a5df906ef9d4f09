//! Backpressure and fairness (issue 22) over real Zenoh sessions on
//! loopback: while env A's state is held by a reset drive that does not
//! end (the test plays A's robot and holds its `goto`), a bounded flood of
//! `status`, `step` and `reset` queries to A is answered — `status` at once,
//! `Busy` beyond the queue, every queued one once the drive ends; never
//! silence — while a client of env B opens, resets and steps as if nothing
//! happened. A client over its rate, a request over the size limit and a
//! malformed client tag are refused typed. Behaviour only: no assertion on
//! how long anything took (waits are bounded, never measured).

use offworld_runtime::Resolution;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::embedded::{Embedded, SimEnv, Stepping, TwinProfile};
use offworld_env_controller::{EnvOptions, RequestLimits, Store, Task};
use offworld_runtime::msg::*;
use offworld_runtime::session::loopback_endpoint;
use offworld_runtime::wire::{self, RequestError};
use offworld_runtime::{Component, EnvId, ErrorCode, SessionConfig, Topic, WireError};
use zenoh::handlers::FifoChannelHandler;
use zenoh::liveliness::LivelinessToken;
use zenoh::query::{Query, Queryable};
use zenoh::Session;

/// Limits small enough to reach with a bounded flood; rates out of the way
/// (the rate test sets its own).
fn limits() -> RequestLimits {
    RequestLimits {
        env_queue: 16,
        client_queue: 8,
        client_rate_per_s: 1_000_000,
        client_burst: 1_000_000,
        ..RequestLimits::default()
    }
}

fn obs() -> ObsOptions {
    ObsOptions {
        channels: Channels::DepthOnly,
        height: 32,
        width: 32,
        depth_format: DepthFormat::Uint8,
    }
}

/// A controller serving B (a twin) and A (a robot played by the test),
/// listening on loopback.
struct Site {
    endpoint: String,
    _embedded: Embedded,
    env_a: EnvId,
    env_b: EnvId,
    _server: Session,
    _robot: Session,
    goto: Queryable<FifoChannelHandler<Query>>,
    _robot_alive: LivelinessToken,
}

async fn site(tag: &str, limits: RequestLimits) -> Site {
    let endpoint = loopback_endpoint().expect("port");
    let server = SessionConfig::listening(&endpoint)
        .open()
        .await
        .expect("server session");
    let env_a = EnvId::sim(&format!("flood-a-{tag}")).expect("env");
    let env_b = EnvId::sim(&format!("flood-b-{tag}")).expect("env");
    let sim = SimEnv {
        env: env_b.clone(),
        task: "MonolithDiscrete".into(),
        resolution: Some(Resolution::new(32, 32)),
        seed: 0,
        profile: TwinProfile::default(),
        render_threads: 1,
        stepping: Stepping::OwnThread,
    };
    let mut embedded = Embedded::start_with(
        &server,
        &[sim],
        Store::in_memory().expect("store"),
        EnvOptions::default(),
        limits,
        None,
    )
    .await
    .expect("embedded B");
    // A's robot: answers nothing until the test says so. Its queryable is
    // declared before its token, so a controller that sees the token sees
    // the queryable.
    let robot = SessionConfig::connecting(&endpoint)
        .open()
        .await
        .expect("robot session");
    let goto = robot
        .declare_queryable(env_a.key(Topic::Goto))
        .await
        .expect("goto");
    let robot_alive = robot
        .liveliness()
        .declare_token(env_a.alive_key(Component::SimTwin))
        .await
        .expect("robot token");
    let server_a = embedded
        .controller
        .serve(
            env_a.clone(),
            Task::by_name("MonolithDiscrete").expect("task"),
            EnvOptions {
                allow_anonymous: true,
                ..EnvOptions::default()
            },
        )
        .await
        .expect("serve A");
    assert!(
        server_a.link().wait_online(Duration::from_secs(10)).await,
        "A's robot never came online"
    );
    Site {
        endpoint,
        _embedded: embedded,
        env_a,
        env_b,
        _server: server,
        _robot: robot,
        goto,
        _robot_alive: robot_alive,
    }
}

impl Site {
    async fn client(&self) -> Session {
        let session = SessionConfig::connecting(&self.endpoint)
            .open()
            .await
            .expect("client session");
        for env in [&self.env_a, &self.env_b] {
            let mut visible = false;
            for _ in 0..100 {
                if status(&session, env, "probe").await.is_ok() {
                    visible = true;
                    break;
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            assert!(visible, "the controller's queryables never showed up");
        }
        session
    }
}

fn tag(id: &str) -> ClientTag {
    ClientTag {
        client_id: id.into(),
    }
}

async fn status(session: &Session, env: &EnvId, id: &str) -> Result<EnvStatus, RequestError> {
    wire::request_as(
        session,
        &env.key(Topic::Status),
        &(),
        Duration::from_secs(5),
        &tag(id),
    )
    .await
}

async fn forged_step(session: &Session, env: &EnvId, id: &str) -> Result<StepReply, RequestError> {
    let request = StepRequest {
        session_id: format!("forged-{id}"),
        seq: 1,
        action: Action::Discrete(0),
    };
    wire::request_tail_as(
        session,
        &env.key(Topic::Step),
        &request,
        Duration::from_secs(60),
        &tag(id),
        Vec::new(),
    )
    .await
}

async fn forged_reset(
    session: &Session,
    env: &EnvId,
    id: &str,
) -> Result<ResetReply, RequestError> {
    let request = ResetRequest {
        session_id: format!("forged-{id}"),
        seed: Seed::Continue,
    };
    wire::request_tail_as(
        session,
        &env.key(Topic::Reset),
        &request,
        Duration::from_secs(60),
        &tag(id),
        Vec::new(),
    )
    .await
}

/// What a flood query got: a reply (`Ok`) or a typed refusal. Silence
/// (a timeout, nobody answering, an undecodable reply) fails the test.
fn answer<T>(what: &str, result: Result<T, RequestError>) -> Result<T, WireError> {
    match result {
        Ok(reply) => Ok(reply),
        Err(RequestError::Remote(e)) => Err(e),
        Err(other) => panic!("{what}: no answer: {other}"),
    }
}

/// Opens B, resets and takes `steps` steps, resetting when an episode ends:
/// every one must succeed.
async fn drive_b(session: &Session, env: &EnvId, steps: u32) -> u32 {
    let mut b = EnvClient::open(
        session,
        env,
        OpenRequest::anonymous(obs()),
        ClientTimeouts::default(),
    )
    .await
    .expect("B opens");
    b.reset(Seed::Fixed(7)).await.expect("B resets");
    let mut taken = 0;
    for i in 0..steps {
        let r = b
            .step(Action::Discrete(i64::from(i % 3)))
            .await
            .expect("B steps");
        taken += 1;
        if r.terminated || r.truncated {
            b.reset(Seed::Continue).await.expect("B resets again");
        }
    }
    b.close().await.expect("B closes");
    taken
}

/// Waits (bounded) for the robot to be asked to drive: A's reset then
/// holds A's state until the test answers.
async fn held_drive(site: &Site) -> Query {
    tokio::time::timeout(Duration::from_secs(30), site.goto.recv_async())
        .await
        .expect("A's reset never asked its robot to drive")
        .expect("goto query")
}

fn release(drive: Query) {
    let released = WireError::unavailable("the test's robot gives up the drive");
    wire::reply_now::<GotoReply>(&drive, Err(released)).expect("goto answered");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_flood_on_one_env_is_answered_and_another_env_is_served_throughout() {
    const FLOOD: usize = 2000;
    let limits = limits();
    let site = site("main", limits).await;
    let trainer = site.client().await;

    // A's holder starts a reset that holds A's state: its robot never
    // arrives until released.
    let mut holder = EnvClient::open(
        &trainer,
        &site.env_a,
        OpenRequest::anonymous(obs()),
        ClientTimeouts::default(),
    )
    .await
    .expect("A opens");
    let holding = tokio::spawn(async move {
        let reset = holder.reset(Seed::Fixed(1)).await;
        (holder, reset)
    });
    let drive = held_drive(&site).await;

    // One greedy client: the state's queue has `env_queue - 1` places left
    // (the holder's reset has one); the greedy client gets its own share
    // and no more.
    let greedy_session = site.client().await;
    let greedy_answered = Arc::new(AtomicUsize::new(0));
    let greedy: Vec<_> = (0..limits.client_queue + 4)
        .map(|_| {
            let (s, env) = (greedy_session.clone(), site.env_a.clone());
            let answered = greedy_answered.clone();
            tokio::spawn(async move {
                let got = answer("greedy step", forged_step(&s, &env, "greedy").await);
                answered.fetch_add(1, Ordering::SeqCst);
                got
            })
        })
        .collect();
    // Its four refusals come back while A's state is held (bounded wait);
    // its other eight are queued.
    wait_until("the greedy client's refusals", || {
        greedy_answered.load(Ordering::SeqCst) >= 4
    })
    .await;

    // The flood: status, step and reset queries from 50 made-up clients,
    // all sent without waiting for any answer.
    let flooder = site.client().await;
    let answered = Arc::new(AtomicUsize::new(0));
    let flood: Vec<_> = (0..FLOOD)
        .map(|i| {
            let (s, env, answered) = (flooder.clone(), site.env_a.clone(), answered.clone());
            let id = format!("flooder-{}", i % 50);
            tokio::spawn(async move {
                let got: Result<Option<EnvStatus>, WireError> = match i % 3 {
                    0 => answer("status", status(&s, &env, &id).await).map(Some),
                    1 => answer("step", forged_step(&s, &env, &id).await).map(|_| None),
                    _ => answer("reset", forged_reset(&s, &env, &id).await).map(|_| None),
                };
                answered.fetch_add(1, Ordering::SeqCst);
                (i % 3, got)
            })
        })
        .collect();

    // Meanwhile B is served as usual.
    let b_session = site.client().await;
    assert_eq!(drive_b(&b_session, &site.env_b, 30).await, 30);

    // Everything but what fits in A's queue is answered while A's state is
    // still held (bounded wait): status from the snapshot, the rest Busy.
    let queued_at_most = limits.env_queue;
    wait_until("the flood's answers while A's state is held", || {
        answered.load(Ordering::SeqCst) >= FLOOD - queued_at_most
    })
    .await;

    // The drive ends: the queued requests are handled and answered.
    release(drive);
    let (mut holder, reset) = holding.await.expect("holder");
    assert_eq!(
        reset.expect_err("the drive was given up").code,
        ErrorCode::Unavailable
    );

    let mut greedy_busy = 0;
    for request in greedy {
        match request.await.expect("greedy task") {
            Ok(_) => panic!("a forged step succeeded"),
            Err(e) if e.code == ErrorCode::Busy => {
                assert!(e.message.contains("--client-queue"), "{e}");
                greedy_busy += 1;
            }
            Err(e) => assert_eq!(e.code, ErrorCode::Unauthorized, "{e}"),
        }
    }
    assert_eq!(greedy_busy, 4, "the greedy client got exactly its share");

    let (mut busy, mut statuses, mut handled) = (0, 0, 0);
    for query in flood {
        let (kind, got) = tokio::time::timeout(Duration::from_secs(60), query)
            .await
            .expect("a flood query was never answered")
            .expect("flood task");
        match (kind, got) {
            (0, Ok(Some(status))) => {
                assert!(
                    matches!(status.state, EnvState::Leased { .. }),
                    "{status:?}"
                );
                statuses += 1;
            }
            (0, other) => panic!("status refused: {other:?}"),
            (_, Ok(_)) => panic!("a forged step or reset succeeded"),
            (_, Err(e)) if e.code == ErrorCode::Busy => busy += 1,
            (_, Err(e)) => {
                assert_eq!(e.code, ErrorCode::Unauthorized, "{e}");
                handled += 1;
            }
        }
    }
    eprintln!("flood on A: {statuses} status answered, {busy} Busy, {handled} queued and handled");
    assert_eq!(statuses, FLOOD.div_ceil(3), "every status answered");
    assert!(busy >= 1, "no Busy beyond a queue of {}", limits.env_queue);
    assert_eq!(statuses + busy + handled, FLOOD);
    assert!(handled < limits.env_queue, "{handled} queued");

    // The controller serves normally after: B again, A's status, A's holder.
    assert_eq!(drive_b(&b_session, &site.env_b, 5).await, 5);
    let after = status(&flooder, &site.env_a, "flooder-0")
        .await
        .expect("status after the flood");
    assert!(matches!(after.state, EnvState::Leased { .. }), "{after:?}");
    holder.close().await.expect("A's holder closes");
    let free = status(&flooder, &site.env_a, "flooder-0")
        .await
        .expect("status after close");
    assert_eq!(free.state, EnvState::Free);
}

/// Polls `done` every 100 ms, for at most a minute.
async fn wait_until(what: &str, done: impl Fn() -> bool) {
    for _ in 0..600 {
        if done() {
            return;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    panic!("{what}: not within a minute");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn over_the_rate_size_or_with_a_bad_tag_requests_are_refused_typed() {
    let limits = RequestLimits {
        client_rate_per_s: 1,
        client_burst: 10,
        ..limits()
    };
    let site = site("limits", limits).await;
    let session = site.client().await;

    // A hasty client: its burst passes, then Busy saying when to retry;
    // another client is not held to the hasty one's rate.
    let hasty: Vec<_> = (0..60)
        .map(|_| {
            let (s, env) = (session.clone(), site.env_b.clone());
            tokio::spawn(async move { status(&s, &env, "hasty").await })
        })
        .collect();
    let mut refused = 0;
    for r in hasty {
        match answer("hasty status", r.await.expect("task")) {
            Ok(_) => {}
            Err(e) => {
                assert_eq!(e.code, ErrorCode::Busy, "{e}");
                assert!(e.message.contains("--client-rate"), "{e}");
                assert!(e.message.contains("retry in"), "{e}");
                refused += 1;
            }
        }
    }
    assert!(refused >= 1, "a burst of 10 let 60 through");
    assert!(refused <= 50, "the burst of 10 was not granted");
    status(&session, &site.env_b, "patient")
        .await
        .expect("another client's status");

    // Over the size limit: BadRequest before anything is decoded.
    let oversized = vec![0u8; limits.max_request_bytes + 1];
    for topic in [Topic::Step, Topic::Open, Topic::Status] {
        let r: Result<EnvStatus, _> = wire::request_raw(
            &session,
            &site.env_b.key(topic),
            oversized.clone(),
            Duration::from_secs(10),
        )
        .await;
        let e = answer("oversized", r).expect_err("refused");
        assert_eq!(e.code, ErrorCode::BadRequest, "{topic:?}: {e}");
        assert!(e.message.contains("--max-request-bytes"), "{e}");
    }

    // A client tag that is not one.
    for bad in ["", "has/slash", &"x".repeat(65)] {
        let e = answer("bad tag", status(&session, &site.env_b, bad).await).expect_err("refused");
        assert_eq!(e.code, ErrorCode::BadRequest, "{bad:?}: {e}");
    }

    // Still serving.
    assert_eq!(drive_b(&session, &site.env_b, 3).await, 3);
}

/// The embedded deployment (Python's default) has its clients on the
/// controller's own session: the queries answered in Zenoh's callback
/// (`status`, `spec`, refusals) and on tasks (the rest) reach them too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_on_the_controllers_own_session_are_answered() {
    use offworld_deploy::{connect, Target};
    let connection = connect(
        Target::Embedded {
            task: "MonolithDiscrete".into(),
            resolution: Resolution::new(32, 32),
            count: 1,
            record: None,
            twin_profile: TwinProfile::default(),
        },
        "MonolithDiscrete",
    )
    .await
    .expect("embedded");
    let (session, env) = (&connection.session, &connection.envs[0]);
    let spec = offworld_client::spec(session, env, Duration::from_secs(5))
        .await
        .expect("spec");
    assert_eq!(spec.task, "MonolithDiscrete");
    let free = status(session, env, "local").await.expect("status");
    assert_eq!(free.state, EnvState::Free);
    let oversized: Result<EnvStatus, _> = wire::request_raw(
        session,
        &env.key(Topic::Status),
        vec![0; RequestLimits::default().max_request_bytes + 1],
        Duration::from_secs(5),
    )
    .await;
    assert_eq!(
        answer("oversized", oversized).expect_err("refused").code,
        ErrorCode::BadRequest
    );
    assert_eq!(drive_b(session, env, 3).await, 3);
}
