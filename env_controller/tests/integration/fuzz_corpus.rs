//! Replays the fuzz corpus of the observation assembly from received camera
//! frames (`fuzz/corpus/observation/`, see `fuzz/README.md`) through the
//! fuzz target's own check (`fuzz/src/checks/observation.rs`).

#[path = "../../../fuzz/src/checks/observation.rs"]
mod checks;
#[path = "../../../fuzz/src/checks/corpus.rs"]
mod corpus;

#[test]
fn observation_corpus() {
    corpus::replay(
        "observation",
        &checks::observation_seeds(),
        checks::observation,
    );
}

/// Writes the seeds into the corpus directory (to start afresh:
/// `cargo test --release --test integration fuzz_corpus::write_seed_corpus -- --ignored`).
#[test]
#[ignore]
fn write_seed_corpus() {
    corpus::write_seeds("observation", &checks::observation_seeds());
}
