//! A sim farm behind the site's router: sim twin processes (agent role,
//! 84×84) under `sim/<name>-<i>` and one gym server process (the sim-farm
//! controller role, confined to `sim/`) serving them all, with one registered user — what a lab runs to
//! give researchers many simulated enclosures through one router. On the
//! router's own host the farm reaches it over its local socket
//! ([`Link::LocalSocket`]: no TLS to pay on every frame).

use std::path::Path;
use std::time::{Duration, Instant};

use offworld_env_controller::Store;
use offworld_runtime::EnvId;

use crate::process::Process;
use crate::site::{Link, Role, RouterSite, SITE_LOG};

/// The user registered on a farm (its token is [`SimFarm::token`]).
pub const FARM_USER: &str = "alice";

/// A sim farm: the router, the twins and the gym server.
pub struct SimFarm {
    /// Declared first, dropped first: the components stop before the
    /// router and before their files are removed.
    _processes: Vec<Process>,
    /// The router and the files.
    pub site: RouterSite,
    /// The envs served.
    pub envs: Vec<EnvId>,
    /// Access token of the registered user [`FARM_USER`].
    pub token: String,
}

impl SimFarm {
    /// Starts the router, the twins and the gym server on this host, the
    /// farm on the router's local socket (not waiting for them to answer:
    /// see [`SimFarm::ready`]).
    pub fn start(name: &str, twins: usize, task: &str) -> anyhow::Result<Self> {
        Self::start_on(
            RouterSite::start(name)?,
            name,
            twins,
            task,
            Link::LocalSocket,
        )
    }

    /// Like [`SimFarm::start`] behind an already started router, the
    /// farm's processes reaching it over `link`.
    pub fn start_on(
        site: RouterSite,
        name: &str,
        twins: usize,
        task: &str,
        link: Link,
    ) -> anyhow::Result<Self> {
        Self::start_profiled(site, name, twins, task, None, link)
    }

    /// Like [`SimFarm::start_on`], every twin built with the twin profile
    /// `twin_profile` (`offworld twin --profile`, `docs/twin-profile.md`).
    pub fn start_profiled(
        site: RouterSite,
        name: &str,
        twins: usize,
        task: &str,
        twin_profile: Option<&Path>,
        link: Link,
    ) -> anyhow::Result<Self> {
        let envs: Vec<EnvId> = (0..twins.max(1))
            .map(|i| EnvId::sim(&format!("{name}-{i}")))
            .collect::<Result<_, _>>()?;
        let db = site.dir.join("gym.db").to_string_lossy().into_owned();
        let token = Store::open(Path::new(&db))?.add_user(FARM_USER, false)?;
        let mut processes = Vec::new();
        let profile = twin_profile.map(|p| p.to_string_lossy().into_owned());
        for env in &envs {
            let env = env.to_string();
            let mut twin = vec!["twin", "--env", &env, "--resolution", "84x84"];
            if let Some(profile) = &profile {
                twin.extend(["--profile", profile]);
            }
            processes.push(site.spawn_over(Role::SimTwin, link, &twin, SITE_LOG)?);
        }
        let mut serve = vec!["--db".to_owned(), db, "serve".to_owned()];
        for env in &envs {
            serve.push("--env".into());
            serve.push(format!("{env}={task}"));
        }
        let serve: Vec<&str> = serve.iter().map(String::as_str).collect();
        processes.push(site.spawn_over(Role::SimController, link, &serve, SITE_LOG)?);
        Ok(Self {
            _processes: processes,
            site,
            envs,
            token,
        })
    }

    /// Waits until every env answers `spec` through the router as a trainer.
    pub async fn ready(&self, limit: Duration) -> anyhow::Result<()> {
        let session = self.site.session(Role::Trainer).open().await?;
        let deadline = Instant::now() + limit;
        for env in &self.envs {
            while offworld_client::spec(&session, env, Duration::from_secs(2))
                .await
                .is_err()
            {
                anyhow::ensure!(
                    Instant::now() < deadline,
                    "{env} did not answer through the router within {limit:?}"
                );
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
        session.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
        Ok(())
    }

    /// What a trainer process needs in its environment to reach the farm:
    /// the site's trainer environment ([`RouterSite::trainer_env`]) and
    /// `OFFWORLD_GYM_ACCESS_TOKEN`.
    pub fn trainer_env(&self) -> Vec<(String, String)> {
        let mut env = self.site.trainer_env();
        env.push(("OFFWORLD_GYM_ACCESS_TOKEN".to_owned(), self.token.clone()));
        env
    }
}
