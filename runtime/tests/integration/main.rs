//! `offworld-runtime`'s integration tests: one test binary whose modules are the
//! suites (README.md, "Layout"). Run one suite by its module:
//! `cargo test --release --test integration <module>::`.

mod codec;
mod common;
mod fuzz_corpus;
mod preview;
mod rosbags_golden;
mod zenoh_loopback;
