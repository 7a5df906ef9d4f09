//! JSON for scripts: `/api/envs`, one env, its leaderboard. The shapes are
//! [`crate::model`]'s; errors are [`HttpError`]s as JSON.

use axum::body::Body;
use axum::extract::rejection::PathRejection;
use axum::extract::{Path, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use offworld_runtime::keys::EnvId;
use serde::Serialize;

use crate::error::{Format, HttpError};
use crate::model::LeaderboardView;
use crate::server::AppState;

/// `body` as a JSON response with `status`.
pub fn json_response<T: Serialize>(status: StatusCode, body: &T) -> Response {
    match serde_json::to_vec(body) {
        Ok(bytes) => {
            let mut response = (status, Body::from(bytes)).into_response();
            response.headers_mut().insert(
                header::CONTENT_TYPE,
                HeaderValue::from_static("application/json"),
            );
            response
        }
        // Our types always serialize; should one not, say so rather than
        // send half a document.
        Err(e) => (
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("the response could not be encoded: {e}"),
        )
            .into_response(),
    }
}

/// The env a `/<realm>/<name>` path names; anything else is a 404 (a path
/// is a location: a malformed one names nothing here).
pub fn env_from_path(
    path: Result<Path<(String, String)>, PathRejection>,
) -> Result<EnvId, HttpError> {
    let Ok(Path((realm, name))) = path else {
        return Err(HttpError::not_found(
            "no such page: the path is not a valid env id",
        ));
    };
    parse_env(&realm, &name)
}

/// The env `<realm>/<name>` names; anything else is a 404.
pub fn parse_env(realm: &str, name: &str) -> Result<EnvId, HttpError> {
    let realm = realm.parse().map_err(|_| {
        HttpError::not_found(format!(
            "no such realm `{realm}`: envs are under sim/ or real/"
        ))
    })?;
    EnvId::new(realm, name).map_err(|e| HttpError::not_found(format!("no such env: {e}")))
}

/// `GET /api/envs`: every env and the deployment's health.
pub async fn envs(State(state): State<AppState>) -> Response {
    json_response(StatusCode::OK, &*state.discovery.snapshot())
}

/// `GET /api/envs/<realm>/<name>`: one env.
pub async fn env(
    State(state): State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
) -> Result<Response, HttpError> {
    let id = env_from_path(path).map_err(|e| e.as_format(Format::Json))?;
    let snapshot = state.discovery.snapshot();
    match snapshot.env(&id) {
        Some(view) => Ok(json_response(StatusCode::OK, view)),
        None => Err(unknown_env(&id).as_format(Format::Json)),
    }
}

/// `GET /api/envs/<realm>/<name>/leaderboard`: its ranked experiments.
pub async fn leaderboard(
    State(state): State<AppState>,
    path: Result<Path<(String, String)>, PathRejection>,
) -> Result<Response, HttpError> {
    let id = env_from_path(path).map_err(|e| e.as_format(Format::Json))?;
    let board = fetch_leaderboard(&state, &id)
        .await
        .map_err(|e| e.as_format(Format::Json))?;
    Ok(json_response(StatusCode::OK, &board))
}

/// The 404 of an env id this service has never seen.
pub fn unknown_env(id: &EnvId) -> HttpError {
    HttpError::not_found(format!("no env `{id}` is known to this deployment"))
}

/// `id`'s leaderboard, for a known env only: an unknown id never reaches
/// the deployment (the service is no relay for arbitrary keys).
pub async fn fetch_leaderboard(state: &AppState, id: &EnvId) -> Result<LeaderboardView, HttpError> {
    if state.discovery.snapshot().env(id).is_none() {
        return Err(unknown_env(id));
    }
    state
        .discovery
        .leaderboard(id)
        .await
        .map(LeaderboardView::from)
        .map_err(|e| HttpError::from_wire(&format!("the leaderboard of {id}"), &e))
}
