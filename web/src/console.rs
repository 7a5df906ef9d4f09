//! The operator console's handlers (`/console`, operators only): the
//! site's and each env's e-stop (engage; release only with a confirmation
//! that the enclosure is clear), maintenance with a reason and an
//! expected return, and revoking a lease. Every action goes where the
//! CLI's goes: an e-stop is pressed on the deployment as
//! `env_controller estop` presses it (who acknowledged is shown), and
//! maintenance and revocation are the controller's operator requests,
//! sent with the signed-in operator's token and checked there again.

use axum::extract::{Request, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use offworld_client::operator::{EStopScope, PressError, PressReport};
use offworld_runtime::keys::{EnvId, Realm};
use offworld_runtime::msg::AdminRequest;

use crate::account::{acting_session, html_with, identify_with, known_env, post_form};
use crate::account_pages::{signin_needed, Notice};
use crate::console_pages;
use crate::discovery::now_unix_ms;
use crate::error::{HttpError, Kind};
use crate::server::AppState;
use crate::session::{field, Session};

/// Longest reason or maintenance message accepted, characters (the
/// controller's own limit is larger: the console adds who pressed).
pub const MAX_REASON_CHARS: usize = 200;
/// How long a press waits for the controllers' statuses to show it.
const SETTLE_WITHIN: std::time::Duration = std::time::Duration::from_secs(1);
/// The furthest expected return of a maintenance, minutes (a week).
pub const MAX_BACK_MINUTES: i64 = 7 * 24 * 60;

/// The page of a signed-in user who is not an operator.
fn not_an_operator(user: &str) -> Response {
    let e = HttpError::forbidden(format!(
        "The operator console is for operators: {user} is not one."
    ));
    html_with(e.status, console_pages::refused_page(&e.message))
}

/// The console with `notice` (and the acknowledgements of a press).
fn render(
    state: &AppState,
    session: &Session,
    status: StatusCode,
    notice: Notice,
    report: Option<&PressReport>,
) -> Response {
    html_with(
        status,
        console_pages::console(&state.discovery.snapshot(), session, Some(&notice), report),
    )
}

/// `GET /console`.
pub async fn console(State(state): State<AppState>, headers: HeaderMap) -> Response {
    let Some(session) = state.sessions.from_headers(&headers) else {
        return html_with(
            StatusCode::UNAUTHORIZED,
            signin_needed("The operator console"),
        );
    };
    if !session.operator {
        return not_an_operator(&session.user);
    }
    html_with(
        StatusCode::OK,
        console_pages::console(&state.discovery.snapshot(), &session, None, None),
    )
}

/// The checks every console action passes first: same origin, a signed-in
/// session with its CSRF token, an operator.
async fn operator_form(
    state: &AppState,
    request: Request,
) -> Result<(Session, Vec<(String, String)>), Response> {
    let (headers, form) = post_form(request)
        .await
        .map_err(IntoResponse::into_response)?;
    let session = acting_session(state, &headers, &form).map_err(IntoResponse::into_response)?;
    if !session.operator {
        return Err(not_an_operator(&session.user));
    }
    Ok((session, form))
}

/// The form's `name` field, trimmed: present, at most
/// [`MAX_REASON_CHARS`] characters, no control characters.
fn said<'a>(form: &'a [(String, String)], name: &str, what: &str) -> Result<&'a str, String> {
    let text = field(form, name).unwrap_or("").trim();
    if text.is_empty() {
        return Err(format!(
            "say {what}: it is shown to everyone and kept with the change"
        ));
    }
    if text.chars().count() > MAX_REASON_CHARS {
        return Err(format!("{what} has at most {MAX_REASON_CHARS} characters"));
    }
    if text.chars().any(char::is_control) {
        return Err(format!("{what} holds a control character"));
    }
    Ok(text)
}

/// The env a form names, known to this service.
fn form_env(state: &AppState, form: &[(String, String)]) -> Result<EnvId, String> {
    let text = field(form, "env").unwrap_or("");
    let (realm, name) = text
        .split_once('/')
        .ok_or_else(|| format!("`{text}` is not an env id such as sim/monolith-0"))?;
    known_env(state, realm, name)
        .map(|(id, _)| id)
        .map_err(|e| e.message)
}

/// The controllers whose word on a user's role counts for `scope`: the
/// env's own; for the site, the real envs' (a sim farm's decides only
/// where the deployment has no real env), at most three.
fn authorities(state: &AppState, scope: &EStopScope) -> Vec<EnvId> {
    if let EStopScope::Env(env) = scope {
        return vec![env.clone()];
    }
    let snapshot = state.discovery.snapshot();
    let controlled: Vec<EnvId> = snapshot
        .envs
        .iter()
        .filter(|e| e.components.iter().any(|c| c == "controller"))
        .filter_map(|e| e.id.parse().ok())
        .collect();
    let real: Vec<EnvId> = controlled
        .iter()
        .filter(|id| id.realm() == Realm::Real)
        .cloned()
        .collect();
    let mut chosen = if real.is_empty() { controlled } else { real };
    chosen.truncate(3);
    chosen
}

/// How a press is told: who acknowledged, and when.
fn acknowledged(report: &PressReport) -> String {
    let who: Vec<String> = report
        .acknowledged
        .iter()
        .map(|a| format!("{} of {}", a.component, a.env))
        .collect();
    if who.is_empty() {
        "nobody acknowledged".into()
    } else {
        format!("acknowledged by {}", who.join(", "))
    }
}

/// `POST /console/estop`: presses or releases the site's or an env's
/// e-stop. A release needs the `confirm` box ticked.
pub async fn estop(State(state): State<AppState>, request: Request) -> Response {
    let (session, form) = match operator_form(&state, request).await {
        Ok(posted) => posted,
        Err(page) => return page,
    };
    let refused =
        |status, why: String| render(&state, &session, status, Notice::Refused(why), None);
    let scope = match field(&form, "scope") {
        Some("site") => EStopScope::Site,
        Some("env") => match form_env(&state, &form) {
            Ok(env) => EStopScope::Env(env),
            Err(why) => return refused(StatusCode::NOT_FOUND, format!("Not pressed: {why}.")),
        },
        _ => {
            return refused(
                StatusCode::BAD_REQUEST,
                "Not pressed: say which e-stop, the site's or an env's.".into(),
            )
        }
    };
    let (engage, verb) = match field(&form, "action") {
        Some("engage") => (true, "engaged"),
        Some("release") => (false, "released"),
        _ => {
            return refused(
                StatusCode::BAD_REQUEST,
                "Not pressed: the action is engage or release.".into(),
            )
        }
    };
    let reason = match said(&form, "reason", "the reason") {
        Ok(reason) => reason,
        Err(why) => return refused(StatusCode::BAD_REQUEST, format!("Not {verb}: {why}.")),
    };
    if !engage && field(&form, "confirm") != Some("yes") {
        return refused(
            StatusCode::BAD_REQUEST,
            "Not released: tick the box that says the enclosure is clear of people and objects."
                .into(),
        );
    }
    // The role may have changed since sign-in: asked again of the
    // controllers that answer for the scope.
    let authorities = authorities(&state, &scope);
    let refusal = format!("Not {verb}: refused");
    match identify_with(&state, &session.token, &authorities, &refusal).await {
        Ok(who) if who.operator => {}
        Ok(who) => return not_an_operator(&who.user),
        Err(e) if e.kind == Kind::Unauthorized => return refused(e.status, e.message),
        // Stopping never waits for a controller: an engage goes out on the
        // role the session was signed in with; a release waits.
        Err(_) if engage => {}
        Err(e) => return refused(e.status, format!("Not {verb}: {}", e.message)),
    }
    let what = match &scope {
        EStopScope::Site => "the site".to_owned(),
        EStopScope::Env(env) => env.to_string(),
    };
    let reason = format!("{reason} ({} via the web console)", session.user);
    tracing::warn!(operator = %session.user, %what, %reason, engage, "e-stop pressed from the console");
    let pressed = state.discovery.press_estop(&scope, engage, &reason).await;
    // The latches as the controllers now report them, shown on the page
    // (a moment behind the acknowledgements).
    state
        .discovery
        .settled(SETTLE_WITHIN, |snapshot| {
            snapshot.envs.iter().all(|env| {
                let latch = match &scope {
                    EStopScope::Site => &env.estop.site,
                    EStopScope::Env(id) if env.id == id.to_string() => &env.estop.env,
                    EStopScope::Env(_) => return true,
                };
                env.task.is_none() || latch.engaged == engage
            })
        })
        .await;
    match pressed {
        Ok(report) => {
            tracing::warn!(operator = %session.user, %what, engage, "{}", acknowledged(&report));
            let told = format!("E-stop {verb} on {what}: {}.", acknowledged(&report));
            render(
                &state,
                &session,
                StatusCode::OK,
                Notice::Done(told),
                Some(&report),
            )
        }
        Err(PressError::Unacknowledged { message, report }) => {
            tracing::error!(operator = %session.user, %what, engage, "{message}");
            render(
                &state,
                &session,
                StatusCode::SERVICE_UNAVAILABLE,
                Notice::Refused(format!("E-stop {verb} on {what}, but {message}.")),
                Some(&report),
            )
        }
        Err(PressError::Overtaken { message, report }) => {
            tracing::error!(operator = %session.user, %what, engage, "{message}");
            render(
                &state,
                &session,
                StatusCode::CONFLICT,
                Notice::Refused(format!("Not {verb} on {what}: {message}.")),
                Some(&report),
            )
        }
        Err(e @ PressError::NotFound(_)) => {
            tracing::error!(operator = %session.user, %what, engage, "not pressed: {e}");
            refused(StatusCode::NOT_FOUND, format!("Not {verb}: {e}."))
        }
        Err(e @ PressError::Zenoh(_)) => {
            tracing::error!(operator = %session.user, %what, engage, "not pressed: {e}");
            refused(
                StatusCode::SERVICE_UNAVAILABLE,
                format!("Not {verb}: the deployment refused the press ({e})."),
            )
        }
    }
}

/// The minutes field of a maintenance, as its expected end (0: not said).
fn back_from(form: &[(String, String)], now_unix_ms: i64) -> Result<i64, String> {
    let text = field(form, "back_minutes").unwrap_or("").trim();
    if text.is_empty() {
        return Ok(0);
    }
    match text.parse::<i64>() {
        Ok(minutes) if (1..=MAX_BACK_MINUTES).contains(&minutes) => {
            Ok(now_unix_ms + minutes * 60_000)
        }
        _ => Err(format!(
            "the expected return is a whole number of minutes from 1 to {MAX_BACK_MINUTES}, not `{}`",
            text.chars().take(16).collect::<String>()
        )),
    }
}

/// An operator's form about one env.
struct EnvForm {
    session: Session,
    form: Vec<(String, String)>,
    env: EnvId,
}

/// [`operator_form`], naming a known env (else the console says
/// `not_done` and why).
async fn env_form(state: &AppState, request: Request, not_done: &str) -> Result<EnvForm, Response> {
    let (session, form) = operator_form(state, request).await?;
    match form_env(state, &form) {
        Ok(env) => Ok(EnvForm { session, form, env }),
        Err(why) => Err(render(
            state,
            &session,
            StatusCode::NOT_FOUND,
            Notice::Refused(format!("{not_done}: {why}.")),
            None,
        )),
    }
}

/// Sends an operator's `request` to `env`'s controller: the console says
/// `done`, or `not_done` and the controller's refusal.
async fn ask_controller(
    state: &AppState,
    session: &Session,
    env: &EnvId,
    request: &AdminRequest,
    not_done: &str,
    done: String,
) -> Response {
    match state.discovery.admin(env, request).await {
        Ok(_) => render(state, session, StatusCode::OK, Notice::Done(done), None),
        Err(e) => {
            let e = HttpError::from_controller(not_done, &e);
            render(state, session, e.status, Notice::Refused(e.message), None)
        }
    }
}

/// `POST /console/maintenance`: starts (`action=start`, with a message and
/// an optional expected return in minutes) or ends an env's maintenance.
pub async fn maintenance(State(state): State<AppState>, request: Request) -> Response {
    const NOT_DONE: &str = "Not changed";
    let EnvForm { session, form, env } = match env_form(&state, request, NOT_DONE).await {
        Ok(posted) => posted,
        Err(page) => return page,
    };
    let refused = |why: String| {
        let notice = Notice::Refused(format!("{NOT_DONE}: {why}."));
        render(&state, &session, StatusCode::BAD_REQUEST, notice, None)
    };
    let token = session.token.clone();
    let (request, done) = match field(&form, "action") {
        Some("start") => {
            let message = match said(&form, "message", "what is being done") {
                Ok(message) => message.to_owned(),
                Err(why) => return refused(why),
            };
            let back_unix_ms = match back_from(&form, now_unix_ms()) {
                Ok(back) => back,
                Err(why) => return refused(why),
            };
            let request = AdminRequest::SetMaintenance {
                token,
                message,
                back_unix_ms,
            };
            let done = format!(
                "{env} is in maintenance: its lease and episode ended, new sessions are refused."
            );
            (request, done)
        }
        Some("end") => (
            AdminRequest::ClearMaintenance { token },
            format!("{env} is back in service."),
        ),
        _ => return refused("the action is start or end".into()),
    };
    ask_controller(&state, &session, &env, &request, NOT_DONE, done).await
}

/// `POST /console/lease`: revokes an env's lease, telling its holder why.
pub async fn revoke_lease(State(state): State<AppState>, request: Request) -> Response {
    const NOT_DONE: &str = "Not revoked";
    let EnvForm { session, form, env } = match env_form(&state, request, NOT_DONE).await {
        Ok(posted) => posted,
        Err(page) => return page,
    };
    let reason = match said(&form, "reason", "the reason (its holder is told)") {
        Ok(reason) => reason.to_owned(),
        Err(why) => {
            let notice = Notice::Refused(format!("{NOT_DONE}: {why}."));
            return render(&state, &session, StatusCode::BAD_REQUEST, notice, None);
        }
    };
    let holder = state
        .discovery
        .snapshot()
        .env(&env)
        .and_then(|e| e.lease.as_ref())
        .and_then(|l| l.holder.clone());
    let whose = holder.map_or(String::new(), |h| format!(" ({h}'s)"));
    let request = AdminRequest::RevokeLease {
        token: session.token.clone(),
        reason,
    };
    let done = format!("The lease on {env}{whose} was revoked: its holder is told why.");
    ask_controller(&state, &session, &env, &request, NOT_DONE, done).await
}

#[cfg(test)]
mod tests {
    use super::*;

    fn form(pairs: &[(&str, &str)]) -> Vec<(String, String)> {
        pairs
            .iter()
            .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
            .collect()
    }

    #[test]
    fn a_reason_is_said_bounded_and_printable() {
        let f = form(&[("reason", "  person in the enclosure ")]);
        assert_eq!(
            said(&f, "reason", "the reason"),
            Ok("person in the enclosure")
        );
        let long = "x".repeat(MAX_REASON_CHARS + 1);
        for bad in ["", "   ", "line\nbreak", long.as_str()] {
            let f = form(&[("reason", bad)]);
            assert!(said(&f, "reason", "the reason").is_err(), "{bad:?}");
        }
        assert!(said(&form(&[]), "reason", "the reason").is_err());
    }

    #[test]
    fn an_expected_return_is_whole_minutes_up_to_a_week() {
        let now = 1_000_000;
        assert_eq!(back_from(&form(&[]), now), Ok(0));
        assert_eq!(back_from(&form(&[("back_minutes", "")]), now), Ok(0));
        assert_eq!(
            back_from(&form(&[("back_minutes", "90")]), now),
            Ok(now + 90 * 60_000)
        );
        for bad in ["0", "-5", "1.5", "soon", "10081", "99999999999999999999"] {
            let e = back_from(&form(&[("back_minutes", bad)]), now).expect_err(bad);
            assert!(e.contains("whole number of minutes"), "{e}");
        }
    }
}
