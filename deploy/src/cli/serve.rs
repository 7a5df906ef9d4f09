//! `offworld serve`: the gym server ([`offworld_env_controller::cli`]) with
//! an in-process sim twin for every `sim/` env on request.
//!
//! ```text
//! offworld serve --env sim/monolith-0=MonolithDiscrete --embedded-twins [--twin-profile FILE] [--render-threads N]
//! ```

use std::path::PathBuf;
use std::process::ExitCode;

use offworld_env_controller::cli::{until_signalled, ServeArgs, Site};

use crate::embedded::{Embedded, SimEnv, Stepping, TwinProfile};
use offworld_sim_twin::RENDER_THREADS_LIMIT;

/// `serve`'s flags: the server's, and its twins'.
#[derive(clap::Args)]
pub struct Args {
    #[command(flatten)]
    server: ServeArgs,
    /// Also run an in-process sim twin for every `sim/` env.
    #[arg(long)]
    embedded_twins: bool,
    /// The embedded twins behave like this physical robot (a twin
    /// profile, docs/twin-profile.md); default: the nominal twin.
    #[arg(long, value_name = "FILE", requires = "embedded_twins")]
    twin_profile: Option<PathBuf>,
    /// Threads each embedded twin renders a frame on (as `sim_twin
    /// --render-threads`; `OFFWORLD_RENDER_THREADS` is for gym front ends,
    /// not read here): more pays while cores idle.
    #[arg(long, default_value_t = 1, requires = "embedded_twins",
          value_parser = clap::value_parser!(u16).range(1..=i64::from(RENDER_THREADS_LIMIT)))]
    render_threads: u16,
}

/// Runs `serve` on the database named before the command (if any).
pub fn run(db_before_command: Option<PathBuf>, args: Args) -> ExitCode {
    offworld_program::run(serve(db_before_command, args))
}

async fn serve(db_before_command: Option<PathBuf>, args: Args) -> anyhow::Result<()> {
    // Read before anything starts: a bad file names itself and its field.
    let twin_profile = match &args.twin_profile {
        Some(path) => TwinProfile::load(path)?,
        None => TwinProfile::default(),
    };
    let site = args.server.open(db_before_command).await?;
    if !args.embedded_twins {
        let controller = site.serve().await?;
        return until_signalled(|reason| async move { controller.shutdown(&reason).await }).await;
    }
    let embedded = start_embedded(site, twin_profile, args.render_threads.into()).await?;
    until_signalled(|reason| async move { embedded.shutdown(&reason).await }).await
}

/// Every env of `site` with its own in-process twin.
async fn start_embedded(
    site: Site,
    profile: TwinProfile,
    render_threads: usize,
) -> anyhow::Result<Embedded> {
    let sims: Vec<SimEnv> = site
        .envs
        .iter()
        .map(|(env, task)| SimEnv {
            env: env.clone(),
            task: task.name.clone(),
            resolution: None,
            seed: 0,
            profile,
            render_threads,
            stepping: Stepping::OwnThread,
        })
        .collect();
    Ok(Embedded::start_with(
        &site.session,
        &sims,
        site.store,
        site.options,
        site.limits,
        site.record.as_deref(),
    )
    .await?)
}
