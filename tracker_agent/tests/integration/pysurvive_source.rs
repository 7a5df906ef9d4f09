//! The libsurvive source script as a user meets it: `--help` explains it
//! without libsurvive installed, and running it without libsurvive's
//! bindings says what to install, with a non-zero exit code.

use std::process::Command;

fn script() -> std::path::PathBuf {
    offworld_test_support::package_dir().join("scripts/pysurvive_source.py")
}

#[test]
fn help_explains_the_script_without_libsurvive() {
    let out = Command::new("python3")
        .arg(script())
        .arg("--help")
        .output()
        .expect("python3 runs");
    assert!(out.status.success(), "{out:?}");
    let help = String::from_utf8(out.stdout).expect("utf-8");
    assert!(
        help.starts_with("Stream Vive tracker poses from libsurvive"),
        "{help}"
    );
    assert!(
        help.contains("| offworld tracker run --env real/monolith-0 --source stdin"),
        "{help}"
    );
}

#[test]
fn without_the_bindings_it_says_what_to_install() {
    let has_bindings = Command::new("python3")
        .args(["-c", "import pysurvive"])
        .status()
        .expect("python3 runs")
        .success();
    if has_bindings {
        return; // a machine with libsurvive: nothing missing to report
    }
    let out = Command::new("python3")
        .arg(script())
        .output()
        .expect("python3 runs");
    assert_eq!(out.status.code(), Some(2), "{out:?}");
    let said = String::from_utf8(out.stderr).expect("utf-8");
    assert!(said.contains("`pip install pysurvive`"), "{said}");
    assert!(!said.contains("Traceback"), "{said}");
}
