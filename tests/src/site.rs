//! A distributed deployment for tests, built from the repository's own
//! deployment files: the real `zenohd` router (installed by `.ci/setup`)
//! with `deploy/router/zenohd.json5` (TLS, mutual TLS for site components,
//! user/password for everyone, access control), and every component as a
//! separate process connecting with its role file from `deploy/roles/`.
//! Certificates come from `deploy/certs/generate.sh`; only paths, passwords
//! and addresses are overridden (`--cfg`), never the rules.
//!
//! The router listens on two loopback addresses other than 127.0.0.1:
//! `127.0.0.2` for trainers (server-authenticated TLS) and `127.0.0.3` for
//! site components (mutual TLS).

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use offworld_env_controller::Store;
use offworld_runtime::session::free_loopback_port;
use offworld_runtime::{EnvId, SessionConfig};

use crate::netns::Namespaces;
use crate::{Process, Spawn};

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

    const ALL: [Role; 8] = [
        Role::Trainer,
        Role::Controller,
        Role::SimController,
        Role::SimTwin,
        Role::RobotAgent,
        Role::TrackerAgent,
        Role::Operator,
        Role::LabWeb,
    ];
}

/// The repository's `deploy/` folder.
pub fn deploy_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .unwrap_or_else(|| Path::new(".."))
        .join("deploy")
}

/// A free TCP port on `ip`.
fn json_string(s: &str) -> String {
    serde_json::to_string(s).unwrap_or_else(|_| format!("\"{s}\""))
}

/// zenohd's access-control module: its decisions are logged at trace level.
pub const ACL_LOG_TARGET: &str = "zenoh::net::routing::interceptor::access_control";

/// The router and the files of one deployment (removed on drop).
pub struct RouterSite {
    /// Certificates, users.txt, databases.
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
    router: Option<Process>,
    /// Extra `--cfg` of the router (see [`RouterSite::restart_router_with`]).
    router_cfg: Vec<String>,
    /// Where the router's log goes when audited ([`RouterSite::audit_router`]).
    router_log: Option<PathBuf>,
    /// Declared last: removed after the router and the processes stopped.
    netns: Option<Namespaces>,
}

impl RouterSite {
    /// Generates certificates and passwords, starts `zenohd` and waits until
    /// both listeners accept connections.
    pub fn start(name: &str) -> anyhow::Result<Self> {
        Self::create(name, None)
    }

    /// Like [`RouterSite::start`], with the router and the site in network
    /// namespaces of their own (see [`Namespaces`]): in-test sessions are
    /// trainers and operators on the host, [`RouterSite::spawn`]ed
    /// components live in the site namespace. Fails with the reason when
    /// namespaces cannot be made (no `ip`, no CAP_NET_ADMIN).
    pub fn start_in_namespaces(name: &str) -> anyhow::Result<Self> {
        Self::create(name, Some(Namespaces::create()?))
    }

    /// The namespaces, if the site has them.
    pub fn namespaces(&self) -> Option<&Namespaces> {
        self.netns.as_ref()
    }

    fn create(name: &str, netns: Option<Namespaces>) -> anyhow::Result<Self> {
        let dir = std::env::temp_dir().join(format!(
            "offworld-site-{name}-{}-{}",
            std::process::id(),
            offworld_runtime::keys::random_id()
        ));
        std::fs::create_dir_all(&dir)?;
        let mut generate = Command::new("bash");
        generate
            .arg(deploy_dir().join("certs/generate.sh"))
            .arg(&dir);
        if let Some(ns) = &netns {
            generate.arg(format!("IP:{},IP:{}", ns.router_host_ip, ns.router_site_ip));
        }
        let status = generate
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status()?;
        anyhow::ensure!(
            status.success(),
            "deploy/certs/generate.sh failed: {status}"
        );
        let users: String = Role::ALL
            .iter()
            .map(|r| format!("{}:{}\n", r.name(), Self::password(r.name())))
            .collect();
        std::fs::write(dir.join("users.txt"), users)?;
        let mut site = match &netns {
            None => {
                let trainer = format!("quic/127.0.0.2:{}", free_loopback_port("127.0.0.2")?);
                let site = format!("quic/127.0.0.3:{}", free_loopback_port("127.0.0.3")?);
                Self {
                    listen: [trainer.clone(), site.clone()],
                    trainer_endpoint: trainer,
                    site_endpoint_inside: site.clone(),
                    site_endpoint: site,
                    dir,
                    router: None,
                    router_cfg: Vec::new(),
                    router_log: None,
                    netns,
                }
            }
            // A fresh namespace: the deployment's own ports are free.
            Some(ns) => Self {
                listen: ["quic/0.0.0.0:7447".into(), "quic/0.0.0.0:7448".into()],
                trainer_endpoint: format!("quic/{}:7447", ns.router_host_ip),
                site_endpoint: format!("quic/{}:7448", ns.router_host_ip),
                site_endpoint_inside: format!("quic/{}:7448", ns.router_site_ip),
                dir,
                router: None,
                router_cfg: Vec::new(),
                router_log: None,
                netns,
            },
        };
        site.start_router()?;
        Ok(site)
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

    /// The test password of a user (users.txt).
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
            "[{},{},{},{}]",
            json_string(trainers),
            json_string(&mtls(site)),
            json_string(&Self::over_tcp(trainers)),
            json_string(&mtls(&Self::over_tcp(site)))
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
            deploy_dir()
                .join("router/zenohd.json5")
                .to_string_lossy()
                .into_owned(),
        ];
        for o in overrides.iter().chain(&self.router_cfg) {
            args.push("--cfg".into());
            args.push(o.clone());
        }
        let mut command = match &self.netns {
            Some(ns) => {
                let mut c = Command::new("ip");
                c.args(["netns", "exec", &ns.router]).arg(zenohd());
                c
            }
            None => Command::new(zenohd()),
        };
        let mut log = std::env::var("ZENOHD_LOG").unwrap_or_else(|_| "warn".into());
        let (stdout, stderr) = match &self.router_log {
            Some(path) => {
                // zenohd logs each access-control decision at trace level,
                // on stdout.
                log += &format!(",{ACL_LOG_TARGET}=trace");
                let file = std::fs::OpenOptions::new()
                    .create(true)
                    .append(true)
                    .open(path)?;
                (Stdio::from(file.try_clone()?), Stdio::from(file))
            }
            None => (Stdio::null(), Stdio::inherit()),
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
            .map_err(|e| anyhow::anyhow!("zenohd (installed by .ci/setup): {e}"))?;
        self.router = Some(Process(child));
        // zenohd opens its listeners together: the TCP ones answering
        // means the QUIC ones are up too.
        for endpoint in [&self.trainer_endpoint, &self.site_endpoint] {
            wait_listening(&Self::over_tcp(endpoint), Duration::from_secs(20))?;
        }
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
    /// `-c deploy/roles/<role>.json5 --connect <endpoint> --cfg …`.
    pub fn role_args(&self, role: Role) -> Vec<String> {
        self.role_args_to(role, self.endpoint(role))
    }

    fn role_args_to(&self, role: Role, endpoint: &str) -> Vec<String> {
        let mut args = vec![
            "-c".to_owned(),
            role_file(role).to_string_lossy().into_owned(),
            "--connect".to_owned(),
            endpoint.to_owned(),
        ];
        for o in self.overrides(role) {
            args.push("--cfg".into());
            args.push(o);
        }
        args
    }

    /// The session config of an in-test participant of `role`.
    pub fn session(&self, role: Role) -> SessionConfig {
        SessionConfig {
            config_file: Some(role_file(role)),
            connect: vec![self.endpoint(role).to_owned()],
            overrides: self.overrides(role),
            ..SessionConfig::default()
        }
    }

    /// Starts a workspace binary as `role` with extra arguments after the
    /// Zenoh flags.
    pub fn spawn(
        &self,
        binary: &str,
        role: Role,
        before: &[&str],
        after: &[&str],
    ) -> anyhow::Result<Process> {
        // Site components live in the site namespace, if there is one.
        let (netns, endpoint) = match &self.netns {
            Some(ns) if role.is_site() => {
                (Some(ns.site.as_str()), self.site_endpoint_inside.as_str())
            }
            _ => (None, self.endpoint(role)),
        };
        let mut args: Vec<String> = before.iter().map(|s| s.to_string()).collect();
        args.extend(self.role_args_to(role, endpoint));
        args.extend(after.iter().map(|s| s.to_string()));
        let refs: Vec<&str> = args.iter().map(String::as_str).collect();
        Ok(Process::spawn_in(netns, binary, &refs, "warn")?)
    }
}

impl Drop for RouterSite {
    fn drop(&mut self) {
        self.stop_router();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// `deploy/roles/<role>.json5`.
pub fn role_file(role: Role) -> PathBuf {
    deploy_dir().join(format!("roles/{}.json5", role.name()))
}

/// The router binary: `$ZENOHD` or `zenohd` on `PATH` (`.ci/env` puts the
/// project's install first).
pub fn zenohd() -> PathBuf {
    std::env::var_os("ZENOHD")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("zenohd"))
}

fn wait_listening(endpoint: &str, timeout: Duration) -> anyhow::Result<()> {
    let addr = endpoint
        .split_once('/')
        .map(|(_, a)| a)
        .unwrap_or(endpoint)
        .to_owned();
    let deadline = Instant::now() + timeout;
    loop {
        if std::net::TcpStream::connect(&addr).is_ok() {
            return Ok(());
        }
        anyhow::ensure!(
            Instant::now() < deadline,
            "zenohd is not listening on {addr}"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A sim farm behind the router: `twins` `sim_twin` processes (agent role,
/// 84×84) under `sim/<name>-<i>` and one `env_controller` process
/// (controller role) serving them all, with one registered user.
pub struct SimFarm {
    /// The router and the files (declared first: dropped last).
    pub site: RouterSite,
    /// The envs served.
    pub envs: Vec<EnvId>,
    /// Access token of the registered user `alice`.
    pub token: String,
    _processes: Vec<Process>,
}

impl SimFarm {
    /// Starts the router, the twins and the controller (not waiting for
    /// them to answer: see [`SimFarm::ready`]).
    pub fn start(name: &str, twins: usize, task: &str) -> anyhow::Result<Self> {
        Self::start_on(RouterSite::start(name)?, name, twins, task)
    }

    /// Like [`SimFarm::start`] behind an already started router.
    pub fn start_on(
        site: RouterSite,
        name: &str,
        twins: usize,
        task: &str,
    ) -> anyhow::Result<Self> {
        Self::start_profiled(site, name, twins, task, None)
    }

    /// Like [`SimFarm::start_on`], every twin built with the twin profile
    /// `twin_profile` (`sim_twin --profile`, `docs/twin-profile.md`).
    pub fn start_profiled(
        site: RouterSite,
        name: &str,
        twins: usize,
        task: &str,
        twin_profile: Option<&std::path::Path>,
    ) -> anyhow::Result<Self> {
        let envs: Vec<EnvId> = (0..twins.max(1))
            .map(|i| EnvId::sim(&format!("{name}-{i}")))
            .collect::<Result<_, _>>()?;
        let db = site.dir.join("gym.db").to_string_lossy().into_owned();
        let token = Store::open(std::path::Path::new(&db))?.add_user("alice", false)?;
        let mut processes = Vec::new();
        let profile = twin_profile.map(|p| p.to_string_lossy().into_owned());
        for env in &envs {
            let env = env.to_string();
            let mut args = vec!["--env", &env, "--resolution", "84x84"];
            if let Some(profile) = &profile {
                args.extend(["--profile", profile]);
            }
            processes.push(site.spawn("sim_twin", Role::SimTwin, &[], &args)?);
        }
        let mut serve = vec!["--db".to_owned(), db, "serve".to_owned()];
        for env in &envs {
            serve.push("--env".into());
            serve.push(format!("{env}={task}"));
        }
        let serve: Vec<&str> = serve.iter().map(String::as_str).collect();
        processes.push(site.spawn("env_controller", Role::Controller, &serve, &[])?);
        Ok(Self {
            site,
            envs,
            token,
            _processes: processes,
        })
    }

    /// Waits until every env answers `spec` through the router as a trainer.
    pub async fn ready(&self, timeout: Duration) -> anyhow::Result<()> {
        let session = self.site.session(Role::Trainer).open().await?;
        let deadline = Instant::now() + timeout;
        for env in &self.envs {
            while offworld_client::spec(&session, env, Duration::from_secs(2))
                .await
                .is_err()
            {
                anyhow::ensure!(Instant::now() < deadline, "{env} did not come up");
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
        session.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(())
    }

    /// What a trainer process needs in its environment to reach the farm:
    /// `OFFWORLD_ZENOH_CONFIG` (the trainer role file), `OFFWORLD_ZENOH_CFG`
    /// (certificate path and password), `OFFWORLD_GYM_CONNECT`,
    /// `OFFWORLD_GYM_ACCESS_TOKEN`.
    pub fn trainer_env(&self) -> Vec<(String, String)> {
        vec![
            (
                offworld_runtime::session::ENV_CONFIG.to_owned(),
                role_file(Role::Trainer).to_string_lossy().into_owned(),
            ),
            (
                offworld_runtime::session::ENV_CFG.to_owned(),
                self.site.overrides(Role::Trainer).join(";"),
            ),
            (
                "OFFWORLD_GYM_CONNECT".to_owned(),
                self.site.trainer_endpoint.clone(),
            ),
            ("OFFWORLD_GYM_ACCESS_TOKEN".to_owned(), self.token.clone()),
        ]
    }
}
