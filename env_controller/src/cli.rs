//! `env_controller`: the gym server and its record-keeping CLI.
//!
//! ```text
//! env_controller serve --env real/monolith-0=MonolithDiscrete
//! env_controller users add alice [--operator]
//! env_controller users list | revoke alice | rotate alice
//! env_controller experiments list
//! env_controller leaderboard --env sim/monolith-0
//! env_controller estop --env real/monolith-0 --reason "person in the enclosure" [--release]
//! env_controller estop --site --reason "fire alarm"
//! ```
//!
//! The server links no simulator: `offworld serve --embedded-twins`
//! (`offworld_deploy`) adds in-process twins to the same [`ServeArgs`].

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use crate::link::LinkSeals;
use crate::store::{self, BookingRules};
use crate::{Controller, EnvOptions, RequestLimits, Store, Task};
use anyhow::Context;
use clap::{Parser, Subcommand};
use offworld_client::operator::{press_estop, EStopScope, PressError};
use offworld_program::CommonArgs;
use offworld_program::SealArgs;
use offworld_runtime::seal::Sealer;
use offworld_runtime::{EnvId, Realm};
use zenoh::Session;

/// The OffWorld gym server.
#[derive(Parser)]
#[command(version)]
pub struct Args {
    /// SQLite database of users, experiments and episodes (also after the
    /// command, e.g. `users --db FILE list`).
    #[arg(long, value_name = "FILE")]
    db: Option<PathBuf>,
    #[command(subcommand)]
    command: ServerCommand,
}

/// `env_controller`'s commands: serving, and the record-keeping ones.
#[derive(Subcommand)]
enum ServerCommand {
    /// Serve envs over Zenoh.
    Serve(ServeArgs),
    #[command(flatten)]
    Records(Command),
}

/// The site's database, for the commands that keep records: `--db` on the
/// command line (before or after the command), else `OFFWORLD_DB`, else
/// `offworld.db`.
#[derive(clap::Args)]
pub struct Database {
    /// SQLite database of users, experiments and episodes [env:
    /// OFFWORLD_DB] [default: offworld.db].
    #[arg(long = "db", value_name = "FILE", global = true)]
    path: Option<PathBuf>,
}

impl Database {
    /// The path in force, given the one named before the command.
    fn resolve(self, before_command: Option<PathBuf>) -> PathBuf {
        self.path
            .or(before_command)
            .or_else(|| std::env::var_os("OFFWORLD_DB").map(PathBuf::from))
            .unwrap_or_else(|| PathBuf::from("offworld.db"))
    }
}

/// What `env_controller` (or `offworld`) does besides serving: each
/// variant's fields are its flags, documented in its `--help`.
#[allow(missing_docs)] // The flattened groups and subcommands document their own flags.
#[derive(Subcommand)]
pub enum Command {
    /// Manage users.
    Users {
        #[command(flatten)]
        db: Database,
        #[command(subcommand)]
        command: UsersCommand,
    },
    /// Manage experiments.
    Experiments {
        #[command(flatten)]
        db: Database,
        #[command(subcommand)]
        command: ExperimentsCommand,
    },
    /// Print the leaderboard of an env (test-mode experiments).
    Leaderboard {
        /// Env id.
        #[arg(long)]
        env: EnvId,
        #[command(flatten)]
        db: Database,
    },
    /// Press (or release) an e-stop: one env's robot, or every robot of the site.
    Estop {
        /// The env whose robot stops.
        #[arg(long, required_unless_present = "site", conflicts_with = "site")]
        env: Option<EnvId>,
        /// Every robot of the site.
        #[arg(long)]
        site: bool,
        /// Who and why, for the robots' logs.
        #[arg(long)]
        reason: String,
        /// Release instead of press.
        #[arg(long)]
        release: bool,
        /// How long to wait for a robot or twin to listen, s.
        #[arg(long, default_value_t = 5.0)]
        wait_s: f64,
        /// Every robot agent and twin present must acknowledge within this
        /// long, ms (else the command fails).
        #[arg(long, default_value_t = 1000)]
        ack_ms: u64,
        #[command(flatten)]
        common: CommonArgs,
    },
}

/// `serve`: the envs, the site's policy and limits, how to reach Zenoh.
#[derive(clap::Args)]
pub struct ServeArgs {
    /// `ENV=TASK`, repeatable, e.g. `sim/monolith-0=MonolithDiscrete`.
    #[arg(long = "env", required = true)]
    envs: Vec<String>,
    /// Real envs also put the robot's pose and distance to the monolith
    /// in each step's info (sim envs always do): privileged information.
    #[arg(long)]
    share_real_pose: bool,
    /// Record every episode of every env served as an MCAP file under
    /// this directory (see docs/recording.md).
    #[arg(long, value_name = "DIR", env = "OFFWORLD_RECORD")]
    record: Option<PathBuf>,
    /// Lease idle timeout, s.
    #[arg(long, default_value_t = 300)]
    lease_idle_s: u64,
    /// Longest booking slot, minutes.
    #[arg(long, default_value_t = 240)]
    max_slot_minutes: u32,
    /// How far ahead a booking may start, days.
    #[arg(long, default_value_t = 30)]
    booking_horizon_days: u32,
    /// Requests queued or running per env (waiting for its state or the
    /// store); more are answered Busy at once. `status` and `spec`
    /// never queue.
    #[arg(long, default_value_t = RequestLimits::default().env_queue)]
    env_queue: usize,
    /// Requests one client may have queued or running per env.
    #[arg(long, default_value_t = RequestLimits::default().client_queue)]
    client_queue: usize,
    /// Requests per second one client may send, sustained.
    #[arg(long, default_value_t = RequestLimits::default().client_rate_per_s)]
    client_rate: u32,
    /// Requests one client may send at once above `--client-rate`.
    #[arg(long, default_value_t = RequestLimits::default().client_burst)]
    client_burst: u32,
    /// Largest request accepted, bytes (larger: BadRequest, undecoded).
    #[arg(long, default_value_t = RequestLimits::default().max_request_bytes)]
    max_request_bytes: usize,
    #[command(flatten)]
    seals: SealArgs,
    #[command(flatten)]
    db: Database,
    #[command(flatten)]
    common: CommonArgs,
}

/// A site ready to serve: what [`ServeArgs`] named, checked, with the
/// database and the Zenoh session open.
pub struct Site {
    /// The envs to serve and their tasks.
    pub envs: Vec<(EnvId, Task)>,
    /// The session every env is served on.
    pub session: Session,
    /// Users, experiments, episodes.
    pub store: Store,
    /// The site's policy (anonymous access is per env: sim only).
    pub options: EnvOptions,
    /// Request limits.
    pub limits: RequestLimits,
    /// Keys for commands to, and poses from, real robots.
    pub seals: LinkSeals,
    /// Record every episode under this directory.
    pub record: Option<PathBuf>,
}

impl ServeArgs {
    /// Checks everything named and opens the database and the session:
    /// a mistake is refused here, before any env starts.
    pub async fn open(self, db_before_command: Option<PathBuf>) -> anyhow::Result<Site> {
        let db = self.db.resolve(db_before_command);
        let envs: Vec<(EnvId, Task)> = self
            .envs
            .iter()
            .map(|e| parse_env(e))
            .collect::<Result<_, _>>()?;
        let seals = LinkSeals {
            command: self.seals.command()?.map(|key| Arc::new(Sealer::new(key))),
            tracker: self.seals.tracker()?,
        };
        if envs.iter().any(|(env, _)| env.realm() == Realm::Real) {
            if seals.command.is_none() {
                tracing::warn!("commands to real robots are not sealed (no --command-key): the router's access control is their only guard");
            }
            if seals.tracker.is_none() {
                tracing::warn!("tracker poses are believed unsealed (no --tracker-key): the router's access control is their only guard");
            }
        }
        let options = EnvOptions {
            lease_idle: std::time::Duration::from_secs(self.lease_idle_s),
            share_real_pose: self.share_real_pose,
            booking_rules: BookingRules {
                max_slot_ms: i64::from(self.max_slot_minutes) * 60_000,
                horizon_ms: i64::from(self.booking_horizon_days) * 86_400_000,
                ..BookingRules::default()
            },
            ..EnvOptions::default()
        };
        let limits = RequestLimits {
            env_queue: self.env_queue,
            client_queue: self.client_queue,
            client_rate_per_s: self.client_rate,
            client_burst: self.client_burst,
            max_request_bytes: self.max_request_bytes,
        };
        // Refused here, before anything starts, rather than per env.
        options.check()?;
        limits.check()?;
        let store = Store::open(&db)?;
        let session = self.common.server_config().open().await?;
        Ok(Site {
            envs,
            session,
            store,
            options,
            limits,
            seals,
            record: self.record,
        })
    }
}

impl Site {
    /// Serves every env with a controller (the robots or twins that
    /// embody them run elsewhere, under the same namespaces).
    pub async fn serve(self) -> anyhow::Result<Controller> {
        let mut controller = Controller::with_limits(self.session, self.store, self.limits)?;
        controller.seal_with(self.seals);
        if let Some(dir) = &self.record {
            controller.record_into(dir)?;
            tracing::info!(dir = %dir.display(), "recording every episode");
        }
        for (env, task) in self.envs {
            let options = EnvOptions {
                allow_anonymous: env.realm() == Realm::Sim,
                ..self.options
            };
            controller.serve(env, task, options).await?;
        }
        Ok(controller)
    }
}

/// Serves until a stop signal, then calls `stop` with the reason.
pub async fn until_signalled<F: std::future::Future<Output = ()>>(
    stop: impl FnOnce(String) -> F,
) -> anyhow::Result<()> {
    tracing::info!("serving; Ctrl-C, SIGTERM or SIGHUP to stop");
    let signal = offworld_runtime::shutdown::signalled().await?;
    // Robots told to stop, episodes in progress recorded; then the
    // liveliness tokens go with the deployment.
    stop(format!("the controller stopped ({signal})")).await;
    Ok(())
}

/// `users …`.
#[derive(Subcommand)]
pub enum UsersCommand {
    /// Register a user and print their token (stored hashed; shown once).
    Add {
        /// User name.
        name: String,
        /// May put envs into maintenance, revoke leases and use the web
        /// page's operator console.
        #[arg(long)]
        operator: bool,
    },
    /// List the registered users (never their tokens).
    List,
    /// Revoke a user's token: it no longer opens, books or administers
    /// (their experiments stay; `rotate` issues a new one).
    Revoke {
        /// User name.
        name: String,
    },
    /// Issue a user a new token (printed once); the old one stops working.
    Rotate {
        /// User name.
        name: String,
    },
}

/// `experiments …`.
#[derive(Subcommand)]
pub enum ExperimentsCommand {
    /// List experiments, newest first.
    List,
}

/// `users …`: the record-keeping of who may use the gym.
fn users(db: &std::path::Path, command: UsersCommand) -> anyhow::Result<()> {
    match command {
        UsersCommand::Add { name, operator } => {
            let token = Store::open(db)?.add_user(&name, operator)?;
            println!("{token}");
        }
        UsersCommand::List => {
            let users = Store::open_existing(db)?.users()?;
            if users.is_empty() {
                println!("no users yet: `users add NAME` registers one");
                return Ok(());
            }
            println!(
                "{:<24} {:<9} {:<20} {:<20} {:>11}  token",
                "name", "role", "registered", "token issued", "experiments"
            );
            for user in users {
                let token = match user.revoked_ms {
                    Some(at) => format!("revoked {}", store::format_unix_ms(at)),
                    None => "active".to_owned(),
                };
                println!(
                    "{:<24} {:<9} {:<20} {:<20} {:>11}  {token}",
                    user.name,
                    user.role,
                    store::format_unix_ms(user.created_ms),
                    store::format_unix_ms(user.token_issued_ms),
                    user.experiments
                );
            }
        }
        UsersCommand::Revoke { name } => {
            Store::open_existing(db)?.revoke_user(&name)?;
            println!(
                "{name}'s token is revoked: it no longer opens, books or administers \
                 (a lease taken before runs until it ends; revoke it from the web console)"
            );
        }
        UsersCommand::Rotate { name } => {
            let token = Store::open_existing(db)?.rotate_token(&name)?;
            println!("{token}");
            eprintln!("{name}'s new token (shown once); the old one no longer works");
        }
    }
    Ok(())
}

fn parse_env(text: &str) -> anyhow::Result<(EnvId, Task)> {
    let (env, task) = text
        .split_once('=')
        .context("--env must look like sim/monolith-0=MonolithDiscrete")?;
    Ok((env.parse()?, Task::by_name(task)?))
}

/// Runs `env_controller` with these arguments.
pub fn run(args: Args) -> ExitCode {
    match args.command {
        ServerCommand::Serve(serve) => offworld_program::run(async move {
            let controller = serve.open(args.db).await?.serve().await?;
            until_signalled(|reason| async move { controller.shutdown(&reason).await }).await
        }),
        ServerCommand::Records(command) => run_command(args.db, command),
    }
}

/// Runs one of its record-keeping commands on the database `db` (also
/// `offworld users`, …).
pub fn run_command(db: Option<PathBuf>, command: Command) -> ExitCode {
    offworld_program::run(main_async(db, command))
}

async fn main_async(db_before: Option<PathBuf>, command: Command) -> anyhow::Result<()> {
    match command {
        Command::Estop {
            env,
            site: _,
            reason,
            release,
            wait_s,
            ack_ms,
            common,
        } => {
            let scope = env.map_or(EStopScope::Site, EStopScope::Env);
            let wait = std::time::Duration::try_from_secs_f64(wait_s)
                .context("--wait-s must be a non-negative number of seconds")?;
            let ack_within = std::time::Duration::from_millis(ack_ms);
            // A press nobody can hear is an error within seconds, naming the
            // endpoint, never a wait.
            let session = common
                .client_config()
                .open_reaching(offworld_runtime::session::REACH_WITHIN)
                .await?;
            let pressed = press_estop(&session, &scope, !release, &reason, wait, ack_within).await;
            session.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
            let verb = if release { "released" } else { "engaged" };
            let report = match &pressed {
                Ok(report) => report,
                Err(
                    PressError::Unacknowledged { report, .. }
                    | PressError::Overtaken { report, .. },
                ) => report,
                Err(_) => return Ok(pressed.map(drop)?),
            };
            println!("e-stop {verb} on {}", scope.key());
            for ack in &report.acknowledged {
                println!(
                    "  acknowledged by {} of {} in {} ms (e-stops now engaged: {})",
                    ack.component,
                    ack.env,
                    ack.after.as_millis(),
                    ack.state.summary()
                );
            }
            for (env, component) in &report.silent {
                println!("  NOT acknowledged by {component} of {env}");
            }
            pressed?;
        }
        Command::Users { db, command } => users(&db.resolve(db_before), command)?,
        Command::Experiments {
            db,
            command: ExperimentsCommand::List,
        } => {
            let db = db.resolve(db_before);
            let store = Store::open_existing(&db)?;
            let experiments = store.experiments()?;
            if experiments.is_empty() {
                println!("no experiments yet in {}", db.display());
                return Ok(());
            }
            println!(
                "{:<5} {:<12} {:<20} {:<28} {:<10} {:<6} {:>8} {:>8}",
                "id", "user", "env", "experiment", "type", "mode", "episodes", "steps"
            );
            for e in experiments {
                println!(
                    "{:<5} {:<12} {:<20} {:<28} {:<10} {:<6} {:>8} {:>8}",
                    e.id,
                    e.user,
                    e.env_id,
                    e.name,
                    e.learning_type,
                    e.algorithm_mode,
                    e.episodes,
                    e.steps
                );
            }
        }
        Command::Leaderboard { env, db } => {
            let store = Store::open_existing(&db.resolve(db_before))?;
            let board = store.leaderboard(&env.to_string())?;
            if board.is_empty() {
                println!("no test-mode experiments on {env} yet: its leaderboard is empty");
                return Ok(());
            }
            println!("leaderboard of {env} (test-mode experiments)");
            offworld_client::cli::print_leaderboard_table(&board)?;
        }
    }
    Ok(())
}
