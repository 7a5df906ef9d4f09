//! Where a component keeps what must outlive it (the robot agent's e-stop
//! latch): `$XDG_STATE_HOME`, else `~/.local/state`, else, for a service
//! started without `HOME` (systemd runs root's services so), the system's
//! `/var/lib`. Written by hand rather than with `dirs`: these are exactly
//! the paths the agent has always used, and a latch that moved with an
//! upgrade would be a latch forgotten (`dirs` ignores a relative
//! `XDG_STATE_HOME` and asks the user database when `HOME` is unset).

use std::ffi::OsString;
use std::path::PathBuf;

/// The system's state directory, for services without a `HOME`.
const SYSTEM_STATE: &str = "/var/lib";

/// `<state dir>/offworld/<component>/<file>`. Never none: a component that
/// needs the file checks that it can write it (the robot agent refuses to
/// start otherwise, naming its flag).
pub fn state_file(component: &str, file: &str) -> PathBuf {
    locate(std::env::var_os("XDG_STATE_HOME"), std::env::var_os("HOME"))
        .join("offworld")
        .join(component)
        .join(file)
}

fn locate(xdg_state_home: Option<OsString>, home: Option<OsString>) -> PathBuf {
    xdg_state_home
        .map(PathBuf::from)
        .or_else(|| home.map(|home| PathBuf::from(home).join(".local/state")))
        .unwrap_or_else(|| PathBuf::from(SYSTEM_STATE))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn xdg_state_home_then_home_then_var_lib() {
        let os = |s: &str| Some(OsString::from(s));
        assert_eq!(
            locate(os("/state"), os("/home/op")),
            PathBuf::from("/state")
        );
        assert_eq!(
            locate(None, os("/home/op")),
            PathBuf::from("/home/op/.local/state")
        );
        assert_eq!(locate(os("/state"), None), PathBuf::from("/state"));
        assert_eq!(locate(None, None), PathBuf::from("/var/lib"));
    }
}
