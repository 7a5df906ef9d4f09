//! `offworld-tracker-agent`'s integration tests: one test binary whose modules are the
//! suites (README.md, "Layout"). Run one suite by its module:
//! `cargo test --release --test integration <module>::`.

mod agent;
mod fuzz_corpus;
mod pysurvive_source;
