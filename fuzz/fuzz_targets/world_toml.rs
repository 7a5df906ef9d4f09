//! `cargo +nightly fuzz run world_toml`: see `offworld_fuzz::checks::robot_agent::world_toml`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| offworld_fuzz::checks::robot_agent::world_toml(data));
