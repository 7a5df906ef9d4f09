//! `monitor replay`: episodes recorded by an embedded sim env (the
//! controller's own recorder, stepped by a real client) and episode files
//! written with known messages, played by the built binary into an `.rrd`
//! and read back with the Python `rerun-sdk==0.36.3`
//! (`tests/check_rrd.py --rows`): every image, pose, odometry, command and
//! step under the live monitor's entity paths, at the recorded times.
//! Broken files fail with a message naming them.

use offworld_runtime::Resolution;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use anyhow::{anyhow, ensure, Context};
use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::{connect, Target};
use offworld_recorder::episode_file::{partial_path, stamp_ns, Compression, EpisodeFile};
use offworld_recorder::msg::{EpisodeEnd, EpisodeInfo, Step};
use offworld_recorder::Channel;
use offworld_runtime::msg::*;
use offworld_runtime::{codec, EnvId};
use serde_json::Value;

/// A fresh directory under the temp dir.
fn scratch(tag: &str) -> anyhow::Result<PathBuf> {
    let dir = std::env::temp_dir().join(format!(
        "offworld-replay-{tag}-{}",
        offworld_runtime::keys::random_id()
    ));
    std::fs::create_dir_all(&dir)?;
    Ok(dir)
}

/// Runs the built `monitor` with `args`.
fn monitor(args: &[&std::ffi::OsStr]) -> anyhow::Result<Output> {
    Command::new(env!("CARGO_BIN_EXE_monitor"))
        .args(args)
        .output()
        .context("running the monitor binary")
}

/// `monitor replay <paths…> --save <rrd>`, which must succeed; its stderr.
fn replay_into(rrd: &Path, paths: &[&Path]) -> anyhow::Result<String> {
    let mut args: Vec<&std::ffi::OsStr> = vec!["replay".as_ref()];
    args.extend(paths.iter().map(|p| p.as_os_str()));
    args.extend(["--save".as_ref(), rrd.as_os_str()]);
    let out = monitor(&args)?;
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    ensure!(
        out.status.success(),
        "monitor replay exited with {}: {stderr}",
        out.status
    );
    Ok(stderr)
}

/// A place on the timelines: `step`, `sim_time` ns, `wall_time` ns.
type Index = [Option<i64>; 3];

/// What `check_rrd.py --rows` read from an `.rrd`.
struct Rrd(Value);

impl Rrd {
    fn read(path: &Path) -> anyhow::Result<Self> {
        let script = offworld_test_support::package_dir().join("tests/check_rrd.py");
        let out = Command::new("python3")
            .arg(&script)
            .arg(path)
            .arg("--rows")
            .output()
            .context("running python3 (needs rerun-sdk==0.36.3)")?;
        ensure!(
            out.status.success(),
            "check_rrd.py failed ({}): {}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
        let summary: Value =
            serde_json::from_slice(&out.stdout).context("check_rrd.py printed no JSON")?;
        ensure!(
            summary["rerun_version"] == "0.36.3",
            "{}",
            summary["rerun_version"]
        );
        ensure!(
            summary["verify"]["ok"] == true,
            "rerun rrd verify: {}",
            summary["verify"]
        );
        ensure!(summary["recordings"] == 1, "one recording");
        Ok(Self(summary))
    }

    /// The entity `/envs/<env>/<relative>`: the live monitor's paths.
    fn entity(&self, env: &EnvId, relative: &str) -> anyhow::Result<&Value> {
        let path = format!("/envs/{}/{}/{relative}", env.realm().as_str(), env.name());
        self.0["entities"].get(&path).ok_or_else(|| {
            let have: Vec<&String> = self.0["entities"]
                .as_object()
                .map(|m| m.keys().collect())
                .unwrap_or_default();
            anyhow!("entity {path} missing; have: {have:?}")
        })
    }

    /// Non-null cells of `component` in the entity's rows.
    fn cells(&self, env: &EnvId, relative: &str, component: &str) -> anyhow::Result<u64> {
        Ok(self.entity(env, relative)?["components"][component]
            .as_u64()
            .unwrap_or(0))
    }

    /// The entity's temporal rows on the timelines, sorted.
    fn index(&self, env: &EnvId, relative: &str) -> anyhow::Result<Vec<Index>> {
        let rows = self.entity(env, relative)?["index"]
            .as_array()
            .ok_or_else(|| anyhow!("{relative}: no index"))?;
        let mut index: Vec<Index> = rows
            .iter()
            .map(|row| std::array::from_fn(|i| row[i].as_i64()))
            .collect();
        index.sort();
        Ok(index)
    }

    fn texts(&self, env: &EnvId, relative: &str) -> anyhow::Result<Vec<String>> {
        Ok(self.entity(env, relative)?["texts"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|t| t.as_str().map(str::to_owned))
            .collect())
    }
}

/// Where each recorded message must appear in the replay, per entity
/// (relative to the env's root), worked out from the files themselves:
/// a step's messages are the ones between the previous `Step` and its own
/// (`docs/recording.md`), all at its `command_seq`; odometry after the last
/// step stays at that step; `sim_time` is the capture time (the log time,
/// the header stamp), `wall_time` when the recorder received it (the
/// publish time).
#[derive(Default)]
struct Expected {
    rows: BTreeMap<&'static str, Vec<Index>>,
    steps: u64,
    /// Episodes whose last step was terminal.
    terminal: u64,
    ends: Vec<EpisodeEnd>,
}

fn ns(value: u64) -> Option<i64> {
    i64::try_from(value).ok()
}

impl Expected {
    /// From complete files, or a `.partial` up to its cut.
    fn read(files: &[PathBuf]) -> anyhow::Result<Self> {
        let mut expected = Self::default();
        let mut seq: Option<i64> = None;
        for file in files {
            let buf = std::fs::read(file)?;
            let options = if file.to_string_lossy().ends_with(".partial") {
                enumset::enum_set!(mcap::read::Options::IgnoreEndMagic)
            } else {
                enumset::enum_set!()
            };
            let mut pending: Vec<(String, u64, u64)> = Vec::new();
            for message in mcap::MessageStream::new_with_options(&buf, options)? {
                let Ok(message) = message else {
                    // A `.partial` ends at its cut; a complete file is whole.
                    ensure!(!options.is_empty(), "{}: cut", file.display());
                    break;
                };
                let topic = message.channel.topic.as_str();
                if topic == Channel::Step.topic() {
                    let step: Step = codec::decode(&message.data)?;
                    seq = ns(step.command_seq);
                    for (topic, log, publish) in pending.drain(..) {
                        expected.message(&topic, seq, log, publish);
                    }
                    let capture = ns(stamp_ns(&step.header.stamp)).filter(|t| *t > 0);
                    for entity in ["metrics/reward", "metrics/return"] {
                        expected.push(entity, [seq, capture, ns(message.publish_time)]);
                    }
                    expected.steps += 1;
                    expected.terminal += u64::from(step.terminated || step.truncated);
                } else if topic == Channel::EpisodeEnd.topic() {
                    expected.ends.push(codec::decode(&message.data)?);
                } else if topic != Channel::Episode.topic() {
                    pending.push((topic.to_owned(), message.log_time, message.publish_time));
                }
            }
            // After the last step: its odometry only.
            for (topic, log, publish) in pending {
                if topic == Channel::Odom.topic() {
                    expected.message(&topic, seq, log, publish);
                }
            }
        }
        Ok(expected)
    }

    fn push(&mut self, entity: &'static str, index: Index) {
        self.rows.entry(entity).or_default().push(index);
    }

    fn message(&mut self, topic: &str, seq: Option<i64>, log: u64, publish: u64) {
        // A zero stamp is "no stamp" to the monitor.
        let capture = ns(log).filter(|t| *t > 0);
        let wall = ns(publish);
        let entities: &[&'static str] = match topic {
            "/camera/color/image_raw" => &["robot/camera/color"],
            "/camera/depth/image_raw" => &["robot/camera/depth"],
            "/tracker/pose" => &["robot"],
            "/odom" => &["odom/robot"],
            // Commands carry the controller's send time, not a capture time.
            "/cmd_vel" => {
                for entity in ["metrics/linear_x", "metrics/angular_z"] {
                    self.push(entity, [seq, None, wall]);
                }
                return;
            }
            _ => &[],
        };
        for entity in entities {
            self.push(entity, [seq, capture, wall]);
        }
    }

    fn rows(&self, entity: &str) -> Vec<Index> {
        let mut rows = self.rows.get(entity).cloned().unwrap_or_default();
        rows.sort();
        rows
    }

    /// Every time-varying entity holds exactly the expected rows.
    fn check(&self, rrd: &Rrd, env: &EnvId) -> anyhow::Result<()> {
        for (entity, component) in [
            ("robot/camera/color", "Image:buffer"),
            ("robot/camera/depth", "DepthImage:buffer"),
            ("robot", "Transform3D:translation"),
            ("odom/robot", "Transform3D:translation"),
            ("metrics/linear_x", "Scalars:scalars"),
            ("metrics/angular_z", "Scalars:scalars"),
            ("metrics/reward", "Scalars:scalars"),
            ("metrics/return", "Scalars:scalars"),
        ] {
            let expected = self.rows(entity);
            let cells = rrd.cells(env, entity, component)?;
            ensure!(
                cells == expected.len() as u64,
                "{entity}: {cells} {component} cells, {} recorded",
                expected.len()
            );
            let index = rrd.index(env, entity)?;
            ensure!(
                index == expected,
                "{entity}: logged at\n{index:?}\nrecorded at\n{expected:?}"
            );
        }
        Ok(())
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn recorded_episodes_replay_as_the_live_view_at_the_recorded_times() -> anyhow::Result<()> {
    let dir = scratch("embedded")?;
    let connection = connect(
        Target::Embedded {
            task: "MonolithDiscrete".into(),
            resolution: Resolution::new(32, 24),
            count: 1,
            record: Some(dir.clone()),
            twin_profile: offworld_deploy::embedded::TwinProfile::default(),
        },
        "MonolithDiscrete",
    )
    .await?;
    let env = connection.envs[0].clone();
    let request = OpenRequest {
        experiment_name: "replay-test".into(),
        ..OpenRequest::anonymous(ObsOptions {
            channels: Channels::Rgbd,
            height: 24,
            width: 32,
            depth_format: DepthFormat::Uint8,
        })
    };
    let mut client = EnvClient::open(
        &connection.session,
        &env,
        request,
        ClientTimeouts::default(),
    )
    .await?;
    // Episode 0: a reset and up to 6 steps; episode 1: a reset, 2 steps, closed.
    client.reset(Seed::Fixed(3)).await?;
    for i in 0..6 {
        let reply = client.step(Action::Discrete(i % 3)).await?;
        if reply.terminated || reply.truncated {
            break;
        }
    }
    client.reset(Seed::Continue).await?;
    for _ in 0..2 {
        client.step(Action::Discrete(0)).await?;
    }
    client.close().await?;
    drop(connection); // every file finished

    let files = offworld_recorder::read::episode_files(&dir)?;
    ensure!(files.len() == 2, "two episode files: {files:?}");
    let expected = Expected::read(&files)?;
    ensure!(expected.ends.len() == 2, "both episodes ended");

    let rrd = dir.join("replay.rrd");
    let stderr = replay_into(&rrd, &[&dir])?;
    println!("{stderr}");
    for file in &files {
        ensure!(
            stderr.contains(&file.display().to_string()),
            "progress names {}: {stderr}",
            file.display()
        );
    }
    let rrd = Rrd::read(&rrd)?;
    expected.check(&rrd, &env)?;
    // One image, pose and step per recorded step (the resets included).
    ensure!(expected.rows("robot/camera/color").len() as u64 == expected.steps);
    ensure!(expected.rows("robot").len() as u64 == expected.steps);
    ensure!(!expected.rows("odom/robot").is_empty(), "odometry recorded");
    ensure!(expected.rows("metrics/linear_x").len() as u64 == expected.steps - 2);

    // Episode boundaries, as the live monitor logs them, and the ends a
    // reset or a close made.
    let texts = rrd.texts(&env, "events")?;
    println!("{texts:#?}");
    ensure!(texts.len() == 5, "world + 2 × (start, end): {texts:?}");
    ensure!(
        texts.contains(&"world: monolith (recorded)".to_owned()),
        "{texts:?}"
    );
    for episode in 0..2 {
        let started = format!("episode {episode} started (replay-test)");
        ensure!(texts.contains(&started), "{started}: {texts:?}");
    }
    let closed = &expected.ends[1];
    ensure!(closed.end_reason == "closed");
    let end = format!(
        "episode 1 ended after {} steps: closed (return {:.3})",
        closed.steps, closed.episode_return
    );
    ensure!(texts.contains(&end), "{end}: {texts:?}");
    ensure!(
        texts.iter().any(|t| t.starts_with("episode 0 ended after")),
        "{texts:?}"
    );
    for entity in ["metrics/success", "metrics/episode_length"] {
        let cells = match rrd.entity(&env, entity) {
            Ok(_) => rrd.cells(&env, entity, "Scalars:scalars")?,
            Err(_) => 0,
        };
        ensure!(cells == expected.terminal, "{entity}: {cells}");
    }
    ensure!(rrd.cells(&env, "trajectory", "LineStrips3D:strips")? >= 2);

    // The static scene: world, body, camera.
    for (entity, component) in [
        ("world/terrain", "Mesh3D:vertex_positions"),
        ("world/walls", "Boxes3D:half_sizes"),
        ("world/monolith", "Boxes3D:half_sizes"),
        ("world/success_radius", "LineStrips3D:strips"),
        ("robot/body", "Boxes3D:half_sizes"),
        ("robot/camera", "Pinhole:image_from_camera"),
    ] {
        let e = rrd.entity(&env, entity)?;
        ensure!(
            e["static_rows"].as_u64().unwrap_or(0) >= 1 && rrd.cells(&env, entity, component)? >= 1,
            "{entity}: {e}"
        );
    }
    ensure!(
        rrd.0["blueprints"].as_u64().unwrap_or(0) >= 1,
        "no blueprint"
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

const W: u32 = 8;
const H: u32 = 6;

/// An episode of `steps` steps after its reset, written as the recorder
/// writes them (each step its own zstd chunk) with known values: step `k`
/// captured at 10 + k/2 s, received at 1.7e9 + k s, command seq 100 + k.
/// Finished, or left a `.partial` (its writer dropped); returns its path.
fn known_episode(dir: &Path, env: &EnvId, steps: u32, finish: bool) -> anyhow::Result<PathBuf> {
    let received = |k: u32| 1_700_000_000_000_000_000 + u64::from(k) * 1_000_000_000;
    let info = EpisodeInfo {
        header: Header::new(Time::from_secs_f64(1.7e9), "world"),
        env_id: env.to_string(),
        task: "MonolithDiscrete".into(),
        world: "monolith_obstacle".into(),
        experiment_id: 1,
        experiment: "known".into(),
        learning_type: "end2end".into(),
        algorithm_mode: "train".into(),
        episode_id: 0,
        seeded: true,
        seed: 1,
        embodiment: "twin".into(),
        software_version: "test".into(),
        max_episode_steps: 100,
        requested_start: [0.0, 0.0, 0.0],
    };
    let path = dir.join("ep-000000.mcap");
    let mut file = EpisodeFile::create(&path, &info, Some(Compression::Zstd))?;
    for k in 0..=steps {
        let capture = Time::from_secs_f64(10.0 + f64::from(k) * 0.5);
        let at = stamp_ns(&capture);
        write_odom(
            &mut file,
            10.0 + f64::from(k) * 0.5 - 0.25,
            received(k) - 500_000,
        )?;
        if k > 0 {
            let sent = received(k) - 1_000_000;
            file.write(Channel::CmdVel, sent, sent, &Twist::planar(0.25, -0.5))?;
        }
        let color = Image::packed(
            Header::new(capture, "camera_color_optical_frame"),
            W,
            H,
            PixelEncoding::Rgb8,
            vec![k as u8; (W * H * 3) as usize],
        );
        let depth = Image::packed(
            Header::new(capture, "camera_depth_optical_frame"),
            W,
            H,
            PixelEncoding::Depth32FC1,
            (0..W * H).flat_map(|_| 1.5f32.to_le_bytes()).collect(),
        );
        let pose = PoseStamped {
            header: Header::new(capture, "world"),
            pose: Pose {
                position: Point {
                    x: f64::from(k) * 0.1,
                    y: 0.0,
                    z: 0.1,
                },
                orientation: Quaternion::from_yaw(0.0),
            },
        };
        let step = known_step(k, capture);
        file.write(Channel::Color, at, received(k), &color)?;
        file.write(Channel::Depth, at, received(k), &depth)?;
        file.write(Channel::Pose, at, received(k), &pose)?;
        file.write(Channel::Step, at, received(k), &step)?;
        file.end_step()?;
    }
    // Odometry after the last step.
    let after = f64::from(steps) + 0.5;
    write_odom(&mut file, 10.0 + after * 0.5, received(steps) + 500_000_000)?;
    if !finish {
        drop(file);
        return Ok(partial_path(&path));
    }
    let end = EpisodeEnd {
        header: Header::new(Time::from_secs_f64(1.7e9 + 100.0), "world"),
        episode_id: 0,
        steps,
        episode_return: -0.01 * f64::from(steps),
        success: false,
        terminated: false,
        truncated: false,
        end_reason: "closed".into(),
    };
    Ok(file.finish(&end, false)?)
}

/// Odometry captured at `secs`, received at `received` ns.
fn write_odom(file: &mut EpisodeFile, secs: f64, received: u64) -> anyhow::Result<()> {
    let stamp = Time::from_secs_f64(secs);
    let odom = Odometry {
        header: Header::new(stamp, "odom"),
        child_frame_id: "base_link".into(),
        pose: PoseWithCovariance {
            pose: Pose {
                position: Point {
                    x: secs * 0.01,
                    y: 0.0,
                    z: 0.0,
                },
                orientation: Quaternion::from_yaw(secs * 0.1),
            },
            covariance: [0.0; 36],
        },
        twist: TwistWithCovariance::default(),
    };
    file.write(Channel::Odom, stamp_ns(&stamp), received, &odom)?;
    Ok(())
}

/// Step `k` of a known episode, captured at `capture`.
fn known_step(k: u32, capture: Time) -> Step {
    Step {
        header: Header::new(capture, "world"),
        episode_id: 0,
        step: k,
        command_seq: 100 + u64::from(k),
        action_discrete: if k == 0 { -1 } else { 0 },
        action_continuous: Vec::new(),
        linear_x: 0.25,
        angular_z: -0.5,
        duration_s: 0.5,
        reward: -0.01,
        episode_return: -0.01 * f64::from(k),
        terminated: false,
        truncated: false,
        success: false,
        end_reason: String::new(),
    }
}

/// Cuts `path` (a whole MCAP file) at `fraction` of its data section
/// (the chunks; the summary after them goes too), as a crash would.
fn cut(path: &Path, fraction: f64) -> anyhow::Result<()> {
    let data_end = mcap::read::footer(&std::fs::read(path)?)?.summary_start;
    let file = std::fs::OpenOptions::new().write(true).open(path)?;
    file.set_len((data_end as f64 * fraction) as u64)?;
    Ok(())
}

#[test]
fn a_crashed_episodes_partial_replays_up_to_its_cut_beside_a_complete_one() -> anyhow::Result<()> {
    let dir = scratch("partial")?;
    let id = std::process::id();
    let complete = EnvId::sim(&format!("replay-complete-{id}"))?;
    let crashed = EnvId::sim(&format!("replay-crashed-{id}"))?;
    let complete_file = known_episode(&dir.join("complete"), &complete, 5, true)?;
    let partial = known_episode(&dir.join("crashed"), &crashed, 8, false)?;
    cut(&partial, 0.7)?;
    let expected_complete = Expected::read(std::slice::from_ref(&complete_file))?;
    let expected_cut = Expected::read(std::slice::from_ref(&partial))?;
    ensure!(expected_complete.steps == 6);
    ensure!(
        (1..9).contains(&expected_cut.steps),
        "the cut keeps some steps: {}",
        expected_cut.steps
    );

    let rrd = dir.join("replay.rrd");
    let stderr = replay_into(&rrd, &[&dir])?;
    println!("{stderr}");
    ensure!(stderr.contains("cut"), "{stderr}");
    let rrd = Rrd::read(&rrd)?;
    expected_complete.check(&rrd, &complete)?;
    expected_cut.check(&rrd, &crashed)?;
    // The known values, on the live monitor's timelines.
    let colors = rrd.index(&complete, "robot/camera/color")?;
    let known: Vec<Index> = (0..=5i64)
        .map(|k| {
            [
                Some(100 + k),
                Some(10_000_000_000 + k * 500_000_000),
                Some(1_700_000_000_000_000_000 + k * 1_000_000_000),
            ]
        })
        .collect();
    ensure!(colors == known, "{colors:?}");
    // The recorded world (with boulders), per env.
    for env in [&complete, &crashed] {
        ensure!(rrd.cells(env, "world/boulders", "Boxes3D:half_sizes")? >= 1);
    }
    let texts = rrd.texts(&complete, "events")?;
    ensure!(
        texts.contains(&"episode 0 ended after 5 steps: closed (return -0.050)".to_owned()),
        "{texts:?}"
    );
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}

/// `monitor replay <path> --save …` fails, naming `named` on stderr, without a panic.
fn fails_naming(path: &Path, named: &Path, rrd: &Path) -> anyhow::Result<()> {
    let out = monitor(&[
        "replay".as_ref(),
        path.as_os_str(),
        "--save".as_ref(),
        rrd.as_os_str(),
    ])?;
    let stderr = String::from_utf8_lossy(&out.stderr);
    ensure!(
        !out.status.success(),
        "{}: exited with {}",
        path.display(),
        out.status
    );
    ensure!(
        out.status.code() == Some(1),
        "an error, not a crash: {}",
        out.status
    );
    ensure!(
        stderr.contains("monitor replay: ") && stderr.contains(&named.display().to_string()),
        "the error names {}: {stderr}",
        named.display()
    );
    ensure!(!stderr.contains("panicked"), "{stderr}");
    Ok(())
}

#[test]
fn missing_corrupt_or_cut_files_fail_with_an_error_naming_them() -> anyhow::Result<()> {
    let dir = scratch("broken")?;
    let env = EnvId::sim(&format!("replay-broken-{}", std::process::id()))?;
    let rrd = dir.join("out.rrd");

    let missing = dir.join("ep-000404.mcap");
    fails_naming(&missing, &missing, &rrd)?;

    let garbage = dir.join("garbage").join("ep-000001.mcap");
    std::fs::create_dir_all(garbage.parent().ok_or_else(|| anyhow!("parent"))?)?;
    std::fs::write(
        &garbage,
        b"this is not an MCAP file, it only has the name of one",
    )?;
    fails_naming(&garbage, &garbage, &rrd)?;
    // Found in a directory, too.
    let garbage_dir = garbage.parent().ok_or_else(|| anyhow!("parent"))?;
    fails_naming(garbage_dir, &garbage, &rrd)?;

    // A finished episode cut short: a complete file must be whole.
    let truncated = known_episode(&dir.join("truncated"), &env, 4, true)?;
    cut(&truncated, 0.6)?;
    fails_naming(&truncated, &truncated, &rrd)?;

    // MCAP, but not an episode: a step before any `/offworld/episode`.
    let foreign = dir.join("foreign").join("ep-000002.mcap");
    std::fs::create_dir_all(foreign.parent().ok_or_else(|| anyhow!("parent"))?)?;
    {
        let mut writer =
            mcap::Writer::new(std::io::BufWriter::new(std::fs::File::create(&foreign)?))?;
        let schema = writer.add_schema("offworld_msgs/msg/Step", "ros2msg", b"")?;
        let channel = writer.add_channel(schema, Channel::Step.topic(), "cdr", &BTreeMap::new())?;
        writer.write_to_known_channel(
            &mcap::records::MessageHeader {
                channel_id: channel,
                sequence: 1,
                log_time: 1,
                publish_time: 1,
            },
            &codec::encode(&known_step(0, Time::from_secs_f64(10.0)))?,
        )?;
        writer.finish()?;
    }
    fails_naming(&foreign, &foreign, &rrd)?;

    let empty = dir.join("empty");
    std::fs::create_dir_all(&empty)?;
    fails_naming(&empty, &empty, &rrd)?;
    let _ = std::fs::remove_dir_all(&dir);
    Ok(())
}
