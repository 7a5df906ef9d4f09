//! Episodes recorded by the controller (issue 23): an embedded sim env
//! with `record`, stepped by a real client; every file read back and
//! compared with what the client was answered.

use offworld_runtime::Resolution;
use offworld_test_support::ScratchDir;
use std::path::PathBuf;
use std::time::Duration;

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::{connect, Target};
use offworld_recorder::msg::{EpisodeEnd, Step};
use offworld_recorder::read;
use offworld_runtime::codec;
use offworld_runtime::msg::{
    Action, Channels, DepthFormat, Image, LearningType, ObsOptions, OpenRequest, RecordingFile,
    Seed,
};

fn scratch(name: &str) -> ScratchDir {
    ScratchDir::new(&format!("recording-{name}"))
}

/// An embedded MonolithDiscrete env rendering `resolution` (w, h),
/// recording into `dir`.
async fn recording_sim(
    resolution: Resolution,
    dir: &std::path::Path,
) -> Result<offworld_deploy::Connection, offworld_env_controller::ControllerError> {
    connect(
        Target::Embedded {
            task: "MonolithDiscrete".into(),
            resolution,
            count: 1,
            record: Some(dir.to_owned()),
            twin_profile: offworld_deploy::embedded::TwinProfile::default(),
        },
        "MonolithDiscrete",
    )
    .await
}

/// Messages of `topic` in a complete file, decoded, in file order.
fn messages<T: serde::de::DeserializeOwned>(path: &std::path::Path, topic: &str) -> Vec<T> {
    let buf = std::fs::read(path).expect("read");
    mcap::MessageStream::new(&buf)
        .expect("a complete MCAP file")
        .map(|m| m.expect("message"))
        .filter(|m| m.channel.topic == topic)
        .map(|m| codec::decode(&m.data).expect("decode"))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_step_the_client_was_answered_is_in_the_episode_file() {
    let dir = scratch("embedded");
    let connection = recording_sim(Resolution::new(16, 12), &dir)
        .await
        .expect("embedded with recording");
    let env = connection.envs[0].clone();
    let request = OpenRequest {
        experiment_name: "recorded".into(),
        learning_type: LearningType::HumanDemos,
        ..OpenRequest::anonymous(ObsOptions {
            channels: Channels::RgbOnly,
            height: 12,
            width: 16,
            depth_format: DepthFormat::Uint8,
        })
    };
    let mut client = EnvClient::open(
        &connection.session,
        &env,
        request,
        ClientTimeouts::default(),
    )
    .await
    .expect("open");
    let experiment_id = client.opened().experiment.id;
    // Episode 0: a reset and 5 steps, then another reset (which ends it).
    let reset = client.reset(Seed::Fixed(7)).await.expect("reset");
    let mut observations = vec![reset.observation.data.clone()];
    let mut replies = Vec::new();
    for i in 0..5 {
        let reply = client.step(Action::Discrete(i % 3)).await.expect("step");
        observations.push(reply.observation.data.clone());
        replies.push(reply);
        if replies.last().is_some_and(|r| r.terminated || r.truncated) {
            break;
        }
    }
    // Episode 1: a reset and 2 steps, then close.
    client.reset(Seed::Continue).await.expect("second reset");
    for _ in 0..2 {
        client.step(Action::Discrete(0)).await.expect("step");
    }
    client.close().await.expect("close");
    // The controller lists each episode's file with the episode's record.
    let (_, episodes) = offworld_client::experiment_episodes(
        &connection.session,
        &env,
        "",
        experiment_id,
        Duration::from_secs(5),
    )
    .await
    .expect("experiment");
    let listed: Vec<_> = episodes
        .iter()
        .map(|e| (e.index, e.recordings.clone()))
        .collect();
    let relative = format!("sim/{}/exp-{experiment_id:06}", env.name());
    let file_of = |episode: u64| {
        let path = format!("{relative}/ep-{episode:06}.mcap");
        let bytes = std::fs::metadata(dir.join(&path))
            .expect("listed file")
            .len();
        vec![RecordingFile {
            path,
            bytes,
            complete: true,
        }]
    };
    assert_eq!(listed, [(0, file_of(0)), (1, file_of(1))]);
    // The deployment stops: every file is finished.
    drop(connection);

    let files = read::episode_files(&dir).expect("files");
    let expected_dir = dir
        .join("sim")
        .join(env.name())
        .join(format!("exp-{experiment_id:06}"));
    assert_eq!(
        files,
        [
            expected_dir.join("ep-000000.mcap"),
            expected_dir.join("ep-000001.mcap")
        ],
        "one complete file per episode, no .partial left"
    );

    let first = &files[0];
    let summary = read::summarize(first).expect("summary");
    assert!(summary.complete);
    assert_eq!(summary.metadata["env_id"], env.to_string());
    assert_eq!(summary.metadata["task"], "MonolithDiscrete");
    assert_eq!(summary.metadata["learning_type"], "humandemos");
    assert_eq!(summary.metadata["seed"], "7");
    assert_eq!(summary.metadata["seeded"], "true");
    assert_eq!(summary.metadata["embodiment"], "twin");
    let steps: Vec<Step> = messages(first, "/offworld/step");
    assert_eq!(steps.len(), replies.len() + 1, "the reset and every step");
    assert_eq!(steps[0].step, 0);
    assert_eq!(steps[0].action_discrete, -1);
    let mut episode_return = 0.0;
    for (i, (step, reply)) in steps[1..].iter().zip(&replies).enumerate() {
        episode_return += reply.reward;
        assert_eq!(step.step, reply.info.step);
        assert_eq!(step.episode_id, reply.info.episode_id);
        assert_eq!(step.action_discrete, (i % 3) as i64);
        assert_eq!(step.reward, reply.reward);
        assert_eq!(step.terminated, reply.terminated);
        assert_eq!(step.truncated, reply.truncated);
        assert_eq!(step.episode_return, episode_return);
        assert!(step.duration_s > 0.0, "the commanded motion: {step:?}");
    }
    // The RGB observation at the render size is the camera frame itself.
    let colors: Vec<Image> = messages(first, "/camera/color/image_raw");
    assert_eq!(colors.len(), steps.len());
    for (color, obs) in colors.iter().zip(&observations) {
        assert_eq!((color.width, color.height), (16, 12));
        assert_eq!(color.encoding, "rgb8");
        assert_eq!(&color.data, obs, "recorded colour == the observation");
    }
    let depths: Vec<Image> = messages(first, "/camera/depth/image_raw");
    assert_eq!(depths.len(), steps.len());
    // Stamps: a step is stamped with its frame's capture time.
    for (step, color) in steps.iter().zip(&colors) {
        assert_eq!(step.header.stamp, color.header.stamp);
    }
    assert_eq!(
        messages::<offworld_runtime::msg::Twist>(first, "/cmd_vel").len(),
        replies.len()
    );
    assert_eq!(
        messages::<offworld_runtime::msg::PoseStamped>(first, "/tracker/pose").len(),
        steps.len()
    );
    // The twin publishes odometry with every answer.
    assert!(
        messages::<offworld_runtime::msg::Odometry>(first, "/odom").len() >= replies.len(),
        "odometry recorded"
    );
    let ends: Vec<EpisodeEnd> = messages(first, "/offworld/episode_end");
    assert_eq!(ends.len(), 1);
    let end = &ends[0];
    assert_eq!(end.steps as usize, replies.len());
    assert_eq!(end.episode_return, episode_return);
    let last = replies.last().expect("a step");
    if last.terminated || last.truncated {
        assert_ne!(end.end_reason, "");
    } else {
        assert_eq!(end.end_reason, "reset before the episode ended");
    }

    let second = read::summarize(&files[1]).expect("second");
    assert_eq!(second.messages["/offworld/step"], 3);
    assert_eq!(
        second.end.as_ref().map(|e| e.end_reason.as_str()),
        Some("closed")
    );
    assert_eq!(second.metadata["seeded"], "false");
    let _ = std::fs::remove_dir_all(&dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unwritable_record_directory_is_refused_before_serving() {
    let dir = scratch("unwritable");
    let file = dir.join("not-a-dir");
    std::fs::write(&file, b"x").expect("file");
    let err = recording_sim(Resolution::new(16, 12), &file.join("runs"))
        .await
        .err()
        .expect("refused");
    let message = err.to_string();
    assert!(
        message.starts_with(&format!(
            "cannot record into {}",
            file.join("runs").display()
        )),
        "{message}"
    );
    tokio::time::sleep(Duration::from_millis(10)).await;
    let _ = std::fs::remove_dir_all(&dir);
}

/// Unmounts on drop.
struct Tmpfs(PathBuf);

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg(&self.0).status();
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_stops_the_recording_and_never_the_episodes() {
    let dir = scratch("full");
    // A 256 KiB filesystem: full within the first episode's frames.
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", "size=256k", "tmpfs"])
        .arg(dir.path())
        .status()
        .expect("mount runs");
    assert!(
        mounted.success(),
        "mounting a tmpfs needs root (CI runs as root): {mounted}"
    );
    // Unmounted before the scratch directory goes (dropped first).
    let _tmpfs = Tmpfs(dir.to_path_buf());
    let connection = recording_sim(Resolution::new(64, 48), &dir)
        .await
        .expect("the directory is writable at the start");
    let mut client = EnvClient::open(
        &connection.session,
        &connection.envs[0],
        OpenRequest::anonymous(ObsOptions {
            channels: Channels::Rgbd,
            height: 48,
            width: 64,
            depth_format: DepthFormat::Uint8,
        }),
        ClientTimeouts::default(),
    )
    .await
    .expect("open");
    let mut steps = 0u64;
    for episode in 0..3 {
        client.reset(Seed::Fixed(episode)).await.expect("reset");
        for i in 0..20 {
            let reply = client
                .step(Action::Discrete(i % 2))
                .await
                .expect("every step answered, disk full or not");
            steps += 1;
            if reply.terminated || reply.truncated {
                break;
            }
        }
    }
    let closed = client.close().await.expect("close");
    // Every episode is on record (the experiment's counters), the disk
    // filled long before the last one.
    assert_eq!(closed.experiment.episodes, 3);
    assert_eq!(closed.experiment.steps, steps);
    assert!(
        steps * 64 * 48 * 7 > 256 * 1024,
        "the frames overflow the disk"
    );
    drop(connection);
    // What was recorded is readable up to the failure: the first episode's
    // file holds its start and steps; files made once the disk was full are
    // .partial (possibly empty), never a "complete" file without its end.
    let files = read::episode_files(&dir).expect("files");
    let first = read::summarize(&files[0]).expect("the first episode's file");
    assert_eq!(first.messages.get("/offworld/episode"), Some(&1));
    assert!(first.messages.get("/offworld/step").is_some_and(|n| *n > 0));
    for file in &files {
        let name = file.to_string_lossy();
        if let Ok(summary) = read::summarize(file) {
            assert!(
                !summary.complete || summary.end.is_some() || name.ends_with(".partial"),
                "{name}: complete but without its end"
            );
        }
    }
    assert!(
        files
            .iter()
            .any(|f| f.to_string_lossy().ends_with(".partial")),
        "the disk filled: some episode stayed a .partial: {files:?}"
    );
}
