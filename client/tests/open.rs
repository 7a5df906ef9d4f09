//! The client over two real Zenoh sessions on loopback, the test playing
//! the controller: an open waits for a server that comes up late and
//! returns a refusal at once.

use std::time::Duration;

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_runtime::msg::{Channels, DepthFormat, ObsOptions, OpenReply, OpenRequest};
use offworld_runtime::session::loopback_pair;
use offworld_runtime::wire;
use offworld_runtime::{EnvId, ErrorCode, Topic, WireError};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn open_when_ready_waits_for_a_late_server_and_returns_hard_errors_at_once() {
    let (server, client) = loopback_pair().await.expect("loopback sessions");
    let env = EnvId::sim("late-server").expect("env");
    let request = OpenRequest::anonymous(ObsOptions {
        channels: Channels::DepthOnly,
        height: 84,
        width: 84,
        depth_format: DepthFormat::Uint8,
    });
    // Nobody serves the env: the last "not yet" error once the wait is over.
    let missing = EnvClient::open_when_ready(
        &client,
        &env,
        request.clone(),
        ClientTimeouts::default(),
        Duration::from_millis(300),
    )
    .await
    .err()
    .expect("no server");
    assert_eq!(missing.code, ErrorCode::NotFound, "{missing}");
    // A server that refuses: its error comes back without retrying.
    let key = env.key(Topic::Open);
    let refusing = server.clone();
    let queryable = refusing.declare_queryable(key).await.expect("queryable");
    let refuser = tokio::spawn(async move {
        while let Ok(query) = queryable.recv_async().await {
            let _ = wire::reply::<OpenReply>(&query, Err(WireError::unauthorized("no"))).await;
        }
    });
    let refused = EnvClient::open_when_ready(
        &client,
        &env,
        request,
        ClientTimeouts::default(),
        Duration::from_secs(30),
    )
    .await
    .err()
    .expect("refused");
    assert_eq!(refused.code, ErrorCode::Unauthorized, "{refused}");
    refuser.abort();
}
