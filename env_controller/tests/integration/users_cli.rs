//! `env_controller users …` as a site's engineer runs it, against a real
//! database file: add (a duplicate named, not a raw constraint error),
//! list (never a token), revoke (the token stops working, the records
//! stay), rotate (a new token works, the old one not), and a mistyped
//! `--db` refused instead of silently creating an empty site.

use offworld_test_support::ScratchDir;
use std::path::Path;
use std::process::{Command, Output};

use offworld_env_controller::Store;

fn cli(db: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_env_controller"))
        .arg("--db")
        .arg(db)
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .expect("env_controller runs")
}

fn stdout(output: &Output) -> String {
    String::from_utf8_lossy(&output.stdout).into_owned()
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

/// The token a successful `add`/`rotate` printed.
fn token_of(output: &Output) -> String {
    assert!(output.status.success(), "{}", stderr(output));
    let token = stdout(output).trim().to_owned();
    assert_eq!(token.len(), 32, "{token}");
    assert!(token.bytes().all(|b| b.is_ascii_hexdigit()), "{token}");
    token
}

fn user_of(db: &Path, token: &str) -> Option<String> {
    Store::open_existing(db)
        .expect("the database")
        .authenticate(token)
        .expect("a query")
        .map(|u| u.name)
}

#[test]
fn users_are_added_listed_revoked_and_rotated_and_mistakes_are_named() {
    let dir = ScratchDir::new("users-cli");
    let db = dir.0.join("site.db");

    // A mistyped --db: refused, and no empty database appears.
    let typo = dir.0.join("sitte.db");
    for args in [
        &["users", "list"][..],
        &["users", "revoke", "alice"],
        &["users", "rotate", "alice"],
        &["experiments", "list"],
        &["leaderboard", "--env", "sim/monolith-0"],
    ] {
        let out = cli(&typo, args);
        assert!(!out.status.success(), "{args:?}");
        assert!(
            stderr(&out).contains(&format!("no database at {}", typo.display())),
            "{args:?}: {}",
            stderr(&out)
        );
    }
    assert!(!typo.exists(), "a mistyped --db created a database");

    let alice = token_of(&cli(&db, &["users", "add", "alice"]));
    let ops = token_of(&cli(&db, &["users", "add", "ops", "--operator"]));
    let again = cli(&db, &["users", "add", "alice"]);
    assert!(!again.status.success());
    assert!(
        stderr(&again).contains("a user named alice exists already"),
        "{}",
        stderr(&again)
    );
    assert!(!stderr(&again).contains("UNIQUE"), "{}", stderr(&again));

    let listed = cli(&db, &["users", "list"]);
    assert!(listed.status.success(), "{}", stderr(&listed));
    let text = stdout(&listed);
    let rows: Vec<&str> = text.lines().collect();
    assert_eq!(rows.len(), 3, "{text}");
    assert!(rows[0].starts_with("name"), "{text}");
    assert!(
        rows[1].starts_with("alice ") && rows[1].contains(" user "),
        "{text}"
    );
    assert!(rows[1].ends_with("active"), "{text}");
    assert!(
        rows[2].starts_with("ops ") && rows[2].contains(" operator "),
        "{text}"
    );
    assert!(
        !text.contains(&alice) && !text.contains(&ops),
        "a token was printed"
    );
    assert_eq!(user_of(&db, &alice).as_deref(), Some("alice"));

    // Revoked: the token stops working; the user is listed as revoked.
    let revoked = cli(&db, &["users", "revoke", "alice"]);
    assert!(revoked.status.success(), "{}", stderr(&revoked));
    assert!(stdout(&revoked).contains("alice's token is revoked"));
    assert_eq!(user_of(&db, &alice), None);
    let text = stdout(&cli(&db, &["users", "list"]));
    assert!(
        text.lines()
            .any(|l| l.starts_with("alice ") && l.contains("revoked 20")),
        "{text}"
    );
    assert_eq!(
        user_of(&db, &ops).as_deref(),
        Some("ops"),
        "others unaffected"
    );

    // Rotated: a new token works (and reinstates her), the old one not.
    let rotated = cli(&db, &["users", "rotate", "alice"]);
    let new = token_of(&rotated);
    assert_ne!(new, alice);
    assert!(stderr(&rotated).contains("the old one no longer works"));
    assert_eq!(user_of(&db, &new).as_deref(), Some("alice"));
    assert_eq!(user_of(&db, &alice), None);
    let text = stdout(&cli(&db, &["users", "list"]));
    assert!(
        text.lines()
            .any(|l| l.starts_with("alice ") && l.ends_with("active")),
        "{text}"
    );

    // Unknown and malformed names are named.
    let unknown = cli(&db, &["users", "revoke", "bob"]);
    assert!(!unknown.status.success());
    assert!(
        stderr(&unknown).contains("no user named bob (env_controller users list shows them)"),
        "{}",
        stderr(&unknown)
    );
    let anonymous = cli(&db, &["users", "rotate", "anonymous"]);
    assert!(
        !anonymous.status.success(),
        "the anonymous user has no token"
    );
}

#[test]
fn an_empty_site_says_how_to_add_a_user() {
    let dir = ScratchDir::new("users-cli");
    let db = dir.0.join("site.db");
    Store::open(&db).expect("a new database");
    let out = cli(&db, &["users", "list"]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(
        stdout(&out),
        "no users yet: `users add NAME` registers one\n"
    );
}
