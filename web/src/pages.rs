//! HTML, rendered on the server (maud escapes every value). The pages
//! work without JavaScript; `static/app.js` only swaps in the rows the
//! event stream sends (rendered here too, by [`live_fragment`]), formats
//! times in the reader's time zone and sorts tables.

use std::time::{Duration, UNIX_EPOCH};

use axum::http::StatusCode;
use maud::{html, Markup, DOCTYPE};

use crate::model::{DeploymentView, EnvView, LeaderboardView, Snapshot, StateKind};

/// A page: the shared head, header and footer around `body`.
pub(crate) fn layout(title: &str, body: Markup) -> Markup {
    html! {
        (DOCTYPE)
        html lang="en" {
            head {
                meta charset="utf-8";
                meta name="viewport" content="width=device-width, initial-scale=1";
                title { (title) " · OffWorld Gym lab" }
                link rel="stylesheet" href="/static/style.css";
                script src="/static/app.js" defer {}
            }
            body {
                header.top {
                    a.brand href="/" { "OffWorld Gym" }
                    span.subtitle { "lab status" }
                    nav {
                        a href="/" { "Availability" }
                        a href="/bookings" { "Bookings" }
                        a href="/account" { "Account" }
                        a href="/api/envs" { "JSON" }
                    }
                }
                main { (body) }
                footer {
                    "Live view of the deployment; bookings and experiments need sign-in. "
                    span #live data-state="static" { "Live updates need JavaScript." }
                }
            }
        }
    }
}

/// `/`: every env and its state, live.
pub fn availability(snapshot: &Snapshot) -> Markup {
    layout(
        "Availability",
        html! {
            h1 { "Availability" }
            p.lead {
                "Every env of the deployment, real and simulated. Free envs can be opened from "
                code { "gymnasium.make(…)" } "; leased ones are in use."
            }
            (banner(&snapshot.deployment, snapshot.envs.is_empty()))
            table.envs data-live {
                (env_table_head())
                tbody #env-rows { @for env in &snapshot.envs { (env_row(env)) } }
            }
        },
    )
}

/// `/envs/<realm>/<name>`: one env's state, live, and its leaderboard.
pub fn env_page(
    snapshot: &Snapshot,
    env: &EnvView,
    leaderboard: Result<&LeaderboardView, &str>,
    rerun_url: Option<&str>,
) -> Markup {
    layout(
        &env.id,
        html! {
            p.crumbs { a href="/" { "Availability" } " / " (env.id) }
            h1 { (env.id) }
            (banner(&snapshot.deployment, false))
            table.envs data-live {
                (env_table_head())
                tbody data-single { (env_row(env)) }
            }
            p.links {
                a href={ "/envs/" (env.realm) "/" (env.name) "/bookings" } { "Bookings" }
                " · "
                a href={ "/envs/" (env.realm) "/" (env.name) "/experiments" } { "Your experiments" }
            }
            (live_view(env, rerun_url))
            h2 #leaderboard { "Leaderboard" }
            p.lead { "Test-mode experiments on this env, best first. Click a column to sort." }
            @match leaderboard {
                Ok(board) if board.entries.is_empty() => {
                    p.empty { "No test-mode experiment has finished an episode on this env yet." }
                }
                Ok(board) => { (leaderboard_table(board)) }
                Err(message) => {
                    div.banner.error role="alert" { "The leaderboard is unavailable: " (message) }
                }
            }
        },
    )
}

/// The env's camera and overhead thumbnails (refreshed by the script every
/// few seconds; without it, on reload) and the rerun link.
fn live_view(env: &EnvView, rerun_url: Option<&str>) -> Markup {
    let base = format!("/envs/{}/{}", env.realm, env.name);
    html! {
        h2 #live-view { "Live view" }
        p.lead {
            "What the robot's camera and the overhead camera last showed, a frame every few seconds. "
            "An env that is not stepping publishes no camera frames."
        }
        div.thumbnails {
            @for (view, caption) in [("camera", "Robot camera"), ("overhead", "Overhead")] {
                figure.thumbnail {
                    img data-thumbnail=(view) src={ (base) "/" (view) ".png" }
                        alt={ "No recent " (caption.to_lowercase()) " frame" };
                    figcaption { (caption) }
                }
            }
        }
        @if let Some(url) = rerun_url {
            p #rerun {
                "Every stream, live, in the rerun viewer: "
                a href=(url) { "open in rerun" } " or " code { "rerun " (url) }
            }
        }
    }
}

/// A page for an HTTP error.
pub fn error_page(status: StatusCode, message: &str) -> Markup {
    let title = status.canonical_reason().unwrap_or("Error");
    layout(
        title,
        html! {
            h1 { (status.as_u16()) " · " (title) }
            p.message { (message) }
            p { a href="/" { "Back to the availability page" } }
        },
    )
}

/// What the pages' event stream sends on every change: the banner and
/// every env's row, as the pages render them.
pub fn live_fragment(snapshot: &Snapshot) -> Markup {
    html! {
        (banner(&snapshot.deployment, snapshot.envs.is_empty()))
        table { tbody { @for env in &snapshot.envs { (env_row(env)) } } }
    }
}

fn banner(deployment: &DeploymentView, no_envs: bool) -> Markup {
    html! {
        @if deployment.last_sweep_unix_ms.is_none() {
            div #banner .banner.info role="status" { "Looking for envs…" }
        } @else if !deployment.reachable {
            div #banner .banner.error role="alert" {
                "The deployment does not answer: "
                (deployment.message.as_deref().unwrap_or("no reason given"))
                ". Envs below show their last known state."
            }
        } @else if no_envs {
            div #banner .banner.info role="status" {
                "The deployment answers, but no env is running in it."
            }
        } @else {
            div #banner .banner.hidden role="status" {}
        }
    }
}

fn env_table_head() -> Markup {
    html! {
        thead {
            tr {
                th scope="col" { "Env" }
                th scope="col" { "Task" }
                th scope="col" { "State" }
                th scope="col" { "Next booking" }
                th scope="col" { "Last seen" }
                th scope="col" { "Last reset" }
                th scope="col" { "Last fault" }
            }
        }
    }
}

fn env_row(env: &EnvView) -> Markup {
    html! {
        tr data-env=(env.id) data-state=(env.state.as_str()) {
            td data-field="env" {
                span.realm.{(env.realm)} { (env.realm) }
                " "
                a href={ "/envs/" (env.realm) "/" (env.name) } { (env.name) }
            }
            td data-field="task" { (env.task.as_deref().unwrap_or("—")) }
            td data-field="state-cell" {
                span.badge.{(env.state.as_str())} data-field="state" { (state_label(env.state)) }
                div.detail data-field="state-detail" { (state_detail(env)) }
            }
            td data-field="booking" {
                @match &env.next_booking {
                    Some(b) => {
                        (b.user) ": " (time(b.start_unix_ms, "clock")) "–" (time(b.end_unix_ms, "clock"))
                    }
                    None => span.muted { "none" },
                }
            }
            td data-field="last-seen" {
                @match env.last_seen_unix_ms {
                    Some(ms) => (time(ms, "relative")),
                    None => span.muted { "never" },
                }
            }
            td data-field="last-reset" {
                @match &env.last_reset {
                    Some(r) => {
                        (format!("{:.2} m, {:.1}° off", r.position_error_m, r.yaw_error_rad.to_degrees()))
                        div.detail { (format!("took {:.2} s · ", r.duration_s)) (time(r.unix_ms, "relative")) }
                    }
                    None => span.muted { "none yet" },
                }
            }
            td data-field="last-fault" {
                @match &env.last_fault {
                    Some(f) => {
                        (f.reason)
                        div.detail { (time(f.unix_ms, "relative")) }
                    }
                    None => span.muted { "none" },
                }
            }
        }
    }
}

fn state_label(state: StateKind) -> &'static str {
    match state {
        StateKind::Offline => "offline",
        StateKind::Estopped => "e-stopped",
        StateKind::Maintenance => "maintenance",
        StateKind::Leased => "leased",
        StateKind::Free => "free",
    }
}

fn state_detail(env: &EnvView) -> Markup {
    html! {
        @if let Some(offline) = &env.offline {
            (offline.reason)
        } @else {
            @if env.estop.engaged {
                @for (scope, latch) in [("site", &env.estop.site), ("env", &env.estop.env)] {
                    @if latch.engaged {
                        div { (scope) " e-stop"
                            @if !latch.reason.is_empty() { ": " (latch.reason) } }
                    }
                }
            }
            @if let Some(t) = env.tracking.as_ref().filter(|t| !t.ok) {
                div.tracking-lost data-field="tracking" { "tracking lost"
                    @if !t.reason.is_empty() { ": " (t.reason) } }
            }
            @if let Some(m) = &env.maintenance {
                div { "maintenance: " (m.message) " (" (m.by)
                    @if let Some(back) = m.back_unix_ms { ", back at " (time(back, "clock")) }
                    ")" }
            }
            @if let Some(lease) = &env.lease {
                div {
                    @if let Some(holder) = &lease.holder { "by " (holder) ", " }
                    "until " (time(lease.until_unix_ms, "clock")) " if idle"
                }
            }
        }
    }
}

/// A time the browser reformats in the reader's zone (`clock`) or as
/// "… ago" (`relative`); UTC for readers without JavaScript.
pub(crate) fn time(unix_ms: i64, style: &str) -> Markup {
    let utc = u64::try_from(unix_ms)
        .ok()
        .and_then(|ms| UNIX_EPOCH.checked_add(Duration::from_millis(ms)))
        .map(|t| humantime::format_rfc3339_seconds(t).to_string());
    html! {
        @match utc {
            Some(utc) => time datetime=(utc) data-unix-ms=(unix_ms) data-style=(style) { (utc.replace('T', " ")) },
            None => span.muted { "—" },
        }
    }
}

fn leaderboard_table(board: &LeaderboardView) -> Markup {
    html! {
        table.leaderboard.sortable {
            thead {
                tr {
                    @for (label, kind) in [
                        ("Rank", "number"), ("Experiment", "text"), ("User", "text"),
                        ("Learning type", "text"), ("Episodes", "number"),
                        ("Success rate", "number"), ("Mean return", "number"),
                    ] {
                        th scope="col" aria-sort=(if label == "Rank" { "ascending" } else { "none" }) {
                            button type="button" data-sort=(kind) { (label) }
                        }
                    }
                }
            }
            tbody {
                @for row in &board.entries {
                    @let entry = &row.entry;
                    tr {
                        td.num data-value=(row.rank) { (row.rank) }
                        td data-value=(entry.experiment) { (entry.experiment) }
                        td data-value=(entry.user) { (entry.user) }
                        td data-value=(entry.learning_type) { (entry.learning_type) }
                        td.num data-value=(entry.episodes) { (entry.episodes) }
                        td.num data-value=(entry.success_rate) { (format!("{:.0} %", entry.success_rate * 100.0)) }
                        td.num data-value=(entry.mean_return) { (format!("{:.2}", entry.mean_return)) }
                    }
                }
            }
        }
    }
}

/// The stylesheet and script, served as files (the pages' Content
/// Security Policy allows no inline code).
pub const STYLE_CSS: &str = include_str!("../static/style.css");
/// See [`STYLE_CSS`].
pub const APP_JS: &str = include_str!("../static/app.js");
