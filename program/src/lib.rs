//! What every OffWorld program shares, beside the contract
//! (`offworld_runtime`): its entry point ([`run`]), logging
//! ([`init_logging`]), session and key-file flags ([`CommonArgs`],
//! [`SealArgs`]), background thread priority ([`priority`]) and where it
//! keeps files across restarts ([`state_dir`]). Stop signals are the
//! contract's (`offworld_runtime::shutdown`): a session waiting for its
//! endpoint hears them.

use std::path::PathBuf;

use offworld_runtime::seal::{SealError, SealKey};
use offworld_runtime::session::{
    Mode, SessionConfig, DEFAULT_ENDPOINT, ENV_CFG, ENV_CONFIG, ENV_CONNECT, ENV_LISTEN, ENV_MODE,
};
use strum::VariantNames;

pub mod priority;
pub mod state_dir;

/// Session flags shared by every binary (flatten into a clap parser).
#[derive(Debug, Clone, Default, clap::Args)]
pub struct CommonArgs {
    /// Zenoh JSON5 config file (a role file of `deploy/roles/`): TLS,
    /// credentials, endpoints. The component's own settings have their own
    /// flag (`--robot-config`, `--calibration`, …).
    #[arg(short = 'c', long = "zenoh-config", env = ENV_CONFIG, value_name = "JSON5")]
    pub zenoh_config: Option<PathBuf>,
    /// Session role (the same variable the Python client reads, so one
    /// environment connects a client and its servers alike). Default: a
    /// program that connects is a client of what it connects to (which
    /// then routes everything to it: a monitor sees the twins behind a
    /// controller) and waits for it; a serving program, the robot agent
    /// and the base guard are peers; with `--zenoh-config`, the file's.
    #[arg(short, long, env = ENV_MODE, value_parser = mode_parser())]
    pub mode: Option<Mode>,
    /// Endpoints to connect to (repeatable), e.g. tcp/127.0.0.1:7447.
    #[arg(short = 'e', long, value_delimiter = ',', env = ENV_CONNECT)]
    pub connect: Vec<String>,
    /// Endpoints to listen on (repeatable).
    #[arg(short, long, value_delimiter = ',', env = ENV_LISTEN)]
    pub listen: Vec<String>,
    /// Enable UDP multicast scouting.
    #[arg(long)]
    pub multicast_scouting: bool,
    /// Override one config value, `KEY:VALUE` with a JSON5 value
    /// (repeatable), e.g. `--cfg 'transport/auth/usrpwd/password:"…"'`.
    #[arg(long = "cfg", value_name = "KEY:VALUE", env = ENV_CFG, value_delimiter = ';')]
    pub cfg: Vec<String>,
}

/// `--mode`: one of [`Mode`]'s names, listed in `--help`.
fn mode_parser() -> impl clap::builder::TypedValueParser<Value = Mode> {
    use clap::builder::{PossibleValuesParser, TypedValueParser};
    PossibleValuesParser::new(Mode::VARIANTS).try_map(|name| name.parse::<Mode>())
}

impl CommonArgs {
    fn is_unset(&self) -> bool {
        self.listen.is_empty() && self.connect.is_empty() && self.zenoh_config.is_none()
    }

    /// The session of a serving process: listens on [`DEFAULT_ENDPOINT`]
    /// unless endpoints or a config file are given.
    pub fn server_config(mut self) -> SessionConfig {
        if self.is_unset() {
            self.listen.push(DEFAULT_ENDPOINT.into());
        }
        let mode = self.mode.unwrap_or(Mode::Peer);
        self.into_config(mode)
    }

    /// The session of a connecting process: connects to [`DEFAULT_ENDPOINT`]
    /// unless endpoints or a config file are given; a client unless a mode
    /// (or a config file) says otherwise.
    pub fn client_config(self) -> SessionConfig {
        self.connecting(Mode::Client)
    }

    /// The session of a process on the robot's own Zenoh network (the
    /// robot agent, the base guard): connects as [`Self::client_config`],
    /// but as a peer unless told otherwise, so that its direct links to
    /// the base driver outlive the robot's router.
    pub fn robot_side_config(self) -> SessionConfig {
        self.connecting(Mode::Peer)
    }

    fn connecting(mut self, default: Mode) -> SessionConfig {
        if self.is_unset() {
            self.connect.push(DEFAULT_ENDPOINT.into());
        }
        let mode = self.mode.unwrap_or(if self.zenoh_config.is_some() {
            // Keeps the file's own mode (see `to_zenoh`).
            Mode::Peer
        } else {
            default
        });
        self.into_config(mode)
    }

    fn into_config(self, mode: Mode) -> SessionConfig {
        SessionConfig {
            config_file: self.zenoh_config,
            mode,
            connect: self.connect,
            listen: self.listen,
            multicast_scouting: self.multicast_scouting,
            overrides: self.cfg,
        }
    }
}

/// The key files a component is given (`--command-key`, `--tracker-key`),
/// the same flags on every binary that takes them.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct SealArgs {
    /// The site's command key (a file of 64 hex digits, mode 600): the
    /// real-site controller seals every command, heartbeat and reset drive
    /// with it; a robot agent given it obeys nothing else.
    #[arg(long, value_name = "FILE", env = "OFFWORLD_COMMAND_KEY")]
    pub command_key: Option<PathBuf>,
    /// The site's tracker key: the tracker agent seals its poses and
    /// tracking reports with it; a controller or robot agent given it
    /// believes no other pose.
    #[arg(long, value_name = "FILE", env = "OFFWORLD_TRACKER_KEY")]
    pub tracker_key: Option<PathBuf>,
}

impl SealArgs {
    /// The command key, if given (loaded and checked).
    pub fn command(&self) -> Result<Option<SealKey>, SealError> {
        self.command_key.as_deref().map(SealKey::load).transpose()
    }

    /// The tracker key, if given (loaded and checked).
    pub fn tracker(&self) -> Result<Option<SealKey>, SealError> {
        self.tracker_key.as_deref().map(SealKey::load).transpose()
    }
}

/// For a command that prints from local files and ends (a listing, a
/// table): a reader that stops reading early (`offworld users list | head
/// -1`) ends the program quietly, as it ends `ls`, where `println!` would
/// panic on the closed pipe. Only for commands without network links:
/// Rust's socket writes pass `MSG_NOSIGNAL`, but vectored ones (`writev`,
/// as TLS streams write) do not, and a closed link must be an error the
/// program reports, not a silent death.
#[allow(unsafe_code)] // one libc call, see SAFETY below
pub fn end_quietly_when_output_closes() {
    #[cfg(unix)]
    // SAFETY: `signal` with SIG_DFL installs no handler code; it only
    // restores the disposition every non-Rust program starts with.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}

/// Logging for binaries and examples: `RUST_LOG` or `info`, on stderr
/// (stdout stays for a command's output, e.g. a printed token).
pub fn init_logging() {
    use std::io::IsTerminal;
    // zenoh 1.10.2's Unix-socket link warns on every connection it makes
    // (a connecting socket has no name of its own): a sim farm's components
    // on the router's local socket would log it at each (re)connect.
    let filter = tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| {
        tracing_subscriber::EnvFilter::new("info,zenoh=warn,zenoh_link_unixsock_stream=error")
    });
    // Colour for people at a terminal; plain text in files, pipes and
    // journald, and wherever NO_COLOR is set (no-color.org).
    let colour = std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none();
    // A second init (tests, embedding) is harmless.
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(colour)
        .try_init();
}

/// What every OffWorld program's entry point does (`env_controller`,
/// `sim_twin`, … and the matching `offworld` subcommand alike): logging as
/// [`init_logging`], `body` on a multi-threaded Tokio runtime (as
/// `#[tokio::main]`), and its result as the exit status (an error printed
/// as `Error: …` with its causes, as `main` returning `Result` does).
pub fn run<R: std::process::Termination>(
    body: impl std::future::Future<Output = R>,
) -> std::process::ExitCode {
    run_on(None, body)
}

/// [`run`] on `workers` runtime threads (default: one per core),
/// for a program that must stay small beside others (the base guard).
pub fn run_on<R: std::process::Termination>(
    workers: Option<usize>,
    body: impl std::future::Future<Output = R>,
) -> std::process::ExitCode {
    init_logging();
    let mut builder = tokio::runtime::Builder::new_multi_thread();
    if let Some(workers) = workers {
        builder.worker_threads(workers);
    }
    match builder.enable_all().build() {
        Ok(runtime) => {
            let status = runtime.block_on(body).report();
            // What the program awaited has finished; a task still holding
            // its thread (Zenoh retrying a connection when a stop came) is
            // abandoned instead of holding the exit.
            runtime.shutdown_timeout(std::time::Duration::from_secs(2));
            status
        }
        Err(e) => {
            eprintln!("Error: cannot start the async runtime: {e}");
            std::process::ExitCode::FAILURE
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What connects is a client of it (routed everything, e.g. the twins
    /// behind a peer controller), what serves a peer; a mode given, or a
    /// config file's, is kept.
    #[test]
    fn connecting_programs_are_clients_and_serving_ones_peers_by_default() {
        let connecting = CommonArgs::default().client_config();
        assert_eq!(connecting.mode, Mode::Client);
        assert_eq!(connecting.connect, [DEFAULT_ENDPOINT]);
        let serving = CommonArgs::default().server_config();
        assert_eq!(serving.mode, Mode::Peer);
        assert_eq!(serving.listen, [DEFAULT_ENDPOINT]);
        let explicit = CommonArgs {
            mode: Some(Mode::Peer),
            ..CommonArgs::default()
        };
        assert_eq!(explicit.client_config().mode, Mode::Peer);
        assert_eq!(CommonArgs::default().robot_side_config().mode, Mode::Peer);
        let role_file = CommonArgs {
            zenoh_config: Some("deploy/roles/monitor.json5".into()),
            ..CommonArgs::default()
        };
        // Peer here means "the file's own mode" (`to_zenoh` keeps it).
        assert_eq!(role_file.client_config().mode, Mode::Peer);
    }

    #[test]
    fn the_mode_flag_takes_the_modes_names_only() {
        use clap::Parser;
        #[derive(clap::Parser)]
        struct Flags {
            #[command(flatten)]
            common: CommonArgs,
        }
        let parsed = Flags::try_parse_from(["p", "--mode", "router"]).expect("router");
        assert_eq!(parsed.common.mode, Some(Mode::Router));
        let refused = Flags::try_parse_from(["p", "--mode", "hub"])
            .err()
            .expect("hub is no mode");
        assert_eq!(refused.kind(), clap::error::ErrorKind::InvalidValue);
        assert!(refused
            .to_string()
            .contains("[possible values: peer, client, router]"));
    }
}
