//! `cargo +nightly fuzz run tracker_calibration`: see `offworld_fuzz::checks::tracker::tracker_calibration`.
#![no_main]

libfuzzer_sys::fuzz_target!(
    |data: &[u8]| offworld_fuzz::checks::tracker::tracker_calibration(data)
);
