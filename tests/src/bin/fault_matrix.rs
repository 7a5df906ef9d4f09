//! `fault_matrix`: the fault-injection matrix as a report. For every
//! process of the emulated enclosure (router, hardware, controller, robot
//! agent, base guard, tracker agent) and every fault (kill -9, SIGTERM,
//! SIGSTOP for 5 s), while a step turns the robot on the worst-case base
//! (it holds the last velocity forever): how long the base kept moving,
//! how far it turned, the client's error and how soon it came; then
//! whether every episode was recorded. Prints a Markdown table
//! (`docs/safety.md` holds the latest).
//!
//! ```text
//! fault_matrix                       # the whole matrix, ~10 min
//! fault_matrix --part robot_agent    # one part
//! fault_matrix --base-timeout-ms 300 # against a base with a command timeout
//! fault_matrix --no-guard --base-timeout-ms 300 --part robot_agent  # the base's timeout alone
//! fault_matrix --part robot_link     # the robot's network link: cut, 30 % loss, 500 ms delay
//! ```
//!
//! With the robot's link among the parts (the default), the robot runs in
//! a network namespace of its own behind an impaired link (root needed).

use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use offworld_client::{ClientTimeouts, EnvClient};
use offworld_env_controller::Store;
use offworld_runtime::SessionConfig;
use offworld_tests::emulated::{EmulatedEnclosure, Options, Part};
use offworld_tests::faults::{
    inject, open_request, recover, reset_when_ready, BaseObserver, Fault, FaultOutcome,
};
use offworld_tests::link::Impairment;

#[derive(Parser)]
#[command(
    version,
    about = "Inject process faults into the emulated enclosure and report what the robot and the client saw"
)]
struct Args {
    /// Only this part (router, hardware, env_controller, robot_agent,
    /// base_guard, tracker_agent, robot_link).
    #[arg(long)]
    part: Option<String>,
    /// The emulated base stops after this long without a command (default:
    /// never, the worst case).
    #[arg(long)]
    base_timeout_ms: Option<u64>,
    /// Run without the robot's base guard (the agent then does not require
    /// one): what the base's own timeout, or nothing, does alone.
    #[arg(long)]
    no_guard: bool,
    /// Watch the base this long after each fault, s.
    #[arg(long, default_value_t = 3.0)]
    window_s: f64,
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let window = Duration::try_from_secs_f64(args.window_s).context("--window-s")?;
    let mut options = Options::new("MonolithContinuous")?;
    options.base_cmd_timeout_ms = args.base_timeout_ms;
    options.base_guard = !args.no_guard;
    let parts: Vec<Part> = Part::ALL
        .into_iter()
        .chain([Part::RobotLink])
        .filter(|p| args.part.as_deref().is_none_or(|name| name == p.name()))
        .filter(|p| *p != Part::BaseGuard || !args.no_guard)
        .collect();
    anyhow::ensure!(!parts.is_empty(), "no such part: {:?}", args.part);
    options.isolated_robot = parts.contains(&Part::RobotLink);
    let held = Duration::from_secs(5);
    let faults = |part: Part| match part {
        Part::RobotLink => vec![
            Fault::Link(Impairment::Cut, held),
            Fault::Link(Impairment::Loss { percent: 30 }, held),
            Fault::Link(Impairment::Delay(Duration::from_millis(500)), held),
        ],
        _ => vec![Fault::Kill, Fault::Terminate, Fault::Freeze(held)],
    };
    eprintln!("starting the emulated enclosure…");
    let mut deployment = EmulatedEnclosure::start(&options)?;
    deployment
        .ready(Duration::from_secs(60))
        .await
        .map_err(anyhow::Error::msg)?;
    let base = BaseObserver::connect(&deployment).await?;
    let mut outcomes: Vec<FaultOutcome> = Vec::new();
    let mut resets = 0u64;
    let matrix: Vec<(Part, Fault)> = parts
        .iter()
        .flat_map(|p| faults(*p).into_iter().map(move |f| (*p, f)))
        .collect();
    let total = matrix.len();
    for (i, (part, fault)) in matrix.into_iter().enumerate() {
        eprintln!("[{}/{total}] {} {fault}", i + 1, part.name());
        // A fresh client session each time: the controller may be the part.
        let session = SessionConfig::connecting(&deployment.endpoint)
            .open()
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut gym = EnvClient::open_when_ready(
            &session,
            &deployment.env,
            open_request(&deployment.token, "fault-matrix", resets > 0),
            ClientTimeouts::default(),
            Duration::from_secs(60),
        )
        .await
        .map_err(|e| anyhow::anyhow!("open: {e}"))?;
        reset_when_ready(&mut gym, 100 + i as u64, Duration::from_secs(90))
            .await
            .map_err(|e| anyhow::anyhow!("reset: {e}"))?;
        resets += 1;
        let watched = match fault {
            Fault::Link(_, d) => window + d,
            _ => window,
        };
        let (mut gym, outcome) = inject(&mut deployment, gym, &base, part, fault, watched).await;
        outcomes.push(outcome);
        recover(&mut deployment, part, fault).await?;
        // The session may be gone with a restarted controller.
        let _ = gym.close().await;
    }
    let store = Store::open(&deployment.dir.join("gym.db"))?;
    let recorded = store
        .experiments()?
        .into_iter()
        .find(|e| e.name == "fault-matrix")
        .map_or(0, |e| e.episodes);
    println!(
        "Base: {}{}. Each fault hits a step turning the robot at 1.5 rad/s; the base is watched for {:.0} s after each fault (after the link clears, for a link fault).\n",
        match args.base_timeout_ms {
            Some(ms) => format!("stops after {ms} ms without a command"),
            None => "holds the last velocity forever (worst case)".into(),
        },
        if args.no_guard { "; no base guard" } else { "" },
        window.as_secs_f64()
    );
    println!("| part | fault | base moved for (ms) | turned after (rad) | client error | error after (ms) |");
    println!("|---|---|---|---|---|---|");
    for o in &outcomes {
        let moved = match o.moved_for {
            _ if !o.observed => "no odometry (hardware gone)".into(),
            Some(d) => d.as_millis().to_string(),
            None => "never stopped".into(),
        };
        let error = o
            .client_error
            .as_ref()
            .map_or("none (step succeeded)".into(), |e| {
                format!("{:?}: {}", e.code, e.message)
            });
        println!(
            "| {} | {} | {moved} | {:.2} | {} | {} |",
            o.part.name(),
            o.fault,
            o.turned_rad,
            error.replace('|', "/"),
            o.result_after.as_millis()
        );
    }
    println!(
        "\nEpisodes started: {resets}; recorded: {recorded}; lost: {}.",
        resets.saturating_sub(recorded)
    );
    Ok(())
}
