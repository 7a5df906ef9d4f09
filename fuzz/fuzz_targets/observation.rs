//! `cargo +nightly fuzz run observation`: see `offworld_fuzz::checks::observation::observation`.
#![no_main]

libfuzzer_sys::fuzz_target!(|data: &[u8]| offworld_fuzz::checks::observation::observation(data));
