//! Replays the fuzz corpora of the runtime's decoders (`fuzz/corpus/<target>/`,
//! see `fuzz/README.md`) through the fuzz targets' own checks
//! (`fuzz/src/checks/runtime.rs`): every file must decode or be refused
//! without a panic, with every invariant held.

#[path = "../../../fuzz/src/checks/runtime.rs"]
mod checks;
#[path = "../../../fuzz/src/checks/corpus.rs"]
mod corpus;

#[test]
fn cdr_gym_corpus() {
    corpus::replay("cdr_gym", &checks::cdr_gym_seeds(), checks::cdr_gym);
}

#[test]
fn cdr_robot_corpus() {
    corpus::replay("cdr_robot", &checks::cdr_robot_seeds(), checks::cdr_robot);
}

#[test]
fn cdr_ros_corpus() {
    corpus::replay("cdr_ros", &checks::cdr_ros_seeds(), checks::cdr_ros);
}

#[test]
fn camera_frame_corpus() {
    corpus::replay(
        "camera_frame",
        &checks::camera_frame_seeds(),
        checks::camera_frame,
    );
}

#[test]
fn keys_corpus() {
    corpus::replay("keys", &checks::keys_seeds(), checks::keys);
}

/// The seeds cover every message type of each family.
#[test]
fn seeds_cover_every_kind() {
    for (seeds, kinds) in [
        (checks::cdr_gym_seeds(), checks::GYM_KINDS),
        (checks::cdr_robot_seeds(), checks::ROBOT_KINDS),
        (checks::cdr_ros_seeds(), checks::ROS_KINDS),
    ] {
        let mut seen: Vec<u8> = seeds.iter().map(|s| s[0] % kinds).collect();
        seen.sort_unstable();
        seen.dedup();
        assert_eq!(seen, (0..kinds).collect::<Vec<_>>());
    }
}

/// Writes the seeds into the corpus directories (to start afresh:
/// `cargo test --release --test integration fuzz_corpus::write_seed_corpus -- --ignored`).
#[test]
#[ignore]
fn write_seed_corpus() {
    corpus::write_seeds("cdr_gym", &checks::cdr_gym_seeds());
    corpus::write_seeds("cdr_robot", &checks::cdr_robot_seeds());
    corpus::write_seeds("cdr_ros", &checks::cdr_ros_seeds());
    corpus::write_seeds("camera_frame", &checks::camera_frame_seeds());
    corpus::write_seeds("keys", &checks::keys_seeds());
}
