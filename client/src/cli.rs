//! The trainer's commands on a deployment — its envs, bookings,
//! experiments and leaderboard — as `offworld gym …` and
//! `python -m offworld_gym …` (one implementation: the Python package
//! calls [`run_from`]). Tables for people, `--json` for scripts; failures
//! are `error: …` on stderr and exit status 1, usage mistakes 2.

use std::collections::BTreeMap;
use std::io::Write;
use std::process::ExitCode;
use std::time::Duration;

use clap::{CommandFactory, FromArgMatches};
use offworld_runtime::keys::EnvId;
use offworld_runtime::msg::{
    Booking, BookingRequest, EnvState, EpisodeRecordEntry, ExperimentRecord, ExperimentsRequest,
    LeaderboardEntry, Pose2D, RecordingFile, ResetAccuracy,
};
use offworld_runtime::WireError;
use serde::Serialize;

use crate::deployment::{on_deployment, CONNECT_ENV, TOKEN_ENV};
use crate::EnvListing;

/// Every request but the listing's: a controller answers within this long.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);

macro_rules! examples {
    ($program:literal) => {
        concat!(
            "Examples:\n  ",
            $program,
            " envs --connect quic/router.example:7447\n  ",
            $program,
            " bookings --env real/monolith-0\n  ",
            $program,
            " bookings --mine\n  ",
            $program,
            " whoami\n  ",
            $program,
            " book --env real/monolith-0 --start 2026-12-01T14:00 --minutes 60\n  ",
            $program,
            " cancel-booking --env real/monolith-0 --id 3\n  ",
            $program,
            " experiments --env real/monolith-0\n  ",
            $program,
            " episodes --env real/monolith-0 --id 12\n  ",
            $program,
            " leaderboard --env real/monolith-0\n\n",
            "Credentials: OFFWORLD_GYM_ACCESS_TOKEN (or --token); TLS and Zenoh user/password \
             from the Zenoh config file in OFFWORLD_ZENOH_CONFIG."
        )
    };
}

/// The examples `offworld gym --help` ends with.
pub const EXAMPLES: &str = examples!("offworld gym");

/// `offworld gym`: flatten into a parent command.
#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    command: Command,
}

/// How a command reaches the deployment and prints its answer.
#[derive(clap::Args)]
struct Deployment {
    /// The deployment's Zenoh endpoint, e.g. quic/router.example:7447.
    #[arg(long, env = CONNECT_ENV, value_name = "ENDPOINT")]
    connect: Option<String>,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

/// An access token, for the commands that act as its user.
#[derive(clap::Args)]
struct Token {
    /// Access token (as `offworld users add` printed it).
    #[arg(long, env = TOKEN_ENV, hide_env_values = true)]
    token: Option<String>,
}

impl Token {
    fn required(self, what: &str) -> Result<String, Failure> {
        self.token.filter(|t| !t.is_empty()).ok_or_else(|| {
            Failure::Invalid(format!(
                "{what} needs an access token: pass --token or set {TOKEN_ENV}"
            ))
        })
    }
}

#[derive(clap::Subcommand)]
enum Command {
    /// List envs, their tasks and availability.
    Envs {
        #[command(flatten)]
        deployment: Deployment,
        /// Seconds each env's controller has to answer.
        #[arg(long, default_value_t = 2.0, value_name = "SECONDS")]
        timeout: f64,
    },
    /// List an env's booked slots, or yours on every env (--mine).
    #[command(group(clap::ArgGroup::new("whose").required(true).args(["env", "mine"])))]
    Bookings {
        /// Env id, e.g. real/monolith-0.
        #[arg(long, value_name = "ENV_ID")]
        env: Option<EnvId>,
        /// Your slots on every env (needs your token).
        #[arg(long)]
        mine: bool,
        #[command(flatten)]
        deployment: Deployment,
        #[command(flatten)]
        token: Token,
    },
    /// Who your access token is, and whether you are an operator.
    Whoami {
        /// Ask this env's controller (default: a real env's, else any).
        #[arg(long, value_name = "ENV_ID")]
        env: Option<EnvId>,
        #[command(flatten)]
        deployment: Deployment,
        #[command(flatten)]
        token: Token,
    },
    /// Reserve a slot on an env.
    Book {
        /// Env id, e.g. real/monolith-0.
        #[arg(long, value_name = "ENV_ID")]
        env: EnvId,
        /// ISO time, e.g. 2026-12-01T14:00 (local time) or 2026-12-01T13:00Z.
        #[arg(long, value_parser = parse_time)]
        start: i64,
        /// Slot length.
        #[arg(long)]
        minutes: f64,
        #[command(flatten)]
        deployment: Deployment,
        #[command(flatten)]
        token: Token,
    },
    /// Cancel one of your slots.
    CancelBooking {
        /// Env id, e.g. real/monolith-0.
        #[arg(long, value_name = "ENV_ID")]
        env: EnvId,
        /// Booking id (see `bookings`).
        #[arg(long)]
        id: i64,
        #[command(flatten)]
        deployment: Deployment,
        #[command(flatten)]
        token: Token,
    },
    /// List your experiments on an env (operators: all).
    Experiments {
        /// Env id, e.g. real/monolith-0.
        #[arg(long, value_name = "ENV_ID")]
        env: EnvId,
        #[command(flatten)]
        deployment: Deployment,
        #[command(flatten)]
        token: Token,
    },
    /// The episodes of one experiment, with their recordings.
    Episodes {
        /// Env id, e.g. real/monolith-0.
        #[arg(long, value_name = "ENV_ID")]
        env: EnvId,
        /// Experiment id (see `experiments`).
        #[arg(long)]
        id: i64,
        #[command(flatten)]
        deployment: Deployment,
        #[command(flatten)]
        token: Token,
    },
    /// An env's test-mode experiments, best first.
    Leaderboard {
        /// Env id, e.g. real/monolith-0.
        #[arg(long, value_name = "ENV_ID")]
        env: EnvId,
        #[command(flatten)]
        deployment: Deployment,
    },
}

/// Why a command failed (exit status 1).
#[derive(Debug, thiserror::Error)]
enum Failure {
    /// The deployment refused or did not answer.
    #[error("{0}")]
    Wire(#[from] WireError),
    /// A value the command cannot use, found before anything was sent.
    #[error("{0}")]
    Invalid(String),
    /// Standard output could not be written (closed by a reader that
    /// stopped reading, `… | head -1`: the command then ends quietly).
    #[error("cannot write the output: {0}")]
    Output(#[from] std::io::Error),
}

/// `println!` that returns a failed write (`Failure::Output`) instead of
/// panicking on it.
macro_rules! out {
    ($($arg:tt)*) => {
        writeln!(std::io::stdout().lock(), $($arg)*)?
    };
}

/// Runs `offworld gym …`.
pub fn run(args: Args) -> ExitCode {
    ExitCode::from(execute(args.command))
}

/// Runs the commands as `python -m offworld_gym`: parses `argv` (the
/// first item is the program, as in `sys.argv`), prints, returns the exit
/// status (0; 1 for a failure; 2 for a usage mistake, with clap's message).
pub fn run_from(argv: Vec<String>) -> u8 {
    #[derive(clap::Parser)]
    #[command(
        name = "python -m offworld_gym",
        bin_name = "python -m offworld_gym",
        version,
        about = "What a deployment offers, from the command line.",
        after_help = examples!("python -m offworld_gym")
    )]
    struct Standalone {
        #[command(subcommand)]
        command: Command,
    }
    let parsed = Standalone::command()
        .try_get_matches_from(argv)
        .and_then(|mut matches| Standalone::from_arg_matches_mut(&mut matches));
    match parsed {
        Ok(standalone) => execute(standalone.command),
        Err(usage) => {
            let _ = usage.print();
            u8::try_from(usage.exit_code()).unwrap_or(2)
        }
    }
}

fn execute(command: Command) -> u8 {
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
    {
        Ok(runtime) => runtime,
        Err(e) => {
            eprintln!("error: cannot start the async runtime: {e}");
            return 1;
        }
    };
    let result = runtime.block_on(command.run());
    // A Zenoh task still retrying a link must not hold the exit.
    runtime.shutdown_timeout(Duration::from_secs(1));
    match result {
        Ok(()) => 0,
        // Whoever reads has all they wanted.
        Err(Failure::Output(e)) if e.kind() == std::io::ErrorKind::BrokenPipe => 0,
        Err(failure) => {
            eprintln!("error: {failure}");
            1
        }
    }
}

impl Command {
    async fn run(self) -> Result<(), Failure> {
        match self {
            Command::Envs {
                deployment,
                timeout,
            } => {
                let timeout = seconds(timeout, "--timeout")?;
                let listed = on_deployment(deployment.connect, |session| async move {
                    crate::discover(&session, timeout).await
                })
                .await?;
                if deployment.json {
                    return print_json(&listed.iter().map(EnvInfo::from).collect::<Vec<_>>());
                }
                for listing in &listed {
                    print_listing(listing)?;
                }
                if listed.is_empty() {
                    eprintln!("no envs found");
                }
                Ok(())
            }
            Command::Bookings {
                env,
                mine: _,
                deployment,
                token,
            } => {
                let slots = match env {
                    Some(env) => {
                        let from_unix_ms = now_unix_ms();
                        let request = BookingRequest::List { from_unix_ms };
                        booking_request(deployment.connect, env, request).await?
                    }
                    None => {
                        let token = token.required("bookings --mine")?;
                        on_deployment(deployment.connect, |session| async move {
                            crate::my_bookings(&session, &token, REQUEST_TIMEOUT).await
                        })
                        .await?
                    }
                };
                print_bookings(&slots, deployment.json)?;
                if slots.is_empty() && !deployment.json {
                    eprintln!("nothing booked");
                }
                Ok(())
            }
            Command::Whoami {
                env,
                deployment,
                token,
            } => {
                let token = token.required("whoami")?;
                let me = on_deployment(deployment.connect, |session| async move {
                    crate::whoami(&session, env.as_ref(), &token, REQUEST_TIMEOUT).await
                })
                .await?;
                if deployment.json {
                    // One line, as before.
                    let identity = Identity {
                        user: &me.user,
                        operator: me.operator,
                    };
                    let line = serde_json::to_string(&identity)
                        .map_err(|e| Failure::Invalid(format!("cannot print JSON: {e}")))?;
                    out!("{line}");
                    return Ok(());
                }
                let role = if me.operator { " (operator)" } else { "" };
                out!("{}{role}", me.user);
                Ok(())
            }
            Command::Book {
                env,
                start,
                minutes,
                deployment,
                token,
            } => {
                let length = seconds(minutes, "--minutes")?.as_secs_f64() * 60.0;
                // Finite and positive; a length past i64 saturates (the
                // controller refuses slots that long).
                let length_ms = (length * 1000.0) as i64;
                let request = BookingRequest::Make {
                    token: token.required("book")?,
                    start_unix_ms: start,
                    end_unix_ms: start.saturating_add(length_ms),
                };
                change_bookings(deployment, env, request).await
            }
            Command::CancelBooking {
                env,
                id,
                deployment,
                token,
            } => {
                let request = BookingRequest::Cancel {
                    token: token.required("cancel-booking")?,
                    id,
                };
                change_bookings(deployment, env, request).await
            }
            Command::Experiments {
                env,
                deployment,
                token,
            } => {
                // No token: anonymous, which sim deployments admit.
                let request = ExperimentsRequest::List {
                    token: token.token.unwrap_or_default(),
                };
                let found = on_deployment(deployment.connect, |session| async move {
                    crate::experiments(&session, &env, &request, REQUEST_TIMEOUT).await
                })
                .await?
                .experiments;
                if deployment.json {
                    return print_json(&found);
                }
                print_experiments(&found)?;
                Ok(())
            }
            Command::Episodes {
                env,
                id,
                deployment,
                token,
            } => {
                let token = token.token.unwrap_or_default();
                let (experiment, episodes) =
                    on_deployment(deployment.connect, |session| async move {
                        crate::experiment_episodes(&session, &env, &token, id, REQUEST_TIMEOUT)
                            .await
                    })
                    .await?;
                if deployment.json {
                    return print_json(&ExperimentEpisodes {
                        episodes: episodes.iter().map(EpisodeInfo::from).collect(),
                        experiment,
                    });
                }
                print_episodes(&experiment, &episodes)?;
                Ok(())
            }
            Command::Leaderboard { env, deployment } => {
                let board = on_deployment(deployment.connect, |session| async move {
                    crate::leaderboard(&session, &env, REQUEST_TIMEOUT).await
                })
                .await?;
                if deployment.json {
                    let ranked: Vec<Ranked> = board
                        .entries
                        .iter()
                        .enumerate()
                        .map(|(index, entry)| Ranked {
                            rank: index + 1,
                            entry,
                        })
                        .collect();
                    return print_json(&ranked);
                }
                if board.entries.is_empty() {
                    eprintln!("no test-mode experiments yet");
                } else {
                    print_leaderboard_table(&board.entries)?;
                }
                Ok(())
            }
        }
    }
}

async fn booking_request(
    connect: Option<String>,
    env: EnvId,
    request: BookingRequest,
) -> Result<Vec<Booking>, Failure> {
    let answer = on_deployment(connect, |session| async move {
        crate::book(&session, &env, &request, REQUEST_TIMEOUT).await
    })
    .await?;
    Ok(answer.bookings)
}

/// Makes or cancels a slot; prints the env's slots the controller answers
/// with (the one made; those left after a cancellation).
async fn change_bookings(
    deployment: Deployment,
    env: EnvId,
    request: BookingRequest,
) -> Result<(), Failure> {
    let slots = booking_request(deployment.connect, env, request).await?;
    print_bookings(&slots, deployment.json)
}

/// A positive, finite number of seconds as a duration, else an error
/// naming the flag.
fn seconds(value: f64, flag: &str) -> Result<Duration, Failure> {
    Duration::try_from_secs_f64(value)
        .ok()
        .filter(|d| !d.is_zero())
        .ok_or_else(|| Failure::Invalid(format!("{flag} must be a positive number, got {value}")))
}

fn now_unix_ms() -> i64 {
    let since_epoch = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default();
    i64::try_from(since_epoch.as_millis()).unwrap_or(i64::MAX)
}

/// `--start`: an ISO date and time, as Unix ms. With an offset (`Z`,
/// `+01:00`) it is that instant; without, the local time.
fn parse_time(text: &str) -> Result<i64, String> {
    use chrono::{DateTime, LocalResult, NaiveDateTime, TimeZone};
    let text = text.trim();
    let with_offset = match text.strip_suffix(['Z', 'z']) {
        Some(utc) => format!("{utc}+00:00"),
        None => text.to_owned(),
    };
    let dated = [
        "%Y-%m-%dT%H:%M:%S%.f",
        "%Y-%m-%dT%H:%M",
        "%Y-%m-%d %H:%M:%S%.f",
        "%Y-%m-%d %H:%M",
    ];
    for format in dated {
        if let Ok(at) = DateTime::parse_from_str(&with_offset, &format!("{format}%:z")) {
            return Ok(at.timestamp_millis());
        }
    }
    let local = dated
        .iter()
        .find_map(|format| NaiveDateTime::parse_from_str(text, format).ok())
        .ok_or_else(|| {
            format!(
                "`{text}` is not an ISO date and time, e.g. 2026-12-01T14:00 or 2026-12-01T13:00Z"
            )
        })?;
    match chrono::Local.from_local_datetime(&local) {
        LocalResult::Single(at) => Ok(at.timestamp_millis()),
        // The clock went back: the first of the two, as Python's `fold=0`.
        LocalResult::Ambiguous(first, _) => Ok(first.timestamp_millis()),
        LocalResult::None => Err(format!(
            "{text} does not exist in local time (the clock skipped it); give an offset, e.g. {text}Z"
        )),
    }
}

/// Unix ms as an ISO UTC time to the second (`2026-12-01T14:00:00+00:00`).
fn when(unix_ms: i64) -> String {
    chrono::DateTime::from_timestamp_millis(unix_ms).map_or_else(
        || format!("{unix_ms} ms"),
        |at| at.format("%Y-%m-%dT%H:%M:%S+00:00").to_string(),
    )
}

/// `3.2 cm 1.4° 41.5 s`: how far from its spawn pose a reset left the
/// robot, and how long it took.
fn reset_text(reset: &ResetAccuracy) -> String {
    format!(
        "{:.1} cm {:.1}° {:.1} s",
        reset.position_error_m * 100.0,
        reset.yaw_error_rad.to_degrees(),
        reset.duration_s
    )
}

fn print_json(value: &impl Serialize) -> Result<(), Failure> {
    let mut out = Vec::new();
    let mut serializer = serde_json::Serializer::with_formatter(
        &mut out,
        serde_json::ser::PrettyFormatter::with_indent(b" "),
    );
    value
        .serialize(&mut serializer)
        .map_err(|e| Failure::Invalid(format!("cannot print JSON: {e}")))?;
    out!("{}", String::from_utf8_lossy(&out));
    Ok(())
}

fn print_listing(listing: &EnvListing) -> Result<(), Failure> {
    let mut state = match &listing.state {
        EnvState::Free => "free".to_owned(),
        EnvState::Leased {
            until_unix_ms,
            holder,
        } => format!("leased by {holder} until {}", when(*until_unix_ms)),
        EnvState::Maintenance {
            message,
            back_unix_ms,
            ..
        } => {
            let mut text = format!("maintenance{}", in_brackets(message));
            if *back_unix_ms > 0 {
                text += &format!(" back at {}", when(*back_unix_ms));
            }
            text
        }
        EnvState::Offline { reason } => format!("offline{}", in_brackets(reason)),
    };
    for (latch, reason) in engaged_estops(listing) {
        state += &format!(" E-STOP {latch} ({reason})");
    }
    let task = if listing.task.is_empty() {
        "-"
    } else {
        &listing.task
    };
    out!(
        "{:<28} {task:<26} {state:<40} {}",
        listing.env.to_string(),
        listing.components.join(",")
    );
    if listing.last_reset.measured {
        out!("    last reset {}", reset_text(&listing.last_reset));
    }
    for slot in &listing.bookings {
        out!(
            "    booked by {} {} – {}",
            slot.user,
            when(slot.start_unix_ms),
            when(slot.end_unix_ms)
        );
    }
    Ok(())
}

/// ` (why)`, or nothing when nobody said why.
fn in_brackets(why: &str) -> String {
    if why.is_empty() {
        String::new()
    } else {
        format!(" ({why})")
    }
}

/// The e-stop latches in force, site first, with their reasons.
fn engaged_estops(listing: &EnvListing) -> Vec<(&'static str, &str)> {
    [("site", &listing.estop.site), ("env", &listing.estop.env)]
        .into_iter()
        .filter(|(_, latch)| latch.engaged)
        .map(|(name, latch)| (name, latch.reason.as_str()))
        .collect()
}

fn print_bookings(slots: &[Booking], json: bool) -> Result<(), Failure> {
    if json {
        return print_json(&slots);
    }
    for b in slots {
        out!(
            "{:>5}  {:<24} {} .. {}  {}",
            b.id,
            b.env_id,
            when(b.start_unix_ms),
            when(b.end_unix_ms),
            b.user
        );
    }
    Ok(())
}

fn print_experiments(found: &[ExperimentRecord]) -> Result<(), Failure> {
    if found.is_empty() {
        eprintln!("no experiments yet");
        return Ok(());
    }
    out!(
        "{:>5}  {:<12} {:<28} {:<10} {:<5} {:>8} {:>8}  last used",
        "id",
        "user",
        "experiment",
        "type",
        "mode",
        "episodes",
        "steps"
    );
    for e in found {
        out!(
            "{:>5}  {:<12} {:<28} {:<10} {:<5} {:>8} {:>8}  {}",
            e.id,
            e.user,
            e.name,
            e.learning_type,
            e.algorithm_mode,
            e.episodes,
            e.steps,
            when(e.updated_unix_ms)
        );
    }
    Ok(())
}

fn print_episodes(
    experiment: &ExperimentRecord,
    episodes: &[EpisodeRecordEntry],
) -> Result<(), Failure> {
    out!(
        "experiment {} '{}' of {}",
        experiment.id,
        experiment.name,
        experiment.user
    );
    out!(
        "{:>7} {:>5} {:>8}  {:<32} {:<24} recording",
        "episode",
        "steps",
        "return",
        "end",
        "reset: off by, took"
    );
    for ep in episodes {
        let files: Vec<String> = ep
            .recordings
            .iter()
            .map(|r| {
                let partial = if r.complete { "" } else { " (partial)" };
                format!("{}{partial}", r.path)
            })
            .collect();
        let files = if files.is_empty() {
            "-".to_owned()
        } else {
            files.join(", ")
        };
        let reset = if ep.reset.measured {
            reset_text(&ep.reset)
        } else {
            "-".to_owned()
        };
        out!(
            "{:>7} {:>5} {:>8.3}  {:<32} {reset:<24} {files}",
            ep.index,
            ep.steps,
            ep.episode_return,
            ep.end_reason
        );
    }
    if episodes.is_empty() {
        eprintln!("no episodes yet");
    }
    Ok(())
}

/// A leaderboard as a table, best first, ranked from 1 (`offworld gym
/// leaderboard`; `offworld leaderboard` from the site's database).
pub fn print_leaderboard_table(entries: &[LeaderboardEntry]) -> std::io::Result<()> {
    out!(
        "{:>4}  {:<28} {:<12} {:<10} {:>8} {:>8} {:>8}",
        "rank",
        "experiment",
        "user",
        "type",
        "episodes",
        "success",
        "return"
    );
    for (index, e) in entries.iter().enumerate() {
        out!(
            "{:>4}  {:<28} {:<12} {:<10} {:>8} {:>7.1}% {:>8.3}",
            index + 1,
            e.experiment,
            e.user,
            e.learning_type,
            e.episodes,
            e.success_rate * 100.0,
            e.mean_return
        );
    }
    Ok(())
}

// The JSON shapes: the same keys as the Python package's dicts
// (`offworld_gym.discovery.EnvInfo`, `experiments.Episode`, …).

#[derive(Serialize)]
struct Identity<'a> {
    user: &'a str,
    operator: bool,
}

/// A discovered env as `offworld gym envs --json` prints it and
/// `offworld_gym.list_envs` returns it (`offworld_gym.discovery.EnvInfo`).
#[derive(Serialize)]
pub struct EnvInfo<'a> {
    /// `sim/monolith-0`, …
    pub env_id: String,
    /// Its task; empty without a live controller.
    pub task: &'a str,
    /// `free`, `leased`, `maintenance` or `offline`.
    pub state: &'static str,
    /// Lease expiry while leased; the announced end of a maintenance.
    pub until_unix_ms: Option<i64>,
    /// Maintenance message or why the env is offline.
    pub message: &'a str,
    /// The lease holder, or who put the env into maintenance.
    pub who: Option<&'a str>,
    /// Live components, sorted.
    pub components: &'a [String],
    /// Booked slots in progress or ahead.
    pub bookings: &'a [Booking],
    /// The engaged e-stop latches (`site`, `env`) with their reasons.
    pub estops: BTreeMap<&'static str, &'a str>,
    /// How well its last reset put the robot at its spawn pose.
    last_reset: Option<ResetInfo>,
}

impl<'a> From<&'a EnvListing> for EnvInfo<'a> {
    fn from(listing: &'a EnvListing) -> Self {
        let (state, until_unix_ms, message, who) = match &listing.state {
            EnvState::Free => ("free", None, "", None),
            EnvState::Leased {
                until_unix_ms,
                holder,
            } => ("leased", Some(*until_unix_ms), "", Some(holder.as_str())),
            EnvState::Maintenance {
                message,
                by,
                back_unix_ms,
            } => (
                "maintenance",
                (*back_unix_ms > 0).then_some(*back_unix_ms),
                message.as_str(),
                Some(by.as_str()),
            ),
            EnvState::Offline { reason } => ("offline", None, reason.as_str(), None),
        };
        Self {
            env_id: listing.env.to_string(),
            task: &listing.task,
            state,
            until_unix_ms,
            message,
            who,
            components: &listing.components,
            bookings: &listing.bookings,
            estops: engaged_estops(listing).into_iter().collect(),
            last_reset: ResetInfo::of(&listing.last_reset),
        }
    }
}

#[derive(Serialize)]
struct ResetInfo {
    requested: [f64; 3],
    achieved: [f64; 3],
    position_error_m: f64,
    yaw_error_rad: f64,
    duration_s: f64,
    unix_ms: i64,
}

impl ResetInfo {
    fn of(reset: &ResetAccuracy) -> Option<Self> {
        let pose = |p: &Pose2D| [p.x, p.y, p.yaw];
        reset.measured.then(|| Self {
            requested: pose(&reset.requested),
            achieved: pose(&reset.achieved),
            position_error_m: reset.position_error_m,
            yaw_error_rad: reset.yaw_error_rad,
            duration_s: reset.duration_s,
            unix_ms: reset.unix_ms,
        })
    }
}

#[derive(Serialize)]
struct ExperimentEpisodes<'a> {
    experiment: ExperimentRecord,
    episodes: Vec<EpisodeInfo<'a>>,
}

#[derive(Serialize)]
struct EpisodeInfo<'a> {
    index: u64,
    seed: Option<u64>,
    steps: u32,
    episode_return: f64,
    success: bool,
    end_reason: &'a str,
    started_unix_ms: i64,
    ended_unix_ms: i64,
    reset: Option<ResetInfo>,
    recordings: &'a [RecordingFile],
}

impl<'a> From<&'a EpisodeRecordEntry> for EpisodeInfo<'a> {
    fn from(ep: &'a EpisodeRecordEntry) -> Self {
        Self {
            index: ep.index,
            seed: ep.seeded.then_some(ep.seed),
            steps: ep.steps,
            episode_return: ep.episode_return,
            success: ep.success,
            end_reason: &ep.end_reason,
            started_unix_ms: ep.started_unix_ms,
            ended_unix_ms: ep.ended_unix_ms,
            reset: ResetInfo::of(&ep.reset),
            recordings: &ep.recordings,
        }
    }
}

#[derive(Serialize)]
struct Ranked<'a> {
    rank: usize,
    #[serde(flatten)]
    entry: &'a LeaderboardEntry,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_command_line_is_consistent() {
        #[derive(clap::Parser)]
        struct Parent {
            #[command(subcommand)]
            command: Command,
        }
        Parent::command().debug_assert();
    }

    #[test]
    fn start_times_with_an_offset_are_that_instant() {
        // 2026-12-01T13:00:00Z
        let instant = 1_796_130_000_000;
        for text in [
            "2026-12-01T13:00Z",
            "2026-12-01T13:00:00Z",
            "2026-12-01T13:00:00.000Z",
            "2026-12-01 13:00Z",
            "2026-12-01T14:00+01:00",
            "2026-12-01T08:00:00-05:00",
        ] {
            assert_eq!(parse_time(text), Ok(instant), "{text}");
        }
    }

    #[test]
    fn start_times_without_an_offset_are_local() {
        use chrono::TimeZone;
        let local = chrono::NaiveDate::from_ymd_opt(2026, 12, 1)
            .and_then(|d| d.and_hms_opt(14, 0, 0))
            .expect("a valid date");
        let expected = chrono::Local
            .from_local_datetime(&local)
            .earliest()
            .expect("14:00 exists")
            .timestamp_millis();
        assert_eq!(parse_time("2026-12-01T14:00"), Ok(expected));
        assert_eq!(parse_time("2026-12-01 14:00:00"), Ok(expected));
    }

    #[test]
    fn a_start_that_is_not_a_time_is_named() {
        let refused = parse_time("tomorrow").expect_err("not a time");
        assert!(
            refused.contains("`tomorrow` is not an ISO date and time"),
            "{refused}"
        );
        assert!(parse_time("2026-13-01T14:00").is_err());
    }

    #[test]
    fn times_print_as_iso_utc_to_the_second() {
        assert_eq!(when(1_796_130_000_999), "2026-12-01T13:00:00+00:00");
        assert_eq!(
            reset_text(&ResetAccuracy {
                position_error_m: 0.032,
                yaw_error_rad: 1.4_f64.to_radians(),
                duration_s: 41.5,
                ..ResetAccuracy::default()
            }),
            "3.2 cm 1.4° 41.5 s"
        );
    }

    #[test]
    fn usage_mistakes_exit_2_and_say_what_is_missing() {
        assert_eq!(run_from(vec!["offworld_gym".into(), "bookings".into()]), 2);
        assert_eq!(run_from(vec!["offworld_gym".into(), "--version".into()]), 0);
    }

    #[test]
    fn a_non_positive_duration_is_refused_before_anything_is_sent() {
        for value in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            let refused = seconds(value, "--minutes").expect_err("refused");
            assert_eq!(
                refused.to_string(),
                format!("--minutes must be a positive number, got {value}")
            );
        }
    }
}
