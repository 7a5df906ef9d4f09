//! `cargo +nightly fuzz run robot_config`: see `offworld_fuzz::checks::robot_agent::robot_config`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| offworld_fuzz::checks::robot_agent::robot_config(data));
