//! The HTTP side: routes, the limits that keep a flood from taking the
//! service down, security headers, and the accept loop (hyper's HTTP/1
//! server driven directly: the tree's axum is built without `serve`).
//!
//! Limits, outermost first:
//! 1. connections: at most `max_connections` open (more wait in the
//!    kernel's backlog), each given `header_read_timeout` to send its
//!    request head (slow-loris clients are cut);
//! 2. per client address, a request rate (GCRA): over it, 429 with
//!    `Retry-After`;
//! 3. requests in progress across the service: over `max_in_flight`, 503 at
//!    once (tower's load shedding in front of a global concurrency limit);
//! 4. each request's deadline: 504 (the Zenoh queries have shorter ones);
//! 5. event streams: at most `max_event_streams` open, else 503.

use std::future::Future;
use std::net::{IpAddr, SocketAddr};
use std::num::NonZeroU32;
use std::sync::Arc;
use std::time::Duration;

use axum::error_handling::HandleErrorLayer;
use axum::extract::rejection::PathRejection;
use axum::extract::{Path, Request, State};
use axum::http::{header, HeaderValue, StatusCode, Uri};
use axum::middleware::{self, Next};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{BoxError, Router};
use governor::clock::{Clock, DefaultClock};
use governor::{DefaultKeyedRateLimiter, Quota, RateLimiter};
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::net::TcpListener;
use tokio::sync::Semaphore;
use tower::limit::GlobalConcurrencyLimitLayer;
use tower::ServiceBuilder;

use crate::discovery::Discovery;
use crate::error::{Format, HttpError};
use crate::session::Sessions;
use crate::thumbnails::{ThumbnailError, Thumbnails, View};
use crate::{account, api, console, events, pages, WebOptions};

/// The service's limits (see the module documentation).
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    /// Open connections.
    pub max_connections: usize,
    /// Requests being answered at once (event streams excluded).
    pub max_in_flight: usize,
    /// Open event streams.
    pub max_event_streams: usize,
    /// Sustained requests per second per client address.
    pub rate_per_client: NonZeroU32,
    /// Requests one client address may send at once above the rate.
    pub burst_per_client: NonZeroU32,
    /// Deadline of one request.
    pub request_timeout: Duration,
    /// Time a connection has to send a request head.
    pub header_read_timeout: Duration,
    /// Signed-in sessions kept at most (the least recently used goes first).
    pub max_sessions: usize,
    /// A session lapses after this long without a request.
    pub session_idle: Duration,
    /// Sign-in attempts per minute per client address, sustained.
    pub signins_per_minute: NonZeroU32,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_connections: 512,
            max_in_flight: 64,
            max_event_streams: 128,
            rate_per_client: NonZeroU32::new(20).unwrap_or(NonZeroU32::MIN),
            burst_per_client: NonZeroU32::new(60).unwrap_or(NonZeroU32::MIN),
            request_timeout: Duration::from_secs(10),
            header_read_timeout: Duration::from_secs(10),
            max_sessions: 10_000,
            session_idle: Duration::from_secs(12 * 3600),
            signins_per_minute: NonZeroU32::new(30).unwrap_or(NonZeroU32::MIN),
        }
    }
}

/// What every handler shares.
#[derive(Clone)]
pub struct AppState {
    /// The live availability.
    pub discovery: Discovery,
    /// Each env's camera and overhead thumbnails.
    pub thumbnails: Thumbnails,
    /// Where the rerun viewer opens the live stream (a monitor's), if set.
    pub rerun_url: Option<String>,
    /// Places for open event streams.
    pub event_streams: Arc<Semaphore>,
    /// Signed-in users.
    pub sessions: Arc<Sessions>,
    /// Sign-in attempts per client address.
    pub signins: Arc<DefaultKeyedRateLimiter<IpAddr>>,
    /// Cookies are marked `Secure` (the service is behind TLS).
    pub secure_cookies: bool,
    /// A session cookie's lifetime, s.
    pub session_idle_s: u64,
    rates: Arc<DefaultKeyedRateLimiter<IpAddr>>,
    request_timeout: Duration,
    members_only: bool,
}

/// The peer address of a request's connection (set by [`serve`]).
#[derive(Debug, Clone, Copy)]
pub struct PeerAddr(pub SocketAddr);

/// The application: every route behind its limits and headers.
pub fn router(discovery: Discovery, thumbnails: Thumbnails, options: &WebOptions) -> Router {
    let limits = &options.limits;
    let state = AppState {
        discovery,
        thumbnails,
        rerun_url: options.rerun_url.clone(),
        event_streams: Arc::new(Semaphore::new(limits.max_event_streams)),
        sessions: Arc::new(Sessions::new(limits.max_sessions, limits.session_idle)),
        signins: Arc::new(RateLimiter::keyed(
            Quota::per_minute(limits.signins_per_minute)
                .allow_burst(NonZeroU32::new(10).unwrap_or(NonZeroU32::MIN)),
        )),
        secure_cookies: options.secure_cookies,
        session_idle_s: limits.session_idle.as_secs(),
        rates: Arc::new(RateLimiter::keyed(
            Quota::per_second(limits.rate_per_client).allow_burst(limits.burst_per_client),
        )),
        request_timeout: limits.request_timeout,
        members_only: options.members_only,
    };
    forget_idle_clients(&state.rates);
    forget_idle_clients(&state.signins);
    let shed = ServiceBuilder::new()
        .layer(HandleErrorLayer::new(|uri: Uri, _: BoxError| async move {
            HttpError::overloaded("requests in progress").as_format(Format::for_path(uri.path()))
        }))
        .load_shed()
        .layer(GlobalConcurrencyLimitLayer::new(limits.max_in_flight));
    Router::new()
        .route("/", get(availability_page))
        .route("/envs/{realm}/{name}", get(env_page))
        .route("/envs/{realm}/{name}/camera.png", get(camera_thumbnail))
        .route("/envs/{realm}/{name}/overhead.png", get(overhead_thumbnail))
        .route("/events", get(events::html))
        .route("/api/envs", get(api::envs))
        .route("/api/envs/{realm}/{name}", get(api::env))
        .route(
            "/api/envs/{realm}/{name}/leaderboard",
            get(api::leaderboard),
        )
        .route(
            "/api/envs/{realm}/{name}/bookings",
            get(account::bookings_json),
        )
        .route("/api/events", get(events::json))
        .route("/account", get(account::account))
        .route("/account/signin", post(account::signin))
        .route("/account/signout", post(account::signout))
        .route("/bookings", get(account::bookings_index))
        .route("/console", get(console::console))
        .route("/console/estop", post(console::estop))
        .route("/console/maintenance", post(console::maintenance))
        .route("/console/lease", post(console::revoke_lease))
        .route(
            "/envs/{realm}/{name}/bookings",
            get(account::bookings_page).post(account::make_booking),
        )
        .route(
            "/envs/{realm}/{name}/bookings/{id}/cancel",
            post(account::cancel_booking),
        )
        .route(
            "/envs/{realm}/{name}/experiments",
            get(account::experiments_page),
        )
        .route(
            "/envs/{realm}/{name}/experiments/{id}",
            get(account::experiment_page),
        )
        .route("/static/style.css", get(style))
        .route("/static/app.js", get(script))
        .route("/healthz", get(|| async { "ok" }))
        .fallback(not_found)
        .method_not_allowed_fallback(method_not_allowed)
        .layer(middleware::from_fn_with_state(state.clone(), members_only))
        .layer(middleware::from_fn_with_state(state.clone(), deadline))
        .layer(shed)
        .layer(middleware::from_fn_with_state(state.clone(), rate_limit))
        .layer(middleware::from_fn(security_headers))
        .with_state(state)
}

async fn availability_page(State(state): State<AppState>) -> Html<String> {
    Html(pages::availability(&state.discovery.snapshot()).into_string())
}

async fn env_page(
    State(state): State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
) -> Result<Html<String>, HttpError> {
    let id = api::env_from_path(path)?;
    let snapshot = state.discovery.snapshot();
    let Some(env) = snapshot.env(&id) else {
        return Err(api::unknown_env(&id));
    };
    // The env's state is shown whatever the leaderboard query gives.
    let board = api::fetch_leaderboard(&state, &id).await;
    let board = board.as_ref().map_err(|e| e.message.as_str());
    Ok(Html(
        pages::env_page(&snapshot, env, board, state.rerun_url.as_deref()).into_string(),
    ))
}

async fn camera_thumbnail(
    state: State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
) -> Result<Response, HttpError> {
    thumbnail(state, path, View::Camera).await
}

async fn overhead_thumbnail(
    state: State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
) -> Result<Response, HttpError> {
    thumbnail(state, path, View::Overhead).await
}

/// A known env's thumbnail as `image/png` (404 with the reason when none).
async fn thumbnail(
    State(state): State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
    view: View,
) -> Result<Response, HttpError> {
    let id = api::env_from_path(path)?;
    let snapshot = state.discovery.snapshot();
    if snapshot.env(&id).is_none() {
        return Err(api::unknown_env(&id));
    }
    state.thumbnails.retain(|env| snapshot.env(env).is_some());
    match state.thumbnails.get(&id, view).await {
        Ok(thumbnail) => Ok((
            [
                (header::CONTENT_TYPE, "image/png"),
                (header::CACHE_CONTROL, "no-store"),
            ],
            thumbnail.png.as_ref().clone(),
        )
            .into_response()),
        Err(e @ (ThumbnailError::NoFrame(..) | ThumbnailError::Unusable(_))) => {
            Err(HttpError::not_found(format!("{id}: {e}")))
        }
        Err(e) => Err(HttpError::unavailable(format!("{id}: {e}"))),
    }
}

async fn style() -> Response {
    asset("text/css; charset=utf-8", pages::STYLE_CSS)
}

async fn script() -> Response {
    asset("text/javascript; charset=utf-8", pages::APP_JS)
}

fn asset(content_type: &'static str, body: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CACHE_CONTROL, "public, max-age=300"),
        ],
        body,
    )
        .into_response()
}

async fn not_found(uri: Uri) -> HttpError {
    HttpError::not_found(format!("no such page: {}", uri.path()))
        .as_format(Format::for_path(uri.path()))
}

async fn method_not_allowed(uri: Uri) -> HttpError {
    HttpError::method_not_allowed().as_format(Format::for_path(uri.path()))
}

async fn rate_limit(State(state): State<AppState>, request: Request, next: Next) -> Response {
    // Requests that did not come through `serve` (none in production)
    // share one budget.
    let ip = request
        .extensions()
        .get::<PeerAddr>()
        .map_or(IpAddr::from([0, 0, 0, 0]), |peer| peer.0.ip());
    if let Err(not_until) = state.rates.check_key(&ip) {
        let wait = not_until.wait_time_from(DefaultClock::default().now());
        let seconds = wait.as_secs() + u64::from(wait.subsec_nanos() > 0);
        return HttpError::rate_limited(seconds.max(1))
            .as_format(Format::for_path(request.uri().path()))
            .into_response();
    }
    next.run(request).await
}

/// What a members-only site still shows to everyone: how to sign in.
const OPEN_TO_ALL: [&str; 6] = [
    "/account",
    "/account/signin",
    "/account/signout",
    "/static/style.css",
    "/static/app.js",
    "/healthz",
];

/// With [`WebOptions::members_only`], everything else needs a session.
async fn members_only(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let path = request.uri().path();
    if !state.members_only
        || OPEN_TO_ALL.contains(&path)
        || state.sessions.from_headers(request.headers()).is_some()
    {
        return next.run(request).await;
    }
    let format = Format::for_path(path);
    if format == Format::Html {
        let page = crate::account_pages::signin_needed("This lab's pages");
        return (StatusCode::UNAUTHORIZED, Html(page.into_string())).into_response();
    }
    HttpError::unauthorized("this lab shows its state to signed-in users only: sign in at /account")
        .as_format(format)
        .into_response()
}

async fn deadline(State(state): State<AppState>, request: Request, next: Next) -> Response {
    let format = Format::for_path(request.uri().path());
    match tokio::time::timeout(state.request_timeout, next.run(request)).await {
        Ok(response) => response,
        Err(_) => HttpError::timeout(format!(
            "the request took longer than {} s",
            state.request_timeout.as_secs_f64()
        ))
        .as_format(format)
        .into_response(),
    }
}

/// Headers on every response: no inline code, forms only to this site, no
/// framing, no sniffing, no referrer to other sites (same-site requests
/// keep theirs, so a form POST carries its `Origin`); pages are never
/// cached (they are live, and some are a signed-in user's).
async fn security_headers(request: Request, next: Next) -> Response {
    let mut response = next.run(request).await;
    let headers = response.headers_mut();
    for (name, value) in [
        (
            header::CONTENT_SECURITY_POLICY,
            "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self'; \
             connect-src 'self'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'",
        ),
        (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
        (header::X_FRAME_OPTIONS, "DENY"),
        (header::REFERRER_POLICY, "same-origin"),
    ] {
        headers.insert(name, HeaderValue::from_static(value));
    }
    headers
        .entry(header::CACHE_CONTROL)
        .or_insert(HeaderValue::from_static("no-store"));
    response
}

/// Answers connections from `listener` with `app` until `shutdown`
/// resolves; open connections are then closed.
pub async fn serve(
    listener: TcpListener,
    app: Router,
    limits: Limits,
    shutdown: impl Future<Output = ()>,
) {
    let places = Arc::new(Semaphore::new(limits.max_connections));
    let mut connections = tokio::task::JoinSet::new();
    tokio::pin!(shutdown);
    loop {
        // A place first: at the limit, new connections wait in the backlog.
        let place = tokio::select! {
            place = Arc::clone(&places).acquire_owned() => place,
            () = &mut shutdown => break,
        };
        let Ok(place) = place else { break };
        let (stream, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(accepted) => accepted,
                Err(e) => {
                    // Out of file descriptors and the like: pause rather
                    // than spin.
                    tracing::warn!("accept failed: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
            () = &mut shutdown => break,
        };
        let app = app.clone();
        connections.spawn(async move {
            let _place = place;
            let service =
                hyper::service::service_fn(move |mut request: Request<hyper::body::Incoming>| {
                    request.extensions_mut().insert(PeerAddr(peer));
                    tower::ServiceExt::oneshot(app.clone(), request)
                });
            let connection = hyper::server::conn::http1::Builder::new()
                .timer(TokioTimer::new())
                .header_read_timeout(limits.header_read_timeout)
                .serve_connection(TokioIo::new(stream), service);
            if let Err(e) = connection.await {
                tracing::debug!(%peer, "connection ended: {e}");
            }
        });
        while connections.try_join_next().is_some() {}
    }
    connections.abort_all();
}

/// Forgets idle client addresses now and then, so the rate limiter's table
/// stays as small as the set of recent clients; ends with the router.
fn forget_idle_clients(rates: &Arc<DefaultKeyedRateLimiter<IpAddr>>) {
    let rates = Arc::downgrade(rates);
    tokio::spawn(async move {
        loop {
            tokio::time::sleep(Duration::from_secs(60)).await;
            let Some(rates) = rates.upgrade() else { return };
            rates.retain_recent();
        }
    });
}
