//! The lab's web page: live availability of every env of an OffWorld Gym
//! deployment (real and sim), each env's leaderboard, and the same as JSON
//! for scripts; for users signed in with their gym access token, each
//! env's bookings (book, cancel) and their experiments with learning
//! curves; for operators, a console (e-stops, maintenance, leases). It
//! joins the deployment as one more Zenoh client; the changes it asks for
//! are a signed-in user's bookings and an operator's maintenance and
//! revocations, each with the user's token, checked by the controller as
//! the CLI's are, and an operator's e-stops, pressed as the CLI presses
//! them (the deployment's access control decides whether this service's
//! Zenoh identity may).
//!
//! - [`discovery`]: the Zenoh side (listing, `status` and `fault`
//!   subscriptions), kept as a live [`model::Snapshot`];
//! - [`model`]: what is shown, as data (the JSON API's shapes);
//! - [`api`]: JSON handlers; [`pages`]: HTML; [`events`]: server-sent events;
//! - [`account`], [`account_pages`], [`chart`]: sign-in, bookings,
//!   experiments and their learning curves; [`session`]: sessions, CSRF;
//! - [`console`], [`console_pages`]: the operator console;
//! - [`thumbnails`]: each env's camera and overhead view, pulled at a
//!   low rate;
//! - [`server`]: routes, limits, security headers, the accept loop;
//! - [`error`]: HTTP errors.

pub mod account;
pub mod account_pages;
pub mod api;
pub mod chart;
pub mod cli;
pub mod console;
pub mod console_pages;
pub mod discovery;
pub mod error;
pub mod events;
pub mod model;
pub mod pages;
pub mod server;
pub mod session;
pub mod thumbnails;

use std::net::SocketAddr;

use offworld_runtime::WireError;
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use zenoh::Session;

pub use discovery::{Discovery, DiscoveryConfig};
pub use server::Limits;

/// How the service runs.
#[derive(Debug, Clone, Default)]
pub struct WebOptions {
    /// Query deadlines and sweep interval.
    pub discovery: DiscoveryConfig,
    /// HTTP limits.
    pub limits: Limits,
    /// Mark cookies `Secure`: the service is reached through TLS (a
    /// reverse proxy); browsers then send them over HTTPS only.
    pub secure_cookies: bool,
    /// Every page and the JSON need a signed-in user (a site that does
    /// not show its state to the public); only sign-in, the stylesheet,
    /// the script and `/healthz` stay open.
    pub members_only: bool,
    /// A URL the rerun viewer opens to watch the deployment live (a
    /// monitor's `--serve` stream, e.g. `rerun+http://lab:9876/proxy`),
    /// linked from each env's page.
    pub rerun_url: Option<String>,
}

/// Why the service could not start.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    /// The HTTP address could not be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address asked for.
        addr: SocketAddr,
        /// Why.
        source: std::io::Error,
    },
    /// Zenoh refused a subscription.
    #[error("cannot subscribe to the deployment: {0}")]
    Zenoh(WireError),
}

/// A running web service; stops when dropped.
pub struct LabWeb {
    local_addr: SocketAddr,
    discovery: Discovery,
    stop: Option<oneshot::Sender<()>>,
    task: tokio::task::JoinHandle<()>,
}

impl LabWeb {
    /// Starts discovering envs through `session` and answering HTTP on
    /// `listen` (port 0: any free port, see [`LabWeb::local_addr`]).
    pub async fn start(
        session: Session,
        listen: SocketAddr,
        options: WebOptions,
    ) -> Result<Self, StartError> {
        let listener = TcpListener::bind(listen)
            .await
            .map_err(|source| StartError::Bind {
                addr: listen,
                source,
            })?;
        let local_addr = listener.local_addr().map_err(|source| StartError::Bind {
            addr: listen,
            source,
        })?;
        let discovery = Discovery::start(session.clone(), options.discovery)
            .await
            .map_err(StartError::Zenoh)?;
        let thumbnails = thumbnails::Thumbnails::new(session.clone());
        let app = server::router(discovery.clone(), thumbnails, &options);
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(server::serve(listener, app, options.limits, async {
            let _ = stopped.await;
        }));
        Ok(Self {
            local_addr,
            discovery,
            stop: Some(stop),
            task,
        })
    }

    /// The address HTTP is served on.
    pub fn local_addr(&self) -> SocketAddr {
        self.local_addr
    }

    /// The live availability behind the pages.
    pub fn discovery(&self) -> &Discovery {
        &self.discovery
    }

    /// Stops answering (open connections are closed) and discovering.
    pub async fn stop(mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        let _ = (&mut self.task).await;
        self.discovery.stop();
    }
}

impl Drop for LabWeb {
    fn drop(&mut self) {
        self.task.abort();
        self.discovery.stop();
    }
}
