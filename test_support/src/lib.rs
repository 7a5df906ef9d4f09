//! What the tests and benches of several OffWorld crates share and no user
//! runs: scratch directories and instruction counts.

pub mod callgrind;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

/// The running test's package directory, as cargo gives it to the test
/// when it runs. A compile-time `env!("CARGO_MANIFEST_DIR")` names the
/// checkout that built the binary, and cargo reuses a binary built in
/// another checkout sharing the target directory (CI's, say): the test
/// would read that checkout's files, or none.
pub fn package_dir() -> PathBuf {
    std::env::var_os("CARGO_MANIFEST_DIR")
        .map(PathBuf::from)
        .expect("CARGO_MANIFEST_DIR is unset: run the tests with cargo test")
}

/// A new empty directory of its own under the system's temporary directory
/// (`offworld-<purpose>-<unique>`), removed with everything in it when
/// dropped. Unique across the threads of a test binary and across
/// processes, so tests running in parallel never share one.
#[derive(Debug)]
pub struct ScratchDir(pub PathBuf);

impl ScratchDir {
    /// Creates the directory; `purpose` names it for a person looking at a
    /// leftover (e.g. `store-test`).
    pub fn new(purpose: &str) -> Self {
        static CREATED: AtomicU64 = AtomicU64::new(0);
        let nanos = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.subsec_nanos());
        let dir = std::env::temp_dir().join(format!(
            "offworld-{purpose}-{}-{}-{nanos:09}",
            std::process::id(),
            CREATED.fetch_add(1, Ordering::Relaxed)
        ));
        std::fs::create_dir_all(&dir)
            .unwrap_or_else(|e| panic!("scratch dir {}: {e}", dir.display()));
        Self(dir)
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.0
    }

    /// A path inside it.
    pub fn join(&self, name: impl AsRef<Path>) -> PathBuf {
        self.0.join(name)
    }
}

impl std::ops::Deref for ScratchDir {
    type Target = Path;

    fn deref(&self) -> &Path {
        &self.0
    }
}

impl AsRef<Path> for ScratchDir {
    fn as_ref(&self) -> &Path {
        &self.0
    }
}

impl Drop for ScratchDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_is_new_empty_and_removed_on_drop() {
        let a = ScratchDir::new("support-test");
        let b = ScratchDir::new("support-test");
        assert_ne!(a.path(), b.path());
        assert!(a.path().is_dir());
        assert_eq!(std::fs::read_dir(a.path()).expect("readable").count(), 0);
        std::fs::write(a.join("f"), b"x").expect("writable");
        let gone = a.path().to_owned();
        drop(a);
        assert!(!gone.exists());
    }
}
