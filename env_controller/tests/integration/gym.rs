//! The gym server over real Zenoh sessions on loopback, against the
//! embedded sim twin: full episodes, determinism, every bad input, leases,
//! disconnects, maintenance, persistence across restarts, the leaderboard.

use offworld_runtime::Resolution;
use offworld_test_support::ScratchDir;
use std::path::Path;
use std::time::Duration;

use offworld_client::{self as client, ClientTimeouts, EnvClient};
use offworld_deploy::embedded::{Embedded, SimEnv, Stepping, TwinProfile};
use offworld_env_controller::Store;
use offworld_runtime::msg::*;
use offworld_runtime::session::loopback_endpoint;
use offworld_runtime::{wire, EnvId, ErrorCode, SessionConfig, Topic, WireError};
use zenoh::qos::Priority;
use zenoh::Session;

struct Deployment {
    _server: Session,
    endpoint: String,
    _embedded: Embedded,
    env: EnvId,
}

async fn deploy(db: &Path, task: &str, token_users: &[(&str, &str, bool)]) -> Deployment {
    let store = Store::open(db).expect("store");
    for (name, token, operator) in token_users {
        // Re-deploying on the same file keeps existing users.
        let _ = store.add_user_with_token(name, token, *operator);
    }
    let endpoint = loopback_endpoint().expect("port");
    let server = SessionConfig::listening(&endpoint)
        .open()
        .await
        .expect("server session");
    let env = EnvId::sim("gym-test").expect("env");
    let sim = SimEnv {
        env: env.clone(),
        task: task.into(),
        resolution: Some(Resolution::new(84, 84)),
        seed: 0,
        profile: TwinProfile::default(),
        render_threads: 1,
        stepping: Stepping::OnArrival,
    };
    let embedded = Embedded::start(&server, &[sim], store)
        .await
        .expect("embedded");
    Deployment {
        _server: server,
        endpoint,
        _embedded: embedded,
        env,
    }
}

async fn client_session(d: &Deployment) -> Session {
    let session = SessionConfig::connecting(&d.endpoint)
        .open()
        .await
        .expect("client session");
    // Bounded wait until the controller's queryables are visible.
    for _ in 0..100 {
        if client::spec(&session, &d.env, Duration::from_secs(2))
            .await
            .is_ok()
        {
            return session;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    panic!("controller not reachable");
}

fn open_request(token: &str, name: &str, resume: bool, mode: AlgorithmMode) -> OpenRequest {
    OpenRequest {
        token: token.into(),
        client_id: String::new(),
        experiment_name: name.into(),
        resume_experiment: resume,
        learning_type: LearningType::EndToEnd,
        algorithm_mode: mode,
        obs: ObsOptions {
            channels: Channels::DepthOnly,
            height: 84,
            width: 84,
            depth_format: DepthFormat::Uint8,
        },
    }
}

async fn open(
    session: &Session,
    env: &EnvId,
    token: &str,
    name: &str,
) -> Result<EnvClient, WireError> {
    EnvClient::open(
        session,
        env,
        open_request(token, name, false, AlgorithmMode::Train),
        ClientTimeouts::default(),
    )
    .await
}

const ALICE: &str = "alice-token-0001";
const BOB: &str = "bob-token-000002";
const OPERATOR: &str = "operator-token-3";

fn users() -> Vec<(&'static str, &'static str, bool)> {
    vec![
        ("alice", ALICE, false),
        ("bob", BOB, false),
        ("ops", OPERATOR, true),
    ]
}

/// Resets with `seed`, takes up to six steps; returns every observation.
async fn seeded_run(env: &mut EnvClient, seed: u64) -> Vec<Vec<u8>> {
    let first = env.reset(Seed::Fixed(seed)).await.expect("reset");
    assert_eq!(
        (
            first.observation.height,
            first.observation.width,
            first.observation.channels
        ),
        (84, 84, 1)
    );
    assert_eq!(first.observation.dtype, DType::U8);
    assert!(first.observation.is_consistent());
    assert_eq!(first.info.step, 0);
    let mut frames = vec![first.observation.data];
    for i in 0..6 {
        let r = env.step(Action::Discrete(i % 4)).await.expect("step");
        assert_eq!(r.info.step, i as u32 + 1);
        frames.push(r.observation.data);
        if r.terminated || r.truncated {
            break;
        }
    }
    frames
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn full_episode_and_seeded_determinism() {
    let dir = ScratchDir::new("gym-test");
    let d = deploy(&dir.path().join("gym.db"), "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;
    let spec = client::spec(&session, &d.env, Duration::from_secs(5))
        .await
        .expect("spec");
    assert_eq!(spec.task, "MonolithDiscrete");
    assert_eq!(spec.max_episode_steps, 100);
    assert!(matches!(
        spec.action_space,
        ActionSpace::Discrete { n: 4, .. }
    ));

    // Commands and heartbeats travel at the control priority (ahead of
    // camera data on every link).
    let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::<(Topic, Priority)>::new()));
    let mut watches = Vec::new();
    for topic in [Topic::Cmd, Topic::Heartbeat] {
        let seen = seen.clone();
        let watch = session
            .declare_subscriber(d.env.key(topic))
            .callback(move |s| seen.lock().expect("lock").push((topic, s.priority())))
            .await
            .expect("subscriber");
        watches.push(watch);
    }
    let mut env = open(&session, &d.env, ALICE, "det").await.expect("open");
    let a = seeded_run(&mut env, 7).await;
    let b = seeded_run(&mut env, 7).await;
    assert_eq!(a, b, "same seed + actions → identical observations");
    let c = seeded_run(&mut env, 8).await;
    assert_ne!(a[0], c[0], "another seed spawns elsewhere");

    // Run one episode to its end: FORWARD until terminated or truncated.
    let reset = env.reset(Seed::Fixed(1)).await.expect("reset");
    let episode_id = reset.info.episode_id;
    // The reset's accuracy is in the status: where it asked for, where the
    // episode starts (the twin teleports there: within a millimetre).
    let status = client::status(&session, &d.env, Duration::from_secs(5))
        .await
        .expect("status");
    let accuracy = status.last_reset;
    assert!(accuracy.measured, "{accuracy:?}");
    assert_eq!(
        (
            accuracy.achieved.x,
            accuracy.achieved.y,
            accuracy.achieved.yaw
        ),
        (reset.info.x, reset.info.y, reset.info.yaw),
        "achieved = the pose the episode starts from"
    );
    assert!(accuracy.position_error_m < 0.001, "{accuracy:?}");
    assert!(accuracy.yaw_error_rad < 0.001, "{accuracy:?}");
    assert!(
        accuracy.duration_s > 0.0 && accuracy.duration_s < 10.0,
        "{accuracy:?}"
    );
    let mut last = None;
    for _ in 0..100 {
        let r = env.step(Action::Discrete(2)).await.expect("step");
        let done = r.terminated || r.truncated;
        last = Some(r);
        if done {
            break;
        }
    }
    let last = last.expect("stepped");
    assert!(
        last.terminated || last.truncated,
        "episode ends within 100 steps"
    );
    assert_eq!(last.info.episode_id, episode_id);
    assert!(last.truncated == (last.info.step == 100) || last.terminated);
    let after = env
        .step(Action::Discrete(2))
        .await
        .expect_err("stepping a finished episode");
    assert_eq!(after.code, ErrorCode::InvalidState);
    let closed = env.close().await.expect("close");
    assert!(closed.experiment.episodes >= 4, "{:?}", closed.experiment);
    // A sim episode can outrun the 50 ms heartbeat: wait (bounded) for one.
    for _ in 0..100 {
        if seen
            .lock()
            .expect("lock")
            .iter()
            .any(|(t, _)| *t == Topic::Heartbeat)
        {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let seen = seen.lock().expect("lock").clone();
    for topic in [Topic::Cmd, Topic::Heartbeat] {
        let priorities: Vec<Priority> = seen
            .iter()
            .filter(|(t, _)| *t == topic)
            .map(|(_, p)| *p)
            .collect();
        assert!(
            !priorities.is_empty(),
            "no {topic:?} seen in {}",
            seen.len()
        );
        assert!(
            priorities.iter().all(|p| *p == wire::CONTROL_PRIORITY),
            "{topic:?} priorities {priorities:?}"
        );
    }
    assert_eq!(env.close().await.expect("idempotent"), closed);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_inputs_get_typed_errors_and_the_server_keeps_serving() {
    let dir = ScratchDir::new("gym-test");
    let d = deploy(&dir.path().join("gym.db"), "MonolithContinuous", &users()).await;
    let session = client_session(&d).await;
    let code = |r: Result<EnvClient, WireError>| r.err().map(|e| e.code);

    // Bad token.
    assert_eq!(
        code(open(&session, &d.env, "wrong-token-xyz", "x").await),
        Some(ErrorCode::Unauthorized)
    );
    // Bad observation options.
    let mut bad_obs = open_request(ALICE, "x", false, AlgorithmMode::Train);
    bad_obs.obs.width = 0;
    let r = EnvClient::open(&session, &d.env, bad_obs, ClientTimeouts::default()).await;
    assert_eq!(code(r), Some(ErrorCode::BadRequest));
    // Resuming an unknown experiment.
    let r = EnvClient::open(
        &session,
        &d.env,
        open_request(ALICE, "nope", true, AlgorithmMode::Train),
        ClientTimeouts::default(),
    )
    .await;
    assert_eq!(code(r), Some(ErrorCode::NotFound));

    let mut env = open(&session, &d.env, ALICE, "bad-inputs")
        .await
        .expect("open");
    // Step before reset.
    let e = env
        .step(Action::Continuous(vec![0.0, 0.0]))
        .await
        .expect_err("before reset");
    assert_eq!(e.code, ErrorCode::InvalidState);
    env.reset(Seed::Fixed(3)).await.expect("reset");
    // Bad actions: never clipped, always refused.
    for action in [
        Action::Continuous(vec![1.5, 0.0]),
        Action::Continuous(vec![f32::NAN, 0.0]),
        Action::Continuous(vec![0.0]),
        Action::Discrete(1),
    ] {
        let e = env.step(action.clone()).await.expect_err("bad action");
        assert_eq!(e.code, ErrorCode::BadRequest, "{action:?}");
    }
    // A session that does not hold the lease.
    let forged = StepRequest {
        session_id: "forged".into(),
        seq: 1,
        action: Action::Continuous(vec![0.0, 0.0]),
    };
    let r: Result<StepReply, _> = wire::request(
        &session,
        &d.env.key(Topic::Step),
        &forged,
        Duration::from_secs(5),
    )
    .await;
    assert_eq!(
        r.map_err(|e| e.into_wire().code).err(),
        Some(ErrorCode::Unauthorized)
    );
    // Garbage bytes.
    let r: Result<StepReply, _> = wire::request_raw(
        &session,
        &d.env.key(Topic::Step),
        vec![9, 9, 9, 9, 9],
        Duration::from_secs(5),
    )
    .await;
    assert_eq!(
        r.map_err(|e| e.into_wire().code).err(),
        Some(ErrorCode::BadRequest)
    );
    // An env nobody serves.
    let ghost = EnvId::sim("ghost").expect("env");
    assert_eq!(
        code(open(&session, &ghost, ALICE, "x").await),
        Some(ErrorCode::NotFound)
    );
    // Still serving.
    let ok = env
        .step(Action::Continuous(vec![0.5, -0.25]))
        .await
        .expect("valid step after errors");
    assert_eq!(ok.info.step, 1);
    env.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn leases_busy_disconnect_and_maintenance() {
    let dir = ScratchDir::new("gym-test");
    let d = deploy(&dir.path().join("gym.db"), "MonolithDiscrete", &users()).await;
    let alice_session = client_session(&d).await;
    let bob_session = client_session(&d).await;
    let mut alice = open(&alice_session, &d.env, ALICE, "lease")
        .await
        .expect("alice opens");
    let status = client::status(&bob_session, &d.env, Duration::from_secs(5))
        .await
        .expect("status");
    assert!(
        matches!(status.state, EnvState::Leased { .. }),
        "{status:?}"
    );
    let busy = open(&bob_session, &d.env, BOB, "lease")
        .await
        .err()
        .expect("bob is refused");
    assert_eq!(busy.code, ErrorCode::Busy);
    assert!(busy.message.contains("until"), "{}", busy.message);

    // Alice drops off mid-episode: the episode is aborted and recorded,
    // the lease waits for her, Bob is still refused, Alice comes back.
    alice.reset(Seed::Fixed(1)).await.expect("reset");
    alice.step(Action::Discrete(2)).await.expect("step");
    drop(alice);
    alice_session.close().await.expect("close session");
    tokio::time::sleep(Duration::from_millis(500)).await;
    let busy = open(&bob_session, &d.env, BOB, "lease")
        .await
        .err()
        .expect("grace period");
    assert_eq!(busy.code, ErrorCode::Busy);
    let alice_again = client_session(&d).await;
    let mut alice = EnvClient::open(
        &alice_again,
        &d.env,
        open_request(ALICE, "lease", true, AlgorithmMode::Train),
        ClientTimeouts::default(),
    )
    .await
    .expect("alice resumes");
    assert_eq!(
        alice.opened().experiment.episodes,
        1,
        "the aborted episode was recorded"
    );
    assert_eq!(alice.opened().experiment.steps, 1);
    let r = alice.reset(Seed::Fixed(2)).await.expect("reset");
    assert_eq!(r.info.episode_id, 1, "episode ids continue");
    alice.close().await.expect("close");

    // Who a token is: any user may ask; nothing changes.
    let who: AdminReply = wire::request(
        &bob_session,
        &d.env.key(Topic::Admin),
        &AdminRequest::Identify { token: BOB.into() },
        Duration::from_secs(5),
    )
    .await
    .expect("identify");
    assert_eq!((who.user.as_str(), who.operator), ("bob", false));
    assert_eq!(who.status.state, EnvState::Free);
    let unknown = wire::request::<_, AdminReply>(
        &bob_session,
        &d.env.key(Topic::Admin),
        &AdminRequest::Identify {
            token: "no-such-token".into(),
        },
        Duration::from_secs(5),
    )
    .await
    .map_err(|e| e.into_wire().code)
    .err();
    assert_eq!(unknown, Some(ErrorCode::Unauthorized));

    // Maintenance: only operators; users are told why and until when.
    let set = AdminRequest::SetMaintenance {
        token: BOB.into(),
        message: "new wheels".into(),
        back_unix_ms: 0,
    };
    let r: Result<AdminReply, _> = wire::request(
        &bob_session,
        &d.env.key(Topic::Admin),
        &set,
        Duration::from_secs(5),
    )
    .await;
    let refused = r.map_err(|e| e.into_wire()).expect_err("not an operator");
    assert_eq!(refused.code, ErrorCode::Unauthorized);
    assert!(
        refused.message.contains("bob is not an operator"),
        "{refused}"
    );
    let back = 4_102_444_800_000; // 2100-01-01
                                  // Bob holds the env when it goes into maintenance: his lease ends.
    let mut held = open(&bob_session, &d.env, BOB, "held")
        .await
        .expect("bob gets the env");
    let set = AdminRequest::SetMaintenance {
        token: OPERATOR.into(),
        message: "new wheels".into(),
        back_unix_ms: back,
    };
    let reply: AdminReply = wire::request(
        &bob_session,
        &d.env.key(Topic::Admin),
        &set,
        Duration::from_secs(5),
    )
    .await
    .expect("admin");
    assert_eq!((reply.user.as_str(), reply.operator), ("ops", true));
    assert_eq!(
        reply.status.state,
        EnvState::Maintenance {
            message: "new wheels".into(),
            by: "ops".into(),
            back_unix_ms: back,
        }
    );
    let ended = held
        .reset(Seed::Fixed(1))
        .await
        .expect_err("the lease ended with the maintenance");
    assert_eq!(ended.code, ErrorCode::Unauthorized, "{ended}");
    assert_eq!(
        ended.message,
        format!(
            "{} went into maintenance (new wheels); your lease ended with it",
            d.env
        )
    );
    let refused = open(&bob_session, &d.env, BOB, "m")
        .await
        .err()
        .expect("maintenance");
    assert_eq!(refused.code, ErrorCode::Unavailable);
    assert!(refused.message.contains("new wheels"), "{refused}");
    assert!(
        refused.message.contains("expected back at 2100-01-01"),
        "{refused}"
    );
    let not_a_date = wire::request::<_, AdminReply>(
        &bob_session,
        &d.env.key(Topic::Admin),
        &AdminRequest::SetMaintenance {
            token: OPERATOR.into(),
            message: "x".into(),
            back_unix_ms: i64::MAX,
        },
        Duration::from_secs(5),
    )
    .await
    .map_err(|e| e.into_wire().code)
    .err();
    assert_eq!(not_a_date, Some(ErrorCode::BadRequest));
    let clear = AdminRequest::ClearMaintenance {
        token: OPERATOR.into(),
    };
    let status = wire::request::<_, AdminReply>(
        &bob_session,
        &d.env.key(Topic::Admin),
        &clear,
        Duration::from_secs(5),
    )
    .await
    .expect("admin")
    .status;
    assert_eq!(status.state, EnvState::Free);

    // A revoked lease: the holder is named on the status while it holds
    // the env, its episode is recorded as aborted, its next request is
    // told who revoked it and why, and the env is free for others.
    let mut bob = open(&bob_session, &d.env, BOB, "revoked")
        .await
        .expect("bob gets the env");
    bob.reset(Seed::Fixed(3)).await.expect("reset");
    bob.step(Action::Discrete(2)).await.expect("step");
    let revoke = |token: &str| AdminRequest::RevokeLease {
        token: token.into(),
        reason: "the enclosure is needed for a demo".into(),
    };
    let status = wire::request::<_, EnvStatus>(
        &bob_session,
        &d.env.key(Topic::Status),
        &(),
        Duration::from_secs(5),
    )
    .await
    .expect("status");
    assert!(
        matches!(&status.state, EnvState::Leased { holder, .. } if holder == "bob"),
        "{status:?}"
    );
    let by_user = wire::request::<_, AdminReply>(
        &bob_session,
        &d.env.key(Topic::Admin),
        &revoke(BOB),
        Duration::from_secs(5),
    )
    .await
    .map_err(|e| e.into_wire().code)
    .err();
    assert_eq!(by_user, Some(ErrorCode::Unauthorized));
    let reply: AdminReply = wire::request(
        &bob_session,
        &d.env.key(Topic::Admin),
        &revoke(OPERATOR),
        Duration::from_secs(5),
    )
    .await
    .expect("revoke");
    assert_eq!(reply.status.state, EnvState::Free);
    let told = bob
        .step(Action::Discrete(2))
        .await
        .expect_err("the lease is gone");
    assert_eq!(told.code, ErrorCode::Unauthorized);
    assert_eq!(
        told.message,
        format!(
            "your lease on {} was revoked by the operator ops: the enclosure is needed for a demo",
            d.env
        )
    );
    let nothing = wire::request::<_, AdminReply>(
        &bob_session,
        &d.env.key(Topic::Admin),
        &revoke(OPERATOR),
        Duration::from_secs(5),
    )
    .await
    .map_err(|e| e.into_wire().code)
    .err();
    assert_eq!(nothing, Some(ErrorCode::NotFound));
    let mut alice = open(&bob_session, &d.env, ALICE, "after")
        .await
        .expect("alice gets the env");
    alice.close().await.expect("close");
    let mut reopened = EnvClient::open(
        &bob_session,
        &d.env,
        open_request(BOB, "revoked", true, AlgorithmMode::Train),
        ClientTimeouts::default(),
    )
    .await
    .expect("bob resumes");
    assert_eq!(
        (
            reopened.opened().experiment.episodes,
            reopened.opened().experiment.steps
        ),
        (1, 1),
        "the revoked episode was recorded (aborted)"
    );
    reopened.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn records_survive_a_restart_and_rank_on_the_leaderboard() {
    let dir = ScratchDir::new("gym-test");
    let db = dir.path().join("gym.db");
    let mut first_steps = 0;
    {
        let d = deploy(&db, "MonolithDiscrete", &users()).await;
        let session = client_session(&d).await;
        let mut env = EnvClient::open(
            &session,
            &d.env,
            open_request(ALICE, "eval", false, AlgorithmMode::Test),
            ClientTimeouts::default(),
        )
        .await
        .expect("open");
        for seed in 0..2 {
            env.reset(Seed::Fixed(seed)).await.expect("reset");
            for _ in 0..3 {
                env.step(Action::Discrete(2)).await.expect("step");
                first_steps += 1;
            }
        }
        env.close().await.expect("close");
    }
    // The controller is gone; a new one on the same file sees everything.
    let store = Store::open(&db).expect("reopen");
    let experiments = store.experiments().expect("list");
    let eval = experiments
        .iter()
        .find(|e| e.name == "eval")
        .expect("eval row");
    assert_eq!((eval.episodes, eval.steps), (2, first_steps));
    assert_eq!(eval.algorithm_mode, "test");
    let episodes = store.episodes(eval.id).expect("episodes");
    assert_eq!(episodes.len(), 2);
    assert!(episodes
        .iter()
        .all(|e| e.end_reason == "reset before the episode ended" || e.end_reason == "closed"));
    drop(store);

    let d = deploy(&db, "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;
    let mut env = EnvClient::open(
        &session,
        &d.env,
        open_request(ALICE, "eval", true, AlgorithmMode::Test),
        ClientTimeouts::default(),
    )
    .await
    .expect("resume after restart");
    assert_eq!(env.opened().experiment.episodes, 2);
    let r = env.reset(Seed::Fixed(9)).await.expect("reset");
    assert_eq!(r.info.episode_id, 2);
    // Finish one scored episode: step until the end.
    loop {
        let s = env.step(Action::Discrete(2)).await.expect("step");
        if s.terminated || s.truncated {
            break;
        }
    }
    env.close().await.expect("close");
    let board = client::leaderboard(&session, &d.env, Duration::from_secs(5))
        .await
        .expect("leaderboard");
    assert_eq!(
        board.entries.len(),
        1,
        "aborted episodes do not count; one scored"
    );
    assert_eq!(board.entries[0].experiment, "eval");
    assert_eq!(board.entries[0].episodes, 1);
}

async fn booking(
    session: &Session,
    env: &EnvId,
    request: BookingRequest,
) -> Result<Vec<Booking>, WireError> {
    client::book(session, env, &request, Duration::from_secs(5))
        .await
        .map(|b| b.bookings)
}

fn make(token: &str, start_unix_ms: i64, end_unix_ms: i64) -> BookingRequest {
    BookingRequest::Make {
        token: token.into(),
        start_unix_ms,
        end_unix_ms,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bookings_reserve_slots_and_end_leases_with_them() {
    let dir = ScratchDir::new("gym-test");
    let db = dir.path().join("gym.db");
    let d = deploy(&db, "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;
    let now = offworld_env_controller::store::now_ms();

    // Bad slots are typed errors; nothing is stored.
    for (request, code) in [
        (make(ALICE, now + 5_000, now + 5_000), ErrorCode::BadRequest),
        (make(ALICE, now - 9_000, now - 1_000), ErrorCode::BadRequest),
        (
            make(ALICE, now, now + 5 * 3600 * 1000),
            ErrorCode::BadRequest,
        ),
        (make("", now, now + 1_000), ErrorCode::Unauthorized),
        (
            make("wrong-token-xyz", now, now + 1_000),
            ErrorCode::Unauthorized,
        ),
    ] {
        let err = booking(&session, &d.env, request)
            .await
            .expect_err("refused");
        assert_eq!(err.code, code, "{err}");
    }
    let listed = booking(&session, &d.env, BookingRequest::List { from_unix_ms: 0 })
        .await
        .expect("list");
    assert!(listed.is_empty(), "{listed:?}");

    // Bob books a slot starting in 1.5 s for 1.5 s; an overlapping one is busy.
    let (start, end) = (now + 1_500, now + 3_000);
    let bobs = booking(&session, &d.env, make(BOB, start, end))
        .await
        .expect("booked");
    assert_eq!(bobs.len(), 1);
    assert_eq!(
        (
            bobs[0].user.as_str(),
            bobs[0].start_unix_ms,
            bobs[0].end_unix_ms
        ),
        ("bob", start, end)
    );
    let clash = booking(&session, &d.env, make(ALICE, end - 1, end + 1_000))
        .await
        .expect_err("overlap");
    assert_eq!(clash.code, ErrorCode::Busy);
    assert!(clash.message.contains("booked by bob"), "{clash}");
    // Alice cannot cancel Bob's slot.
    let not_hers = booking(
        &session,
        &d.env,
        BookingRequest::Cancel {
            token: ALICE.into(),
            id: bobs[0].id,
        },
    )
    .await
    .expect_err("not hers");
    assert_eq!(not_hers.code, ErrorCode::Unauthorized);

    // Before the slot, leases are first come: Alice steps…
    let mut alice = open(&session, &d.env, ALICE, "before-slot")
        .await
        .expect("alice opens before the slot");
    alice.reset(Seed::Fixed(1)).await.expect("reset");
    alice.step(Action::Discrete(2)).await.expect("step");
    // …until Bob's slot begins: her lease ends and she is told why.
    tokio::time::sleep(Duration::from_millis(
        (start - offworld_env_controller::store::now_ms()).max(0) as u64 + 100,
    ))
    .await;
    let ended = alice
        .step(Action::Discrete(2))
        .await
        .expect_err("slot began");
    assert_eq!(ended.code, ErrorCode::Unauthorized);
    assert!(ended.message.contains("booked by bob"), "{ended}");
    // During the slot only Bob may take the lease.
    let Err(busy) = open(&session, &d.env, ALICE, "during-slot").await else {
        panic!("Alice took the lease in Bob's slot");
    };
    assert_eq!(busy.code, ErrorCode::Busy);
    assert!(busy.message.contains("booked by bob until"), "{busy}");
    let mut bob = open(&session, &d.env, BOB, "in-slot")
        .await
        .expect("bob opens in his slot");
    bob.reset(Seed::Fixed(2)).await.expect("reset");
    bob.step(Action::Discrete(2)).await.expect("step in slot");
    // The slot ends: so does Bob's lease, with an error that says so.
    tokio::time::sleep(Duration::from_millis(
        (end - offworld_env_controller::store::now_ms()).max(0) as u64 + 100,
    ))
    .await;
    let over = bob.step(Action::Discrete(2)).await.expect_err("slot over");
    assert_eq!(over.code, ErrorCode::Unauthorized);
    assert!(over.message.contains("booked slot"), "{over}");
    assert!(over.message.contains("ended"), "{over}");
    // Afterwards first come again.
    let mut alice = open(&session, &d.env, ALICE, "after-slot")
        .await
        .expect("first come again");
    alice.close().await.expect("close");

    // Bookings live in the store: listed after a controller restart, and
    // cancelled by their holder.
    let later = offworld_env_controller::store::now_ms() + 60_000;
    let made = booking(&session, &d.env, make(ALICE, later, later + 60_000))
        .await
        .expect("book later");
    drop(session);
    drop(d);
    let d = deploy(&db, "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;
    let listed = booking(&session, &d.env, BookingRequest::List { from_unix_ms: 0 })
        .await
        .expect("list after restart");
    assert_eq!(listed.len(), 2, "{listed:?}");
    assert_eq!(listed[1], made[0]);
    let remaining = booking(
        &session,
        &d.env,
        BookingRequest::Cancel {
            token: ALICE.into(),
            id: made[0].id,
        },
    )
    .await
    .expect("cancel");
    assert!(
        remaining.iter().all(|b| b.id != made[0].id),
        "{remaining:?}"
    );
}

/// A sim env under an e-stop refuses motion exactly as a real one does:
/// reset and step answer `InvalidState` naming the latches in force, the
/// episode in progress is recorded as aborted, `status` shows the latches;
/// releasing the env latch leaves the site latch in force; releasing both
/// lets a new episode start.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sim_env_under_an_estop_refuses_motion_and_shows_it() {
    use offworld_client::operator::{press_estop, EStopScope};
    let dir = ScratchDir::new("gym-test");
    let d = deploy(&dir.path().join("gym.db"), "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;
    let mut gym = open(&session, &d.env, ALICE, "estopped")
        .await
        .expect("open");
    gym.reset(Seed::Fixed(1)).await.expect("reset");
    gym.step(Action::Discrete(2)).await.expect("step");
    let wait = Duration::from_secs(10);
    let press = |scope: EStopScope, engaged: bool, reason: &'static str| {
        let session = session.clone();
        async move {
            press_estop(&session, &scope, engaged, reason, wait, wait)
                .await
                .expect("acknowledged")
        }
    };
    press(EStopScope::Site, true, "fire alarm").await;
    press(EStopScope::Env(d.env.clone()), true, "person inside").await;
    let refused = gym.step(Action::Discrete(2)).await.expect_err("refused");
    assert_eq!(refused.code, ErrorCode::InvalidState);
    assert_eq!(
        refused.message,
        "e-stop engaged: site (fire alarm), env (person inside)"
    );
    let status = client::status(&session, &d.env, wait)
        .await
        .expect("status");
    assert_eq!(status.estop.summary(), "site+env");
    assert_eq!(status.estop.env.reason, "person inside");

    // The env release leaves the site latch.
    press(EStopScope::Env(d.env.clone()), false, "person out").await;
    let refused = gym.reset(Seed::Fixed(2)).await.expect_err("still refused");
    assert_eq!(refused.code, ErrorCode::InvalidState);
    assert_eq!(refused.message, "e-stop engaged: site (fire alarm)");
    press(EStopScope::Site, false, "all clear").await;
    let status = client::status(&session, &d.env, wait)
        .await
        .expect("status");
    assert_eq!(status.estop.summary(), "none");
    gym.reset(Seed::Fixed(3))
        .await
        .expect("a new episode after the release");
    let closed = gym.close().await.expect("close");
    // The interrupted episode and the new one.
    assert_eq!(closed.experiment.episodes, 2, "{:?}", closed.experiment);
}

/// Issue 22: hostile bookings (after year 9999, reversed, `[i64::MIN,
/// i64::MAX)`, too long, too far ahead, long past) are refused 400 with a
/// message saying what is wrong, nothing is stored, and another user's
/// open/reset/step go on working; so do they after a panic (here: forced)
/// while the store was held.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn hostile_bookings_are_refused_and_the_env_keeps_serving() {
    let dir = ScratchDir::new("gym-test");
    let d = deploy(&dir.path().join("gym.db"), "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;
    let now = offworld_env_controller::store::now_ms();
    let (day, after_9999) = (86_400_000, 300_000_000_000_000);
    for (request, says) in [
        (make(BOB, after_9999, after_9999 - 1), "between 1970"),
        (make(BOB, after_9999, now), "between 1970"),
        (make(BOB, i64::MIN, i64::MAX), "between 1970"),
        (make(BOB, now + 1_000, i64::MAX), "between 1970"),
        (
            make(BOB, now + 10_000, now + 5_000),
            "must end after it starts",
        ),
        (
            make(BOB, now + 1_000, now + 1_000 + 4 * 3_600_000 + 1),
            "at most 4h long",
        ),
        (
            make(BOB, now + 31 * day, now + 31 * day + 60_000),
            "at most 30days ahead",
        ),
        (make(BOB, now - 3_600_000, now + 60_000), "in the past"),
    ] {
        let shown = format!("{request:?}");
        let err = booking(&session, &d.env, request)
            .await
            .expect_err("refused");
        assert_eq!(err.code, ErrorCode::BadRequest, "{shown}: {err}");
        assert!(err.message.contains(says), "{shown}: {err}");
    }
    let listed = booking(&session, &d.env, BookingRequest::List { from_unix_ms: 0 })
        .await
        .expect("list");
    assert!(listed.is_empty(), "{listed:?}");

    // Another user is served as before.
    let mut alice = open(&session, &d.env, ALICE, "after-hostile-bookings")
        .await
        .expect("open after hostile bookings");
    alice.reset(Seed::Fixed(1)).await.expect("reset");
    alice.step(Action::Discrete(2)).await.expect("step");

    // A panic while the store is held poisons its mutex: requests are
    // served regardless (closing records the aborted episode in it).
    let store = d._embedded.controller.store();
    let poisoner = store.clone();
    let _ = std::thread::spawn(move || {
        let _held = poisoner.lock();
        panic!("a bug while the store is held");
    })
    .join();
    assert!(store.is_poisoned());
    alice.close().await.expect("close after the panic");
    let mut bob = open(&session, &d.env, BOB, "after-the-panic")
        .await
        .expect("open after the panic");
    bob.reset(Seed::Fixed(2))
        .await
        .expect("reset after the panic");
    bob.close().await.expect("close");
    let later = offworld_env_controller::store::now_ms() + 60_000;
    let made = booking(&session, &d.env, make(ALICE, later, later + 60_000))
        .await
        .expect("a valid booking after the panic");
    assert_eq!(made.len(), 1);
}

/// Issue 22: booking rows an older version stored (the `[i64::MIN,
/// i64::MAX)` one became `[then, i64::MAX)`), reversed or before 1970 are
/// quarantined by every reader: never listed, never holding the env, never
/// clashing; `open` works, across a restart too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_booking_rows_on_disk_are_quarantined_and_open_works() {
    let dir = ScratchDir::new("gym-test");
    let db = dir.path().join("gym.db");
    {
        let store = Store::open(&db).expect("store");
        for (name, token, operator) in users() {
            store
                .add_user_with_token(name, token, operator)
                .expect("user");
        }
    }
    let now = offworld_env_controller::store::now_ms();
    {
        let conn = rusqlite::Connection::open(&db).expect("db");
        let bob: i64 = conn
            .query_row("SELECT id FROM users WHERE name = 'bob'", [], |r| r.get(0))
            .expect("bob");
        conn.execute_batch("PRAGMA ignore_check_constraints = ON")
            .expect("pragma");
        for (start, end) in [
            (now - 1_000, i64::MAX),
            (now + 60_000, now - 60_000),
            (-5_000, now + 5_000),
            (i64::MIN, i64::MIN + 1),
        ] {
            conn.execute(
                "INSERT INTO bookings (env_id, user_id, start_ms, end_ms, created_ms) VALUES ('sim/gym-test', ?1, ?2, ?3, 0)",
                rusqlite::params![bob, start, end],
            )
            .expect("planted");
        }
    }
    for restart in 0..2 {
        let d = deploy(&db, "MonolithDiscrete", &users()).await;
        assert_eq!(d.env.to_string(), "sim/gym-test");
        let session = client_session(&d).await;
        let listed = booking(&session, &d.env, BookingRequest::List { from_unix_ms: 0 })
            .await
            .expect("list");
        assert!(listed.is_empty(), "restart {restart}: {listed:?}");
        let mut alice = open(&session, &d.env, ALICE, &format!("quarantine-{restart}"))
            .await
            .expect("open despite the invalid rows");
        alice.reset(Seed::Fixed(3)).await.expect("reset");
        alice.step(Action::Discrete(1)).await.expect("step");
        alice.close().await.expect("close");
    }
    // Nor do they clash with a valid booking over the same time.
    let d = deploy(&db, "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;
    let start = offworld_env_controller::store::now_ms() + 30_000;
    let made = booking(&session, &d.env, make(ALICE, start, start + 60_000))
        .await
        .expect("booked over quarantined rows");
    assert_eq!(made[0].user, "alice");
}

async fn ask_experiments(
    session: &Session,
    env: &EnvId,
    request: ExperimentsRequest,
) -> Result<Experiments, WireError> {
    client::experiments(session, env, &request, Duration::from_secs(5)).await
}

fn list(token: &str) -> ExperimentsRequest {
    ExperimentsRequest::List {
        token: token.into(),
    }
}

fn show(token: &str, experiment_id: i64) -> ExperimentsRequest {
    ExperimentsRequest::Show {
        token: token.into(),
        experiment_id,
        from_episode: 0,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn experiments_are_shown_to_their_owner_and_operators_only() {
    let dir = ScratchDir::new("gym-test");
    let d = deploy(&dir.path().join("gym.db"), "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;

    // Alice: two seeded episodes of known returns and lengths.
    let mut env = open(&session, &d.env, ALICE, "alice-ppo")
        .await
        .expect("open");
    let alice_id = env.opened().experiment.id;
    let mut played = Vec::new();
    let mut starts = Vec::new();
    for seed in [11, 12] {
        let reset = env.reset(Seed::Fixed(seed)).await.expect("reset");
        starts.push((reset.info.x, reset.info.y, reset.info.yaw));
        let (mut steps, mut total, mut ended) = (0u32, 0.0, false);
        for _ in 0..4 {
            let s = env.step(Action::Discrete(2)).await.expect("step");
            steps += 1;
            total += s.reward;
            ended = s.terminated || s.truncated;
            if ended {
                break;
            }
        }
        played.push((seed, steps, total, ended));
    }
    env.close().await.expect("close");
    // Bob: one experiment of his own.
    let mut env = open(&session, &d.env, BOB, "bob-dqn").await.expect("open");
    let bob_id = env.opened().experiment.id;
    env.close().await.expect("close");

    // Each user lists only their own; the operator lists both.
    let alice_list = ask_experiments(&session, &d.env, list(ALICE))
        .await
        .expect("list");
    assert_eq!(alice_list.experiments.len(), 1);
    let listed = &alice_list.experiments[0];
    assert_eq!(
        (
            listed.id,
            listed.user.as_str(),
            listed.env_id.as_str(),
            listed.task.as_str(),
            listed.name.as_str(),
            listed.learning_type.as_str(),
            listed.algorithm_mode.as_str(),
            listed.episodes,
            listed.steps,
        ),
        (
            alice_id,
            "alice",
            d.env.to_string().as_str(),
            "MonolithDiscrete",
            "alice-ppo",
            "end2end",
            "train",
            2,
            u64::from(played[0].1 + played[1].1),
        )
    );
    assert!(listed.created_unix_ms <= listed.updated_unix_ms);
    assert!(alice_list.episodes.is_empty() && !alice_list.more);
    let names = |e: &Experiments| {
        e.experiments
            .iter()
            .map(|x| x.name.clone())
            .collect::<Vec<_>>()
    };
    assert_eq!(
        names(
            &ask_experiments(&session, &d.env, list(BOB))
                .await
                .expect("list")
        ),
        ["bob-dqn"]
    );
    let mut everyone = names(
        &ask_experiments(&session, &d.env, list(OPERATOR))
            .await
            .expect("list"),
    );
    everyone.sort();
    assert_eq!(everyone, ["alice-ppo", "bob-dqn"]);

    // Alice's experiment in full: every episode as played.
    let shown = ask_experiments(&session, &d.env, show(ALICE, alice_id))
        .await
        .expect("show");
    assert_eq!(shown.experiments, alice_list.experiments);
    assert!(!shown.more);
    let episodes: Vec<_> = shown
        .episodes
        .iter()
        .map(|e| (e.index, e.seeded, e.seed, e.steps, e.episode_return))
        .collect();
    assert_eq!(
        episodes,
        [
            (0, true, 11, played[0].1, played[0].2),
            (1, true, 12, played[1].1, played[1].2)
        ]
    );
    for (episode, cut_by) in shown
        .episodes
        .iter()
        .zip(["reset before the episode ended", "closed"])
    {
        let ended_itself = played[episode.index as usize].3;
        assert_eq!(episode.end_reason == cut_by, !ended_itself, "{episode:?}");
    }
    assert!(shown
        .episodes
        .iter()
        .all(|e| e.started_unix_ms <= e.ended_unix_ms && e.recordings.is_empty()));
    // Each episode keeps its reset's accuracy: it starts where it was put.
    for (episode, start) in shown.episodes.iter().zip(&starts) {
        let reset = episode.reset;
        assert!(reset.measured, "{reset:?}");
        assert_eq!(
            (reset.achieved.x, reset.achieved.y, reset.achieved.yaw),
            *start
        );
        assert!(
            reset.position_error_m < 0.001 && reset.duration_s > 0.0,
            "{reset:?}"
        );
        assert_eq!(reset.unix_ms, episode.started_unix_ms);
    }
    // The operator sees it too; the client's paging gives the same.
    let by_operator = ask_experiments(&session, &d.env, show(OPERATOR, alice_id))
        .await
        .expect("operator show");
    assert_eq!(by_operator, shown);
    let (experiment, all) =
        client::experiment_episodes(&session, &d.env, ALICE, alice_id, Duration::from_secs(5))
            .await
            .expect("paged");
    assert_eq!((vec![experiment], all), (shown.experiments, shown.episodes));

    // Another user's experiment is "not found", like a missing one; a bad
    // token is refused; the env keeps serving.
    for (token, id) in [
        (BOB, alice_id),
        (ALICE, bob_id),
        (ALICE, 999_999),
        (ALICE, -1),
    ] {
        let e = ask_experiments(&session, &d.env, show(token, id))
            .await
            .expect_err("not theirs");
        assert_eq!(e.code, ErrorCode::NotFound, "{token} {id}: {e:?}");
    }
    for request in [list("not-a-token"), show("not-a-token", alice_id)] {
        let e = ask_experiments(&session, &d.env, request)
            .await
            .expect_err("bad token");
        assert_eq!(e.code, ErrorCode::Unauthorized);
    }
    assert!(client::spec(&session, &d.env, Duration::from_secs(2))
        .await
        .is_ok());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_long_experiment_is_answered_a_page_at_a_time() {
    let dir = ScratchDir::new("gym-test");
    let db = dir.path().join("gym.db");
    let episodes = u64::from(EXPERIMENT_EPISODES_PER_REPLY) * 2 + 37;
    let experiment_id = {
        let mut store = Store::open(&db).expect("store");
        store
            .add_user_with_token("alice", ALICE, false)
            .expect("user");
        let alice = store.authenticate(ALICE).expect("db").expect("alice");
        let experiment = store
            .open_experiment(
                &alice,
                "sim/gym-test",
                "MonolithDiscrete",
                "long",
                false,
                LearningType::EndToEnd,
                AlgorithmMode::Train,
            )
            .expect("experiment");
        for index in 0..episodes {
            store
                .record_episode(&offworld_env_controller::store::EpisodeRecord {
                    experiment_id: experiment.id,
                    episode_index: index,
                    seed: index.is_multiple_of(2).then_some(index),
                    steps: (index % 100) as u32,
                    episode_return: index as f64 * 0.5,
                    success: index.is_multiple_of(3),
                    end_reason: "step_limit".into(),
                    reset: Default::default(),
                    started_ms: 1_000 + index as i64,
                    ended_ms: 2_000 + index as i64,
                })
                .expect("episode");
        }
        experiment.id
    };
    let d = deploy(&db, "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;

    let first = ask_experiments(&session, &d.env, show(ALICE, experiment_id))
        .await
        .expect("first page");
    assert_eq!(first.episodes.len(), EXPERIMENT_EPISODES_PER_REPLY as usize);
    assert!(first.more);
    let last = ask_experiments(
        &session,
        &d.env,
        ExperimentsRequest::Show {
            token: ALICE.into(),
            experiment_id,
            from_episode: episodes - 5,
        },
    )
    .await
    .expect("last page");
    assert_eq!(
        last.episodes.iter().map(|e| e.index).collect::<Vec<_>>(),
        (episodes - 5..episodes).collect::<Vec<_>>()
    );
    assert!(!last.more);

    let (_, all) = client::experiment_episodes(
        &session,
        &d.env,
        ALICE,
        experiment_id,
        Duration::from_secs(5),
    )
    .await
    .expect("every page");
    assert_eq!(all.len() as u64, episodes);
    for (i, e) in all.iter().enumerate() {
        let i = i as u64;
        assert_eq!(
            (
                e.index,
                e.seeded,
                e.seed,
                e.steps,
                e.episode_return,
                e.success
            ),
            (
                i,
                i.is_multiple_of(2),
                if i.is_multiple_of(2) { i } else { 0 },
                (i % 100) as u32,
                i as f64 * 0.5,
                i.is_multiple_of(3)
            )
        );
        assert_eq!(
            (e.started_unix_ms, e.ended_unix_ms),
            (1_000 + i as i64, 2_000 + i as i64)
        );
    }
}

/// `open_waiting` with every refusal's message sent to `said`.
fn wait_in_line(
    session: Session,
    env: EnvId,
    token: &'static str,
    said: tokio::sync::mpsc::UnboundedSender<String>,
) -> tokio::task::JoinHandle<Result<EnvClient, WireError>> {
    tokio::spawn(async move {
        EnvClient::open_waiting(
            &session,
            &env,
            open_request(token, "line", false, AlgorithmMode::Train),
            ClientTimeouts::default(),
            Duration::from_secs(60),
            |busy| {
                let _ = said.send(busy.message.clone());
            },
        )
        .await
    })
}

/// The next refusal a waiter was given (bounded).
async fn next_said(said: &mut tokio::sync::mpsc::UnboundedReceiver<String>) -> String {
    tokio::time::timeout(Duration::from_secs(10), said.recv())
        .await
        .expect("a refusal within 10 s")
        .expect("still waiting")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_busy_env_goes_to_its_waiting_line_first_come_first_served() {
    let dir = ScratchDir::new("gym-line");
    let d = deploy(&dir.path().join("gym.db"), "MonolithDiscrete", &users()).await;
    let alice_session = client_session(&d).await;
    let bob_session = client_session(&d).await;
    let ops_session = client_session(&d).await;
    let mut alice = open(&alice_session, &d.env, ALICE, "holder")
        .await
        .expect("alice opens");

    // Bob waits, then the operator: each refusal says the place in line.
    let (bob_said, mut bob_heard) = tokio::sync::mpsc::unbounded_channel();
    let bob = wait_in_line(bob_session.clone(), d.env.clone(), BOB, bob_said);
    next_said(&mut bob_heard).await;
    let bob_second = next_said(&mut bob_heard).await;
    assert!(
        bob_second.contains("is leased by another user until")
            && bob_second.ends_with("; 1st in line"),
        "{bob_second}"
    );
    let (ops_said, mut ops_heard) = tokio::sync::mpsc::unbounded_channel();
    let ops = wait_in_line(ops_session.clone(), d.env.clone(), OPERATOR, ops_said);
    next_said(&mut ops_heard).await;
    let ops_second = next_said(&mut ops_heard).await;
    assert!(ops_second.ends_with("; 2nd in line"), "{ops_second}");

    // The lease ends: a client that does not wait is refused (the env is
    // the line's), Bob gets it, the operator moves up.
    alice.close().await.expect("close");
    let jumper = open(&alice_session, &d.env, ALICE, "jumper")
        .await
        .err()
        .expect("the line goes first");
    assert_eq!(jumper.code, ErrorCode::Busy);
    // (Before Bob asks again: held for two; after: leased, the operator first.)
    assert!(jumper.message.ends_with(" in line"), "{jumper}");
    let mut bob = tokio::time::timeout(Duration::from_secs(10), bob)
        .await
        .expect("bob's turn within 10 s")
        .expect("task")
        .expect("bob opens");
    assert_eq!(bob.opened().experiment.name, "line");
    // Refusals from before Bob's turn may still be queued: bounded, the
    // operator hears it is first within 20 more refusals.
    let mut moved_up = None;
    for _ in 0..20 {
        let said = next_said(&mut ops_heard).await;
        if said.ends_with("; 1st in line") {
            moved_up = Some(said);
            break;
        }
    }
    let moved_up = moved_up.expect("the operator moves up to 1st");
    assert!(
        moved_up.contains("is leased by another user until"),
        "{moved_up}"
    );
    bob.close().await.expect("close");
    let mut ops = tokio::time::timeout(Duration::from_secs(10), ops)
        .await
        .expect("the operator's turn within 10 s")
        .expect("task")
        .expect("the operator opens");
    assert_eq!(
        client::status(&bob_session, &d.env, Duration::from_secs(5))
            .await
            .expect("status")
            .state,
        EnvState::Leased {
            holder: "ops".into(),
            until_unix_ms: ops.opened().lease_until_unix_ms,
        }
    );

    // Nobody waits for long: a wait that ends returns the last refusal.
    let refused = EnvClient::open_waiting(
        &alice_session,
        &d.env,
        open_request(ALICE, "late", false, AlgorithmMode::Train),
        ClientTimeouts::default(),
        Duration::from_millis(1500),
        |_| {},
    )
    .await
    .err()
    .expect("still leased");
    assert_eq!(refused.code, ErrorCode::Busy);
    assert!(refused.message.ends_with(" in line"), "{refused}");
    ops.close().await.expect("close");
}

/// A raw `open` with a chosen client id.
async fn open_as(
    session: &Session,
    env: &EnvId,
    token: &str,
    client_id: &str,
) -> Result<OpenReply, WireError> {
    let mut request = open_request(token, "same-client", false, AlgorithmMode::Train);
    request.client_id = client_id.into();
    wire::request(
        session,
        &env.key(Topic::Open),
        &request,
        Duration::from_secs(5),
    )
    .await
    .map_err(|e| e.into_wire())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_open_repeated_by_the_leases_own_client_gets_that_lease_never_anothers() {
    let dir = ScratchDir::new("gym-again");
    let d = deploy(&dir.path().join("gym.db"), "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;
    // An identified user's client asks again (its reply was lost): the same lease.
    let first = open_as(&session, &d.env, ALICE, "alice-client")
        .await
        .expect("open");
    let again = open_as(&session, &d.env, ALICE, "alice-client")
        .await
        .expect("again");
    assert_eq!(again.session_id, first.session_id);
    assert_eq!(again.experiment.id, first.experiment.id);
    // Another user sending that client id is someone else.
    let other = open_as(&session, &d.env, BOB, "alice-client")
        .await
        .expect_err("bob is not alice");
    assert_eq!(other.code, ErrorCode::Busy);
    assert!(
        other.message.contains("is leased by another user"),
        "{other}"
    );
    let closed: CloseReply = wire::request(
        &session,
        &d.env.key(Topic::Close),
        &CloseRequest {
            session_id: first.session_id.clone(),
        },
        Duration::from_secs(5),
    )
    .await
    .expect("close");
    assert_eq!(closed.experiment.id, first.experiment.id);
    // Anonymous users share one user, and a client id is no secret: a
    // second anonymous session is refused, whatever client id it sends.
    let held = open_as(&session, &d.env, "", "anon-client")
        .await
        .expect("open");
    let hijack = open_as(&session, &d.env, "", "anon-client")
        .await
        .expect_err("not the holder's lease");
    assert_eq!(hijack.code, ErrorCode::Busy);
    assert!(
        hijack
            .message
            .contains("is in use by another anonymous session"),
        "{hijack}"
    );
    assert_ne!(held.session_id, "");
}

/// The controller hears its lease holder's presence token: gone, the lease
/// waits only the reconnect grace (120 s, where an idle lease has 300 s)
/// and its requests are refused; back with the same client id, the lease
/// is the holder's again without a new `open`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_lease_follows_its_holders_presence_token() {
    let dir = ScratchDir::new("gym-presence");
    let d = deploy(&dir.path().join("gym.db"), "MonolithDiscrete", &users()).await;
    let session = client_session(&d).await;
    let watcher = client_session(&d).await;
    let key = d.env.client_alive_key("alice-present").expect("id");
    let token = session
        .liveliness()
        .declare_token(&key)
        .await
        .expect("token");
    let opened = open_as(&session, &d.env, ALICE, "alice-present")
        .await
        .expect("open");
    let reset = || async {
        wire::request::<_, ResetReply>(
            &session,
            &d.env.key(Topic::Reset),
            &ResetRequest {
                session_id: opened.session_id.clone(),
                seed: Seed::Fixed(1),
            },
            Duration::from_secs(10),
        )
        .await
        .map_err(|e| e.into_wire())
    };
    reset().await.expect("reset");
    let lease_left_ms = || async {
        let status = client::status(&watcher, &d.env, Duration::from_secs(5))
            .await
            .expect("status");
        let EnvState::Leased { until_unix_ms, .. } = status.state else {
            panic!("not leased: {status:?}");
        };
        until_unix_ms - offworld_env_controller::store::now_ms()
    };
    assert!(lease_left_ms().await > 250_000);

    // Bounded waits (5 s) for the token's news to reach the controller.
    let lease_left_once = |done: fn(i64) -> bool| async move {
        let mut left = lease_left_ms().await;
        for _ in 0..50 {
            if done(left) {
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
            left = lease_left_ms().await;
        }
        left
    };
    drop(token);
    let left = lease_left_once(|left| left <= 120_000).await;
    assert!((100_000..=120_000).contains(&left), "{left} ms left");
    let refused = reset().await.expect_err("gone");
    assert_eq!(refused.code, ErrorCode::Unauthorized, "{refused}");

    let _token = session
        .liveliness()
        .declare_token(&key)
        .await
        .expect("token");
    let left = lease_left_once(|left| left > 250_000).await;
    assert!(left > 250_000, "{left} ms left");
    let back = reset().await.expect("the lease is the holder's again");
    assert_eq!(back.info.step, 0);
}
