//! `cargo +nightly fuzz run cdr_gym`: see `offworld_fuzz::checks::runtime::cdr_gym`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| offworld_fuzz::checks::runtime::cdr_gym(data));
