//! `offworld-tests`'s integration tests: one test binary whose modules are the
//! suites (README.md, "Layout"). Run one suite by its module:
//! `cargo test --release --test integration <module>::`.

mod distributed;
mod estop;
mod faults;
mod parity;
mod processes;
mod real_side;
mod ros2_wire;
