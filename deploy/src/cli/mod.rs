//! The `offworld` commands that put pieces together: `serve` (the gym
//! server, with in-process twins on request), `emulate-hardware` (a twin
//! behaving like the enclosure's hardware) and `emulate-enclosure` (the
//! real stack against that hardware, as processes).

pub mod enclosure;
pub mod hardware;
pub mod serve;
