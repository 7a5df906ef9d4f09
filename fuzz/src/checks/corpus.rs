//! Replays a fuzz target's corpus (`fuzz/corpus/<target>/`) and seeds
//! through its check, for the `fuzz_corpus` regression tests of the
//! workspace crates (included there with `#[path]`, like the checks).

// Each test crate uses the helpers it needs.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

/// `fuzz/corpus/<target>` seen from the running test's package directory,
/// as cargo gives it to the test when it runs (a compile-time `env!` would
/// name the checkout that built the binary, which a shared target
/// directory may reuse from another checkout).
pub fn dir(target: &str) -> PathBuf {
    let package = std::env::var_os("CARGO_MANIFEST_DIR")
        .expect("CARGO_MANIFEST_DIR: run the corpus tests with cargo test");
    Path::new(&package).join("../fuzz/corpus").join(target)
}

/// Runs `check` on every seed and every corpus file of `target` (sorted by
/// name), naming the file that fails; returns the number of files.
pub fn replay(target: &str, seeds: &[Vec<u8>], check: fn(&[u8])) -> usize {
    for seed in seeds {
        check(seed);
    }
    let dir = dir(target);
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|entry| entry.expect("corpus entry").path())
        .filter(|path| path.is_file())
        .collect();
    files.sort();
    assert!(!files.is_empty(), "{}: empty corpus", dir.display());
    for file in &files {
        let data = std::fs::read(file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
        let outcome = std::panic::catch_unwind(|| check(&data));
        assert!(
            outcome.is_ok(),
            "{target}: corpus file {} ({} bytes) fails its check",
            file.display(),
            data.len()
        );
    }
    files.len()
}

/// Writes `seeds` into `target`'s corpus as `seed-<n>` (to start a fresh
/// corpus; `cargo fuzz cmin` renames what it keeps).
pub fn write_seeds(target: &str, seeds: &[Vec<u8>]) {
    let dir = dir(target);
    std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
    for (n, seed) in seeds.iter().enumerate() {
        let path = dir.join(format!("seed-{n:03}"));
        std::fs::write(&path, seed).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    }
}
