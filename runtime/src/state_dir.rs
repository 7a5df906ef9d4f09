//! Where a component keeps what must outlive it (the robot agent's e-stop
//! latch), by the platform's convention: systemd's `StateDirectory=`
//! (`$STATE_DIRECTORY`), else the user's state directory (`dirs`:
//! `$XDG_STATE_HOME`, else `~/.local/state`), else the user's local data
//! directory (platforms without a state directory).

use std::path::PathBuf;

use crate::error::ContractError;

/// `<state dir>/offworld/<component>/<file>`; under systemd's
/// `StateDirectory=` the unit already names the component's directory, so
/// `$STATE_DIRECTORY/<file>`. With no location at all (no systemd state
/// directory, no `HOME` and no home in the user database) an error naming
/// `flag`, which sets the path instead: a component that needs the file
/// must not run without it.
pub fn state_file(component: &str, file: &str, flag: &str) -> Result<PathBuf, ContractError> {
    let systemd =
        std::env::var_os("STATE_DIRECTORY").map(|dirs| dirs.to_string_lossy().into_owned());
    locate(
        systemd.as_deref(),
        dirs::state_dir().or_else(dirs::data_local_dir),
        component,
        file,
        flag,
    )
}

fn locate(
    systemd: Option<&str>,
    user: Option<PathBuf>,
    component: &str,
    file: &str,
    flag: &str,
) -> Result<PathBuf, ContractError> {
    // Several directories are separated by `:`; the first is the unit's own.
    if let Some(first) = systemd
        .and_then(|dirs| dirs.split(':').next())
        .filter(|d| !d.is_empty())
    {
        return Ok(PathBuf::from(first).join(file));
    }
    user.map(|dir| dir.join("offworld").join(component).join(file))
        .ok_or_else(|| {
            ContractError::Config(format!(
                "no state directory for {component}'s {file}: neither $STATE_DIRECTORY, \
                 $XDG_STATE_HOME nor $HOME is set; pass {flag} PATH"
            ))
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn systemd_first_then_the_user_state_dir_else_an_error_naming_the_flag() {
        let user = Some(PathBuf::from("/home/op/.local/state"));
        let at = |systemd, user| {
            locate(
                systemd,
                user,
                "robot_agent",
                "real+a.estop",
                "--estop-latch",
            )
        };
        assert_eq!(
            at(
                Some("/var/lib/offworld/robot_agent:/var/lib/other"),
                user.clone()
            )
            .expect("systemd's directory"),
            PathBuf::from("/var/lib/offworld/robot_agent/real+a.estop")
        );
        assert_eq!(
            at(Some(""), user.clone()).expect("the user's directory"),
            PathBuf::from("/home/op/.local/state/offworld/robot_agent/real+a.estop")
        );
        let ContractError::Config(why) = at(None, None).expect_err("nowhere") else {
            panic!("not a config error");
        };
        assert!(why.contains("pass --estop-latch PATH"), "{why}");
    }
}
