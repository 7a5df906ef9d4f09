//! `offworld-env-controller`'s integration tests: one test binary whose modules are the
//! suites (README.md, "Layout"). Run one suite by its module:
//! `cargo test --release --test integration <module>::`.

mod flood;
mod fuzz_corpus;
mod gym;
mod link;
mod operator;
mod recording;
mod users_cli;
