//! Where a component keeps what must outlive it (the robot agent's e-stop
//! latch), by the platform's convention: the user's state directory
//! (`dirs`: `$XDG_STATE_HOME`, else `~/.local/state`; the local data
//! directory where a platform has no state directory), and for a service
//! started without `HOME` (systemd runs root's services so) the system's,
//! `/var/lib`.

use std::path::{Path, PathBuf};

use crate::error::ContractError;

/// The system's state directory, for services without a `HOME`.
const SYSTEM_STATE: &str = "/var/lib";

/// `<state dir>/offworld/<component>/<file>`. With no location at all (a
/// `HOME` set but no state directory the platform knows) an error naming
/// `flag`, which sets the path instead: a component that needs the file
/// must not run without it.
pub fn state_file(component: &str, file: &str, flag: &str) -> Result<PathBuf, ContractError> {
    let has_home = std::env::var_os("HOME").is_some_and(|home| !home.is_empty());
    let user = has_home
        .then(|| dirs::state_dir().or_else(dirs::data_local_dir))
        .flatten();
    locate(has_home, user, component, file, flag)
}

fn locate(
    has_home: bool,
    user: Option<PathBuf>,
    component: &str,
    file: &str,
    flag: &str,
) -> Result<PathBuf, ContractError> {
    let dir = if has_home {
        user
    } else {
        Some(Path::new(SYSTEM_STATE).to_path_buf())
    };
    dir.map(|dir| dir.join("offworld").join(component).join(file))
        .ok_or_else(|| {
            ContractError::Config(format!(
                "no state directory for {component}'s {file} on this platform; pass {flag} PATH"
            ))
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_user_state_dir_a_service_without_home_var_lib_else_an_error_naming_the_flag() {
        let at = |has_home, user| {
            locate(
                has_home,
                user,
                "robot_agent",
                "real+a.estop",
                "--estop-latch",
            )
        };
        assert_eq!(
            at(true, Some(PathBuf::from("/home/op/.local/state"))).expect("the user's directory"),
            PathBuf::from("/home/op/.local/state/offworld/robot_agent/real+a.estop")
        );
        assert_eq!(
            at(false, None).expect("the system's directory"),
            PathBuf::from("/var/lib/offworld/robot_agent/real+a.estop")
        );
        let ContractError::Config(why) = at(true, None).expect_err("nowhere") else {
            panic!("not a config error");
        };
        assert!(why.contains("pass --estop-latch PATH"), "{why}");
    }
}
