//! `cargo +nightly fuzz run keys`: see `offworld_fuzz::checks::runtime::keys`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| offworld_fuzz::checks::runtime::keys(data));
