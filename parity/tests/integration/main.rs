//! `offworld-parity`'s integration tests: one test binary whose modules are the
//! suites (README.md, "Layout"). Run one suite by its module:
//! `cargo test --release --test integration <module>::`.

mod common;
mod identify;
mod plots;
mod replay;
