//! The signed-in side's handlers: sign-in and sign-out, each env's
//! bookings (list for anyone; book and cancel for the signed in), a
//! user's experiments and one experiment. Every rule is the controller's:
//! the token, the slot rules, overlaps and ownership are checked where
//! the CLI's requests are checked, and its typed refusal is shown as is.

use std::net::IpAddr;

use axum::extract::rejection::PathRejection;
use axum::extract::{Path, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use governor::clock::{Clock, DefaultClock};
use offworld_runtime::keys::{EnvId, Realm};
use offworld_runtime::msg::{
    AdminReply, AdminRequest, Booking, BookingRequest, EpisodeRecordEntry, ExperimentsRequest,
};
use offworld_runtime::ErrorCode;
use serde::Serialize;

use crate::account_pages::{self as pages, Notice, Reader, SlotForm};
use crate::api::{self, json_response, parse_env, unknown_env};
use crate::discovery::now_unix_ms;
use crate::error::{Format, HttpError};
use crate::model::EnvView;
use crate::server::{AppState, PeerAddr};
use crate::session::{
    self, check_same_origin, field, parse_form, same_secret, Session, MAX_TOKEN_LEN,
    SESSION_COOKIE, SIGNIN_COOKIE,
};

/// Largest form accepted.
const MAX_FORM_BYTES: usize = 8 * 1024;
/// Answers fetched for one experiment page at most, each of up to
/// [`offworld_runtime::msg::EXPERIMENT_EPISODES_PER_REPLY`] episodes.
const MAX_EPISODE_PAGES: u64 = 4;
/// How long the sign-in form's CSRF cookie lives, s.
const SIGNIN_COOKIE_AGE_S: u64 = 3600;

pub(crate) fn reader(session: Option<&Session>) -> Reader<'_> {
    session.map_or(Reader::ANONYMOUS, |s| Reader {
        csrf: Some(&s.csrf),
        user: Some(&s.user),
        operator: s.operator,
    })
}

pub(crate) fn see_other(location: &str) -> Response {
    let mut response = StatusCode::SEE_OTHER.into_response();
    if let Ok(value) = HeaderValue::from_str(location) {
        response.headers_mut().insert(header::LOCATION, value);
    }
    response
}

pub(crate) fn html_with(status: StatusCode, markup: maud::Markup) -> Response {
    (status, Html(markup.into_string())).into_response()
}

/// The known env `path` names (404 otherwise).
pub(crate) fn known_env(
    state: &AppState,
    realm: &str,
    name: &str,
) -> Result<(EnvId, EnvView), HttpError> {
    let id = parse_env(realm, name)?;
    let snapshot = state.discovery.snapshot();
    let view = snapshot.env(&id).cloned().ok_or_else(|| unknown_env(&id))?;
    Ok((id, view))
}

fn env_path(
    path: Result<Path<(String, String)>, PathRejection>,
) -> Result<(String, String), HttpError> {
    path.map(|Path(p)| p)
        .map_err(|_| HttpError::not_found("no such page: the path is not a valid env id"))
}

/// The checks every POST passes before anything else: same origin, a
/// form of bounded size.
pub(crate) async fn post_form(
    request: Request,
) -> Result<(HeaderMap, Vec<(String, String)>), HttpError> {
    let (parts, body) = request.into_parts();
    check_same_origin(&parts.headers)
        .map_err(|why| HttpError::forbidden(format!("refused: {why}")))?;
    let bytes = axum::body::to_bytes(body, MAX_FORM_BYTES)
        .await
        .map_err(|_| HttpError::bad_request(format!("the form is over {MAX_FORM_BYTES} bytes")))?;
    Ok((parts.headers, parse_form(&bytes)))
}

/// The session a POST acts for: signed in, with its CSRF token.
pub(crate) fn acting_session(
    state: &AppState,
    headers: &HeaderMap,
    form: &[(String, String)],
) -> Result<Session, HttpError> {
    let session = state.sessions.from_headers(headers).ok_or_else(|| {
        HttpError::unauthorized("you are not signed in (or your session lapsed): sign in first")
    })?;
    match field(form, "csrf") {
        Some(csrf) if same_secret(csrf, &session.csrf) => Ok(session),
        _ => Err(HttpError::forbidden(
            "refused: the form's CSRF token is missing or stale; reload the page and retry",
        )),
    }
}

// ---------------------------------------------------------------- sign-in

/// `GET /account`: the sign-in form, or the signed-in user's page.
pub async fn account(State(state): State<AppState>, headers: HeaderMap) -> Response {
    match state.sessions.from_headers(&headers) {
        Some(session) => html_with(
            StatusCode::OK,
            pages::account_page(&state.discovery.snapshot(), reader(Some(&session)), None),
        ),
        None => signin_form(&state, &headers, StatusCode::OK, None),
    }
}

/// The sign-in form with its CSRF token (the cookie's, or a new one).
fn signin_form(
    state: &AppState,
    headers: &HeaderMap,
    status: StatusCode,
    notice: Option<Notice>,
) -> Response {
    let csrf = session::cookie(headers, SIGNIN_COOKIE)
        .filter(|c| c.len() == 64 && c.bytes().all(|b| b.is_ascii_hexdigit()))
        .map_or_else(session::random_token, str::to_owned);
    let mut response = html_with(status, pages::signin_page(&csrf, notice.as_ref()));
    response.headers_mut().append(
        header::SET_COOKIE,
        session::set_cookie(
            SIGNIN_COOKIE,
            &csrf,
            SIGNIN_COOKIE_AGE_S,
            state.secure_cookies,
        ),
    );
    response
}

/// `POST /account/signin`: checks the pasted token with a controller and
/// opens a session.
pub async fn signin(State(state): State<AppState>, request: Request) -> Response {
    let ip = request
        .extensions()
        .get::<PeerAddr>()
        .map_or(IpAddr::from([0, 0, 0, 0]), |peer| peer.0.ip());
    if let Err(not_until) = state.signins.check_key(&ip) {
        let wait = not_until.wait_time_from(DefaultClock::default().now());
        return HttpError::rate_limited(wait.as_secs().max(1)).into_response();
    }
    let (headers, form) = match post_form(request).await {
        Ok(posted) => posted,
        Err(e) => return e.into_response(),
    };
    let cookie = session::cookie(&headers, SIGNIN_COOKIE).unwrap_or("");
    let posted = field(&form, "csrf").unwrap_or("");
    if cookie.is_empty() || !same_secret(cookie, posted) {
        return HttpError::forbidden(
            "refused: the sign-in form's CSRF token is missing or stale; reload the page and retry",
        )
        .into_response();
    }
    let token = field(&form, "token").unwrap_or("").trim().to_owned();
    let refuse = |status, message: String| {
        signin_form(&state, &headers, status, Some(Notice::Refused(message)))
    };
    if token.is_empty() {
        return refuse(
            StatusCode::BAD_REQUEST,
            "Paste your access token to sign in.".into(),
        );
    }
    if token.len() > MAX_TOKEN_LEN {
        return refuse(
            StatusCode::UNAUTHORIZED,
            format!("Sign-in refused: access tokens have at most {MAX_TOKEN_LEN} characters."),
        );
    }
    match identify(&state, &token).await {
        Ok(who) => {
            let session = state.sessions.create(token, who.user, who.operator);
            let mut response = see_other("/account");
            let headers = response.headers_mut();
            headers.append(
                header::SET_COOKIE,
                session::set_cookie(
                    SESSION_COOKIE,
                    &session.id,
                    state.session_idle_s,
                    state.secure_cookies,
                ),
            );
            headers.append(
                header::SET_COOKIE,
                session::set_cookie(SIGNIN_COOKIE, "", 0, state.secure_cookies),
            );
            response
        }
        Err(e) => refuse(e.status, e.message),
    }
}

/// Asks a controller (real envs' first) whose `token` is.
pub(crate) async fn identify(state: &AppState, token: &str) -> Result<AdminReply, HttpError> {
    let snapshot = state.discovery.snapshot();
    let mut candidates: Vec<EnvId> = snapshot
        .envs
        .iter()
        .filter(|e| e.components.iter().any(|c| c == "controller"))
        .filter_map(|e| parse_env(&e.realm, &e.name).ok())
        .collect();
    candidates.sort_by_key(|id| id.realm() != Realm::Real);
    candidates.truncate(3);
    identify_with(state, token, &candidates, "Sign-in refused").await
}

/// Asks the controllers of `envs`, in turn, whose `token` is; a refusal
/// says `refused` and the controller's reason.
pub(crate) async fn identify_with(
    state: &AppState,
    token: &str,
    envs: &[EnvId],
    refused: &str,
) -> Result<AdminReply, HttpError> {
    let mut last = HttpError::unavailable(
        "no controller of the deployment is reachable to check your token: retry shortly",
    );
    let request = AdminRequest::Identify {
        token: token.to_owned(),
    };
    for id in envs {
        match state.discovery.admin(id, &request).await {
            Ok(who) => return Ok(who),
            Err(e) if e.code == ErrorCode::Unauthorized => {
                return Err(HttpError::unauthorized(format!(
                    "{refused} by the controller of {id}: {}",
                    e.message
                )))
            }
            Err(e) => last = HttpError::from_wire(&format!("checking your token with {id}"), &e),
        }
    }
    Err(last)
}

/// `POST /account/signout`: forgets the session.
pub async fn signout(State(state): State<AppState>, request: Request) -> Response {
    let (headers, form) = match post_form(request).await {
        Ok(posted) => posted,
        Err(e) => return e.into_response(),
    };
    if state.sessions.from_headers(&headers).is_some() {
        match acting_session(&state, &headers, &form) {
            Ok(session) => state.sessions.remove(&session.id),
            Err(e) => return e.into_response(),
        }
    }
    let mut response = see_other("/account");
    response.headers_mut().append(
        header::SET_COOKIE,
        session::set_cookie(SESSION_COOKIE, "", 0, state.secure_cookies),
    );
    response
}

// --------------------------------------------------------------- bookings

/// `GET /bookings`: every env and its next slot.
pub async fn bookings_index(State(state): State<AppState>) -> Html<String> {
    Html(pages::bookings_index(&state.discovery.snapshot()).into_string())
}

async fn list_slots(state: &AppState, id: &EnvId) -> Result<Vec<Booking>, HttpError> {
    state
        .discovery
        .book(
            id,
            &BookingRequest::List {
                from_unix_ms: now_unix_ms(),
            },
        )
        .await
        .map(|b| b.bookings)
        .map_err(|e| HttpError::from_wire(&format!("the bookings of {id}"), &e))
}

/// The form's defaults: the next full hour (UTC; the script puts the
/// reader's own zone in), an hour long.
fn default_form() -> SlotForm {
    let hour = 3_600_000;
    let next = (now_unix_ms() / hour + 1) * hour;
    SlotForm {
        start: datetime_local(next),
        minutes: "60".into(),
        kept: false,
    }
}

/// `YYYY-MM-DDTHH:MM`, UTC.
fn datetime_local(unix_ms: i64) -> String {
    let t = std::time::UNIX_EPOCH
        + std::time::Duration::from_millis(u64::try_from(unix_ms).unwrap_or(0));
    humantime::format_rfc3339_seconds(t)
        .to_string()
        .chars()
        .take(16)
        .collect()
}

async fn render_bookings(
    state: &AppState,
    id: &EnvId,
    env: &EnvView,
    session: Option<&Session>,
    form: &SlotForm,
    status: StatusCode,
    notice: Option<Notice>,
) -> Response {
    let slots = list_slots(state, id).await;
    let slots = slots.as_deref().map_err(|e| e.message.as_str());
    html_with(
        status,
        pages::bookings_page(env, slots, reader(session), form, notice.as_ref()),
    )
}

/// `GET /envs/<realm>/<name>/bookings`.
pub async fn bookings_page(
    State(state): State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
    uri: axum::http::Uri,
    headers: HeaderMap,
) -> Result<Response, HttpError> {
    let (realm, name) = env_path(path)?;
    let (id, env) = known_env(&state, &realm, &name)?;
    let session = state.sessions.from_headers(&headers);
    let query = parse_form(uri.query().unwrap_or("").as_bytes());
    let notice = if let Some(made) = field(&query, "made") {
        Some(Notice::Done(format!("Booked: slot #{made}.")))
    } else {
        field(&query, "cancelled").map(|id| Notice::Done(format!("Cancelled slot #{id}.")))
    };
    // Only digits are echoed (the notice is escaped anyway).
    let notice = notice.filter(|_| {
        query
            .iter()
            .all(|(_, v)| v.bytes().all(|b| b.is_ascii_digit()))
    });
    Ok(render_bookings(
        &state,
        &id,
        &env,
        session.as_ref(),
        &default_form(),
        StatusCode::OK,
        notice,
    )
    .await)
}

/// The slot a booking form asks for, `[start, end)` in Unix ms.
fn slot_from(form: &[(String, String)]) -> Result<(i64, i64), String> {
    let start = match field(form, "start_unix_ms").map(str::trim) {
        Some(ms) if !ms.is_empty() => ms
            .parse::<i64>()
            .map_err(|_| format!("the start `{ms}` is not a time"))?,
        _ => {
            let text = field(form, "start").unwrap_or("").trim();
            if text.is_empty() {
                return Err("choose when the slot starts".into());
            }
            let full = if text.len() == 16 {
                format!("{text}:00")
            } else {
                text.to_owned()
            };
            let t = humantime::parse_rfc3339_weak(&full).map_err(|_| {
                format!("the start `{text}` is not a date and time (YYYY-MM-DDTHH:MM)")
            })?;
            let ms = t
                .duration_since(std::time::UNIX_EPOCH)
                .map_err(|_| format!("the start `{text}` is before 1970"))?
                .as_millis();
            i64::try_from(ms).map_err(|_| format!("the start `{text}` is too far ahead"))?
        }
    };
    let minutes_text = field(form, "minutes").unwrap_or("").trim();
    let minutes: i64 = minutes_text
        .parse()
        .ok()
        .filter(|m| *m > 0)
        .ok_or_else(|| format!("the length `{minutes_text}` is not a whole number of minutes"))?;
    let end = minutes
        .checked_mul(60_000)
        .and_then(|ms| start.checked_add(ms))
        .ok_or_else(|| "the slot ends too far ahead".to_owned())?;
    Ok((start, end))
}

/// `POST /envs/<realm>/<name>/bookings`: books a slot, as
/// `offworld gym book` does.
pub async fn make_booking(
    State(state): State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
    request: Request,
) -> Result<Response, HttpError> {
    let (realm, name) = env_path(path)?;
    let (headers, form) = post_form(request).await?;
    let session = acting_session(&state, &headers, &form)?;
    let (id, env) = known_env(&state, &realm, &name)?;
    let kept = SlotForm {
        start: field(&form, "start")
            .unwrap_or("")
            .chars()
            .take(32)
            .collect(),
        minutes: field(&form, "minutes")
            .unwrap_or("")
            .chars()
            .take(12)
            .collect(),
        kept: true,
    };
    let refused = |status, message: String| {
        let kept = kept.clone();
        let (state, id, env, session) = (&state, &id, &env, &session);
        async move {
            render_bookings(
                state,
                id,
                env,
                Some(session),
                &kept,
                status,
                Some(Notice::Refused(message)),
            )
            .await
        }
    };
    let (start_unix_ms, end_unix_ms) = match slot_from(&form) {
        Ok(slot) => slot,
        Err(why) => {
            return Ok(refused(StatusCode::BAD_REQUEST, format!("Not booked: {why}.")).await)
        }
    };
    let request = BookingRequest::Make {
        token: session.token.clone(),
        start_unix_ms,
        end_unix_ms,
    };
    match state.discovery.book(&id, &request).await {
        Ok(made) => {
            let Some(slot) = made.bookings.first() else {
                return Err(HttpError::internal(
                    "the controller answered the booking without its slot",
                ));
            };
            Ok(see_other(&format!(
                "/envs/{realm}/{name}/bookings?made={}",
                slot.id
            )))
        }
        Err(e) => {
            let e = HttpError::from_controller("Not booked", &e);
            Ok(refused(e.status, e.message).await)
        }
    }
}

/// `POST /envs/<realm>/<name>/bookings/<id>/cancel`: cancels one of the
/// user's slots, as `offworld gym cancel-booking` does (the
/// controller refuses someone else's).
pub async fn cancel_booking(
    State(state): State<AppState>,
    path: Result<Path<(String, String, String)>, PathRejection>,
    request: Request,
) -> Result<Response, HttpError> {
    let Ok(Path((realm, name, booking))) = path else {
        return Err(HttpError::not_found("no such page"));
    };
    let booking: i64 = booking
        .parse()
        .map_err(|_| HttpError::not_found(format!("no booking `{booking}`")))?;
    let (headers, form) = post_form(request).await?;
    let session = acting_session(&state, &headers, &form)?;
    let (id, env) = known_env(&state, &realm, &name)?;
    let request = BookingRequest::Cancel {
        token: session.token.clone(),
        id: booking,
    };
    match state.discovery.book(&id, &request).await {
        Ok(_) => Ok(see_other(&format!(
            "/envs/{realm}/{name}/bookings?cancelled={booking}"
        ))),
        Err(e) => {
            let e = HttpError::from_controller("Not cancelled", &e);
            Ok(render_bookings(
                &state,
                &id,
                &env,
                Some(&session),
                &default_form(),
                e.status,
                Some(Notice::Refused(e.message)),
            )
            .await)
        }
    }
}

#[derive(Serialize)]
struct SlotsJson<'a> {
    env: String,
    bookings: &'a [Booking],
}

/// `GET /api/envs/<realm>/<name>/bookings`: the env's slots that have not
/// ended, earliest first (public, as the CLI's `bookings`).
pub async fn bookings_json(
    State(state): State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
) -> Result<Response, HttpError> {
    let json = |e: HttpError| e.as_format(Format::Json);
    let id = api::env_from_path(path).map_err(json)?;
    if state.discovery.snapshot().env(&id).is_none() {
        return Err(json(unknown_env(&id)));
    }
    let slots = list_slots(&state, &id).await.map_err(json)?;
    Ok(json_response(
        StatusCode::OK,
        &SlotsJson {
            env: id.to_string(),
            bookings: &slots,
        },
    ))
}

// ------------------------------------------------------------ experiments

fn signin_needed(what: &str) -> Response {
    html_with(StatusCode::UNAUTHORIZED, pages::signin_needed(what))
}

/// `GET /envs/<realm>/<name>/experiments`: the signed-in user's
/// experiments on the env.
pub async fn experiments_page(
    State(state): State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
    headers: HeaderMap,
) -> Result<Response, HttpError> {
    let (realm, name) = env_path(path)?;
    let (id, env) = known_env(&state, &realm, &name)?;
    let Some(session) = state.sessions.from_headers(&headers) else {
        return Ok(signin_needed("Listing your experiments"));
    };
    let request = ExperimentsRequest::List {
        token: session.token.clone(),
    };
    let listed = state
        .discovery
        .experiments(&id, &request)
        .await
        .map_err(|e| HttpError::from_controller(&format!("your experiments on {id}"), &e))?;
    Ok(html_with(
        StatusCode::OK,
        pages::experiments_page(&env, &listed.experiments),
    ))
}

/// `GET /envs/<realm>/<name>/experiments/<id>`: one experiment with its
/// learning curve and episodes (its owner's, or an operator's view).
pub async fn experiment_page(
    State(state): State<AppState>,
    path: Result<Path<(String, String, String)>, PathRejection>,
    headers: HeaderMap,
) -> Result<Response, HttpError> {
    let Ok(Path((realm, name, experiment))) = path else {
        return Err(HttpError::not_found("no such page"));
    };
    let experiment_id: i64 = experiment
        .parse()
        .map_err(|_| HttpError::not_found(format!("no experiment `{experiment}`")))?;
    let (id, env) = known_env(&state, &realm, &name)?;
    let Some(session) = state.sessions.from_headers(&headers) else {
        return Ok(signin_needed("Showing an experiment"));
    };
    let what = format!("experiment {experiment_id} on {id}");
    let mut episodes: Vec<EpisodeRecordEntry> = Vec::new();
    let mut record = None;
    let mut from_episode = 0;
    let mut truncated = false;
    for page in 0..MAX_EPISODE_PAGES {
        let request = ExperimentsRequest::Show {
            token: session.token.clone(),
            experiment_id,
            from_episode,
        };
        let answer = state
            .discovery
            .experiments(&id, &request)
            .await
            .map_err(|e| HttpError::from_controller(&what, &e))?;
        if record.is_none() {
            record = answer.experiments.into_iter().next();
        }
        let next = answer.episodes.last().and_then(|e| e.index.checked_add(1));
        episodes.extend(answer.episodes);
        match next {
            Some(next) if answer.more && next > from_episode => {
                from_episode = next;
                truncated = page + 1 == MAX_EPISODE_PAGES;
            }
            _ => break,
        }
    }
    let record = record
        .ok_or_else(|| HttpError::internal(format!("the controller answered {what} without it")))?;
    Ok(html_with(
        StatusCode::OK,
        pages::experiment_page(&env, &record, &episodes, truncated),
    ))
}
