//! `cargo +nightly fuzz run cdr_robot`: see `offworld_fuzz::checks::runtime::cdr_robot`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| offworld_fuzz::checks::runtime::cdr_robot(data));
