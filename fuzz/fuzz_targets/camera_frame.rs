//! `cargo +nightly fuzz run camera_frame`: see `offworld_fuzz::checks::runtime::camera_frame`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| offworld_fuzz::checks::runtime::camera_frame(data));
