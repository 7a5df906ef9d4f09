//! Replays the fuzz corpora of the tracker agent's parsers
//! (`fuzz/corpus/<target>/`, see `fuzz/README.md`) through the fuzz
//! targets' own checks (`fuzz/src/checks/tracker.rs`).

#[path = "../../../fuzz/src/checks/tracker.rs"]
mod checks;
#[path = "../../../fuzz/src/checks/corpus.rs"]
mod corpus;

#[test]
fn tracker_line_corpus() {
    corpus::replay(
        "tracker_line",
        &checks::tracker_line_seeds(),
        checks::tracker_line,
    );
}

#[test]
fn tracker_calibration_corpus() {
    corpus::replay(
        "tracker_calibration",
        &checks::tracker_calibration_seeds(),
        checks::tracker_calibration,
    );
}

/// Writes the seeds into the corpus directories (to start afresh:
/// `cargo test --release --test integration fuzz_corpus::write_seed_corpus -- --ignored`).
#[test]
#[ignore]
fn write_seed_corpus() {
    corpus::write_seeds("tracker_line", &checks::tracker_line_seeds());
    corpus::write_seeds("tracker_calibration", &checks::tracker_calibration_seeds());
}
