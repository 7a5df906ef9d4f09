//! `recorder record` as a separate process following an embedded sim
//! deployment (controller and twin, recording nothing themselves) over
//! TCP on loopback, while a real client steps two episodes: every step the
//! client was answered is in the subscriber's files, with its observation.

use offworld_runtime::Resolution;
use offworld_test_support::ScratchDir;
use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::embedded::{Embedded, SimEnv, Stepping, TwinProfile};
use offworld_env_controller::Store;
use offworld_recorder::msg::{EpisodeEnd, Step};
use offworld_recorder::read;
use offworld_runtime::codec;
use offworld_runtime::msg::{
    Action, Channels, DepthFormat, Image, ObsOptions, OpenRequest, PoseStamped, Seed, StepReply,
    Twist,
};
use offworld_runtime::session::loopback_endpoint;
use offworld_runtime::{EnvId, SessionConfig, Topic};

const RECORDER: &str = env!("CARGO_BIN_EXE_recorder");

fn scratch(name: &str) -> ScratchDir {
    ScratchDir::new(&format!("follow-{name}"))
}

/// A `recorder` child, its stderr lines collected; killed when dropped.
struct Recorder {
    child: Child,
    lines: Arc<Mutex<Vec<String>>>,
}

impl Recorder {
    fn spawn(args: &[&str]) -> Self {
        let mut child = Command::new(RECORDER)
            .args(args)
            .env("RUST_LOG", "info,zenoh=warn")
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn recorder");
        let lines = Arc::new(Mutex::new(Vec::new()));
        let stderr = child.stderr.take().expect("stderr");
        let collected = lines.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                collected.lock().expect("lines").push(line);
            }
        });
        Self { child, lines }
    }

    fn stderr(&self) -> String {
        self.lines.lock().expect("lines").join("\n")
    }

    /// Waits (at most `within`) for a stderr line containing `text`.
    async fn wait_for(&self, text: &str, within: Duration) {
        let deadline = Instant::now() + within;
        while !self.stderr().contains(text) {
            assert!(
                Instant::now() < deadline,
                "the recorder never said `{text}`; its stderr:\n{}",
                self.stderr()
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }

    /// SIGINT, then waits (at most `within`) for a clean exit.
    async fn interrupt(&mut self, within: Duration) {
        let status = Command::new("kill")
            .args(["-INT", &self.child.id().to_string()])
            .status()
            .expect("kill");
        assert!(status.success());
        let deadline = Instant::now() + within;
        loop {
            if let Some(status) = self.child.try_wait().expect("wait") {
                assert!(status.success(), "{status}; stderr:\n{}", self.stderr());
                return;
            }
            assert!(
                Instant::now() < deadline,
                "the recorder did not stop after SIGINT; stderr:\n{}",
                self.stderr()
            );
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Messages of `topic` in a complete file, decoded, in file order.
fn messages<T: serde::de::DeserializeOwned>(path: &Path, topic: &str) -> Vec<T> {
    let buf = std::fs::read(path).expect("read");
    mcap::MessageStream::new(&buf)
        .expect("a complete MCAP file")
        .map(|m| m.expect("message"))
        .filter(|m| m.channel.topic == topic)
        .map(|m| codec::decode(&m.data).expect("decode"))
        .collect()
}

/// What the client was answered in one episode.
struct Answered {
    /// The reset's observation, then each step's.
    observations: Vec<Vec<u8>>,
    replies: Vec<StepReply>,
}

async fn play(client: &mut EnvClient, seed: Seed, steps: usize) -> Answered {
    let reset = client.reset(seed).await.expect("reset");
    let mut answered = Answered {
        observations: vec![reset.observation.data],
        replies: Vec::new(),
    };
    for i in 0..steps {
        let reply = client
            .step(Action::Discrete((i % 3) as i64))
            .await
            .expect("step");
        answered.observations.push(reply.observation.data.clone());
        let over = reply.terminated || reply.truncated;
        answered.replies.push(reply);
        if over {
            break;
        }
    }
    answered
}

/// Checks one recorded episode file against what the client was answered.
fn check_episode(path: &Path, answered: &Answered, episode_id: u64, env: &EnvId) -> Vec<Step> {
    let summary = read::summarize(path).expect("summary");
    assert!(summary.complete, "{}", path.display());
    let meta = &summary.metadata;
    assert_eq!(meta["env_id"], env.to_string());
    assert_eq!(meta["task"], "MonolithDiscrete");
    assert_eq!(meta["world"], "monolith");
    assert_eq!(meta["experiment"], "followed");
    assert_eq!(meta["episode_id"], episode_id.to_string());
    assert_eq!(meta["embodiment"], "twin");
    assert_eq!(meta["recorder"], "subscriber");
    let unknown: Vec<&str> = meta["unknown"].split(' ').collect();
    for field in [
        "learning_type",
        "algorithm_mode",
        "seeded",
        "seed",
        "requested_start",
        "action_discrete",
    ] {
        assert!(unknown.contains(&field), "{field} unknown: {meta:?}");
    }
    assert!(!unknown.contains(&"task"), "the spec was answered");
    assert_eq!(
        (meta["learning_type"].as_str(), meta["seed"].as_str()),
        ("", "0")
    );

    let steps: Vec<Step> = messages(path, "/offworld/step");
    assert_eq!(
        steps.len(),
        answered.replies.len() + 1,
        "the reset and every step"
    );
    assert_eq!((steps[0].step, steps[0].reward), (0, 0.0));
    let mut episode_return = 0.0;
    for (step, reply) in steps[1..].iter().zip(&answered.replies) {
        episode_return += reply.reward;
        assert_eq!(step.step, reply.info.step);
        assert_eq!(step.episode_id, reply.info.episode_id);
        assert_eq!(step.reward, reply.reward);
        assert_eq!(step.terminated, reply.terminated);
        assert_eq!(step.truncated, reply.truncated);
        assert_eq!(step.episode_return, episode_return);
        assert_eq!(step.action_discrete, -1, "unknown to a subscriber");
        assert!(step.duration_s > 0.0, "the commanded motion: {step:?}");
    }
    for pair in steps.windows(2) {
        assert!(pair[0].command_seq < pair[1].command_seq, "{pair:?}");
    }
    // At the render size the RGB observation is the camera frame itself.
    let colors: Vec<Image> = messages(path, "/camera/color/image_raw");
    assert_eq!(colors.len(), steps.len());
    for (color, obs) in colors.iter().zip(&answered.observations) {
        assert_eq!((color.width, color.height), (16, 12));
        assert_eq!(color.encoding, "rgb8");
        assert_eq!(&color.data, obs, "recorded colour == the observation");
    }
    for (step, color) in steps.iter().zip(&colors) {
        assert_eq!(step.header.stamp, color.header.stamp);
    }
    assert_eq!(
        messages::<Image>(path, "/camera/depth/image_raw").len(),
        steps.len()
    );
    assert_eq!(
        messages::<PoseStamped>(path, "/tracker/pose").len(),
        steps.len()
    );
    assert_eq!(
        messages::<Twist>(path, "/cmd_vel").len(),
        answered.replies.len()
    );
    steps
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_subscriber_records_every_step_the_client_was_answered() {
    let scratch_dir = scratch("deployment");
    let (by_env, by_all) = (scratch_dir.join("by-env"), scratch_dir.join("by-all"));
    // The deployment: twin and controller, recording nothing themselves.
    let mut attempts = 0;
    let (server, endpoint) = loop {
        let endpoint = loopback_endpoint().expect("port");
        match SessionConfig::listening(&endpoint).open().await {
            Ok(session) => break (session, endpoint),
            Err(e) if attempts >= 4 => panic!("listen: {e}"),
            Err(_) => attempts += 1,
        }
    };
    let env = EnvId::sim(&format!(
        "follow-{}",
        &offworld_runtime::keys::random_id()[..8]
    ))
    .expect("env");
    let sim = SimEnv {
        env: env.clone(),
        task: "MonolithDiscrete".into(),
        resolution: Some(Resolution::new(16, 12)),
        seed: 0,
        profile: TwinProfile::default(),
        render_threads: 1,
        stepping: Stepping::OwnThread,
    };
    let embedded = Embedded::start(&server, &[sim], Store::in_memory().expect("store"))
        .await
        .expect("embedded");

    let env_arg = env.to_string();
    let dir_env = by_env.to_str().expect("utf8");
    let dir_all = by_all.to_str().expect("utf8");
    let mut one = Recorder::spawn(&[
        "record",
        "--env",
        &env_arg,
        "--out",
        dir_env,
        "-e",
        &endpoint,
        "--duration",
        "120",
    ]);
    let mut every = Recorder::spawn(&["record", "--all", dir_all, "-e", &endpoint]);
    for recorder in [&one, &every] {
        recorder
            .wait_for("following", Duration::from_secs(20))
            .await;
    }
    // Their subscriptions reach the deployment.
    let probe = server
        .declare_publisher(env.key(Topic::Reward))
        .await
        .expect("probe");
    let deadline = Instant::now() + Duration::from_secs(10);
    while !probe.matching_status().await.expect("matching").matching() {
        assert!(
            Instant::now() < deadline,
            "no subscriber reached the deployment"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    drop(probe);
    tokio::time::sleep(Duration::from_millis(500)).await;

    let request = OpenRequest {
        experiment_name: "followed".into(),
        ..OpenRequest::anonymous(ObsOptions {
            channels: Channels::RgbOnly,
            height: 12,
            width: 16,
            depth_format: DepthFormat::Uint8,
        })
    };
    let mut client = EnvClient::open(&server, &env, request, ClientTimeouts::default())
        .await
        .expect("open");
    let experiment_id = client.opened().experiment.id;
    // Episode 0 ends by a reset, episode 1 by a close.
    let first = play(&mut client, Seed::Fixed(7), 5).await;
    let second = play(&mut client, Seed::Continue, 2).await;
    client.close().await.expect("close");
    // The close ends episode 1's file at once (the lease ended).
    for recorder in [&one, &every] {
        recorder
            .wait_for("episode 1:", Duration::from_secs(10))
            .await;
    }
    one.interrupt(Duration::from_secs(20)).await;
    every.interrupt(Duration::from_secs(20)).await;
    drop(embedded);
    let stderr = one.stderr();
    assert!(
        stderr.contains("2 episodes (2 finished)") && stderr.contains("0 skipped"),
        "{stderr}"
    );

    let expected_dir = |root: &Path| {
        root.join("sim")
            .join(env.name())
            .join(format!("exp-{experiment_id:06}"))
    };
    let mut recorded = Vec::new();
    for root in [&by_env, &by_all] {
        let files = read::episode_files(root).expect("files");
        assert_eq!(
            files,
            [
                expected_dir(root).join("ep-000000.mcap"),
                expected_dir(root).join("ep-000001.mcap")
            ],
            "one complete file per episode, no .partial left"
        );
        let steps = [
            check_episode(&files[0], &first, 0, &env),
            check_episode(&files[1], &second, 1, &env),
        ];
        let ends: Vec<Vec<EpisodeEnd>> = files
            .iter()
            .map(|f| messages(f, "/offworld/episode_end"))
            .collect();
        assert_eq!((ends[0].len(), ends[1].len()), (1, 1));
        assert_eq!(ends[0][0].steps as usize, first.replies.len());
        assert!(
            ends[0][0].end_reason.contains("next episode began"),
            "{:?}",
            ends[0][0]
        );
        assert_eq!(ends[1][0].steps, 2);
        assert!(
            ends[1][0].end_reason.contains("lease ended"),
            "{:?}",
            ends[1][0]
        );
        recorded.push(steps);
    }
    assert_eq!(recorded[0], recorded[1], "--env and --all record the same");
    let _ = std::fs::remove_dir_all(&scratch_dir);
}

#[test]
fn an_unwritable_directory_is_refused_at_start() {
    let scratch_dir = scratch("unwritable");
    // A file where a directory is needed: unwritable even for root.
    let file = scratch_dir.join("a-file");
    std::fs::write(&file, b"not a directory").expect("file");
    let out = file.join("runs");
    let output = Command::new(RECORDER)
        .args(["record", "--env", "sim/x", "--out"])
        .arg(&out)
        .args(["-e", "tcp/127.0.0.1:1", "--duration", "5"])
        .output()
        .expect("run recorder");
    assert_eq!(output.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(
        stderr.contains(&format!("cannot record into {}", out.display())),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&scratch_dir);
}

#[test]
fn a_scope_and_a_directory_are_required() {
    for args in [
        &["record", "--out", "runs"][..],
        &["record", "--env", "sim/x"],
        &["record", "--env", "sim/x", "--all", "runs"],
        &["record", "--env", "sim/x", "--out", "a", "b"],
    ] {
        let output = Command::new(RECORDER).args(args).output().expect("run");
        assert_eq!(output.status.code(), Some(2), "{args:?}");
    }
    let help = Command::new(RECORDER)
        .args(["record", "--help"])
        .output()
        .expect("help");
    let text = String::from_utf8_lossy(&help.stdout);
    for flag in ["--env", "--all", "--out", "--duration", "--connect"] {
        assert!(text.contains(flag), "{flag}: {text}");
    }
}
