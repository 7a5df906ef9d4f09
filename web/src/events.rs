//! Server-sent events: every change of the snapshot, to the pages as HTML
//! rows (`/events`) and to scripts as JSON (`/api/events`).
//!
//! Each stream holds a place among `--max-event-streams` for as long as it
//! is open: the request limit cannot cover them (their response is sent
//! at once, the body never ends).

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::State;
use axum::response::sse::{Event, Sse};
use axum::response::{IntoResponse, Response};
use tokio::sync::{watch, OwnedSemaphorePermit};
use tokio::time::Instant;

use crate::error::{Format, HttpError};
use crate::model::Snapshot;
use crate::server::AppState;

/// At most one event per stream this often: a training run renews its
/// lease on every step, and a page needs no more than a few updates a
/// second (well within the 1 s a change must take to show).
const MIN_GAP: Duration = Duration::from_millis(150);
/// A comment this often keeps proxies from closing an idle stream.
const KEEP_ALIVE: Duration = Duration::from_secs(15);
/// How soon a browser reconnects a dropped stream.
const RETRY: Duration = Duration::from_secs(2);

/// `GET /events`: the banner and rows the pages show, rendered.
pub async fn html(State(state): State<AppState>) -> Response {
    stream(&state, Format::Html, |snapshot| {
        crate::pages::live_fragment(snapshot).into_string()
    })
}

/// `GET /api/events`: each snapshot as `/api/envs` returns it.
pub async fn json(State(state): State<AppState>) -> Response {
    stream(&state, Format::Json, |snapshot| {
        serde_json::to_string(snapshot)
            .unwrap_or_else(|e| format!(r#"{{"error":"the snapshot could not be encoded: {e}"}}"#))
    })
}

struct Cursor {
    snapshots: watch::Receiver<Arc<Snapshot>>,
    render: fn(&Snapshot) -> String,
    last_sent: Option<Instant>,
    _place: OwnedSemaphorePermit,
}

fn stream(state: &AppState, format: Format, render: fn(&Snapshot) -> String) -> Response {
    let Ok(place) = Arc::clone(&state.event_streams).try_acquire_owned() else {
        return HttpError::overloaded("open event streams")
            .as_format(format)
            .into_response();
    };
    let cursor = Cursor {
        snapshots: state.discovery.watch(),
        render,
        last_sent: None,
        _place: place,
    };
    Sse::new(futures::stream::unfold(cursor, next_event)).into_response()
}

async fn next_event(mut cursor: Cursor) -> Option<(Result<Event, Infallible>, Cursor)> {
    let Some(last_sent) = cursor.last_sent else {
        // The current state first, so a page (re)connecting is up to date.
        let snapshot = cursor.snapshots.borrow_and_update().clone();
        let event = Event::default()
            .event("envs")
            .retry(RETRY)
            .data((cursor.render)(&snapshot));
        cursor.last_sent = Some(Instant::now());
        return Some((Ok(event), cursor));
    };
    tokio::time::sleep_until(last_sent + MIN_GAP).await;
    tokio::select! {
        changed = cursor.snapshots.changed() => {
            // The sender is gone: the service is stopping.
            changed.ok()?;
            let snapshot = cursor.snapshots.borrow_and_update().clone();
            let event = Event::default().event("envs").data((cursor.render)(&snapshot));
            cursor.last_sent = Some(Instant::now());
            Some((Ok(event), cursor))
        }
        _ = tokio::time::sleep(KEEP_ALIVE) => {
            Some((Ok(Event::default().comment("keep-alive")), cursor))
        }
    }
}
