//! Two real Zenoh sessions on loopback exchange every message type through
//! put/subscribe and get/queryable, using the contract's keys and wire helpers.

use crate::common;

use std::fmt::Debug;
use std::time::Duration;

use offworld_runtime::msg::*;
use offworld_runtime::session::loopback_pair;
use offworld_runtime::wire::{self, RequestError};
use offworld_runtime::{codec, EnvId, ErrorCode, Topic, WireError};
use serde::{de::DeserializeOwned, Serialize};
use zenoh::Session;

/// Bounded retries while declarations propagate between the two peers.
const ATTEMPTS: usize = 100;
const RETRY: Duration = Duration::from_millis(50);

async fn pair() -> (Session, Session) {
    loopback_pair().await.expect("loopback sessions")
}

async fn pub_sub<T: Serialize + DeserializeOwned + PartialEq + Debug>(
    a: &Session,
    b: &Session,
    key: &str,
    msg: &T,
) {
    let sub = b.declare_subscriber(key).await.expect("subscriber");
    for _ in 0..ATTEMPTS {
        wire::put(a, key, msg).await.expect("put");
        if let Ok(Ok(sample)) = tokio::time::timeout(RETRY, sub.recv_async()).await {
            assert_eq!(sample.encoding(), &zenoh::bytes::Encoding::APPLICATION_CDR);
            let got: T = codec::decode_payload(sample.payload()).expect("decode");
            assert_eq!(&got, msg, "{key}");
            return;
        }
    }
    panic!("no sample on {key}");
}

async fn get_reply<Req, Rep>(a: &Session, b: &Session, key: &str, req: Req, rep: Rep)
where
    Req: Serialize + DeserializeOwned + PartialEq + Debug + Send + Sync + 'static,
    Rep: Serialize + DeserializeOwned + PartialEq + Debug + Clone + Send + Sync + 'static,
{
    let queryable = a.declare_queryable(key).await.expect("queryable");
    let expected = req.clone_via_codec();
    let answer = rep.clone();
    let server = tokio::spawn(async move {
        let query = queryable.recv_async().await.expect("query");
        let got: Req = wire::decode_query(&query).expect("decode request");
        assert_eq!(got, expected);
        wire::reply(&query, Ok(&answer)).await.expect("reply");
    });
    let reply: Rep = retry_request(b, key, &req).await.expect("request");
    assert_eq!(reply, rep, "{key}");
    server.await.expect("server task");
}

async fn retry_request<Req: Serialize, Rep: DeserializeOwned>(
    b: &Session,
    key: &str,
    req: &Req,
) -> Result<Rep, RequestError> {
    for _ in 0..ATTEMPTS {
        match wire::request(b, key, req, Duration::from_secs(2)).await {
            Err(RequestError::NoResponder(_)) => tokio::time::sleep(RETRY).await,
            other => return other,
        }
    }
    Err(RequestError::NoResponder(key.to_owned()))
}

trait CloneViaCodec: Serialize + DeserializeOwned {
    fn clone_via_codec(&self) -> Self {
        codec::decode(&codec::encode(self).expect("encode")).expect("decode")
    }
}
impl<T: Serialize + DeserializeOwned> CloneViaCodec for T {}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_published_message_crosses_loopback() {
    let (a, b) = pair().await;
    let env = EnvId::sim("loopback-0").expect("env");
    pub_sub(&a, &b, &env.key(Topic::Cmd), &common::motion()).await;
    pub_sub(&a, &b, &env.key(Topic::Obs), &common::camera_frame()).await;
    pub_sub(&a, &b, &env.key(Topic::Odom), &common::odometry()).await;
    pub_sub(&a, &b, &env.key(Topic::Pose), &common::pose_stamped()).await;
    pub_sub(&a, &b, &env.key(Topic::Reward), &common::episode_event()).await;
    pub_sub(&a, &b, &env.key(Topic::Status), &common::env_status()).await;
    pub_sub(&a, &b, &env.key(Topic::EStop), &EStop::new(true, "t")).await;
    pub_sub(
        &a,
        &b,
        &env.key(Topic::Heartbeat),
        &Heartbeat {
            stamp: Time::now(),
            counter: 1,
        },
    )
    .await;
    pub_sub(
        &a,
        &b,
        &env.key(Topic::Tracking),
        &TrackingStatus {
            tracking: true,
            last_pose_age_s: 0.01,
            reason: String::new(),
        },
    )
    .await;
    pub_sub(&a, &b, "ros/cmd_vel", &common::twist()).await;
    pub_sub(&a, &b, "ros/image", &common::image_rgb()).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_request_reply_pair_crosses_loopback() {
    let (a, b) = pair().await;
    let env = EnvId::real("loopback-1").expect("env");
    get_reply(
        &a,
        &b,
        &env.key(Topic::Open),
        common::open_request(),
        common::open_reply(),
    )
    .await;
    get_reply(
        &a,
        &b,
        &env.key(Topic::Reset),
        common::reset_request(),
        common::reset_reply(),
    )
    .await;
    get_reply(
        &a,
        &b,
        &env.key(Topic::Step),
        common::step_request(),
        common::step_reply(),
    )
    .await;
    get_reply(
        &a,
        &b,
        &env.key(Topic::Close),
        CloseRequest {
            session_id: "s-1".into(),
        },
        CloseReply {
            experiment: common::experiment(),
        },
    )
    .await;
    get_reply(
        &a,
        &b,
        &env.key(Topic::Goto),
        common::goto_request(),
        common::goto_reply(),
    )
    .await;
    get_reply(&a, &b, &env.key(Topic::Spec), (), common::spec()).await;
    get_reply(
        &a,
        &b,
        &env.key(Topic::Admin),
        AdminRequest::ClearMaintenance { token: "op".into() },
        common::env_status(),
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn typed_errors_timeouts_and_missing_servers() {
    let (a, b) = pair().await;
    let env = EnvId::sim("errors-0").expect("env");
    let key = env.key(Topic::Step);

    // A queryable that answers the first query with a typed error, ignores
    // the second (so the client times out), and rejects garbage.
    let queryable = a.declare_queryable(&key).await.expect("queryable");
    let server = tokio::spawn(async move {
        let first = queryable.recv_async().await.expect("query");
        let err = WireError::busy("leased until 12:00");
        wire::reply::<StepReply>(&first, Err(err))
            .await
            .expect("reply");
        let _ignored = queryable.recv_async().await.expect("query");
        let garbage = queryable.recv_async().await.expect("query");
        let decoded = wire::decode_query::<StepRequest>(&garbage);
        assert_eq!(
            decoded.as_ref().map_err(|e| e.code),
            Err(ErrorCode::BadRequest)
        );
        let err = decoded.expect_err("garbage decoded");
        wire::reply::<StepReply>(&garbage, Err(err))
            .await
            .expect("reply");
        // Still serving after the garbage.
        let last = queryable.recv_async().await.expect("query");
        wire::reply(&last, Ok(&common::step_reply()))
            .await
            .expect("reply");
        _ignored
    });

    match retry_request::<_, StepReply>(&b, &key, &common::step_request()).await {
        Err(RequestError::Remote(e)) => {
            assert_eq!(e.code, ErrorCode::Busy);
            assert_eq!(e.message, "leased until 12:00");
        }
        other => panic!("expected Busy, got {other:?}"),
    }
    let timeout = Duration::from_millis(300);
    match wire::request::<_, StepReply>(&b, &key, &common::step_request(), timeout).await {
        Err(e @ RequestError::Timeout { .. }) => {
            assert_eq!(e.into_wire().code, ErrorCode::Timeout)
        }
        other => panic!("expected timeout, got {other:?}"),
    }
    match wire::request_raw::<StepReply>(&b, &key, vec![0, 1, 0, 0, 9], Duration::from_secs(2))
        .await
    {
        Err(RequestError::Remote(e)) => assert_eq!(e.code, ErrorCode::BadRequest),
        other => panic!("expected BadRequest, got {other:?}"),
    }
    let ok: StepReply = wire::request(&b, &key, &common::step_request(), Duration::from_secs(2))
        .await
        .expect("served after garbage");
    assert_eq!(ok, common::step_reply());
    drop(server.await.expect("server"));

    let nobody = EnvId::sim("nobody").expect("env").key(Topic::Step);
    match wire::request::<_, StepReply>(
        &b,
        &nobody,
        &common::step_request(),
        Duration::from_secs(5),
    )
    .await
    {
        Err(e @ RequestError::NoResponder(_)) => {
            assert_eq!(e.into_wire().code, ErrorCode::NotFound)
        }
        other => panic!("expected NoResponder, got {other:?}"),
    }
}

/// A native 320×240 RGBD observation crosses loopback in fragments; the
/// reply received with its pixels copied once out of them is the very
/// reply sent (and the same as the joined-then-decoded one).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_native_observation_arrives_intact_from_its_fragments() {
    let (a, b) = pair().await;
    let key = EnvId::sim("loopback-tail").expect("env").key(Topic::Step);
    let data: Vec<u8> = (0..320 * 240 * 4u32).map(|i| (i % 251) as u8).collect();
    let reply = StepReply {
        observation: ObsArray {
            height: 240,
            width: 320,
            channels: 4,
            dtype: DType::U8,
            data,
        },
        ..common::step_reply()
    };
    let queryable = a.declare_queryable(&key).await.expect("queryable");
    let answer = reply.clone();
    let server = tokio::spawn(async move {
        for _ in 0..2 {
            let query = queryable.recv_async().await.expect("query");
            wire::reply(&query, Ok(&answer)).await.expect("reply");
        }
    });
    let request = common::step_request();
    let mut tail = Err(RequestError::NoResponder(key.clone()));
    for _ in 0..ATTEMPTS {
        tail = wire::request_tail::<_, StepReply>(&b, &key, &request, Duration::from_secs(5)).await;
        if !matches!(tail, Err(RequestError::NoResponder(_))) {
            break;
        }
        tokio::time::sleep(RETRY).await;
    }
    assert_eq!(tail.expect("tail request"), reply);
    let plain: StepReply = retry_request(&b, &key, &request).await.expect("request");
    assert_eq!(plain, reply);
    server.await.expect("server task");
}

/// A starting component recalls its own env's latch from the network, not
/// another env's, and the site latch from any env's answer: each
/// `estop_state` queryable answers on its env's key.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn estop_state_is_recalled_per_env_from_the_network() {
    use offworld_runtime::estop::{self, Latch};
    let (a, b) = pair().await;
    let (mine, other) = (
        EnvId::real("mine").expect("env"),
        EnvId::sim("other").expect("env"),
    );
    let mut kept_mine = EStopState::default();
    kept_mine.apply(Latch::Env, &EStop::new(true, "person inside"), Time::now());
    let mut kept_other = EStopState::default();
    kept_other.apply(Latch::Site, &EStop::new(true, "fire alarm"), Time::now());
    kept_other.apply(Latch::Env, &EStop::new(true, "not mine"), Time::now());
    let mut queryables = Vec::new();
    for (env, state) in [(&mine, kept_mine), (&other, kept_other)] {
        let (_tx, rx) = tokio::sync::watch::channel(state);
        queryables.push((
            _tx,
            a.declare_queryable(env.key(Topic::EStopState))
                .callback(estop::state_replier(env, rx))
                .await
                .expect("queryable"),
        ));
    }
    for _ in 0..ATTEMPTS {
        let recalled = estop::recall(&b, &mine, Duration::from_millis(500)).await;
        if recalled.summary() == "site+env" {
            assert_eq!(recalled.env.reason, "person inside");
            assert_eq!(recalled.site.reason, "fire alarm");
            return;
        }
        tokio::time::sleep(RETRY).await;
    }
    panic!("the env latch was never recalled from its own env's answer");
}
