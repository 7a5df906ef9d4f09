//! The e-stop latch: an engaged e-stop written to the robot's disk, so a
//! robot agent restarted (crash, reboot, update) while e-stopped comes back
//! e-stopped. Only an operator's release clears it. E-stops travel as
//! plain publications that nobody repeats, so without the latch a restart
//! would silently forget one.
//!
//! The file holds the reason; its presence is what counts. A latch file
//! that cannot be read still engages (fail safe).

use std::io::Write;
use std::path::{Path, PathBuf};

/// Where the e-stop state is remembered.
#[derive(Debug, Clone)]
pub struct EStopLatch {
    path: PathBuf,
}

impl EStopLatch {
    /// A latch kept in `path` (its directory is created on first engage).
    pub fn new(path: impl Into<PathBuf>) -> Self {
        Self { path: path.into() }
    }

    /// The latch file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The reason of an e-stop engaged before this start, if any.
    pub fn engaged(&self) -> Option<String> {
        match std::fs::read(&self.path) {
            Ok(bytes) => Some(String::from_utf8_lossy(&bytes).trim().to_owned()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => Some(format!(
                "unreadable e-stop latch {}: {e}",
                self.path.display()
            )),
        }
    }

    /// Remembers an engaged e-stop (written whole, then renamed into place,
    /// so a crash mid-write never leaves a half latch).
    pub fn engage(&self, reason: &str) -> std::io::Result<()> {
        if let Some(dir) = self.path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)?;
        }
        let mut staging = self.path.clone().into_os_string();
        staging.push(".tmp");
        let staging = PathBuf::from(staging);
        {
            let mut file = std::fs::File::create(&staging)?;
            file.write_all(reason.as_bytes())?;
            file.sync_all()?;
        }
        std::fs::rename(&staging, &self.path)
    }

    /// Forgets the e-stop (an operator released it).
    pub fn release(&self) -> std::io::Result<()> {
        match std::fs::remove_file(&self.path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(e),
            _ => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!(
            "offworld-latch-{name}-{}",
            offworld_runtime::client::random_id()
        ))
    }

    #[test]
    fn remembers_an_engaged_estop_until_released() -> std::io::Result<()> {
        let dir = scratch("cycle");
        let latch = EStopLatch::new(dir.join("nested/estop"));
        assert_eq!(latch.engaged(), None, "never engaged");
        latch.engage("operator: boulder moved")?;
        assert_eq!(
            EStopLatch::new(latch.path()).engaged().as_deref(),
            Some("operator: boulder moved"),
            "a new agent reads it back"
        );
        latch.engage("second press")?;
        assert_eq!(latch.engaged().as_deref(), Some("second press"));
        latch.release()?;
        assert_eq!(latch.engaged(), None);
        latch.release()?;
        std::fs::remove_dir_all(dir)
    }

    #[test]
    fn an_unreadable_latch_engages() -> std::io::Result<()> {
        let dir = scratch("unreadable");
        // A directory where the file should be cannot be read as one.
        std::fs::create_dir_all(&dir)?;
        let reason = EStopLatch::new(&dir).engaged().unwrap_or_default();
        assert!(reason.starts_with("unreadable e-stop latch"), "{reason}");
        std::fs::remove_dir_all(dir)
    }
}
