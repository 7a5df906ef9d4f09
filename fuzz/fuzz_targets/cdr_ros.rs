//! `cargo +nightly fuzz run cdr_ros`: see `offworld_fuzz::checks::runtime::cdr_ros`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| offworld_fuzz::checks::runtime::cdr_ros(data));
