//! A site behind the real `zenohd` router, built from the deployment's own
//! files (`deploy/router/zenohd.json5`: TLS, mutual TLS for site
//! components, user/password for everyone, access control; one role file
//! per component in `deploy/roles/`; certificates from
//! `deploy/certs/generate.sh`). The files are compiled into this crate and
//! written beside the site's certificates, so an installed `offworld`
//! needs no checkout; only paths, passwords and addresses are overridden
//! (`--cfg`), never the rules.
//!
//! On one machine the router listens on two loopback addresses other than
//! 127.0.0.1: `127.0.0.2` for trainers (server-authenticated TLS) and
//! `127.0.0.3` for site components (mutual TLS). With [`Namespaced`] the
//! router and the site components run in network namespaces made
//! beforehand instead. It also listens on a Unix socket in the site's
//! directory, the way a sim farm on the router's own host reaches it
//! ([`Link::LocalSocket`]).

use std::io::Write;
use std::os::unix::fs::DirBuilderExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Duration;

use offworld_runtime::session::{free_loopback_port, UNIX_SOCKET_LINK};
use offworld_runtime::SessionConfig;

use crate::process::{offworld_command, wait_until_listening, Process};

/// The router's configuration (`deploy/router/zenohd.json5`).
const ROUTER_CONFIG: &str = include_str!("../router/zenohd.json5");

/// How long the router may take to open its listeners.
const ROUTER_START_LIMIT: Duration = Duration::from_secs(20);

/// How often a starting router is checked for having exited.
const ROUTER_POLL: Duration = Duration::from_millis(250);

/// The certificate generator (`deploy/certs/generate.sh`).
const GENERATE_CERTIFICATES: &str = include_str!("../certs/generate.sh");

/// The router's local socket in the site's directory (a deployment's is
/// `/run/offworld-router/zenohd.sock`: `deploy/router/zenohd.json5`).
const LOCAL_SOCKET: &str = "zenohd.sock";

/// How a component reaches the router.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Link {
    /// Over the network: QUIC with the role's TLS (mutual TLS for site
    /// components), as a component on another host does.
    Network,
    /// Over the router's local Unix socket, as a sim farm on the router's
    /// own host does: a password and no certificate; the router's access
    /// control lets only the sim roles act through it.
    LocalSocket,
}

/// The roles of `deploy/roles/` (and of the router's ACL subjects).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// A researcher's client: gym queries and spectator keys only.
    Trainer,
    /// The gym server of the real site.
    Controller,
    /// The gym server of a sim-farm host (confined to `sim/`).
    SimController,
    /// A sim twin (an agent).
    SimTwin,
    /// The robot agent.
    RobotAgent,
    /// The tracker agent.
    TrackerAgent,
    /// An operator: e-stops, admin, watching everything.
    Operator,
    /// The lab's web page: read-only queries, spectator keys, e-stops.
    LabWeb,
}

impl Role {
    /// Every role.
    pub const ALL: [Role; 8] = [
        Role::Trainer,
        Role::Controller,
        Role::SimController,
        Role::SimTwin,
        Role::RobotAgent,
        Role::TrackerAgent,
        Role::Operator,
        Role::LabWeb,
    ];

    /// The role's user name, certificate common name and file stem.
    pub fn name(self) -> &'static str {
        match self {
            Role::Trainer => "trainer",
            Role::Controller => "env_controller",
            Role::SimController => "sim_controller",
            Role::SimTwin => "sim_twin",
            Role::RobotAgent => "robot_agent",
            Role::TrackerAgent => "tracker_agent",
            Role::Operator => "operator",
            Role::LabWeb => "lab_web",
        }
    }

    /// Site components connect with a client certificate (mutual TLS).
    pub fn is_site(self) -> bool {
        self != Role::Trainer
    }

    /// The role's Zenoh configuration (`deploy/roles/<role>.json5`).
    pub fn config(self) -> &'static str {
        match self {
            Role::Trainer => include_str!("../roles/trainer.json5"),
            Role::Controller => include_str!("../roles/env_controller.json5"),
            Role::SimController => include_str!("../roles/sim_controller.json5"),
            Role::SimTwin => include_str!("../roles/sim_twin.json5"),
            Role::RobotAgent => include_str!("../roles/robot_agent.json5"),
            Role::TrackerAgent => include_str!("../roles/tracker_agent.json5"),
            Role::Operator => include_str!("../roles/operator.json5"),
            Role::LabWeb => include_str!("../roles/lab_web.json5"),
        }
    }
}

/// Writes a certificate authority, the router's certificate (for
/// `router_san`, default localhost and 127.0.0.1–9), one client
/// certificate per site role and the site's seal keys into `dir`
/// (`deploy/certs/generate.sh`; needs `bash` and `openssl`).
pub fn generate_certificates(dir: &Path, router_san: Option<&str>) -> anyhow::Result<()> {
    let mut command = Command::new("bash");
    command.args(["-s", "--"]).arg(dir);
    if let Some(san) = router_san {
        command.arg(san);
    }
    let mut child = command
        .stdin(Stdio::piped())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| anyhow::anyhow!("bash (to generate certificates): {e}"))?;
    if let Some(mut stdin) = child.stdin.take() {
        stdin.write_all(GENERATE_CERTIFICATES.as_bytes())?;
    }
    let out = child.wait_with_output()?;
    anyhow::ensure!(
        out.status.success(),
        "generating certificates (deploy/certs/generate.sh, needs openssl) failed: {}",
        String::from_utf8_lossy(&out.stderr).trim()
    );
    Ok(())
}

fn json_string(s: &str) -> String {
    serde_json::to_string(s).unwrap_or_else(|_| format!("\"{s}\""))
}

/// zenohd's access-control module (a macro: [`SITE_LOG`] is built from it).
macro_rules! acl_log_target {
    () => {
        "zenoh::net::routing::interceptor::access_control"
    };
}

/// zenohd's access-control module: its decisions are logged at trace level.
pub const ACL_LOG_TARGET: &str = acl_log_target!();

/// The log filter of the router and the components (`ZENOHD_LOG` overrides
/// the router's): warnings, except the access-control module's warning on
/// every link that rules naming network interfaces may misapply
/// (eclipse-zenoh/zenoh#1204): the deployment's rules name none; and
/// except the Unix-socket link's warning on every connection it makes
/// (zenoh 1.10.2 warns that a connecting socket has no name of its own).
pub const SITE_LOG: &str = concat!(
    "warn,",
    acl_log_target!(),
    "=error,zenoh_link_unixsock_stream=error"
);

/// Where a namespaced site runs: network namespaces made beforehand (`ip
/// netns add`; needs CAP_NET_ADMIN), the router reachable from this host
/// and from the site namespace on addresses of its own.
#[derive(Debug, Clone)]
pub struct Namespaced {
    /// The router's namespace.
    pub router: String,
    /// The site components' namespace.
    pub site: String,
    /// The router's address on the host link (trainers connect here).
    pub router_host_ip: String,
    /// The router's address on the site link (site components connect here).
    pub router_site_ip: String,
}

/// The router and the files of one deployment (removed on drop).
pub struct RouterSite {
    /// Certificates, users.txt, role files, databases.
    pub dir: PathBuf,
    /// Where trainers connect: `quic/127.0.0.2:<port>`.
    pub trainer_endpoint: String,
    /// Where site components connect: `quic/127.0.0.3:<port>` (mutual TLS).
    pub site_endpoint: String,
    /// Where site components spawned by [`RouterSite::spawn`] connect (the
    /// router's site-side address when the site has its own namespace).
    site_endpoint_inside: String,
    /// The router's listeners (QUIC; TLS over TCP added on the same ports).
    listen: [String; 2],
    /// The router's local socket ([`Link::LocalSocket`]).
    local_socket: PathBuf,
    router: Option<Process>,
    /// Extra `--cfg` of the router (see [`RouterSite::restart_router_with`]).
    router_cfg: Vec<String>,
    /// Where the router's log goes when audited ([`RouterSite::audit_router`]).
    router_log: Option<PathBuf>,
    namespaced: Option<Namespaced>,
}

impl RouterSite {
    /// Generates certificates and passwords, writes the deployment's files,
    /// starts `zenohd` and waits until both listeners accept connections.
    pub fn start(name: &str) -> anyhow::Result<Self> {
        Self::create(name, None)
    }

    /// Like [`RouterSite::start`], with the router and the site in network
    /// namespaces: in-process sessions are trainers and operators on the
    /// host, [`RouterSite::spawn`]ed components live in the site namespace.
    pub fn start_namespaced(name: &str, namespaced: Namespaced) -> anyhow::Result<Self> {
        Self::create(name, Some(namespaced))
    }

    /// The namespaces, if the site runs in some.
    pub fn namespaced(&self) -> Option<&Namespaced> {
        self.namespaced.as_ref()
    }

    fn create(name: &str, namespaced: Option<Namespaced>) -> anyhow::Result<Self> {
        let dir = std::env::temp_dir().join(format!(
            "offworld-site-{name}-{}-{}",
            std::process::id(),
            offworld_runtime::keys::random_id()
        ));
        let local_socket = dir.join(LOCAL_SOCKET);
        // The kernel's limit on a socket's path (`sun_path`, 108 bytes).
        anyhow::ensure!(
            local_socket.as_os_str().len() < 108,
            "the router's socket path {} is too long for a Unix socket: set TMPDIR to a shorter directory",
            local_socket.display()
        );
        let mut site = match &namespaced {
            None => {
                let trainer = format!("quic/127.0.0.2:{}", free_loopback_port("127.0.0.2")?);
                let site = format!("quic/127.0.0.3:{}", free_loopback_port("127.0.0.3")?);
                Self {
                    listen: [trainer.clone(), site.clone()],
                    trainer_endpoint: trainer,
                    site_endpoint_inside: site.clone(),
                    site_endpoint: site,
                    local_socket,
                    dir,
                    router: None,
                    router_cfg: Vec::new(),
                    router_log: None,
                    namespaced,
                }
            }
            // A fresh namespace: the deployment's own ports are free.
            Some(ns) => Self {
                listen: ["quic/0.0.0.0:7447".into(), "quic/0.0.0.0:7448".into()],
                trainer_endpoint: format!("quic/{}:7447", ns.router_host_ip),
                site_endpoint: format!("quic/{}:7448", ns.router_host_ip),
                site_endpoint_inside: format!("quic/{}:7448", ns.router_site_ip),
                local_socket,
                dir,
                router: None,
                router_cfg: Vec::new(),
                router_log: None,
                namespaced,
            },
        };
        // Made once `site` owns it: an error from here on removes it.
        // Its owner's only: it holds the keys, and the router's socket
        // (whose sim passwords a trial site derives from the user names).
        std::fs::DirBuilder::new().mode(0o700).create(&site.dir)?;
        std::fs::create_dir(site.dir.join("roles"))?;
        let san = site
            .namespaced
            .as_ref()
            .map(|ns| format!("IP:{},IP:{}", ns.router_host_ip, ns.router_site_ip));
        generate_certificates(&site.dir, san.as_deref())?;
        let users: String = Role::ALL
            .iter()
            .map(|r| format!("{}:{}\n", r.name(), Self::password(r.name())))
            .collect();
        std::fs::write(site.dir.join("users.txt"), users)?;
        std::fs::write(site.dir.join("zenohd.json5"), ROUTER_CONFIG)?;
        for role in Role::ALL {
            std::fs::write(site.role_file(role), role.config())?;
        }
        site.start_router()?;
        Ok(site)
    }

    /// This site's copy of `deploy/roles/<role>.json5`.
    pub fn role_file(&self, role: Role) -> PathBuf {
        self.dir.join(format!("roles/{}.json5", role.name()))
    }

    /// Every role connects through the router's TLS-over-TCP listeners
    /// from now on instead of QUIC (same ports, same certificates).
    pub fn use_tls_over_tcp(&mut self) {
        self.trainer_endpoint = Self::over_tcp(&self.trainer_endpoint);
        self.site_endpoint = Self::over_tcp(&self.site_endpoint);
        self.site_endpoint_inside = Self::over_tcp(&self.site_endpoint_inside);
    }

    /// The TLS-over-TCP fallback of a QUIC endpoint (same port number).
    pub fn over_tcp(endpoint: &str) -> String {
        endpoint.replacen("quic/", "tls/", 1)
    }

    /// The password of a user on this site (users.txt): a trial site's,
    /// derived from the user name.
    pub fn password(user: &str) -> String {
        format!("{user}-secret")
    }

    /// Starts (or restarts) `zenohd` on the same endpoints and waits until it
    /// accepts connections.
    pub fn start_router(&mut self) -> anyhow::Result<()> {
        self.stop_router();
        let file = |name: &str| json_string(&self.dir.join(name).to_string_lossy());
        // QUIC, and the TLS-over-TCP fallback on the same port numbers.
        let mtls = |endpoint: &str| format!("{endpoint}#enable_mtls=true");
        let [trainers, site] = &self.listen;
        let listen = format!(
            "[{},{},{},{},{}]",
            json_string(trainers),
            json_string(&mtls(site)),
            json_string(&Self::over_tcp(trainers)),
            json_string(&mtls(&Self::over_tcp(site))),
            json_string(&self.local_endpoint())
        );
        let overrides = [
            format!("transport/link/tls/root_ca_certificate:{}", file("ca.pem")),
            format!(
                "transport/link/tls/listen_private_key:{}",
                file("router.key")
            ),
            format!(
                "transport/link/tls/listen_certificate:{}",
                file("router.pem")
            ),
            format!(
                "transport/auth/usrpwd/dictionary_file:{}",
                file("users.txt")
            ),
            format!("listen/endpoints:{listen}"),
        ];
        let mut args = vec![
            "-c".to_owned(),
            self.dir.join("zenohd.json5").to_string_lossy().into_owned(),
        ];
        for o in overrides.iter().chain(&self.router_cfg) {
            args.push("--cfg".into());
            args.push(o.clone());
        }
        let mut command = match &self.namespaced {
            Some(ns) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", &ns.router]).arg(zenohd());
                c
            }
            None => Command::new(zenohd()),
        };
        let chosen = std::env::var("ZENOHD_LOG").ok();
        let (log, stdout, stderr) = match &self.router_log {
            Some(path) => {
                // zenohd logs each access-control decision at trace level,
                // on stdout.
                let log = format!(
                    "{},{ACL_LOG_TARGET}=trace",
                    chosen.as_deref().unwrap_or("warn")
                );
                let file = std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(path)?;
                (log, Stdio::from(file.try_clone()?), Stdio::from(file))
            }
            None => (
                chosen.unwrap_or_else(|| SITE_LOG.to_owned()),
                Stdio::null(),
                Stdio::inherit(),
            ),
        };
        let child = command
            .args(&args)
            .env("RUST_LOG", log)
            // As deploy/README.md runs it: glibc's default arenas double
            // the router's growth at client reconnects (docs/soak.md).
            .env("MALLOC_ARENA_MAX", "2")
            .stdout(stdout)
            .stderr(stderr)
            .spawn()
            .map_err(|e| anyhow::anyhow!("zenohd (`.ci/setup` installs it): {e}"))?;
        let mut router = Process(child);
        // zenohd opens its listeners together: the TCP ones answering
        // means the QUIC ones are up too. One deadline for all; a router
        // that exits (a listener it cannot open) is reported at once.
        let deadline = std::time::Instant::now() + ROUTER_START_LIMIT;
        for endpoint in [
            Self::over_tcp(&self.trainer_endpoint),
            Self::over_tcp(&self.site_endpoint),
            self.local_endpoint(),
        ] {
            while let Err(e) = wait_until_listening(None, &endpoint, ROUTER_POLL) {
                if let Some(status) = router.0.try_wait()? {
                    anyhow::bail!("zenohd exited ({status}) before listening at {endpoint}");
                }
                if std::time::Instant::now() >= deadline {
                    anyhow::bail!("zenohd: {e} (waited {ROUTER_START_LIMIT:?} in all)");
                }
            }
        }
        self.router = Some(router);
        Ok(())
    }

    /// Restarts the router logging every access-control decision (what a
    /// site's security engineer audits: `…is unauthorized to Put (ingress)
    /// on <key>`) into a file, read by [`RouterSite::router_log`].
    pub fn audit_router(&mut self) -> anyhow::Result<()> {
        self.router_log = Some(self.dir.join("router.log"));
        self.start_router()
    }

    /// The audited router's log so far (empty when not audited).
    pub fn router_log(&self) -> String {
        self.router_log
            .as_ref()
            .and_then(|path| std::fs::read_to_string(path).ok())
            .unwrap_or_default()
    }

    /// Restarts the router with extra `--cfg KEY:VALUE` settings on top of
    /// the deployment's (e.g. `access_control/enabled:false`).
    pub fn restart_router_with(&mut self, cfg: &[&str]) -> anyhow::Result<()> {
        self.router_cfg = cfg.iter().map(|c| c.to_string()).collect();
        self.start_router()
    }

    /// Kills the router (SIGKILL): every link drops at once.
    pub fn stop_router(&mut self) {
        self.router = None;
    }

    /// The endpoint a role connects to.
    pub fn endpoint(&self, role: Role) -> &str {
        if role.is_site() {
            &self.site_endpoint
        } else {
            &self.trainer_endpoint
        }
    }

    /// The router's local socket: `unixsock-stream/<site dir>/zenohd.sock`.
    pub fn local_endpoint(&self) -> String {
        format!("{UNIX_SOCKET_LINK}{}", self.local_socket.display())
    }

    /// Where a component of `role` connects over `link`.
    fn endpoint_over(&self, role: Role, link: Link) -> String {
        match link {
            Link::Network => self.endpoint(role).to_owned(),
            Link::LocalSocket => self.local_endpoint(),
        }
    }

    /// `--cfg` overrides a role's process needs on top of its role file:
    /// certificate paths and its password.
    pub fn overrides(&self, role: Role) -> Vec<String> {
        let file = |name: &str| json_string(&self.dir.join(name).to_string_lossy());
        let mut o = vec![
            format!("transport/link/tls/root_ca_certificate:{}", file("ca.pem")),
            format!(
                "transport/auth/usrpwd/password:{}",
                json_string(&Self::password(role.name()))
            ),
        ];
        if role.is_site() {
            o.push(format!(
                "transport/link/tls/connect_private_key:{}",
                file(&format!("{}.key", role.name()))
            ));
            o.push(format!(
                "transport/link/tls/connect_certificate:{}",
                file(&format!("{}.pem", role.name()))
            ));
        }
        o
    }

    /// The Zenoh flags of a component process of `role`:
    /// `-c <site>/roles/<role>.json5 --connect <endpoint> --cfg …`.
    pub fn role_args(&self, role: Role) -> Vec<String> {
        self.role_args_to(role, self.endpoint(role))
    }

    fn role_args_to(&self, role: Role, endpoint: &str) -> Vec<String> {
        let mut args = vec![
            "-c".to_owned(),
            self.role_file(role).to_string_lossy().into_owned(),
            "--connect".to_owned(),
            endpoint.to_owned(),
        ];
        for o in self.overrides(role) {
            args.push("--cfg".into());
            args.push(o);
        }
        args
    }

    /// The session config of an in-process participant of `role`.
    pub fn session(&self, role: Role) -> SessionConfig {
        self.session_over(role, Link::Network)
    }

    /// The session config of an in-process participant of `role` reaching
    /// the router over `link`.
    pub fn session_over(&self, role: Role, link: Link) -> SessionConfig {
        SessionConfig {
            config_file: Some(self.role_file(role)),
            connect: vec![self.endpoint_over(role, link)],
            overrides: self.overrides(role),
            ..SessionConfig::default()
        }
    }

    /// What a trainer process needs in its environment to reach the site:
    /// `OFFWORLD_ZENOH_CONFIG` (the trainer role file), `OFFWORLD_ZENOH_CFG`
    /// (certificate path and password) and `OFFWORLD_GYM_CONNECT`.
    pub fn trainer_env(&self) -> Vec<(String, String)> {
        vec![
            (
                offworld_runtime::session::ENV_CONFIG.to_owned(),
                self.role_file(Role::Trainer).to_string_lossy().into_owned(),
            ),
            (
                offworld_runtime::session::ENV_CFG.to_owned(),
                self.overrides(Role::Trainer).join(";"),
            ),
            (
                "OFFWORLD_GYM_CONNECT".to_owned(),
                self.trainer_endpoint.clone(),
            ),
        ]
    }

    /// Starts `offworld <command…>` as `role`, its Zenoh flags appended
    /// (site components in the site namespace, if there is one).
    pub fn spawn(&self, role: Role, command: &[&str]) -> anyhow::Result<Process> {
        self.spawn_logged(role, command, SITE_LOG)
    }

    /// Like [`RouterSite::spawn`] with the child's `RUST_LOG` filter.
    pub fn spawn_logged(&self, role: Role, command: &[&str], log: &str) -> anyhow::Result<Process> {
        self.spawn_over(role, Link::Network, command, log)
    }

    /// Like [`RouterSite::spawn_logged`], the component reaching the router
    /// over `link`.
    pub fn spawn_over(
        &self,
        role: Role,
        link: Link,
        command: &[&str],
        log: &str,
    ) -> anyhow::Result<Process> {
        let (netns, endpoint) = match &self.namespaced {
            Some(ns) if role.is_site() => {
                let endpoint = match link {
                    Link::Network => self.site_endpoint_inside.clone(),
                    Link::LocalSocket => self.local_endpoint(),
                };
                (Some(ns.site.as_str()), endpoint)
            }
            _ => (None, self.endpoint_over(role, link)),
        };
        let mut args: Vec<String> = command.iter().map(|s| s.to_string()).collect();
        args.extend(self.role_args_to(role, &endpoint));
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        Ok(Process::start(
            netns,
            &offworld_command(),
            &refs,
            log,
            Stdio::null(),
        )?)
    }
}

impl Drop for RouterSite {
    fn drop(&mut self) {
        self.stop_router();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// The router binary: `$ZENOHD` or `zenohd` on `PATH` (`.ci/env` puts the
/// project's install first).
pub fn zenohd() -> PathBuf {
    std::env::var_os("ZENOHD")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("zenohd"))
}

#[cfg(test)]
mod tests {
    use super::ROUTER_CONFIG;
    use serde_json::Value;
    use zenoh::key_expr::keyexpr;

    /// `key`'s value in the router's configuration, as JSON.
    fn setting(key: &str) -> Value {
        let config = zenoh::Config::from_json5(ROUTER_CONFIG).expect("the router's config parses");
        let json = config.get_json(key).expect(key);
        serde_json::from_str(&json).expect("JSON")
    }

    /// The strings of `list`.
    fn strings(list: &Value) -> Vec<&str> {
        list.as_array()
            .map(|a| a.iter().filter_map(Value::as_str).collect())
            .unwrap_or_default()
    }

    /// Every question access control lets a trainer, an operator or the
    /// lab's web page ask is forwarded "drop" (`gym_answers_never_wait`):
    /// a key added to their rules and not to that one would let a client
    /// that stops reading hold the controller's link again.
    #[test]
    fn every_question_a_client_may_ask_is_forwarded_drop() {
        let [drop_rule] = <[Value; 1]>::try_from(
            setting("qos/network")
                .as_array()
                .expect("qos/network")
                .clone(),
        )
        .expect("one qos rule");
        assert_eq!(drop_rule["id"], "gym_answers_never_wait");
        assert_eq!(strings(&drop_rule["messages"]), ["query"]);
        assert_eq!(strings(&drop_rule["flows"]), ["ingress"]);
        assert_eq!(drop_rule["overwrite"]["congestion_control"], "drop");
        let dropped: Vec<&keyexpr> = strings(&drop_rule["key_exprs"])
            .into_iter()
            .map(|k| keyexpr::new(k).expect("key expression"))
            .collect();

        let acl = setting("access_control");
        let clients = ["trainers", "operators", "lab_web"];
        let mut checked = 0;
        for policy in acl["policies"].as_array().expect("policies") {
            let subjects = strings(&policy["subjects"]);
            if !subjects.iter().any(|s| clients.contains(s)) {
                continue;
            }
            for id in strings(&policy["rules"]) {
                let rule = acl["rules"]
                    .as_array()
                    .expect("rules")
                    .iter()
                    .find(|r| r["id"] == id)
                    .unwrap_or_else(|| panic!("rule {id}"));
                let asks = strings(&rule["messages"]).contains(&"query")
                    && rule["permission"] == "allow"
                    && (rule["flows"].is_null() || strings(&rule["flows"]).contains(&"ingress"));
                if !asks {
                    continue;
                }
                for key in strings(&rule["key_exprs"]) {
                    let key = keyexpr::new(key).expect("key expression");
                    assert!(
                        dropped.iter().any(|d| d.includes(key)),
                        "`{key}` (rule {id}, {subjects:?}) is not forwarded drop"
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked >= 10, "only {checked} keys checked");
    }
}
