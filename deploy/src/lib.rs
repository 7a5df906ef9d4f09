//! How OffWorld Gym's pieces are put together.
//!
//! The components (controller, twin, robot and tracker agents) each do one
//! job and meet only on Zenoh keys; this crate assembles them:
//!
//! - [`embedded`]: sim twins and a controller in one process, still
//!   talking only through Zenoh keys.
//! - [`target`]: where a client's envs live (embedded, named remote envs,
//!   or discovered free ones) and connecting to them.
//! - [`hardware`]: a twin behaving like the enclosure's hardware (the
//!   robot's ROS 2 topics, a raw tracker line stream) for the real stack
//!   to drive.
//! - [`enclosure`]: the real stack (gym server, robot agent, base guard,
//!   tracker agent) as processes against the emulated hardware.
//! - [`site`]: the real `zenohd` router with the deployment's files
//!   (TLS, mutual TLS, passwords, access control) and components
//!   connecting in their roles.
//! - [`farm`]: sim twins and a gym server as processes behind that router.
//! - [`process`]: components as child processes, the `offworld` command.
//! - [`cli`]: `offworld serve`, the gym server with optional in-process
//!   twins (`env_controller serve` is the same server without a
//!   simulator), `offworld emulate-hardware`, `offworld
//!   emulate-enclosure` and `offworld farm`.
//!
//! Every module but [`embedded`] and [`target`] is the `programs` feature:
//! the `offworld` command and the tests enable it; a Python package needs
//! neither the deployments a person runs nor their compile time.
//!
//! The site's files (router configs, access roles, certificates, systemd
//! units) live beside this crate, in `deploy/`; the router's, the roles'
//! and the certificate generator are compiled in ([`site`]).

// Without `programs` the module list above names modules left out.
#![cfg_attr(not(feature = "programs"), allow(rustdoc::broken_intra_doc_links))]

#[cfg(feature = "programs")]
pub mod cli;
pub mod embedded;
#[cfg(feature = "programs")]
pub mod enclosure;
#[cfg(feature = "programs")]
pub mod farm;
#[cfg(feature = "programs")]
pub mod hardware;
#[cfg(feature = "programs")]
pub mod process;
#[cfg(feature = "programs")]
pub mod site;
pub mod target;

pub use embedded::{Embedded, SimEnv, Stepping, TwinProfile};
pub use target::{connect, Connection, Target};
