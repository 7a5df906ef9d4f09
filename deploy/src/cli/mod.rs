//! The `offworld` commands that put pieces together: `serve` (the gym
//! server, with in-process twins on request) and `emulate-hardware` (a twin
//! behaving like the enclosure's hardware).

pub mod hardware;
pub mod serve;
