//! The web service against a real deployment: sim twins and a controller
//! on one Zenoh session, the service on another joined over TCP loopback,
//! requests over real HTTP. Checks `/api/envs` field by field, that every
//! malformed or unknown path is a 404, that the event stream delivers a
//! lease and its release, the leaderboard, a dead deployment shown offline
//! without hanging a request, and the per-client and stream limits.

use offworld_runtime::Resolution;
use std::net::SocketAddr;
use std::num::NonZeroU32;
use std::time::Duration;

use bytes::Bytes;
use http_body_util::{BodyExt, Empty};
use hyper::body::Incoming;
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::client::legacy::connect::HttpConnector;
use hyper_util::client::legacy::Client;
use hyper_util::rt::TokioExecutor;
use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::embedded::{Embedded, SimEnv, Stepping, TwinProfile};
use offworld_env_controller::Store;
use offworld_runtime::keys::EnvId;
use offworld_runtime::msg::{AlgorithmMode, ObsOptions, OpenRequest, Seed};
use offworld_runtime::session::{loopback_pair, SessionConfig};
use offworld_web::{DiscoveryConfig, LabWeb, Limits, WebOptions};
use serde_json::{json, Value};
use zenoh::Session;

/// Bound of every wait for something that must happen (never a speed).
use crate::common;

const EVENTUALLY: Duration = Duration::from_secs(20);

type HttpClient = Client<HttpConnector, Empty<Bytes>>;

fn http_client() -> HttpClient {
    Client::builder(TokioExecutor::new()).build_http()
}

fn env_ids() -> [EnvId; 2] {
    [
        EnvId::sim("web-a").expect("env id"),
        EnvId::sim("web-b").expect("env id"),
    ]
}

/// A deployment with two sim envs, and the web service in front of it.
struct Lab {
    web: LabWeb,
    deployment: Session,
    embedded: Option<Embedded>,
    http: HttpClient,
}

impl Lab {
    async fn start(options: WebOptions) -> Self {
        let (deployment, web_side) = loopback_pair().await.expect("sessions");
        let envs: Vec<SimEnv> = env_ids()
            .into_iter()
            .map(|env| SimEnv {
                env,
                task: "MonolithDiscrete".into(),
                resolution: Some(Resolution::new(8, 6)),
                seed: 7,
                profile: TwinProfile::default(),
                render_threads: 1,
                stepping: Stepping::OwnThread,
            })
            .collect();
        let embedded = Embedded::start(&deployment, &envs, Store::in_memory().expect("store"))
            .await
            .expect("deployment");
        let listen: SocketAddr = "127.0.0.1:0".parse().expect("address");
        let web = LabWeb::start(web_side, listen, options)
            .await
            .expect("web service");
        let lab = Self {
            web,
            deployment,
            embedded: Some(embedded),
            http: http_client(),
        };
        lab.until_envs("both envs listed with their task", |envs| {
            envs.len() == 2 && envs.iter().all(|e| e["task"] == "MonolithDiscrete")
        })
        .await;
        lab
    }

    fn url(&self, path: &str) -> String {
        format!("http://{}{path}", self.web.local_addr())
    }

    async fn get(&self, path: &str) -> (StatusCode, hyper::HeaderMap, String) {
        request(&self.http, Method::GET, &self.url(path)).await
    }

    async fn envs(&self) -> Value {
        let (status, _, body) = self.get("/api/envs").await;
        assert_eq!(status, StatusCode::OK, "{body}");
        serde_json::from_str(&body).expect("JSON")
    }

    /// Polls `/api/envs` (bounded) until `check` holds for its `envs`.
    async fn until_envs(&self, what: &str, check: impl Fn(&[Value]) -> bool) -> Value {
        let deadline = tokio::time::Instant::now() + EVENTUALLY;
        loop {
            let snapshot = self.envs().await;
            let envs = snapshot["envs"].as_array().cloned().unwrap_or_default();
            if check(&envs) {
                return snapshot;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "{what}: not within {EVENTUALLY:?}; last: {snapshot:#}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }
}

async fn request(
    client: &HttpClient,
    method: Method,
    url: &str,
) -> (StatusCode, hyper::HeaderMap, String) {
    let (status, headers, body) = request_bytes(client, method, url).await;
    (
        status,
        headers,
        String::from_utf8(body).expect("UTF-8 body"),
    )
}

async fn request_bytes(
    client: &HttpClient,
    method: Method,
    url: &str,
) -> (StatusCode, hyper::HeaderMap, Vec<u8>) {
    let response = send(client, method, url).await;
    let (parts, body) = response.into_parts();
    let body = tokio::time::timeout(EVENTUALLY, body.collect())
        .await
        .expect("the body within the bound")
        .expect("body")
        .to_bytes();
    (parts.status, parts.headers, body.to_vec())
}

async fn send(client: &HttpClient, method: Method, url: &str) -> Response<Incoming> {
    let request = Request::builder()
        .method(method)
        .uri(url)
        .body(Empty::new())
        .expect("request");
    tokio::time::timeout(EVENTUALLY, client.request(request))
        .await
        .expect("an answer within the bound")
        .expect("HTTP response")
}

/// The volatile clock fields: checked to be recent Unix times, then nulled
/// so the rest compares exactly.
fn without_clocks(mut snapshot: Value, since_unix_ms: i64) -> Value {
    let now = offworld_web::discovery::now_unix_ms();
    let check = |value: &mut Value, what: &str| {
        let ms = value.as_i64().unwrap_or_else(|| panic!("{what}: {value}"));
        assert!((since_unix_ms..=now).contains(&ms), "{what} = {ms}");
        *value = Value::Null;
    };
    check(&mut snapshot["generated_unix_ms"], "generated_unix_ms");
    check(
        &mut snapshot["deployment"]["last_sweep_unix_ms"],
        "last_sweep_unix_ms",
    );
    if let Some(envs) = snapshot["envs"].as_array_mut() {
        for env in envs {
            check(&mut env["last_seen_unix_ms"], "last_seen_unix_ms");
        }
    }
    snapshot
}

fn free_sim_env(name: &str) -> Value {
    let latch = json!({"engaged": false, "reason": "", "changed_unix_ms": null});
    json!({
        "id": format!("sim/{name}"),
        "realm": "sim",
        "name": name,
        "task": "MonolithDiscrete",
        "state": "free",
        "lease": null,
        "maintenance": null,
        "offline": null,
        "estop": {"engaged": false, "scope": "none", "site": latch, "env": latch},
        "next_booking": null,
        "components": ["controller", "sim_twin"],
        "last_seen_unix_ms": null,
        "last_reset": null,
        "last_fault": null,
        "tracking": null,
    })
}

async fn open(session: &Session, env: &EnvId, mode: AlgorithmMode, experiment: &str) -> EnvClient {
    let request = OpenRequest {
        experiment_name: experiment.to_owned(),
        algorithm_mode: mode,
        ..OpenRequest::anonymous(ObsOptions {
            height: 6,
            width: 8,
            ..ObsOptions::default()
        })
    };
    EnvClient::open_when_ready(session, env, request, ClientTimeouts::default(), EVENTUALLY)
        .await
        .expect("open")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn api_envs_lists_every_env_with_its_state() {
    let since = offworld_web::discovery::now_unix_ms();
    let lab = Lab::start(WebOptions::default()).await;
    let snapshot = without_clocks(lab.envs().await, since);
    assert_eq!(
        snapshot,
        json!({
            "generated_unix_ms": null,
            "deployment": {"reachable": true, "message": null, "last_sweep_unix_ms": null},
            "envs": [free_sim_env("web-a"), free_sim_env("web-b")],
        })
    );
    let (status, headers, body) = lab.get("/api/envs/sim/web-b").await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(headers["content-type"], "application/json");
    let mut one: Value = serde_json::from_str(&body).expect("JSON");
    one["last_seen_unix_ms"] = Value::Null;
    assert_eq!(one, free_sim_env("web-b"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn malformed_and_unknown_paths_are_typed_404s() {
    let lab = Lab::start(WebOptions::default()).await;
    let long = format!("/envs/sim/{}", "x".repeat(5000));
    for path in [
        "/envs/sim/nowhere",
        "/envs/lab/web-a",
        "/envs/sim/%FF",
        "/envs/sim/%2A%2A",
        "/envs/sim/a%2Fb",
        "/envs/sim/@v1",
        "/envs/sim/web-a/extra",
        "/envs/sim",
        "/envs/sim/web-a/",
        "/nope",
        "/static/secrets",
        long.as_str(),
    ] {
        let (status, headers, body) = lab.get(path).await;
        assert_eq!(status, StatusCode::NOT_FOUND, "{path}: {body}");
        assert_eq!(
            headers["content-type"], "text/html; charset=utf-8",
            "{path}"
        );
        assert!(body.contains("404 · Not Found"), "{path}: {body}");
    }
    for path in [
        "/api/envs/sim/nowhere",
        "/api/envs/lab/web-a",
        "/api/envs/sim/%FF",
        "/api/envs/sim/nowhere/leaderboard",
        "/api/envs/sim/%2A/leaderboard",
        "/api/nope",
    ] {
        let (status, headers, body) = lab.get(path).await;
        assert_eq!(status, StatusCode::NOT_FOUND, "{path}: {body}");
        assert_eq!(headers["content-type"], "application/json", "{path}");
        let error: Value = serde_json::from_str(&body).expect("JSON error");
        assert_eq!(error["error"]["status"], 404, "{path}");
        assert_eq!(error["error"]["kind"], "not_found", "{path}");
        assert!(error["error"]["message"]
            .as_str()
            .is_some_and(|m| !m.is_empty()));
    }
    for method in [Method::POST, Method::PUT, Method::DELETE] {
        let (status, _, body) = request(&lab.http, method.clone(), &lab.url("/api/envs")).await;
        assert_eq!(status, StatusCode::METHOD_NOT_ALLOWED, "{method}");
        let error: Value = serde_json::from_str(&body).expect("JSON error");
        assert_eq!(error["error"]["kind"], "method_not_allowed");
    }
    // Still serving after all of that.
    assert_eq!(lab.get("/").await.0, StatusCode::OK);
}

/// Reads server-sent events (bounded) until one satisfies `check`.
async fn until_event(
    body: &mut Incoming,
    buffer: &mut String,
    what: &str,
    check: impl Fn(&Value) -> bool,
) {
    let deadline = tokio::time::Instant::now() + EVENTUALLY;
    loop {
        while let Some(end) = buffer.find("\n\n") {
            let event: String = buffer.drain(..end + 2).collect();
            let data: String = event
                .lines()
                .filter_map(|line| line.strip_prefix("data: "))
                .collect();
            if event.lines().any(|l| l == "event: envs") {
                let snapshot: Value = serde_json::from_str(&data).expect("JSON event");
                if check(&snapshot) {
                    return;
                }
            }
        }
        let frame = tokio::time::timeout_at(deadline, body.frame())
            .await
            .unwrap_or_else(|_| panic!("{what}: no such event within {EVENTUALLY:?}"))
            .expect("the stream goes on")
            .expect("frame");
        if let Ok(data) = frame.into_data() {
            buffer.push_str(std::str::from_utf8(&data).expect("UTF-8 events"));
        }
    }
}

fn state_of<'a>(snapshot: &'a Value, id: &str) -> &'a Value {
    snapshot["envs"]
        .as_array()
        .and_then(|envs| envs.iter().find(|e| e["id"] == id))
        .map_or(&Value::Null, |env| &env["state"])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_event_stream_delivers_a_lease_and_its_release() {
    let lab = Lab::start(WebOptions::default()).await;
    let response = send(&lab.http, Method::GET, &lab.url("/api/events")).await;
    assert_eq!(response.status(), StatusCode::OK);
    assert_eq!(response.headers()["content-type"], "text/event-stream");
    let mut body = response.into_body();
    let mut buffer = String::new();
    until_event(&mut body, &mut buffer, "web-a free", |s| {
        state_of(s, "sim/web-a") == "free"
    })
    .await;

    let mut client = open(&lab.deployment, &env_ids()[0], AlgorithmMode::Train, "").await;
    let until = client.opened().lease_until_unix_ms;
    until_event(&mut body, &mut buffer, "web-a leased", |s| {
        let env = s["envs"]
            .as_array()
            .and_then(|e| e.iter().find(|e| e["id"] == "sim/web-a"));
        env.is_some_and(|e| {
            e["state"] == "leased"
                && e["lease"] == json!({"holder": "anonymous", "until_unix_ms": until})
        }) && state_of(s, "sim/web-b") == "free"
    })
    .await;
    client.close().await.expect("close");
    until_event(&mut body, &mut buffer, "web-a free again", |s| {
        state_of(s, "sim/web-a") == "free"
    })
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_leaderboard_ranks_test_runs_as_json_and_on_the_env_page() {
    let lab = Lab::start(WebOptions::default()).await;
    let (status, _, body) = lab.get("/api/envs/sim/web-a/leaderboard").await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(
        serde_json::from_str::<Value>(&body).expect("JSON"),
        json!({"env": "sim/web-a", "entries": []})
    );

    let mut client = open(
        &lab.deployment,
        &env_ids()[0],
        AlgorithmMode::Test,
        "web-eval",
    )
    .await;
    client.reset(Seed::Fixed(3)).await.expect("reset");
    common::play_to_end(&mut client).await;
    client.close().await.expect("close");

    let (status, _, body) = lab.get("/api/envs/sim/web-a/leaderboard").await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let board: Value = serde_json::from_str(&body).expect("JSON");
    let entries = board["entries"].as_array().expect("entries");
    assert_eq!(entries.len(), 1, "{board:#}");
    let entry = &entries[0];
    assert_eq!(
        (
            &entry["rank"],
            &entry["experiment"],
            &entry["user"],
            &entry["learning_type"],
            &entry["episodes"]
        ),
        (
            &json!(1),
            &json!("web-eval"),
            &json!("anonymous"),
            &json!("end2end"),
            &json!(1)
        ),
    );
    let success = entry["success_rate"].as_f64().expect("rate");
    assert!(success == 0.0 || success == 1.0, "one episode: {success}");
    assert!(entry["mean_return"].is_f64());

    let (status, _, page) = lab.get("/envs/sim/web-a").await;
    assert_eq!(status, StatusCode::OK);
    assert!(
        page.contains("<td data-value=\"web-eval\">web-eval</td>"),
        "{page}"
    );
    assert!(page.contains("class=\"leaderboard sortable\""));
    // The other env's board is still empty.
    let (_, _, page) = lab.get("/envs/sim/web-b").await;
    assert!(page.contains("No test-mode experiment has finished an episode on this env yet."));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_dead_deployment_shows_offline_and_never_hangs_a_request() {
    let options = WebOptions {
        discovery: DiscoveryConfig {
            query_timeout: Duration::from_millis(500),
            sweep_interval: Duration::from_secs(1),
        },
        ..WebOptions::default()
    };
    let mut lab = Lab::start(options).await;
    if let Some(embedded) = lab.embedded.take() {
        embedded.shutdown("the test stops the deployment").await;
    }
    lab.deployment.close().await.expect("close the deployment");
    let snapshot = lab
        .until_envs("both envs offline", |envs| {
            envs.len() == 2 && envs.iter().all(|e| e["state"] == "offline")
        })
        .await;
    assert_eq!(snapshot["deployment"]["reachable"], false, "{snapshot:#}");
    assert_eq!(
        snapshot["deployment"]["message"],
        "not connected to the deployment: no Zenoh router or peer is reachable"
    );
    for env in snapshot["envs"].as_array().expect("envs") {
        assert_eq!(env["offline"]["reason"], "the deployment is unreachable");
        assert_eq!(env["task"], "MonolithDiscrete", "the last known task stays");
    }
    // The page answers (within the query timeout), saying so.
    let (status, _, page) = lab.get("/envs/sim/web-a").await;
    assert_eq!(status, StatusCode::OK);
    assert!(page.contains("The deployment does not answer"), "{page}");
    assert!(page.contains("The leaderboard is unavailable"), "{page}");
    let (status, _, body) = lab.get("/api/envs/sim/web-a/leaderboard").await;
    assert!(
        [
            StatusCode::NOT_FOUND,
            StatusCode::GATEWAY_TIMEOUT,
            StatusCode::SERVICE_UNAVAILABLE
        ]
        .contains(&status),
        "{status}: {body}"
    );
}

/// A service on an isolated session (no deployment): limits only.
async fn lone_service(limits: Limits) -> (LabWeb, HttpClient) {
    let session = SessionConfig::isolated().open().await.expect("session");
    let options = WebOptions {
        limits,
        ..WebOptions::default()
    };
    let listen: SocketAddr = "127.0.0.1:0".parse().expect("address");
    let web = LabWeb::start(session, listen, options).await.expect("web");
    (web, http_client())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_over_its_rate_is_told_when_to_retry() {
    let one = NonZeroU32::MIN;
    let (web, http) = lone_service(Limits {
        rate_per_client: one,
        burst_per_client: NonZeroU32::new(2).expect("2"),
        ..Limits::default()
    })
    .await;
    let url = format!("http://{}/api/envs", web.local_addr());
    // A burst of two, then one request per second.
    assert_eq!(request(&http, Method::GET, &url).await.0, StatusCode::OK);
    assert_eq!(request(&http, Method::GET, &url).await.0, StatusCode::OK);
    let (status, headers, body) = request(&http, Method::GET, &url).await;
    assert_eq!(status, StatusCode::TOO_MANY_REQUESTS, "{body}");
    assert_eq!(headers["retry-after"], "1");
    let error: Value = serde_json::from_str(&body).expect("JSON error");
    assert_eq!(error["error"]["kind"], "rate_limited");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn event_streams_over_the_limit_are_refused_not_queued() {
    let (web, http) = lone_service(Limits {
        max_event_streams: 1,
        ..Limits::default()
    })
    .await;
    let url = format!("http://{}/api/events", web.local_addr());
    let first = send(&http, Method::GET, &url).await;
    assert_eq!(first.status(), StatusCode::OK);
    let (status, headers, body) = request(&http, Method::GET, &url).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert_eq!(headers["retry-after"], "1");
    let error: Value = serde_json::from_str(&body).expect("JSON error");
    assert_eq!(error["error"]["kind"], "overloaded");
    // Closing the first stream frees its place.
    drop(first);
    let deadline = tokio::time::Instant::now() + EVENTUALLY;
    loop {
        let again = send(&http, Method::GET, &url).await;
        if again.status() == StatusCode::OK {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "the place never came back"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// GET `path`: status, content type, body bytes.
async fn get_bytes(lab: &Lab, path: &str) -> (StatusCode, String, Vec<u8>) {
    let (status, headers, body) = request_bytes(&lab.http, Method::GET, &lab.url(path)).await;
    let content_type = headers
        .get("content-type")
        .and_then(|v| v.to_str().ok())
        .unwrap_or("")
        .to_owned();
    (status, content_type, body)
}

/// The size of a PNG, decoded with the `png` crate.
fn png_size(bytes: &[u8]) -> (u32, u32) {
    let reader = png::Decoder::new(std::io::Cursor::new(bytes))
        .read_info()
        .expect("a PNG");
    let info = reader.info();
    (info.width, info.height)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thumbnails_show_a_stepping_envs_views_and_say_why_an_idle_one_has_none() {
    let rerun = "rerun+http://127.0.0.1:9876/proxy";
    let lab = Lab::start(WebOptions {
        rerun_url: Some(rerun.into()),
        ..WebOptions::default()
    })
    .await;
    let (status, _, page) = lab.get("/envs/sim/web-a").await;
    assert_eq!(status, StatusCode::OK);
    assert!(
        page.contains(r#"<img data-thumbnail="camera" src="/envs/sim/web-a/camera.png""#),
        "{page}"
    );
    assert!(
        page.contains(r#"src="/envs/sim/web-a/overhead.png""#),
        "{page}"
    );
    assert!(
        page.contains(&format!(r#"<a href="{rerun}">open in rerun</a>"#)),
        "{page}"
    );

    // An idle env publishes no camera frame: a 404 that says so.
    let (status, _, body) = lab.get("/envs/sim/web-b/camera.png").await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{body}");
    assert!(
        body.contains("sim/web-b: no camera frame from this env in the last 1.5 s"),
        "{body}"
    );
    let (status, _, _) = lab.get("/envs/sim/nowhere/camera.png").await;
    assert_eq!(status, StatusCode::NOT_FOUND);

    // A stepping env: its camera (8×6 frames, kept whole) and its overhead view.
    let mut client = open(&lab.deployment, &env_ids()[0], AlgorithmMode::Train, "").await;
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stepping = {
        let stop = stop.clone();
        tokio::spawn(async move {
            client.reset(Seed::Fixed(1)).await.expect("reset");
            // Bounded: until told to stop, at most 20,000 steps, paced
            // below the controller's per-client rate (an 8×6 twin steps
            // faster than the 2,000 requests/s it allows one client).
            for _ in 0..20_000 {
                if stop.load(std::sync::atomic::Ordering::Relaxed) {
                    break;
                }
                tokio::time::sleep(std::time::Duration::from_millis(1)).await;
                let reply = client
                    .step(offworld_runtime::msg::Action::Discrete(1))
                    .await
                    .expect("step");
                if reply.terminated || reply.truncated {
                    client.reset(Seed::Continue).await.expect("reset");
                }
            }
            client.close().await.expect("close");
        })
    };
    let (status, content_type, png) = get_bytes(&lab, "/envs/sim/web-a/camera.png").await;
    assert_eq!(status, StatusCode::OK, "{}", String::from_utf8_lossy(&png));
    assert_eq!(content_type, "image/png");
    assert_eq!(png_size(&png), (8, 6));
    let (status, content_type, png) = get_bytes(&lab, "/envs/sim/web-a/overhead.png").await;
    assert_eq!(status, StatusCode::OK, "{}", String::from_utf8_lossy(&png));
    assert_eq!(content_type, "image/png");
    let (width, height) = png_size(&png);
    assert!(width <= 240 && width > 0 && height > 0, "{width}×{height}");
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    stepping.await.expect("the stepping task");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_trackers_word_on_localisation_is_shown() {
    let lab = Lab::start(WebOptions::default()).await;
    // As a tracker agent publishes it, on the env's `tracking` key.
    let lost = offworld_runtime::msg::TrackingStatus {
        tracking: false,
        last_pose_age_s: 1.5,
        reason: "no lighthouse pose for 1.5 s".into(),
    };
    let key = env_ids()[0].key(offworld_runtime::Topic::Tracking);
    offworld_runtime::wire::put(&lab.deployment, &key, &lost)
        .await
        .expect("put");
    let snapshot = lab
        .until_envs("tracking lost on web-a", |envs| {
            envs.iter()
                .any(|e| e["id"] == "sim/web-a" && e["tracking"]["ok"] == false)
        })
        .await;
    let env = &snapshot["envs"][0];
    assert_eq!(env["tracking"]["reason"], "no lighthouse pose for 1.5 s");
    assert_eq!(env["tracking"]["last_pose_age_s"], 1.5);
    assert_eq!(snapshot["envs"][1]["tracking"], Value::Null);
    let (_, _, page) = lab.get("/").await;
    assert!(
        page.contains("tracking lost: no lighthouse pose for 1.5 s"),
        "{page}"
    );
    let back = offworld_runtime::msg::TrackingStatus {
        tracking: true,
        last_pose_age_s: 0.01,
        reason: String::new(),
    };
    offworld_runtime::wire::put(&lab.deployment, &key, &back)
        .await
        .expect("put");
    lab.until_envs("tracking back on web-a", |envs| {
        envs.iter()
            .any(|e| e["id"] == "sim/web-a" && e["tracking"]["ok"] == true)
    })
    .await;
    let (_, _, page) = lab.get("/").await;
    assert!(!page.contains("tracking lost"), "{page}");
}
