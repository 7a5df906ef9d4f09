//! The signed-in side against a real deployment: a controller with users
//! (alice, bob) serving a sim env (twin embedded, recording every
//! episode) and a real env (no robot needed to book it), the web service
//! on another Zenoh session, requests over real HTTP with a cookie jar.
//! Checks sign-in (a bad token refused, clearly), bookings made through
//! the page and listed, an overlap refused with the controller's message,
//! CSRF and origin refusals (403), cancel only by the holder, sign-out,
//! the experiments pages (episode count, learning curve, recordings), and
//! the operator console (operators only: an e-stop acknowledged by the
//! twin, a release only with its confirmation, maintenance with its
//! expected return, a revoked lease whose holder is told why).

use offworld_runtime::Resolution;
use offworld_test_support::ScratchDir;
use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::time::Duration;

use bytes::Bytes;
use http_body_util::{BodyExt, Full};
use hyper::{Method, Request, StatusCode};
use hyper_util::client::legacy::connect::HttpConnector;
use hyper_util::client::legacy::Client;
use hyper_util::rt::TokioExecutor;
use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::embedded::{Embedded, SimEnv, Stepping, TwinProfile};
use offworld_env_controller::{EnvOptions, RequestLimits, Store, Task};
use offworld_runtime::keys::EnvId;
use offworld_runtime::msg::{AlgorithmMode, ObsOptions, OpenRequest, Seed};
use offworld_runtime::session::loopback_pair;
use offworld_web::{LabWeb, WebOptions};
use serde_json::Value;
use zenoh::Session;

/// Bound of every wait for something that must happen (never a speed).
use crate::common;

const EVENTUALLY: Duration = Duration::from_secs(20);

const ALICE: &str = "alice-web-token-0001";
const BOB: &str = "bob-web-token-00002";
const OPS: &str = "ops-web-token-000003";

const SIM: &str = "sim/acct-a";
const REAL: &str = "real/acct-bench";

/// A deployment with users, a sim env and a real env, and the service.
struct Lab {
    web: LabWeb,
    deployment: Session,
    _embedded: Embedded,
    _records: ScratchDir,
}

impl Lab {
    async fn start() -> Self {
        Self::start_with(WebOptions::default()).await
    }

    async fn start_with(options: WebOptions) -> Self {
        let (deployment, web_side) = loopback_pair().await.expect("sessions");
        let store = Store::in_memory().expect("store");
        store
            .add_user_with_token("alice", ALICE, false)
            .expect("alice");
        store.add_user_with_token("bob", BOB, false).expect("bob");
        store.add_user_with_token("ops", OPS, true).expect("ops");
        let records = ScratchDir::new("web-test");
        let sim = SimEnv {
            env: EnvId::sim("acct-a").expect("env id"),
            task: "MonolithDiscrete".into(),
            resolution: Some(Resolution::new(8, 6)),
            seed: 7,
            profile: TwinProfile::default(),
            render_threads: 1,
            stepping: Stepping::OwnThread,
        };
        let mut embedded = Embedded::start_with(
            &deployment,
            &[sim],
            store,
            EnvOptions::default(),
            RequestLimits::default(),
            Some(&records.0),
        )
        .await
        .expect("deployment");
        // A real env: its controller answers bookings without a robot.
        embedded
            .controller
            .serve(
                EnvId::real("acct-bench").expect("env id"),
                Task::by_name("MonolithDiscrete").expect("task"),
                EnvOptions::default(),
            )
            .await
            .expect("real env");
        let listen: SocketAddr = "127.0.0.1:0".parse().expect("address");
        let web = LabWeb::start(web_side, listen, options)
            .await
            .expect("web service");
        let lab = Self {
            web,
            deployment,
            _embedded: embedded,
            _records: records,
        };
        lab.until_listed().await;
        lab
    }

    /// Waits (bounded) until both envs are listed with their controller.
    async fn until_listed(&self) {
        let deadline = tokio::time::Instant::now() + EVENTUALLY;
        let mut browser = self.browser();
        // A members-only site lists nothing to strangers.
        while browser.sign_in(ALICE).await.0 != StatusCode::SEE_OTHER {
            assert!(
                tokio::time::Instant::now() < deadline,
                "signing in: not within {EVENTUALLY:?}"
            );
            // Sign-in attempts are rate-limited (bursts of 10).
            tokio::time::sleep(Duration::from_millis(300)).await;
        }
        loop {
            let (_, _, body) = browser.get("/api/envs").await;
            let snapshot: Value = serde_json::from_str(&body).expect("JSON");
            let with_controller = |id: &str| {
                snapshot["envs"].as_array().is_some_and(|envs| {
                    envs.iter().any(|e| {
                        e["id"] == id
                            && e["components"]
                                .as_array()
                                .is_some_and(|c| c.iter().any(|c| c == "controller"))
                    })
                })
            };
            if with_controller(SIM) && with_controller(REAL) {
                return;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "both envs listed: not within {EVENTUALLY:?}; last: {snapshot:#}"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
    }

    fn browser(&self) -> Browser {
        Browser {
            base: format!("http://{}", self.web.local_addr()),
            http: Client::builder(TokioExecutor::new()).build_http(),
            cookies: BTreeMap::new(),
            origin: None,
        }
    }
}

/// A client that keeps cookies and sends the `Origin` a browser sends.
struct Browser {
    base: String,
    http: Client<HttpConnector, Full<Bytes>>,
    cookies: BTreeMap<String, String>,
    /// Sent with every POST: this service's own by default.
    origin: Option<String>,
}

type Answer = (StatusCode, hyper::HeaderMap, String);

impl Browser {
    async fn send(&mut self, method: Method, path: &str, form: Option<&str>) -> Answer {
        let mut request = Request::builder()
            .method(method.clone())
            .uri(format!("{}{path}", self.base));
        if !self.cookies.is_empty() {
            let jar: Vec<String> = self
                .cookies
                .iter()
                .map(|(k, v)| format!("{k}={v}"))
                .collect();
            request = request.header("cookie", jar.join("; "));
        }
        if method == Method::POST {
            let origin = self.origin.clone().unwrap_or_else(|| self.base.clone());
            if !origin.is_empty() {
                request = request.header("origin", origin);
            }
            request = request.header("content-type", "application/x-www-form-urlencoded");
        }
        let body = Full::new(Bytes::from(form.unwrap_or("").to_owned()));
        let response = tokio::time::timeout(
            EVENTUALLY,
            self.http.request(request.body(body).expect("request")),
        )
        .await
        .expect("an answer within the bound")
        .expect("HTTP response");
        let (parts, body) = response.into_parts();
        for cookie in parts.headers.get_all("set-cookie") {
            let text = cookie.to_str().expect("ASCII cookie");
            assert!(
                text.contains("HttpOnly") && text.contains("SameSite=Strict"),
                "{text}"
            );
            let (name, value) = text
                .split(';')
                .next()
                .and_then(|pair| pair.split_once('='))
                .expect("name=value");
            if text.contains("Max-Age=0") {
                self.cookies.remove(name);
            } else {
                self.cookies.insert(name.to_owned(), value.to_owned());
            }
        }
        let body = tokio::time::timeout(EVENTUALLY, body.collect())
            .await
            .expect("the body within the bound")
            .expect("body")
            .to_bytes();
        (
            parts.status,
            parts.headers,
            String::from_utf8(body.to_vec()).expect("UTF-8 body"),
        )
    }

    async fn get(&mut self, path: &str) -> Answer {
        self.send(Method::GET, path, None).await
    }

    async fn post(&mut self, path: &str, form: &str) -> Answer {
        self.send(Method::POST, path, Some(form)).await
    }

    /// Signs in with `token` through the form; returns the POST's answer.
    async fn sign_in(&mut self, token: &str) -> Answer {
        let (status, _, page) = self.get("/account").await;
        assert_eq!(status, StatusCode::OK, "{page}");
        let csrf = csrf_of(&page);
        self.post(
            "/account/signin",
            &format!("csrf={csrf}&token={}", encode(token)),
        )
        .await
    }
}

/// The CSRF token of the first form on `page`.
fn csrf_of(page: &str) -> String {
    page.split("name=\"csrf\" value=\"")
        .nth(1)
        .and_then(|rest| rest.split('"').next())
        .unwrap_or_else(|| panic!("no CSRF field in {page}"))
        .to_owned()
}

fn encode(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' => {
                char::from(b).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

fn location(headers: &hyper::HeaderMap) -> &str {
    headers["location"].to_str().expect("location")
}

fn now_ms() -> i64 {
    offworld_web::discovery::now_unix_ms()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn signing_in_with_a_bad_token_is_refused_clearly() {
    let lab = Lab::start().await;
    let mut browser = lab.browser();

    let (status, _, page) = browser.sign_in("not-a-real-token").await;
    assert_eq!(status, StatusCode::UNAUTHORIZED, "{page}");
    assert!(
        page.contains("Sign-in refused by the controller of"),
        "{page}"
    );
    assert!(page.contains("unknown access token"), "{page}");
    assert!(
        !page.contains("not-a-real-token"),
        "the token is never echoed"
    );
    assert!(!browser.cookies.contains_key("offworld_session"));

    let (status, _, page) = browser.sign_in("").await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{page}");
    assert!(page.contains("Paste your access token"), "{page}");

    // The form's CSRF token is required, and the origin must be this site.
    let (status, _, page) = browser
        .post("/account/signin", &format!("token={ALICE}"))
        .await;
    assert_eq!(status, StatusCode::FORBIDDEN, "{page}");
    let (_, _, form) = browser.get("/account").await;
    let csrf = csrf_of(&form);
    browser.origin = Some("http://evil.example".into());
    let (status, _, page) = browser
        .post("/account/signin", &format!("csrf={csrf}&token={ALICE}"))
        .await;
    assert_eq!(status, StatusCode::FORBIDDEN, "{page}");
    assert!(page.contains("is not this site"), "{page}");
    assert!(!browser.cookies.contains_key("offworld_session"));

    // The right token, from this site: signed in.
    browser.origin = None;
    let (status, headers, _) = browser.sign_in(ALICE).await;
    assert_eq!(status, StatusCode::SEE_OTHER);
    assert_eq!(location(&headers), "/account");
    assert!(browser.cookies.contains_key("offworld_session"));
    let (status, _, page) = browser.get("/account").await;
    assert_eq!(status, StatusCode::OK);
    assert!(page.contains("You are signed in"), "{page}");
    assert!(!page.contains(ALICE), "the token is never in a page");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bookings_are_made_listed_refused_on_overlap_and_cancelled_by_their_holder_only() {
    let lab = Lab::start().await;
    let page_path = format!("/envs/{REAL}/bookings");

    // Anyone may list; nothing is booked yet.
    let mut anyone = lab.browser();
    let (status, _, page) = anyone.get(&page_path).await;
    assert_eq!(status, StatusCode::OK, "{page}");
    assert!(page.contains("Nothing is booked."), "{page}");
    assert!(!page.contains("name=\"csrf\""), "no form before sign-in");

    let mut alice = lab.browser();
    assert_eq!(alice.sign_in(ALICE).await.0, StatusCode::SEE_OTHER);
    let (_, _, page) = alice.get(&page_path).await;
    let csrf = csrf_of(&page);
    let start = now_ms() + 3_600_000;

    // A POST without the CSRF token, or from another site, is refused.
    let slot = format!("start_unix_ms={start}&minutes=30");
    let (status, _, body) = alice.post(&page_path, &slot).await;
    assert_eq!(status, StatusCode::FORBIDDEN, "{body}");
    let (status, _, body) = alice
        .post(&page_path, &format!("csrf={}&{slot}", "0".repeat(64)))
        .await;
    assert_eq!(status, StatusCode::FORBIDDEN, "{body}");
    alice.origin = Some("null".into());
    let (status, _, body) = alice.post(&page_path, &format!("csrf={csrf}&{slot}")).await;
    assert_eq!(status, StatusCode::FORBIDDEN, "{body}");
    alice.origin = Some(String::new());
    let (status, _, body) = alice.post(&page_path, &format!("csrf={csrf}&{slot}")).await;
    assert_eq!(
        status,
        StatusCode::FORBIDDEN,
        "no origin, no referer: {body}"
    );
    alice.origin = None;
    let listed: Value =
        serde_json::from_str(&anyone.get(&format!("/api/envs/{REAL}/bookings")).await.2)
            .expect("JSON");
    assert_eq!(
        listed["bookings"],
        serde_json::json!([]),
        "nothing booked by refused POSTs"
    );

    // Booked through the page: listed, on the page and as JSON.
    let (status, headers, body) = alice.post(&page_path, &format!("csrf={csrf}&{slot}")).await;
    assert_eq!(status, StatusCode::SEE_OTHER, "{body}");
    let made = location(&headers).to_owned();
    let id: i64 = made
        .strip_prefix(&format!("{page_path}?made="))
        .and_then(|id| id.parse().ok())
        .unwrap_or_else(|| panic!("{made}"));
    let (status, _, page) = alice.get(&made).await;
    assert_eq!(status, StatusCode::OK);
    assert!(page.contains(&format!("Booked: slot #{id}.")), "{page}");
    assert!(
        page.contains(&format!("data-booking=\"{id}\" data-user=\"alice\"")),
        "{page}"
    );
    assert!(page.contains("class=\"badge yours\""), "{page}");
    assert!(!page.contains(ALICE), "the token is never in a page");
    let (_, _, body) = anyone.get(&format!("/api/envs/{REAL}/bookings")).await;
    let listed: Value = serde_json::from_str(&body).expect("JSON");
    assert_eq!(listed["env"], REAL);
    assert_eq!(listed["bookings"][0]["id"], id);
    assert_eq!(listed["bookings"][0]["user"], "alice");
    assert_eq!(listed["bookings"][0]["start_unix_ms"], start);
    assert_eq!(listed["bookings"][0]["end_unix_ms"], start + 30 * 60_000);
    let (_, _, page) = anyone.get(&page_path).await;
    assert!(
        page.contains(&format!("data-booking=\"{id}\"")),
        "public: {page}"
    );

    // An overlapping slot: the controller's refusal, shown (409).
    let mut bob = lab.browser();
    assert_eq!(bob.sign_in(BOB).await.0, StatusCode::SEE_OTHER);
    let (_, _, page) = bob.get(&page_path).await;
    let bob_csrf = csrf_of(&page);
    let overlap = format!(
        "csrf={bob_csrf}&start_unix_ms={}&minutes=60",
        start + 10 * 60_000
    );
    let (status, _, page) = bob.post(&page_path, &overlap).await;
    assert_eq!(status, StatusCode::CONFLICT, "{page}");
    assert!(page.contains("role=\"alert\""), "{page}");
    assert!(
        page.contains("Not booked: real/acct-bench is booked by alice from"),
        "{page}"
    );
    // The controller's rules, too: a slot in the past.
    let past = format!("csrf={bob_csrf}&start=2020-01-01T10:00&minutes=60");
    let (status, _, page) = bob.post(&page_path, &past).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{page}");
    assert!(page.contains("in the past"), "{page}");

    // Bob cannot cancel Alice's slot; she can.
    let cancel = format!("{page_path}/{id}/cancel");
    let (status, _, page) = bob.post(&cancel, &format!("csrf={bob_csrf}")).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED, "{page}");
    assert!(
        page.contains(&format!("booking {id} is someone else")),
        "{page}"
    );
    let (status, _, body) = alice.post(&cancel, "").await;
    assert_eq!(
        status,
        StatusCode::FORBIDDEN,
        "cancel needs the CSRF token too: {body}"
    );
    let (status, headers, body) = alice.post(&cancel, &format!("csrf={csrf}")).await;
    assert_eq!(status, StatusCode::SEE_OTHER, "{body}");
    assert_eq!(location(&headers), format!("{page_path}?cancelled={id}"));
    let (_, _, page) = anyone.get(&page_path).await;
    assert!(page.contains("Nothing is booked."), "{page}");

    // Signed out: the session is gone, its forms refused.
    let (status, _, body) = alice
        .post("/account/signout", &format!("csrf={csrf}"))
        .await;
    assert_eq!(status, StatusCode::SEE_OTHER, "{body}");
    assert!(!alice.cookies.contains_key("offworld_session"));
    let (status, _, body) = alice.post(&page_path, &format!("csrf={csrf}&{slot}")).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED, "{body}");
}

async fn run_episodes(session: &Session, token: &str, experiment: &str, episodes: u32) {
    let env = EnvId::sim("acct-a").expect("env id");
    let request = OpenRequest {
        token: token.to_owned(),
        experiment_name: experiment.to_owned(),
        algorithm_mode: AlgorithmMode::Train,
        ..OpenRequest::anonymous(ObsOptions {
            height: 6,
            width: 8,
            ..ObsOptions::default()
        })
    };
    let mut client = EnvClient::open_when_ready(
        session,
        &env,
        request,
        ClientTimeouts::default(),
        EVENTUALLY,
    )
    .await
    .expect("open");
    for episode in 0..episodes {
        client
            .reset(Seed::Fixed(u64::from(episode) + 1))
            .await
            .expect("reset");
        common::play_to_end(&mut client).await;
    }
    client.close().await.expect("close");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_experiments_pages_show_the_users_experiment_its_episodes_and_curve() {
    let lab = Lab::start().await;
    run_episodes(&lab.deployment, ALICE, "web-exp", 2).await;
    let list_path = format!("/envs/{SIM}/experiments");

    let mut anyone = lab.browser();
    let (status, _, page) = anyone.get(&list_path).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED, "{page}");
    assert!(page.contains("sign in"), "{page}");

    let mut alice = lab.browser();
    assert_eq!(alice.sign_in(ALICE).await.0, StatusCode::SEE_OTHER);
    let (status, _, page) = alice.get(&list_path).await;
    assert_eq!(status, StatusCode::OK, "{page}");
    let row = page
        .split("<tr data-experiment=\"")
        .nth(1)
        .unwrap_or_else(|| panic!("no experiment row: {page}"));
    let id: i64 = row
        .split('"')
        .next()
        .and_then(|id| id.parse().ok())
        .expect("experiment id");
    assert!(row.contains(">web-exp</a>"), "{row}");
    assert!(
        row.contains("data-field=\"episodes\" data-value=\"2\""),
        "two episodes: {row}"
    );

    let (status, _, page) = alice.get(&format!("{list_path}/{id}")).await;
    assert_eq!(status, StatusCode::OK, "{page}");
    assert!(page.contains("<dd id=\"episode-count\">2</dd>"), "{page}");
    assert_eq!(page.matches("<tr data-episode=").count(), 2, "{page}");
    assert!(page.contains("<svg class=\"curve\""), "{page}");
    assert!(page.contains("data-points=\"2\""), "{page}");
    // Each episode's recording, by its path under the recording directory.
    for episode in 0..2 {
        assert!(
            page.contains(&format!("ep-{episode:06}.mcap</code>")),
            "episode {episode}'s recording: {page}"
        );
    }

    // Bob sees none of it: his list is empty, her experiment not found.
    let mut bob = lab.browser();
    assert_eq!(bob.sign_in(BOB).await.0, StatusCode::SEE_OTHER);
    let (status, _, page) = bob.get(&list_path).await;
    assert_eq!(status, StatusCode::OK);
    assert!(
        page.contains("You have no experiment on this env yet."),
        "{page}"
    );
    let (status, _, page) = bob.get(&format!("{list_path}/{id}")).await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{page}");
    assert!(
        page.contains(&format!("no experiment {id} of yours")),
        "{page}"
    );
    // Malformed ids are 404s that never reach the deployment.
    let (status, _, _) = alice.get(&format!("{list_path}/x1")).await;
    assert_eq!(status, StatusCode::NOT_FOUND);
}

/// The `/api/envs` entry of `id`.
async fn env_json(browser: &mut Browser, id: &str) -> Value {
    let (_, _, body) = browser.get("/api/envs").await;
    let snapshot: Value = serde_json::from_str(&body).expect("JSON");
    snapshot["envs"]
        .as_array()
        .and_then(|envs| envs.iter().find(|e| e["id"] == id).cloned())
        .unwrap_or(Value::Null)
}

/// Waits (bounded) until `id`'s `/api/envs` entry satisfies `check`.
async fn until_env(browser: &mut Browser, id: &str, what: &str, check: impl Fn(&Value) -> bool) {
    let deadline = tokio::time::Instant::now() + EVENTUALLY;
    loop {
        let env = env_json(browser, id).await;
        if check(&env) {
            return;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{what}: not within {EVENTUALLY:?}; last: {env:#}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_operator_console_is_for_operators_and_its_actions_reach_the_deployment() {
    let lab = Lab::start().await;
    let mut anonymous = lab.browser();
    let (status, _, page) = anonymous.get("/console").await;
    assert_eq!(status, StatusCode::UNAUTHORIZED, "{page}");
    assert!(page.contains("The operator console needs you to"), "{page}");

    // A user who is not an operator: no console, no console action.
    let mut alice = lab.browser();
    let (status, _, _) = alice.sign_in(ALICE).await;
    assert_eq!(status, StatusCode::SEE_OTHER);
    let (_, _, account) = alice.get("/account").await;
    assert!(!account.contains("console-link"), "{account}");
    let (status, _, page) = alice.get("/console").await;
    assert_eq!(status, StatusCode::FORBIDDEN, "{page}");
    assert!(
        page.contains("The operator console is for operators: alice is not one."),
        "{page}"
    );
    let csrf = csrf_of(&account);
    let (status, _, page) = alice
        .post(
            "/console/estop",
            &format!("csrf={csrf}&scope=site&action=engage&reason=mine"),
        )
        .await;
    assert_eq!(status, StatusCode::FORBIDDEN, "{page}");
    assert_eq!(env_json(&mut alice, SIM).await["estop"]["engaged"], false);

    // The operator.
    let mut ops = lab.browser();
    let (status, _, _) = ops.sign_in(OPS).await;
    assert_eq!(status, StatusCode::SEE_OTHER);
    let (_, _, account) = ops.get("/account").await;
    assert!(account.contains("id=\"console-link\""), "{account}");
    let (status, _, page) = ops.get("/console").await;
    assert_eq!(status, StatusCode::OK, "{page}");
    assert!(
        page.contains("Signed in as <strong id=\"operator\">ops</strong>"),
        "{page}"
    );
    assert!(page.contains(&format!("data-env=\"{SIM}\"")), "{page}");
    let csrf = csrf_of(&page);

    // An e-stop needs a reason; then the twin acknowledges it.
    let estop = |action: &str, extra: &str| {
        format!(
            "csrf={csrf}&scope=env&env={}&action={action}{extra}",
            encode(SIM)
        )
    };
    let (status, _, page) = ops
        .post("/console/estop", &estop("engage", "&reason="))
        .await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{page}");
    assert!(page.contains("Not engaged: say the reason"), "{page}");
    let (status, _, page) = ops
        .post(
            "/console/estop",
            &estop("engage", "&reason=person+in+the+enclosure"),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{page}");
    assert!(
        page.contains(&format!(
            "E-stop engaged on {SIM}: acknowledged by sim_twin of {SIM}."
        )),
        "{page}"
    );
    assert!(
        page.contains(&format!("data-env=\"{SIM}\" data-component=\"sim_twin\"")),
        "{page}"
    );
    until_env(&mut ops, SIM, "the e-stop on the page", |env| {
        env["state"] == "estopped"
            && env["estop"]["env"]["reason"] == "person in the enclosure (ops via the web console)"
    })
    .await;
    // A release without its confirmation is refused; with it, done.
    let (status, _, page) = ops
        .post("/console/estop", &estop("release", "&reason=all+clear"))
        .await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{page}");
    assert!(page.contains("Not released: tick the box"), "{page}");
    assert_eq!(env_json(&mut ops, SIM).await["state"], "estopped");
    let (status, _, page) = ops
        .post(
            "/console/estop",
            &estop("release", "&reason=all+clear&confirm=yes"),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{page}");
    assert!(
        page.contains(&format!("E-stop released on {SIM}")),
        "{page}"
    );
    until_env(&mut ops, SIM, "the release on the page", |env| {
        env["state"] == "free"
    })
    .await;

    // Maintenance with an expected return, shown to everyone; then ended.
    let before = now_ms();
    let (status, _, page) = ops
        .post(
            "/console/maintenance",
            &format!(
                "csrf={csrf}&env={}&action=start&message=wheel+swap&back_minutes=30",
                encode(SIM)
            ),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{page}");
    assert!(page.contains(&format!("{SIM} is in maintenance")), "{page}");
    let env = env_json(&mut anonymous, SIM).await;
    assert_eq!(env["state"], "maintenance", "{env:#}");
    assert_eq!(env["maintenance"]["message"], "wheel swap");
    assert_eq!(env["maintenance"]["by"], "ops");
    let back = env["maintenance"]["back_unix_ms"].as_i64().expect("back");
    assert!(
        (before + 30 * 60_000..=now_ms() + 30 * 60_000).contains(&back),
        "{back}"
    );
    let (status, _, page) = ops
        .post(
            "/console/maintenance",
            &format!(
                "csrf={csrf}&env={}&action=start&message=x&back_minutes=soon",
                encode(SIM)
            ),
        )
        .await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{page}");
    assert!(page.contains("whole number of minutes"), "{page}");
    let (status, _, page) = ops
        .post(
            "/console/maintenance",
            &format!("csrf={csrf}&env={}&action=end", encode(SIM)),
        )
        .await;
    assert_eq!(status, StatusCode::OK, "{page}");
    assert_eq!(env_json(&mut anonymous, SIM).await["state"], "free");

    // A revoked lease: its holder is told who and why.
    let request = OpenRequest {
        token: ALICE.to_owned(),
        experiment_name: "revoked".to_owned(),
        ..OpenRequest::anonymous(ObsOptions {
            height: 6,
            width: 8,
            ..ObsOptions::default()
        })
    };
    let mut client = EnvClient::open_when_ready(
        &lab.deployment,
        &EnvId::sim("acct-a").expect("env id"),
        request,
        ClientTimeouts::default(),
        EVENTUALLY,
    )
    .await
    .expect("open");
    client.reset(Seed::Fixed(1)).await.expect("reset");
    until_env(&mut ops, SIM, "alice's lease on the page", |env| {
        env["lease"]["holder"] == "alice"
    })
    .await;
    let revoke = format!("csrf={csrf}&env={}&reason=demo+time", encode(SIM));
    let (status, _, page) = ops.post("/console/lease", &revoke).await;
    assert_eq!(status, StatusCode::OK, "{page}");
    assert!(
        page.contains(&format!("The lease on {SIM} (alice's) was revoked")),
        "{page}"
    );
    let told = client
        .reset(Seed::Fixed(2))
        .await
        .expect_err("the lease is gone");
    assert_eq!(
        told.message,
        format!("your lease on {SIM} was revoked by the operator ops: demo time")
    );
    let (status, _, page) = ops.post("/console/lease", &revoke).await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{page}");
    assert!(
        page.contains(&format!("Not revoked: {SIM} has no lease to revoke")),
        "{page}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_members_only_lab_shows_its_state_to_signed_in_users_only() {
    let lab = Lab::start_with(WebOptions {
        members_only: true,
        ..WebOptions::default()
    })
    .await;
    let mut stranger = lab.browser();
    for path in ["/", "/envs/sim/acct-a", "/bookings", "/events", "/console"] {
        let (status, _, page) = stranger.get(path).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED, "{path}: {page}");
        assert!(
            page.contains("This lab's pages needs you to"),
            "{path}: {page}"
        );
        assert!(!page.contains(SIM), "{path} shows nothing of the lab");
    }
    for path in [
        "/api/envs",
        "/api/envs/sim/acct-a/leaderboard",
        "/api/events",
    ] {
        let (status, _, body) = stranger.get(path).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED, "{path}: {body}");
        let error: Value = serde_json::from_str(&body).expect("JSON");
        assert_eq!(error["error"]["kind"], "unauthorized", "{body}");
    }
    for path in [
        "/account",
        "/static/style.css",
        "/static/app.js",
        "/healthz",
    ] {
        assert_eq!(stranger.get(path).await.0, StatusCode::OK, "{path}");
    }
    let mut alice = lab.browser();
    assert_eq!(alice.sign_in(ALICE).await.0, StatusCode::SEE_OTHER);
    let (status, _, page) = alice.get("/").await;
    assert_eq!(status, StatusCode::OK, "{page}");
    assert!(page.contains(SIM), "{page}");
    assert_eq!(alice.get("/api/envs").await.0, StatusCode::OK);
}
