//! `cargo +nightly fuzz run tracker_line`: see `offworld_fuzz::checks::tracker::tracker_line`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| offworld_fuzz::checks::tracker::tracker_line(data));
