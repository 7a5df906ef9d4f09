//! Replays the fuzz corpora of the robot side's files (agent configuration,
//! e-stop latch, world files; `fuzz/corpus/<target>/`, see
//! `fuzz/README.md`) through the fuzz targets' own checks
//! (`fuzz/src/checks/robot_agent.rs`).

#[path = "../../../fuzz/src/checks/robot_agent.rs"]
mod checks;
#[path = "../../../fuzz/src/checks/corpus.rs"]
mod corpus;

#[test]
fn robot_config_corpus() {
    corpus::replay(
        "robot_config",
        &checks::robot_config_seeds(),
        checks::robot_config,
    );
}

#[test]
fn world_toml_corpus() {
    corpus::replay(
        "world_toml",
        &checks::world_toml_seeds(),
        checks::world_toml,
    );
}

/// Writes the seeds into the corpus directories (to start afresh:
/// `cargo test --release --test integration fuzz_corpus::write_seed_corpus -- --ignored`).
#[test]
#[ignore]
fn write_seed_corpus() {
    corpus::write_seeds("robot_config", &checks::robot_config_seeds());
    corpus::write_seeds("world_toml", &checks::world_toml_seeds());
}
