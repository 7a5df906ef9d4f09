//! HTML of the signed-in side: the sign-in form and account page, each
//! env's bookings (public list, forms for the signed-in), a user's
//! experiments and one experiment with its learning curve (an SVG drawn
//! here) and episodes. Never renders an access token: the forms carry
//! only the CSRF token.

use maud::{html, Markup};
use offworld_runtime::msg::{Booking, EpisodeRecordEntry, ExperimentRecord};

use crate::model::{EnvView, Snapshot};
use crate::pages::{layout, time};

/// A sentence at the top of a page: what a form did, or why not.
#[derive(Debug, Clone)]
pub enum Notice {
    /// It worked.
    Done(String),
    /// It was refused; the controller's (or this service's) reason.
    Refused(String),
}

pub(crate) fn notice(n: Option<&Notice>) -> Markup {
    html! {
        @match n {
            Some(Notice::Done(m)) => div #notice .banner.ok role="status" { (m) },
            Some(Notice::Refused(m)) => div #notice .banner.error role="alert" { (m) },
            None => {},
        }
    }
}

fn env_href(env: &EnvView, tail: &str) -> String {
    format!("/envs/{}/{}{tail}", env.realm, env.name)
}

/// Who is reading a page, as far as pages need to know.
#[derive(Debug, Clone, Copy)]
pub struct Reader<'a> {
    /// The session's CSRF token, when signed in.
    pub csrf: Option<&'a str>,
    /// The user's name, once known.
    pub user: Option<&'a str>,
    /// The user is an operator.
    pub operator: bool,
}

impl Reader<'_> {
    /// Nobody signed in.
    pub const ANONYMOUS: Reader<'static> = Reader {
        csrf: None,
        user: None,
        operator: false,
    };
}

/// `/account` when not signed in: the sign-in form.
pub fn signin_page(csrf: &str, n: Option<&Notice>) -> Markup {
    layout(
        "Sign in",
        html! {
            h1 { "Sign in" }
            p.lead {
                "Paste your gym access token: the one you pass to "
                code { "gymnasium.make(…, token=…)" } " or set as "
                code { "OFFWORLD_GYM_ACCESS_TOKEN" } ". It stays on this server for your session, "
                "is checked by the deployment's controller, and is forgotten when you sign out."
            }
            (notice(n))
            form.card method="post" action="/account/signin" data-signin {
                input type="hidden" name="csrf" value=(csrf);
                label for="token" { "Access token" }
                input #token type="password" name="token" autocomplete="off" spellcheck="false" required;
                button type="submit" { "Sign in" }
            }
        },
    )
}

/// `/account` when signed in: where to go, and sign-out.
pub fn account_page(snapshot: &Snapshot, reader: Reader<'_>, n: Option<&Notice>) -> Markup {
    let envs: Vec<&EnvView> = ordered_envs(snapshot);
    layout(
        "Account",
        html! {
            h1 { "Account" }
            (notice(n))
            p #signed-in {
                "You are signed in"
                @if let Some(user) = reader.user { " as " strong { (user) } }
                "."
                @if reader.operator { " " a #console-link href="/console" { "Operator console" } }
            }
            @if envs.is_empty() {
                p.empty { "No env is known yet." }
            } @else {
                table.links {
                    thead { tr { th scope="col" { "Env" } th scope="col" { "" } th scope="col" { "" } } }
                    tbody {
                        @for env in envs {
                            tr {
                                td { span.realm.{(env.realm)} { (env.realm) } " " (env.name) }
                                td { a href=(env_href(env, "/bookings")) { "Bookings" } }
                                td { a href=(env_href(env, "/experiments")) { "Your experiments" } }
                            }
                        }
                    }
                }
            }
            (signout_form(reader))
        },
    )
}

fn signout_form(reader: Reader<'_>) -> Markup {
    html! {
        @if let Some(csrf) = reader.csrf {
            form.inline method="post" action="/account/signout" {
                input type="hidden" name="csrf" value=(csrf);
                button.secondary type="submit" { "Sign out" }
            }
        }
    }
}

/// Real envs first (those are the ones booked), then by id.
fn ordered_envs(snapshot: &Snapshot) -> Vec<&EnvView> {
    let mut envs: Vec<&EnvView> = snapshot.envs.iter().collect();
    envs.sort_by_key(|e| (e.realm != "real", e.id.clone()));
    envs
}

/// `/bookings`: every env with its next slot, real envs first.
pub fn bookings_index(snapshot: &Snapshot) -> Markup {
    layout(
        "Bookings",
        html! {
            h1 { "Bookings" }
            p.lead {
                "Real robots are booked in slots: during a slot only its holder can take the env's lease; "
                "outside slots leases are first come, first served. Pick an env to see its calendar and book."
            }
            table.bookable {
                thead { tr { th scope="col" { "Env" } th scope="col" { "Task" } th scope="col" { "Next booking" } } }
                tbody {
                    @for env in ordered_envs(snapshot) {
                        tr data-env=(env.id) {
                            td {
                                span.realm.{(env.realm)} { (env.realm) } " "
                                a href=(env_href(env, "/bookings")) { (env.name) }
                            }
                            td { (env.task.as_deref().unwrap_or("—")) }
                            td {
                                @match &env.next_booking {
                                    Some(b) => { (b.user) ": " (time(b.start_unix_ms, "clock")) "–" (time(b.end_unix_ms, "clock")) }
                                    None => span.muted { "none" },
                                }
                            }
                        }
                    }
                }
            }
        },
    )
}

/// The values of the booking form (kept when a booking is refused).
#[derive(Debug, Clone)]
pub struct SlotForm {
    /// `datetime-local` value (`YYYY-MM-DDTHH:MM`, UTC without JavaScript).
    pub start: String,
    /// Length, minutes.
    pub minutes: String,
    /// The reader's own values, sent back with a refusal (already in
    /// their zone: the script leaves them alone).
    pub kept: bool,
}

/// `/envs/<realm>/<name>/bookings`: the env's slots (anyone may list
/// them, as `offworld gym bookings` does) and, for the signed
/// in, the booking form and a cancel button per slot.
pub fn bookings_page(
    env: &EnvView,
    slots: Result<&[Booking], &str>,
    reader: Reader<'_>,
    form: &SlotForm,
    n: Option<&Notice>,
) -> Markup {
    let title = format!("Bookings · {}", env.id);
    html! {
        (layout(&title, html! {
            p.crumbs {
                a href="/" { "Availability" } " / "
                a href=(env_href(env, "")) { (env.id) } " / Bookings"
            }
            h1 { "Bookings of " (env.id) }
            p.lead {
                "Slots that have not ended, earliest first. During a slot only its holder can take the lease. "
                "Same rules and errors as " code { "offworld gym book" } "."
            }
            (notice(n))
            @match slots {
                Err(message) => div.banner.error role="alert" { "The bookings are unavailable: " (message) },
                Ok([]) => p.empty #no-bookings { "Nothing is booked." },
                Ok(slots) => (slot_table(env, slots, reader)),
            }
            @if let Some(csrf) = reader.csrf {
                h2 { "Book a slot" }
                form.card method="post" action=(env_href(env, "/bookings")) data-slot-form data-kept[form.kept] {
                    input type="hidden" name="csrf" value=(csrf);
                    input type="hidden" name="start_unix_ms" value="";
                    label for="start" { "Start " span.muted data-zone { "(UTC)" } }
                    input #start type="datetime-local" name="start" value=(form.start) required;
                    label for="minutes" { "Minutes" }
                    input #minutes type="number" name="minutes" min="1" step="1" value=(form.minutes) required;
                    button type="submit" { "Book" }
                }
                (signout_form(reader))
            } @else {
                p.signin { a href="/account" { "Sign in" } " with your access token to book or cancel slots." }
            }
        }))
    }
}

fn slot_table(env: &EnvView, slots: &[Booking], reader: Reader<'_>) -> Markup {
    html! {
        table.bookings {
            thead {
                tr {
                    th scope="col" { "Slot" }
                    th scope="col" { "From" }
                    th scope="col" { "To" }
                    th scope="col" { "Length" }
                    th scope="col" { "Holder" }
                    @if reader.csrf.is_some() { th scope="col" { "" } }
                }
            }
            tbody {
                @for slot in slots {
                    @let yours = reader.user == Some(slot.user.as_str());
                    tr data-booking=(slot.id) data-user=(slot.user) {
                        td.num { "#" (slot.id) }
                        td { (time(slot.start_unix_ms, "clock")) }
                        td { (time(slot.end_unix_ms, "clock")) }
                        td.num { (format_minutes(slot.end_unix_ms - slot.start_unix_ms)) }
                        td { (slot.user) @if yours { " " span.badge.yours { "yours" } } }
                        @if let Some(csrf) = reader.csrf {
                            td {
                                @if yours {
                                    form.inline method="post"
                                        action=(env_href(env, &format!("/bookings/{}/cancel", slot.id))) {
                                        input type="hidden" name="csrf" value=(csrf);
                                        button.secondary type="submit" { "Cancel" }
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
    }
}

fn format_minutes(ms: i64) -> String {
    let minutes = ms / 60_000;
    match (minutes / 60, minutes % 60) {
        (0, m) => format!("{m} min"),
        (h, 0) => format!("{h} h"),
        (h, m) => format!("{h} h {m} min"),
    }
}

/// A page asking to sign in first (401).
pub fn signin_needed(what: &str) -> Markup {
    layout(
        "Sign in needed",
        html! {
            h1 { "Sign in needed" }
            p.message { (what) " needs you to " a href="/account" { "sign in" } " with your access token." }
        },
    )
}

/// `/envs/<realm>/<name>/experiments`: the reader's experiments there.
pub fn experiments_page(env: &EnvView, experiments: &[ExperimentRecord]) -> Markup {
    let title = format!("Experiments · {}", env.id);
    layout(
        &title,
        html! {
            p.crumbs {
                a href="/" { "Availability" } " / "
                a href=(env_href(env, "")) { (env.id) } " / Experiments"
            }
            h1 { "Your experiments on " (env.id) }
            p.lead { "Most recently used first (operators see everyone's)." }
            @if experiments.is_empty() {
                p.empty #no-experiments { "You have no experiment on this env yet." }
            } @else {
                table.experiments.sortable {
                    thead {
                        tr {
                            @for (label, kind) in [
                                ("Id", "number"), ("Experiment", "text"), ("User", "text"), ("Mode", "text"),
                                ("Learning type", "text"), ("Episodes", "number"), ("Steps", "number"),
                                ("Last used", "number"),
                            ] {
                                th scope="col" aria-sort="none" { button type="button" data-sort=(kind) { (label) } }
                            }
                        }
                    }
                    tbody {
                        @for e in experiments {
                            tr data-experiment=(e.id) {
                                td.num data-value=(e.id) { (e.id) }
                                td data-value=(e.name) {
                                    a href=(env_href(env, &format!("/experiments/{}", e.id))) {
                                        @if e.name.is_empty() { "(unnamed)" } @else { (e.name) }
                                    }
                                }
                                td data-value=(e.user) { (e.user) }
                                td data-value=(e.algorithm_mode) { (e.algorithm_mode) }
                                td data-value=(e.learning_type) { (e.learning_type) }
                                td.num data-field="episodes" data-value=(e.episodes) { (e.episodes) }
                                td.num data-value=(e.steps) { (e.steps) }
                                td data-value=(e.updated_unix_ms) { (time(e.updated_unix_ms, "relative")) }
                            }
                        }
                    }
                }
            }
        },
    )
}

/// `/envs/<realm>/<name>/experiments/<id>`: counters, learning curve,
/// episodes with their recordings. `truncated`: more episodes exist than
/// were fetched.
pub fn experiment_page(
    env: &EnvView,
    experiment: &ExperimentRecord,
    episodes: &[EpisodeRecordEntry],
    truncated: bool,
) -> Markup {
    let name = if experiment.name.is_empty() {
        "(unnamed)"
    } else {
        experiment.name.as_str()
    };
    let title = format!("{name} · {}", env.id);
    let finished: Vec<&EpisodeRecordEntry> = episodes
        .iter()
        .filter(|e| e.end_reason != "in_progress")
        .collect();
    let successes = finished.iter().filter(|e| e.success).count();
    layout(
        &title,
        html! {
            p.crumbs {
                a href="/" { "Availability" } " / "
                a href=(env_href(env, "")) { (env.id) } " / "
                a href=(env_href(env, "/experiments")) { "Experiments" } " / " (experiment.id)
            }
            h1 { (name) }
            dl.facts {
                dt { "User" } dd { (experiment.user) }
                dt { "Task" } dd { (experiment.task) }
                dt { "Mode" } dd { (experiment.algorithm_mode) " · " (experiment.learning_type) }
                dt { "Episodes" } dd #episode-count { (experiment.episodes) }
                dt { "Steps" } dd { (experiment.steps) }
                dt { "Successes" } dd { (successes) " of " (finished.len()) }
                dt { "Created" } dd { (time(experiment.created_unix_ms, "clock")) }
                dt { "Last used" } dd { (time(experiment.updated_unix_ms, "relative")) }
            }
            h2 { "Learning curve" }
            @if truncated {
                p.banner.info { "Only the first " (episodes.len()) " episodes are shown." }
            }
            (crate::chart::learning_curve(&finished))
            h2 { "Episodes" }
            @if episodes.is_empty() {
                p.empty #no-episodes { "No episode yet." }
            } @else {
                table.episodes {
                    thead {
                        tr {
                            th scope="col" { "#" } th scope="col" { "Seed" } th scope="col" { "Steps" }
                            th scope="col" { "Return" } th scope="col" { "End" } th scope="col" { "Started" }
                            th scope="col" { "Duration" } th scope="col" { "Reset error" }
                            th scope="col" { "Recording" }
                        }
                    }
                    tbody {
                        @for e in episodes {
                            tr data-episode=(e.index) {
                                td.num { (e.index) }
                                td.num { @if e.seeded { (e.seed) } @else { span.muted { "—" } } }
                                td.num { (e.steps) }
                                td.num { (format!("{:.3}", e.episode_return)) }
                                td {
                                    span.badge.{(if e.success { "free" } else { "offline" })} { (e.end_reason) }
                                }
                                td { (time(e.started_unix_ms, "clock")) }
                                td.num { (format!("{:.1} s", (e.ended_unix_ms - e.started_unix_ms).max(0) as f64 / 1000.0)) }
                                td { (format!("{:.2} m, {:.1}°", e.reset.position_error_m, e.reset.yaw_error_rad.to_degrees())) }
                                td data-field="recordings" {
                                    @if e.recordings.is_empty() { span.muted { "none" } }
                                    @for r in &e.recordings {
                                        div {
                                            code { (r.path) }
                                            span.detail { " " (format_bytes(r.bytes)) @if !r.complete { " · partial" } }
                                        }
                                    }
                                }
                            }
                        }
                    }
                }
                p.lead { "Recording paths are relative to the controller's recording directory ("
                    code { "serve --record" } "); " code { "monitor replay" } " and " code { "recorder info" } " read them." }
            }
        },
    )
}

fn format_bytes(bytes: u64) -> String {
    match bytes {
        b if b >= 1 << 20 => format!("{:.1} MiB", b as f64 / f64::from(1u32 << 20)),
        b if b >= 1 << 10 => format!("{:.1} KiB", b as f64 / 1024.0),
        b => format!("{b} B"),
    }
}
