//! HTML of the operator console: the site's e-stop, then every env with
//! its e-stop, lease and maintenance, each with the forms that change
//! them. Forms work without JavaScript; a release carries a required
//! confirmation box (the server refuses one without it too).

use maud::{html, Markup};
use offworld_client::operator::PressReport;

use crate::account_pages::{notice, Notice};
use crate::console::{MAX_BACK_MINUTES, MAX_REASON_CHARS};
use crate::model::{EnvView, LatchView, Snapshot};
use crate::pages::{layout, time};
use crate::session::Session;

/// `/console`.
pub fn console(
    snapshot: &Snapshot,
    session: &Session,
    n: Option<&Notice>,
    report: Option<&PressReport>,
) -> Markup {
    let csrf = session.csrf.as_str();
    // The site latch is the same in every env's status: the first that has
    // a controller says it.
    let site = snapshot
        .envs
        .iter()
        .find(|e| e.task.is_some())
        .map(|e| &e.estop.site);
    layout(
        "Operator console",
        html! {
            h1 { "Operator console" }
            p.lead {
                "Signed in as " strong #operator { (session.user) } " (operator). "
                "An e-stop goes straight to the robots and twins, which acknowledge it below; "
                "maintenance and lease revocation are checked again by each env's controller."
            }
            (notice(n))
            @if let Some(report) = report { (acknowledgements(report)) }
            section.card #site-estop data-engaged=(site.is_some_and(|l| l.engaged)) {
                h2 { "Site e-stop" }
                p #site-latch {
                    @match site {
                        Some(latch) => { (latch_text(latch)) }
                        None => { "Unknown: no controller has reported yet." }
                    }
                }
                (estop_forms(csrf, "site", None, site.is_some_and(|l| l.engaged), "the site e-stop"))
            }
            h2 { "Envs" }
            @if snapshot.envs.is_empty() {
                p.empty { "No env is known yet." }
            } @else {
                table.console {
                    thead {
                        tr {
                            th scope="col" { "Env" }
                            th scope="col" { "State" }
                            th scope="col" { "E-stop" }
                            th scope="col" { "Lease" }
                            th scope="col" { "Maintenance" }
                        }
                    }
                    tbody { @for env in &snapshot.envs { (env_row(csrf, env)) } }
                }
            }
        },
    )
}

/// The page of a refusal (a signed-in user who is not an operator).
pub fn refused_page(message: &str) -> Markup {
    layout(
        "Operators only",
        html! {
            h1 { "Operators only" }
            p.message #refused { (message) }
            p { a href="/" { "Back to the availability page" } }
        },
    )
}

fn latch_text(latch: &LatchView) -> Markup {
    html! {
        @if latch.engaged { strong.estop { "Engaged" } } @else { "Released" }
        @if let Some(at) = latch.changed_unix_ms { " since " (time(at, "clock")) }
        @if !latch.reason.is_empty() { ": " (latch.reason) }
    }
}

fn acknowledgements(report: &PressReport) -> Markup {
    html! {
        ul #acks {
            @for ack in &report.acknowledged {
                li data-env=(ack.env) data-component=(ack.component) {
                    (ack.component) " of " (ack.env) " acknowledged in "
                    (ack.after.as_millis()) " ms; e-stops now engaged there: " (ack.state.summary())
                }
            }
            @for (env, component) in &report.silent {
                li.silent data-env=(env) data-component=(component) {
                    "NOT acknowledged by " (component) " of " (env) ": check it in person"
                }
            }
        }
    }
}

/// The fields every console form carries: its CSRF token and the env it
/// is about.
fn form_fields(csrf: &str, env: Option<&str>) -> Markup {
    html! {
        input type="hidden" name="csrf" value=(csrf);
        @if let Some(env) = env { input type="hidden" name="env" value=(env); }
    }
}

/// Engage, or release with its confirmation, for `scope` (`site` or
/// `env`, with `env` the env's id).
fn estop_forms(csrf: &str, scope: &str, env: Option<&str>, engaged: bool, what: &str) -> Markup {
    html! {
        form.inline.estop method="post" action="/console/estop" data-action=(if engaged { "release" } else { "engage" }) {
            (form_fields(csrf, env))
            input type="hidden" name="scope" value=(scope);
            @if engaged {
                input type="hidden" name="action" value="release";
                label { "Reason " input type="text" name="reason" required maxlength=(MAX_REASON_CHARS) placeholder="checked, all clear"; }
                label.confirm {
                    input type="checkbox" name="confirm" value="yes" required;
                    " The enclosure is clear of people and objects"
                }
                button.secondary type="submit" { "Release " (what) }
            } @else {
                input type="hidden" name="action" value="engage";
                label { "Reason " input type="text" name="reason" required maxlength=(MAX_REASON_CHARS) placeholder="person in the enclosure"; }
                button.danger type="submit" { "Engage " (what) }
            }
        }
    }
}

fn env_row(csrf: &str, env: &EnvView) -> Markup {
    html! {
        tr data-env=(env.id) data-state=(env.state.as_str()) {
            td { span.realm.{(env.realm)} { (env.realm) } " " a href={ "/envs/" (env.realm) "/" (env.name) } { (env.name) } }
            td data-field="state" { span.badge.{(env.state.as_str())} { (env.state.as_str()) } }
            td data-field="estop" {
                div { (latch_text(&env.estop.env)) }
                @if env.estop.site.engaged { div { "The site e-stop is engaged too." } }
                (estop_forms(csrf, "env", Some(&env.id), env.estop.env.engaged, "this env's e-stop"))
            }
            td data-field="lease" {
                @match &env.lease {
                    Some(lease) => {
                        div {
                            "Held by " (lease.holder.as_deref().unwrap_or("someone"))
                            ", until " (time(lease.until_unix_ms, "clock")) " if idle"
                        }
                        form.inline method="post" action="/console/lease" data-action="revoke" {
                            (form_fields(csrf, Some(&env.id)))
                            label { "Reason " input type="text" name="reason" required maxlength=(MAX_REASON_CHARS) placeholder="told to the holder"; }
                            button.danger type="submit" { "Revoke the lease" }
                        }
                    }
                    None => { span.muted { "none" } }
                }
            }
            td data-field="maintenance" {
                @match &env.maintenance {
                    Some(m) => {
                        div {
                            (m.message) " (" (m.by)
                            @if let Some(back) = m.back_unix_ms { ", back at " (time(back, "clock")) }
                            ")"
                        }
                        form.inline method="post" action="/console/maintenance" data-action="end" {
                            (form_fields(csrf, Some(&env.id)))
                            input type="hidden" name="action" value="end";
                            button.secondary type="submit" { "End maintenance" }
                        }
                    }
                    None => {
                        form.inline method="post" action="/console/maintenance" data-action="start" {
                            (form_fields(csrf, Some(&env.id)))
                            input type="hidden" name="action" value="start";
                            label { "What " input type="text" name="message" required maxlength=(MAX_REASON_CHARS) placeholder="wheel swap"; }
                            label { "Back in (min) " input type="number" name="back_minutes" min="1" max=(MAX_BACK_MINUTES) step="1"; }
                            button type="submit" { "Start maintenance" }
                        }
                    }
                }
            }
        }
    }
}
