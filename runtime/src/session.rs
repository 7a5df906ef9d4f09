//! Opening Zenoh sessions: one config type shared by every binary and the
//! Python package, filled from a config file, environment variables, CLI
//! flags or defaults.

use std::path::PathBuf;
use std::time::Duration;

use crate::error::ContractError;

/// Environment variable naming a Zenoh JSON5 config file.
pub const ENV_CONFIG: &str = "OFFWORLD_ZENOH_CONFIG";
/// Environment variable: `peer`, `client` or `router`.
pub const ENV_MODE: &str = "OFFWORLD_ZENOH_MODE";
/// Environment variable: comma-separated endpoints to connect to.
pub const ENV_CONNECT: &str = "OFFWORLD_ZENOH_CONNECT";
/// Environment variable: comma-separated endpoints to listen on.
pub const ENV_LISTEN: &str = "OFFWORLD_ZENOH_LISTEN";
/// Environment variable: `;`-separated `KEY:VALUE` config overrides (as
/// zenohd's `--cfg`), e.g. `transport/auth/usrpwd/password:"…"`.
pub const ENV_CFG: &str = "OFFWORLD_ZENOH_CFG";

/// Zenoh session role.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Default,
    strum::IntoStaticStr,
    strum::EnumIter,
    strum::VariantNames,
)]
#[strum(serialize_all = "snake_case")]
pub enum Mode {
    /// Talks to other peers directly.
    #[default]
    Peer,
    /// Talks only through a router.
    Client,
    /// Routes for others.
    Router,
}

impl Mode {
    /// Its name in configs and flags (`peer`, `client`, `router`).
    pub fn as_str(self) -> &'static str {
        self.into()
    }
}

impl std::str::FromStr for Mode {
    type Err = ContractError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        crate::named::parse("mode", s).map_err(ContractError::Config)
    }
}

/// How to open a session. Explicit endpoints; multicast scouting is off
/// unless asked for, so tests and embedded envs never find strangers.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct SessionConfig {
    /// A Zenoh JSON5 config file applied first; the fields below override it.
    pub config_file: Option<PathBuf>,
    /// Role.
    pub mode: Mode,
    /// Endpoints to connect to, e.g. `tcp/127.0.0.1:7447`.
    pub connect: Vec<String>,
    /// Endpoints to listen on.
    pub listen: Vec<String>,
    /// Discover peers by UDP multicast.
    pub multicast_scouting: bool,
    /// `KEY:VALUE` overrides applied last, as zenohd's `--cfg`: the key is
    /// a config path (`transport/link/tls/root_ca_certificate`), the value
    /// JSON5 (`"certs/ca.pem"`, `true`, `["tls/…"]`).
    pub overrides: Vec<String>,
}

impl SessionConfig {
    /// An isolated peer: no listening, no scouting. In-process components
    /// sharing it talk to each other and to nobody else.
    pub fn isolated() -> Self {
        Self::default()
    }

    /// A peer listening on `endpoint`.
    pub fn listening(endpoint: impl Into<String>) -> Self {
        Self {
            listen: vec![endpoint.into()],
            ..Self::default()
        }
    }

    /// A peer connecting to `endpoint`.
    pub fn connecting(endpoint: impl Into<String>) -> Self {
        Self {
            connect: vec![endpoint.into()],
            ..Self::default()
        }
    }

    /// Reads [`ENV_CONFIG`], [`ENV_MODE`], [`ENV_CONNECT`], [`ENV_LISTEN`];
    /// unset variables keep the defaults.
    pub fn from_env() -> Result<Self, ContractError> {
        let list = |name: &str| -> Vec<String> {
            std::env::var(name)
                .map(|v| {
                    v.split(',')
                        .map(str::trim)
                        .filter(|s| !s.is_empty())
                        .map(str::to_owned)
                        .collect()
                })
                .unwrap_or_default()
        };
        Ok(Self {
            config_file: std::env::var_os(ENV_CONFIG).map(PathBuf::from),
            mode: match std::env::var(ENV_MODE) {
                Ok(mode) => mode.parse()?,
                Err(_) => Mode::Peer,
            },
            connect: list(ENV_CONNECT),
            listen: list(ENV_LISTEN),
            multicast_scouting: false,
            overrides: std::env::var(ENV_CFG)
                .map(|v| {
                    v.split(';')
                        .map(str::trim)
                        .filter(|s| !s.is_empty())
                        .map(str::to_owned)
                        .collect()
                })
                .unwrap_or_default(),
        })
    }

    /// [`SessionConfig::from_env`] for a client of a remote deployment
    /// (the Python client's `connect=`): a client of what it connects to
    /// unless [`ENV_MODE`] or a config file says otherwise, as the
    /// programs' [`CommonArgs::client_config`].
    pub fn connecting_from_env() -> Result<Self, ContractError> {
        let mut config = Self::from_env()?;
        if std::env::var_os(ENV_MODE).is_none() && config.config_file.is_none() {
            config.mode = Mode::Client;
        }
        Ok(config)
    }

    /// Builds the Zenoh config.
    pub fn to_zenoh(&self) -> Result<zenoh::Config, ContractError> {
        let mut config = match &self.config_file {
            Some(path) => zenoh::Config::from_file(path).map_err(|e| {
                ContractError::Config(format!("cannot load {}: {e}", path.display()))
            })?,
            None => zenoh::Config::default(),
        };
        let set = |config: &mut zenoh::Config, key: &str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| ContractError::Config(format!("{key} = {value}: {e}")))
        };
        let json_list =
            |items: &[String]| serde_json::to_string(items).unwrap_or_else(|_| "[]".to_owned());
        // A config file keeps its own mode and endpoints unless overridden.
        if self.config_file.is_none() || self.mode != Mode::Peer {
            set(&mut config, "mode", format!("\"{}\"", self.mode.as_str()))?;
        }
        if !self.connect.is_empty() {
            set(&mut config, "connect/endpoints", json_list(&self.connect))?;
        }
        if !self.listen.is_empty() {
            set(&mut config, "listen/endpoints", json_list(&self.listen))?;
        } else if self.config_file.is_none() && self.mode == Mode::Peer {
            // Default peers listen nowhere: an embedded env opens no port.
            set(&mut config, "listen/endpoints", "[]".to_owned())?;
        }
        if self.config_file.is_none() || self.multicast_scouting {
            set(
                &mut config,
                "scouting/multicast/enabled",
                self.multicast_scouting.to_string(),
            )?;
        }
        // Zenoh drops a stream sample after waiting 1 ms for a full queue;
        // on a loaded 2-core host (or a TLS hop) that loses most of a
        // stream. Wait up to 50 ms first. What a step cannot lose (commands
        // and their answers) is published with `Delivery::Every` instead.
        if self.config_file.is_none() {
            set(
                &mut config,
                "transport/link/tx/queue/congestion_control/drop/wait_before_drop",
                PATIENT_DROP_US.to_string(),
            )?;
        }
        for item in &self.overrides {
            let (key, value) = item.split_once(':').ok_or_else(|| {
                ContractError::Config(format!(
                    "`{item}`: expected KEY:VALUE, e.g. mode:\"client\""
                ))
            })?;
            set(&mut config, key.trim(), value.trim().to_owned())?;
        }
        if self.waits_for_its_endpoint(&config) {
            // A client waits for what it connects to, as a peer does (Zenoh's
            // client default: one attempt, then fail), so programs may
            // start in any order; one-shot clients bound the wait
            // (`open_reaching`).
            set(&mut config, "connect/timeout_ms", "-1".to_owned())?;
        }
        links_compiled_in(&config, cfg!(feature = "tls-quic"))?;
        Ok(config)
    }

    /// Whether this session, a client, waits for its endpoint to answer:
    /// our own config (a role file keeps Zenoh's one attempt, which the
    /// credential checks rely on), exactly one endpoint (Zenoh tries a
    /// client's endpoints in turn, each until it answers: a dead first one
    /// would hide the others), and no `--cfg` of the timeout.
    fn waits_for_its_endpoint(&self, config: &zenoh::Config) -> bool {
        self.config_file.is_none()
            && is_client(config)
            && self.connect.len() == 1
            && !self
                .overrides
                .iter()
                .any(|o| o.trim_start().starts_with("connect/timeout_ms"))
    }

    /// Opens the session, and says where it listens and connects (a
    /// person starting a program learns which address to give the others)
    /// and whether anyone answered at the endpoints it connects to. A
    /// client waits here until one of its endpoints answers.
    pub async fn open(&self) -> Result<zenoh::Session, ContractError> {
        self.open_with(self.to_zenoh()?, None).await
    }

    async fn open_with(
        &self,
        config: zenoh::Config,
        within: Option<Duration>,
    ) -> Result<zenoh::Session, ContractError> {
        let listen = config.get_json("listen/endpoints").unwrap_or_default();
        let connect = config.get_json("connect/endpoints").unwrap_or_default();
        let client = is_client(&config);
        // The mode in effect (a config file's, if it names one).
        let mode = config
            .get_json("mode")
            .map(|m| m.trim_matches('"').to_owned())
            .unwrap_or_default();
        let waits = within.is_none() && self.waits_for_its_endpoint(&config);
        if client {
            let waiting = match within {
                Some(within) => format!("waiting up to {} ms", within.as_millis()),
                None if waits => "waiting until it answers".to_owned(),
                None => "one attempt per endpoint".to_owned(),
            };
            tracing::info!(%connect, "connecting as a client ({waiting})");
        }
        for refusal in local_sockets_refusing(&connect) {
            tracing::warn!("{refusal}");
        }
        let session = if waits {
            // A stop while waiting ends the wait (the program's own signal
            // handlers only act once its session is open).
            // Zenoh's open may hold its thread while it retries: on a task
            // of its own, the signal is still heard.
            let opening = tokio::spawn(async move { zenoh::open(config).await });
            tokio::select! {
                opened = opening => opened
                    .map_err(|e| ContractError::Zenoh(format!("opening the session: {e}")))?
                    .map_err(ContractError::from)?,
                signal = crate::shutdown::signalled() => {
                    return Err(ContractError::Zenoh(format!(
                        "stopped ({}) while waiting for {} to answer",
                        signal.map_or_else(|e| e.to_string(), |s| s.to_string()),
                        self.connect.join(", ")
                    )));
                }
            }
        } else {
            zenoh::open(config).await.map_err(ContractError::from)?
        };
        if client {
            // A client listens nowhere, whatever the config's defaults say.
            tracing::info!(%mode, %connect, "zenoh session open");
        } else {
            tracing::info!(%mode, %listen, %connect, "zenoh session open");
        }
        if !client && !self.connect.is_empty() && !answered(&session).await {
            tracing::warn!(
                "nobody answers at {} yet: still trying (is the address right, and is \
                 the router or server there running?)",
                self.connect.join(", ")
            );
        }
        Ok(session)
    }

    /// [`SessionConfig::open`] for a one-shot client (a listing, a booking,
    /// opening an env, an e-stop): when it names endpoints to connect to,
    /// one of them must answer (a router or a peer connected) within
    /// `within`, else [`ContractError::Unreachable`] names them. A peer
    /// session otherwise opens fine with nobody there, and an unreachable
    /// deployment would look like an empty one; a client would wait.
    pub async fn open_reaching(&self, within: Duration) -> Result<zenoh::Session, ContractError> {
        let unreachable = || ContractError::Unreachable {
            endpoints: self.connect.join(", "),
            waited_ms: u64::try_from(within.as_millis()).unwrap_or(u64::MAX),
        };
        let mut config = self.to_zenoh()?;
        if is_client(&config) {
            if self.waits_for_its_endpoint(&config) {
                let timeout = within.as_millis().to_string();
                config
                    .insert_json5("connect/timeout_ms", &timeout)
                    .map_err(|e| ContractError::Config(format!("connect/timeout_ms: {e}")))?;
            }
            return match self.open_with(config, Some(within)).await {
                // Nobody answered; any other failure (a refused
                // certificate or password, a bad endpoint) says so itself.
                Err(ContractError::Zenoh(e))
                    if !self.connect.is_empty() && e.contains("Unable to connect") =>
                {
                    Err(unreachable())
                }
                other => other,
            };
        }
        let session = self.open_with(config, None).await?;
        if self.connect.is_empty() {
            return Ok(session);
        }
        let deadline = tokio::time::Instant::now() + within;
        loop {
            if answered(&session).await {
                return Ok(session);
            }
            if tokio::time::Instant::now() >= deadline {
                let _ = session.close().await;
                return Err(unreachable());
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

/// The scheme of a Unix-socket endpoint (`unixsock-stream/PATH`): the
/// site router's local socket, for a sim farm on its host.
pub const UNIX_SOCKET_LINK: &str = "unixsock-stream/";

/// Refuses the site's links (TLS, QUIC, the router's local socket) in a
/// build without them (the `tls-quic` feature off: the demo's lean wheel),
/// where Zenoh would fail later with its bare "unsupported protocol".
fn links_compiled_in(config: &zenoh::Config, tls_quic: bool) -> Result<(), ContractError> {
    if tls_quic {
        return Ok(());
    }
    for key in ["connect/endpoints", "listen/endpoints"] {
        let endpoints = config.get_json(key).unwrap_or_default();
        let site_links = ["tls/", "quic/", UNIX_SOCKET_LINK];
        if site_links
            .iter()
            .any(|link| endpoints.contains(&format!("\"{link}")))
        {
            return Err(ContractError::Config(format!(
                "{key} = {endpoints}: this build has no TLS, QUIC or Unix-socket links (offworld-runtime's \
                 `tls-quic` feature; the demo's lean offworld_gym package is built without \
                 it): `bash .ci/setup` builds the full one"
            )));
        }
    }
    Ok(())
}

/// Why each `unixsock-stream/PATH` endpoint of `endpoints` (a config's
/// JSON list) refuses this process, tried once: Zenoh's own warning
/// (`zenoh_link_unixsock_stream`) is filtered out, as it also fires on
/// every connection that succeeds, and its retries log at debug.
fn local_sockets_refusing(endpoints: &str) -> Vec<String> {
    let endpoints: Vec<String> = serde_json::from_str(endpoints).unwrap_or_default();
    endpoints
        .iter()
        .filter_map(|endpoint| {
            let path = endpoint.strip_prefix(UNIX_SOCKET_LINK)?;
            let path = path.split(['?', '#']).next().unwrap_or(path);
            let refused = std::os::unix::net::UnixStream::connect(path).err()?;
            let hint = match refused.kind() {
                std::io::ErrorKind::NotFound => {
                    "no socket there: is the router running on this host, and is the path right?"
                }
                std::io::ErrorKind::PermissionDenied => {
                    "run this program as the user the socket belongs to (`offworld` in deploy/systemd)"
                }
                std::io::ErrorKind::ConnectionRefused => {
                    "the router that made it is not running"
                }
                _ => "is the router running on this host?",
            };
            Some(format!(
                "the router's local socket {endpoint} refuses this process: {refused} ({hint})"
            ))
        })
        .collect()
}

/// Whether `config` opens a client session (its own mode, or a file's).
fn is_client(config: &zenoh::Config) -> bool {
    config.get_json("mode").is_ok_and(|m| m == "\"client\"")
}

/// Whether a router or a peer is connected to `session`.
async fn answered(session: &zenoh::Session) -> bool {
    let info = session.info();
    info.routers_zid().await.next().is_some() || info.peers_zid().await.next().is_some()
}

/// How long a one-shot client waits for one of its endpoints to answer
/// ([`SessionConfig::open_reaching`]): a router on the other side of the
/// world connects well within it.
pub const REACH_WITHIN: Duration = Duration::from_secs(3);

/// How long a publisher waits for room in a full queue before Zenoh drops
/// the message, µs (Zenoh's default: 1000). Deployment files set the same.
pub const PATIENT_DROP_US: u64 = 50_000;

/// Where standalone processes meet when no endpoint is given: servers
/// (controller, routers) listen here and everything else connects here.
pub const DEFAULT_ENDPOINT: &str = "tcp/127.0.0.1:7447";

/// Where [`loopback_endpoint`] picks ports: below Linux's ephemeral range
/// (32768–60999), so that no `bind(0)` or outgoing connection elsewhere in
/// the process can be handed the port between our check and the listen.
const TEST_PORTS: std::ops::Range<u16> = 20_000..32_000;

/// A port free on the loopback address `ip` (e.g. `127.0.0.1`), for tests
/// and benches that start a listener or hand the port to another process.
pub fn free_loopback_port(ip: &str) -> std::io::Result<u16> {
    use rand::Rng;
    let mut rng = rand::rng();
    let mut attempts = 0;
    loop {
        let port = rng.random_range(TEST_PORTS);
        // Free for TCP and UDP alike: QUIC endpoints listen on UDP.
        let bound = std::net::TcpListener::bind((ip, port))
            .and_then(|_tcp| std::net::UdpSocket::bind((ip, port)));
        match bound {
            Ok(_) => return Ok(port),
            Err(e) if attempts >= 64 => return Err(e),
            Err(_) => attempts += 1,
        }
    }
}

/// A TCP endpoint on a free loopback port, for tests and benches that need
/// to listen.
pub fn loopback_endpoint() -> std::io::Result<String> {
    Ok(format!(
        "tcp/127.0.0.1:{}",
        free_loopback_port("127.0.0.1")?
    ))
}

/// Two sessions joined over TCP on loopback: (listener, connector).
pub async fn loopback_pair() -> Result<(zenoh::Session, zenoh::Session), ContractError> {
    // Another test may take the same free port before our listen: retry.
    let mut attempts = 0;
    let (listener, endpoint) = loop {
        let endpoint = loopback_endpoint().map_err(|e| ContractError::Config(e.to_string()))?;
        match SessionConfig::listening(&endpoint).open().await {
            Ok(session) => break (session, endpoint),
            Err(e) if attempts >= 4 => return Err(e),
            Err(_) => attempts += 1,
        }
    };
    let connector = SessionConfig::connecting(&endpoint).open().await?;
    Ok((listener, connector))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn isolated_peer_has_no_endpoints_and_no_scouting() {
        let config = SessionConfig::isolated().to_zenoh().expect("config");
        assert_eq!(config.get_json("mode").expect("mode"), "\"peer\"");
        assert_eq!(config.get_json("listen/endpoints").expect("listen"), "[]");
        assert_eq!(
            config
                .get_json("scouting/multicast/enabled")
                .expect("scouting"),
            "false"
        );
    }

    #[test]
    fn endpoints_and_mode_are_applied() {
        let cfg = SessionConfig {
            mode: Mode::Client,
            connect: vec!["tcp/127.0.0.1:7447".into()],
            ..SessionConfig::default()
        };
        let config = cfg.to_zenoh().expect("config");
        assert_eq!(config.get_json("mode").expect("mode"), "\"client\"");
        assert!(config
            .get_json("connect/endpoints")
            .expect("connect")
            .contains("tcp/127.0.0.1:7447"));
    }

    #[test]
    fn bad_inputs_are_typed_errors() {
        assert!(matches!(
            "hub".parse::<Mode>(),
            Err(ContractError::Config(_))
        ));
        let cfg = SessionConfig {
            connect: vec!["not an endpoint".into()],
            ..SessionConfig::default()
        };
        assert!(matches!(cfg.to_zenoh(), Err(ContractError::Config(_))));
        let cfg = SessionConfig {
            config_file: Some("/nonexistent/zenoh.json5".into()),
            ..SessionConfig::default()
        };
        assert!(matches!(cfg.to_zenoh(), Err(ContractError::Config(_))));
    }

    #[test]
    fn a_local_socket_that_refuses_says_why() {
        let dir =
            std::env::temp_dir().join(format!("offworld-sockets-{}", crate::keys::random_id()));
        std::fs::create_dir(&dir).expect("scratch");
        let listening = dir.join("router.sock");
        let _listener = std::os::unix::net::UnixListener::bind(&listening).expect("bind");
        let missing = dir.join("missing.sock");
        let endpoints = serde_json::json!([
            format!("unixsock-stream/{}", listening.display()),
            format!("unixsock-stream/{}", missing.display()),
            "tcp/127.0.0.1:7447",
        ])
        .to_string();
        let refusals = local_sockets_refusing(&endpoints);
        std::fs::remove_dir_all(&dir).ok();
        assert_eq!(refusals.len(), 1, "{refusals:?}");
        assert!(
            refusals[0].contains(&missing.display().to_string())
                && refusals[0].contains("is the router running on this host"),
            "{}",
            refusals[0]
        );
        assert!(local_sockets_refusing("not json").is_empty());
    }

    #[test]
    fn site_link_endpoints_are_refused_in_a_build_without_them() {
        for endpoint in [
            "quic/router.example:7447",
            "tls/127.0.0.1:7447",
            "unixsock-stream//run/offworld/zenohd.sock",
        ] {
            let config = SessionConfig::connecting(endpoint)
                .to_zenoh()
                .expect("this test build has the links");
            match links_compiled_in(&config, false) {
                Err(ContractError::Config(message)) => {
                    assert!(message.contains(endpoint), "{message}");
                    assert!(
                        message.contains("no TLS, QUIC or Unix-socket links"),
                        "{message}"
                    );
                    assert!(message.contains("bash .ci/setup"), "{message}");
                }
                other => panic!("{endpoint}: {other:?}"),
            }
            assert!(links_compiled_in(&config, true).is_ok());
        }
        let tcp = SessionConfig::connecting("tcp/127.0.0.1:7447")
            .to_zenoh()
            .expect("tcp");
        assert!(links_compiled_in(&tcp, false).is_ok());
        let listening = SessionConfig::listening("quic/127.0.0.1:0")
            .to_zenoh()
            .expect("listen");
        assert!(links_compiled_in(&listening, false).is_err());
    }

    #[test]
    fn overrides_apply_last_and_bad_ones_are_typed_errors() {
        let cfg = SessionConfig {
            mode: Mode::Client,
            overrides: vec![
                r#"transport/auth/usrpwd/user:"trainer""#.into(),
                "transport/link/tls/enable_mtls: true".into(),
                r#"mode:"router""#.into(),
            ],
            ..SessionConfig::default()
        };
        let config = cfg.to_zenoh().expect("config");
        assert_eq!(
            config.get_json("transport/auth/usrpwd/user").expect("user"),
            "\"trainer\""
        );
        assert_eq!(
            config
                .get_json("transport/link/tls/enable_mtls")
                .expect("mtls"),
            "true"
        );
        assert_eq!(config.get_json("mode").expect("mode"), "\"router\"");
        for bad in ["no-colon", "nonexistent/key:1", "mode:[unclosed"] {
            let cfg = SessionConfig {
                overrides: vec![bad.into()],
                ..SessionConfig::default()
            };
            assert!(
                matches!(cfg.to_zenoh(), Err(ContractError::Config(_))),
                "{bad}"
            );
        }
    }
}
