//! How every long-running binary learns it must stop: SIGINT (Ctrl-C),
//! SIGTERM (systemd, `kill`, a container runtime) and SIGHUP (the terminal
//! or the SSH session went away) all mean "stop cleanly now". A robot-side
//! process treats each of them like Ctrl-C: the base is zeroed first.

use std::fmt;

/// The signal that asked the process to stop.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ShutdownSignal {
    /// SIGINT (Ctrl-C).
    Interrupt,
    /// SIGTERM.
    Terminate,
    /// SIGHUP.
    Hangup,
}

impl fmt::Display for ShutdownSignal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Interrupt => "SIGINT",
            Self::Terminate => "SIGTERM",
            Self::Hangup => "SIGHUP",
        })
    }
}

/// Handlers for SIGINT, SIGTERM and SIGHUP, installed at once (a signal
/// that arrives before [`ShutdownSignals::recv`] is awaited is kept, not
/// lost to the default action that would kill the process).
pub struct ShutdownSignals {
    #[cfg(unix)]
    streams: [(tokio::signal::unix::Signal, ShutdownSignal); 3],
}

impl ShutdownSignals {
    /// Installs the handlers. Needs a tokio runtime.
    pub fn install() -> std::io::Result<Self> {
        #[cfg(unix)]
        {
            use tokio::signal::unix::{signal, SignalKind};
            Ok(Self {
                streams: [
                    (signal(SignalKind::interrupt())?, ShutdownSignal::Interrupt),
                    (signal(SignalKind::terminate())?, ShutdownSignal::Terminate),
                    (signal(SignalKind::hangup())?, ShutdownSignal::Hangup),
                ],
            })
        }
        #[cfg(not(unix))]
        Ok(Self {})
    }

    /// Waits for the first of the three signals.
    pub async fn recv(&mut self) -> ShutdownSignal {
        #[cfg(unix)]
        {
            let [(a, sa), (b, sb), (c, sc)] = &mut self.streams;
            tokio::select! {
                _ = a.recv() => *sa,
                _ = b.recv() => *sb,
                _ = c.recv() => *sc,
            }
        }
        #[cfg(not(unix))]
        {
            let _ = tokio::signal::ctrl_c().await;
            ShutdownSignal::Interrupt
        }
    }
}

/// Installs the handlers and waits for the first stop signal; logs it.
pub async fn signalled() -> std::io::Result<ShutdownSignal> {
    let signal = ShutdownSignals::install()?.recv().await;
    tracing::info!(%signal, "stop requested");
    Ok(signal)
}
