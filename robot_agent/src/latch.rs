//! The e-stop latch on the robot's disk: the site and env latches
//! ([`EStopState`]) written on every change, so a robot agent restarted
//! (crash, reboot, update) while e-stopped comes back e-stopped. On start
//! the agent merges it with what the network remembers (the newer report
//! per latch wins, see [`offworld_runtime::estop`]).
//!
//! The file is TOML (`[site]` and `[env]`, each `engaged`, `reason`,
//! `changed`). A file that cannot be read or parsed engages both latches
//! (fail safe), stamped "now" so the network cannot silently outvote it.

use std::io::Write;
use std::path::{Path, PathBuf};

use atomic_write_file::AtomicWriteFile;
use offworld_runtime::msg::{EStopState, LatchState, Time};

/// Where the e-stop state is remembered.
#[derive(Debug, Clone)]
pub struct EStopLatch {
    path: PathBuf,
}

impl EStopLatch {
    /// A latch kept in `path` (its directory is created on first write).
    pub fn new(path: impl Into<PathBuf>) -> Self {
        Self { path: path.into() }
    }

    /// The latch file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The state written before this start (`None`: never written).
    pub fn load(&self) -> Option<EStopState> {
        let text = match std::fs::read_to_string(&self.path) {
            Ok(text) => text,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return None,
            Err(e) => {
                return Some(both_engaged(format!(
                    "unreadable e-stop latch {}: {e}",
                    self.path.display()
                )))
            }
        };
        Some(toml::from_str(&text).unwrap_or_else(|e| {
            both_engaged(format!(
                "unparsable e-stop latch {}: {}",
                self.path.display(),
                e.message()
            ))
        }))
    }

    /// Writes `state` (whole, synced, renamed into place, directory synced,
    /// by `atomic-write-file`: a crash or power cut leaves the old state or
    /// the new one).
    pub fn store(&self, state: &EStopState) -> std::io::Result<()> {
        if let Some(dir) = self.path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)?;
        }
        let text = toml::to_string(state).map_err(std::io::Error::other)?;
        let mut file = AtomicWriteFile::open(&self.path)?;
        file.write_all(text.as_bytes())?;
        file.commit()
    }
}

fn both_engaged(reason: String) -> EStopState {
    let latch = LatchState {
        engaged: true,
        reason,
        changed: Time::now(),
    };
    EStopState {
        site: latch.clone(),
        env: latch,
    }
}

#[cfg(test)]
mod tests {
    use offworld_runtime::estop::Latch;
    use offworld_runtime::msg::EStop;

    use super::*;

    fn scratch(name: &str) -> PathBuf {
        std::env::temp_dir().join(format!(
            "offworld-latch-{name}-{}",
            offworld_runtime::keys::random_id()
        ))
    }

    #[test]
    fn remembers_both_latches_exactly() -> std::io::Result<()> {
        let dir = scratch("cycle");
        let latch = EStopLatch::new(dir.join("nested/estop"));
        assert_eq!(latch.load(), None, "never written");
        let mut state = EStopState::default();
        let t = Time {
            sec: 1_700_000_000,
            nanosec: 5,
        };
        state.apply(Latch::Site, &EStop::new(true, "operator: boulder moved"), t);
        latch.store(&state)?;
        assert_eq!(EStopLatch::new(latch.path()).load(), Some(state.clone()));
        state.apply(Latch::Env, &EStop::new(true, "second press"), t);
        state.apply(Latch::Site, &EStop::new(false, "site clear"), t);
        latch.store(&state)?;
        let back = latch.load().expect("written");
        assert_eq!(back, state);
        assert!(!back.site.engaged && back.env.engaged);
        std::fs::remove_dir_all(dir)
    }

    #[test]
    fn an_unreadable_or_garbled_latch_engages_both() -> std::io::Result<()> {
        let dir = scratch("unreadable");
        // A directory where the file should be cannot be read as one.
        std::fs::create_dir_all(&dir)?;
        let state = EStopLatch::new(&dir).load().expect("engaged");
        assert!(state.site.engaged && state.env.engaged);
        assert!(
            state.env.reason.starts_with("unreadable e-stop latch"),
            "{state:?}"
        );
        // An older agent's latch held just the reason.
        let old = dir.join("old.estop");
        std::fs::write(&old, "operator: person inside")?;
        let state = EStopLatch::new(&old).load().expect("engaged");
        assert!(state.site.engaged && state.env.engaged);
        assert!(
            state.env.reason.starts_with("unparsable e-stop latch"),
            "{state:?}"
        );
        std::fs::remove_dir_all(dir)
    }
}
