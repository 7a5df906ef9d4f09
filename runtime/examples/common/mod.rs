//! Shared defaults for the runtime examples: the "server" side listens on
//! tcp/127.0.0.1:7447 and the "client" side connects there, so every pair
//! works with no flags and without multicast.
#![allow(dead_code)]

use offworld_runtime::{CommonArgs, SessionConfig};

pub const DEFAULT_ENDPOINT: &str = "tcp/127.0.0.1:7447";

pub fn server_config(mut args: CommonArgs) -> SessionConfig {
    if args.listen.is_empty() && args.connect.is_empty() && args.config.is_none() {
        args.listen.push(DEFAULT_ENDPOINT.into());
    }
    args.into()
}

pub fn client_config(mut args: CommonArgs) -> SessionConfig {
    if args.listen.is_empty() && args.connect.is_empty() && args.config.is_none() {
        args.connect.push(DEFAULT_ENDPOINT.into());
    }
    args.into()
}
