//! `offworld`: every OffWorld Gym program behind one command, with the
//! flags each program has on its own (`offworld twin` is `sim_twin`,
//! `offworld serve` is `env_controller serve` plus in-process twins on
//! request, …): the per-component binaries stay for site services
//! (systemd units run one each).

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{CommandFactory, Parser, Subcommand};

const EXAMPLES: &str = "\
Examples:
  offworld serve --env sim/monolith-0=MonolithDiscrete --embedded-twins   # a gym server with its twin
  offworld twin --env sim/monolith-0                                      # a standalone twin
  offworld emulate-enclosure                                              # the real stack on emulated hardware
  offworld farm --twins 4                                                 # sim twins behind the site's router
  offworld monitor --all --viewer                                         # watch every env in rerun
  offworld recorder record --all runs                                     # record every episode
  offworld --db site.db users add alice                                   # prints alice's token once
  offworld estop --env real/monolith-0 --reason \"person inside\"           # stop a robot
  offworld web --http 0.0.0.0:8080                                        # the lab's web page
  offworld gym envs --connect quic/router.example:7447                    # a deployment's envs, as a trainer
  offworld gym book --env real/monolith-0 --start 2026-12-01T14:00 --minutes 60

`offworld gym …` is `python -m offworld_gym …`; docs: README.md";

/// OffWorld Gym on Zenoh: serve envs, run twins and robots, watch, record
/// and administer a site.
#[derive(Parser)]
#[command(name = "offworld", version, after_help = EXAMPLES)]
struct Cli {
    /// The gym server's SQLite database of users, experiments and episodes
    /// (serve, users, experiments, leaderboard; also after the command)
    /// [env: OFFWORLD_DB] [default: offworld.db].
    #[arg(long, value_name = "FILE")]
    db: Option<PathBuf>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Serve envs over Zenoh (`env_controller serve`), with an in-process
    /// twin for every sim env on request.
    Serve(offworld_deploy::cli::serve::Args),
    #[command(flatten)]
    Controller(offworld_env_controller::cli::Command),
    /// Serve a simulated enclosure (`sim_twin`).
    Twin(offworld_sim_twin::cli::Args),
    /// Emulate the enclosure's hardware with a sim twin: the robot's ROS 2
    /// topics and a raw tracker stream, for the real stack to drive.
    EmulateHardware(offworld_deploy::cli::hardware::Args),
    /// Run the real stack (gym server, robot agent, base guard, tracker
    /// agent) against an emulated enclosure, as separate processes.
    EmulateEnclosure(offworld_deploy::cli::enclosure::Args),
    /// Run a sim farm (sim twins and a gym server) behind the zenohd
    /// router, with the deployment's TLS, passwords and access control.
    Farm(offworld_deploy::cli::farm::Args),
    /// Serve a real enclosure's robot (`robot_agent`).
    Robot(offworld_robot_agent::cli::Args),
    /// Zero the robot's base when the robot agent dies, freezes or goes
    /// silent: its independent safety process (`base_guard`).
    Guard(offworld_robot_agent::guard_cli::Args),
    /// Localise the robot with the enclosure's Vive tracker (`tracker_agent`).
    Tracker(offworld_tracker_agent::cli::Args),
    /// Watch envs live in rerun, or replay a recorded episode (`monitor`).
    Monitor(offworld_monitor::cli::Args),
    /// Record episodes from outside the controller, inspect and recover
    /// recordings (`recorder`).
    Recorder(offworld_recorder::cli::Args),
    /// Measure and calibrate the twin against recorded robot episodes
    /// (`parity`).
    Parity(offworld_parity::cli::Args),
    /// Serve the lab's web page (`lab_web`).
    Web(offworld_web::cli::Args),
    /// A trainer's view of a deployment: envs, bookings, who you are, your
    /// experiments and episodes, the leaderboard (`python -m offworld_gym`).
    #[command(after_help = offworld_client::cli::EXAMPLES)]
    Gym(offworld_client::cli::Args),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let keeps_records = match &cli.command {
        Command::Serve(_) => true,
        Command::Controller(command) => {
            !matches!(command, offworld_env_controller::cli::Command::Estop { .. })
        }
        _ => false,
    };
    if cli.db.is_some() && !keeps_records {
        // Said, not ignored: a site file named for a command that keeps no records.
        Cli::command()
            .error(
                clap::error::ErrorKind::ArgumentConflict,
                "--db names the gym server's database: it is for serve, users, experiments and leaderboard",
            )
            .exit();
    }
    if prints_records_and_ends(&cli.command) {
        offworld_program::end_quietly_when_output_closes();
    }
    match cli.command {
        Command::Serve(args) => offworld_deploy::cli::serve::run(cli.db, args),
        Command::Controller(command) => offworld_env_controller::cli::run_command(cli.db, command),
        Command::Twin(args) => offworld_sim_twin::cli::run(args),
        Command::EmulateHardware(args) => offworld_deploy::cli::hardware::run(args),
        Command::EmulateEnclosure(args) => offworld_deploy::cli::enclosure::run(args),
        Command::Farm(args) => offworld_deploy::cli::farm::run(args),
        Command::Robot(args) => offworld_robot_agent::cli::run(args),
        Command::Guard(args) => offworld_robot_agent::guard_cli::run(args),
        Command::Tracker(args) => offworld_tracker_agent::cli::run(args),
        Command::Monitor(args) => offworld_monitor::cli::run(args),
        Command::Recorder(args) => offworld_recorder::cli::run(args),
        Command::Parity(args) => offworld_parity::cli::run(args),
        Command::Web(args) => offworld_web::cli::run(args),
        Command::Gym(args) => offworld_client::cli::run(args),
    }
}

/// Commands that print the site's records from its database and end: no
/// socket of theirs can raise SIGPIPE (`offworld gym` reports a closed
/// output itself; an e-stop must say what went wrong on any link).
fn prints_records_and_ends(command: &Command) -> bool {
    use offworld_env_controller::cli::Command as Site;
    matches!(
        command,
        Command::Controller(
            Site::Users { .. } | Site::Experiments { .. } | Site::Leaderboard { .. }
        )
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;

    /// The workspace's root directory.
    fn workspace() -> PathBuf {
        let package = offworld_test_support::package_dir();
        package.parent().expect("workspace").to_owned()
    }

    #[test]
    fn the_command_line_is_consistent() {
        Cli::command().debug_assert();
    }

    /// Every `offworld …` command in the README and the docs' code blocks
    /// parses (flags, values, subcommands): the documentation cannot drift
    /// from the command line. Lines with placeholders (`…`) are prose.
    #[test]
    fn the_documented_commands_parse() {
        let root = workspace();
        let mut files = vec![root.join("README.md"), root.join("deploy/README.md")];
        for entry in std::fs::read_dir(root.join("docs")).expect("docs/") {
            let path = entry.expect("entry").path();
            if path.extension().is_some_and(|e| e == "md") {
                files.push(path);
            }
        }
        let mut checked = 0;
        for file in &files {
            let text = std::fs::read_to_string(file).expect("readable");
            for command in documented_commands(&text) {
                if command.contains('…') || command.contains("$(") {
                    continue;
                }
                let words = shell_words(&command);
                if let Err(e) = Cli::try_parse_from(&words) {
                    panic!("{}: `{command}` does not parse:\n{e}", file.display());
                }
                checked += 1;
            }
        }
        assert!(checked >= 20, "only {checked} documented commands found");
    }

    /// The project's own scripts (`.ci/*`) start `offworld` commands that
    /// parse: `bash .ci/emulate` cannot drift from the command line either.
    #[test]
    fn the_scripts_start_commands_that_parse() {
        let dir = workspace().join(".ci");
        let mut checked = 0;
        for entry in std::fs::read_dir(&dir).expect(".ci/") {
            let path = entry.expect("entry").path();
            let script = std::fs::read_to_string(&path).expect("readable");
            // The one command, never a per-component binary that may go.
            for (at, _) in script.match_indices("/release/") {
                let program = &script[at + "/release/".len()..];
                // Cargo's own folders (its incremental caches) are not programs.
                if program.starts_with("incremental") {
                    continue;
                }
                assert!(
                    program.starts_with("offworld\""),
                    "{}: runs {:?}, not `offworld`",
                    path.display(),
                    program.lines().next().unwrap_or_default()
                );
            }
            // As a fenced block, with the binary's path as its name.
            let code = script.replace("\"$CARGO_TARGET_DIR/release/offworld\"", "offworld");
            for command in documented_commands(&format!("```\n{code}\n```")) {
                let words = shell_words(&command);
                if let Err(e) = Cli::try_parse_from(&words) {
                    panic!("{}: `{command}` does not parse:\n{e}", path.display());
                }
                checked += 1;
            }
        }
        assert!(checked >= 1, "no `offworld` command in .ci/");
    }

    /// Every unit of `deploy/systemd/` starts an `offworld` command that
    /// parses, with the example environment file's values (`${VAR}` one
    /// word, `$VAR` split into words, as systemd does).
    #[test]
    fn the_systemd_units_start_commands_that_parse() {
        let dir = workspace().join("deploy/systemd");
        let env_file = std::fs::read_to_string(dir.join("offworld.env")).expect("offworld.env");
        let vars: Vec<(String, String)> = env_file
            .lines()
            .filter(|l| !l.trim_start().starts_with('#'))
            .filter_map(|l| l.split_once('='))
            .map(|(k, v)| (k.trim().to_owned(), v.trim().to_owned()))
            .chain([("STATE_DIRECTORY".into(), "/var/lib/offworld".into())])
            .collect();
        let mut checked = 0;
        for entry in std::fs::read_dir(&dir).expect("deploy/systemd") {
            let path = entry.expect("entry").path();
            if path.extension().is_none_or(|e| e != "service") {
                continue;
            }
            let unit = std::fs::read_to_string(&path).expect("readable");
            let Some(exec) = unit
                .lines()
                .find_map(|l| l.strip_prefix("ExecStart=/usr/local/bin/offworld "))
            else {
                continue;
            };
            let mut words = vec!["offworld".to_owned()];
            for word in exec.replace("%i", "0").split_whitespace() {
                let mut word = word.to_owned();
                for (name, value) in &vars {
                    word = word.replace(&format!("${{{name}}}"), value);
                }
                match vars.iter().find(|(name, _)| word == format!("${name}")) {
                    Some((_, value)) => words.extend(shell_words(value)),
                    None => words.push(word),
                }
            }
            assert!(
                !words.iter().any(|w| w.contains('$')),
                "{}: an unknown variable in {words:?}",
                path.display()
            );
            if let Err(e) = Cli::try_parse_from(&words) {
                panic!(
                    "{}: `{}` does not parse:\n{e}",
                    path.display(),
                    words.join(" ")
                );
            }
            checked += 1;
        }
        assert_eq!(checked, 7, "units starting `offworld`");
    }

    /// The `offworld …` commands of the fenced code blocks, continuation
    /// lines joined, comments and a trailing `&` removed.
    fn documented_commands(markdown: &str) -> Vec<String> {
        let mut commands = Vec::new();
        let mut in_code = false;
        let mut pending: Option<String> = None;
        for line in markdown.lines() {
            if line.trim_start().starts_with("```") {
                in_code = !in_code;
                continue;
            }
            if !in_code {
                continue;
            }
            let code = without_comment(line).trim().to_owned();
            let (code, continues) = match code.strip_suffix('\\') {
                Some(head) => (head.trim().to_owned(), true),
                None => (code, false),
            };
            let command = match pending.take() {
                Some(head) => format!("{head} {code}"),
                None if code.starts_with("offworld ") => code,
                None => continue,
            };
            if continues {
                pending = Some(command);
            } else {
                commands.push(command.trim_end_matches('&').trim().to_owned());
            }
        }
        commands
    }

    /// `line` up to a `#` that starts a shell comment (outside quotes).
    fn without_comment(line: &str) -> &str {
        let mut quoted = false;
        let mut previous = ' ';
        for (i, c) in line.char_indices() {
            match c {
                '"' => quoted = !quoted,
                '#' if !quoted && previous.is_whitespace() => return &line[..i],
                _ => {}
            }
            previous = c;
        }
        line
    }

    /// Words as a shell splits them (double quotes only).
    fn shell_words(command: &str) -> Vec<String> {
        let mut words = Vec::new();
        let mut word = String::new();
        let mut quoted = false;
        let mut started = false;
        for c in command.chars() {
            match c {
                '"' => {
                    quoted = !quoted;
                    started = true;
                }
                c if c.is_whitespace() && !quoted => {
                    if started {
                        words.push(std::mem::take(&mut word));
                        started = false;
                    }
                }
                c => {
                    word.push(c);
                    started = true;
                }
            }
        }
        if started {
            words.push(word);
        }
        words
    }
}
