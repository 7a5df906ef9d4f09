//! Episode files written and read back: complete ones, a crash mid-episode
//! (the bytes on disk without the finish) and its recovery.

use std::path::Path;

use offworld_recorder::episode_file::{partial_path, stamp_ns, Channel, Compression, EpisodeFile};
use offworld_recorder::msg::{EpisodeEnd, EpisodeInfo, Step};
use offworld_recorder::read;
use offworld_runtime::codec;
use offworld_runtime::msg::{
    CameraFrame, Header, Image, PixelEncoding, Point, Pose, PoseStamped, Quaternion, Time, Twist,
};

fn info(episode_id: u64) -> EpisodeInfo {
    EpisodeInfo {
        header: Header::new(
            Time {
                sec: 1_700_000_000,
                nanosec: 5,
            },
            "world",
        ),
        env_id: "sim/monolith-0".into(),
        task: "MonolithDiscrete".into(),
        world: "monolith".into(),
        experiment_id: 3,
        experiment: "my run".into(),
        learning_type: "end2end".into(),
        algorithm_mode: "train".into(),
        episode_id,
        seeded: true,
        seed: 42,
        embodiment: "twin".into(),
        software_version: "0.1.0".into(),
        max_episode_steps: 100,
        requested_start: [1.0, -0.5, 0.25],
    }
}

fn stamp(step: u32) -> Time {
    Time {
        sec: 1_700_000_001 + step as i32,
        nanosec: 1_000 * step,
    }
}

fn frame(step: u32) -> CameraFrame {
    let header = Header::new(stamp(step), "camera");
    let color: Vec<u8> = (0..4 * 3 * 3).map(|i| (i as u32 + step) as u8).collect();
    let depth: Vec<u8> = (0..4 * 3)
        .flat_map(|i| (i as f32 * 0.5 + step as f32).to_le_bytes())
        .collect();
    CameraFrame {
        seq: u64::from(step) + 10,
        color: Image::packed(header.clone(), 4, 3, PixelEncoding::Rgb8, color),
        depth: Image::packed(header, 4, 3, PixelEncoding::Depth32FC1, depth),
    }
}

fn step_msg(step: u32) -> Step {
    Step {
        header: Header::new(stamp(step), "world"),
        episode_id: 7,
        step,
        command_seq: u64::from(step) + 10,
        action_discrete: if step == 0 { -1 } else { 2 },
        action_continuous: Vec::new(),
        linear_x: 0.1,
        angular_z: -0.2,
        duration_s: 0.5,
        reward: if step == 3 { 1.0 } else { 0.0 },
        episode_return: if step == 3 { 1.0 } else { 0.0 },
        terminated: step == 3,
        truncated: false,
        success: step == 3,
        end_reason: if step == 3 {
            "success".into()
        } else {
            String::new()
        },
    }
}

fn pose(step: u32) -> PoseStamped {
    PoseStamped {
        header: Header::new(stamp(step), "world"),
        pose: Pose {
            position: Point {
                x: f64::from(step),
                y: 0.5,
                z: 0.0,
            },
            orientation: Quaternion::from_yaw(0.1 * f64::from(step)),
        },
    }
}

/// Writes steps 0..=`steps` the way the recorder does.
fn write_steps(file: &mut EpisodeFile, steps: u32) {
    for step in 0..=steps {
        if step > 0 {
            let at = stamp_ns(&stamp(step)) - 1;
            file.write(Channel::CmdVel, at, at, &Twist::planar(0.1, -0.2))
                .expect("cmd");
        }
        let f = frame(step);
        let at = stamp_ns(&stamp(step));
        file.write(Channel::Color, at, at, &f.color.view())
            .expect("color");
        file.write(Channel::Depth, at, at, &f.depth.view())
            .expect("depth");
        file.write(Channel::Pose, at, at, &pose(step))
            .expect("pose");
        file.write(Channel::Step, at, at, &step_msg(step))
            .expect("step");
        file.end_step().expect("flush");
    }
}

fn end() -> EpisodeEnd {
    EpisodeEnd {
        header: Header::new(stamp(4), "world"),
        episode_id: 7,
        steps: 3,
        episode_return: 1.0,
        success: true,
        terminated: true,
        truncated: false,
        end_reason: "success".into(),
    }
}

fn counts(summary: &read::EpisodeSummary) -> Vec<(String, u64)> {
    summary.messages.clone().into_iter().collect()
}

#[test]
fn a_finished_episode_is_a_complete_file_with_every_message() {
    let dir = tempdir("finished");
    let path = dir.join("sim/monolith-0/exp-000003/ep-000007.mcap");
    let mut file = EpisodeFile::create(&path, &info(7), Some(Compression::Zstd)).expect("create");
    assert!(partial_path(&path).exists(), "written as .partial first");
    assert!(!path.exists());
    write_steps(&mut file, 3);
    let written = file.finish(&end(), true).expect("finish");
    assert_eq!(written, path);
    assert!(path.exists() && !partial_path(&path).exists());

    let summary = read::summarize(&path).expect("summary");
    assert!(summary.complete);
    assert_eq!(
        counts(&summary),
        [
            ("/camera/color/image_raw".to_owned(), 4),
            ("/camera/depth/image_raw".to_owned(), 4),
            ("/cmd_vel".to_owned(), 3),
            ("/offworld/episode".to_owned(), 1),
            ("/offworld/episode_end".to_owned(), 1),
            ("/offworld/step".to_owned(), 4),
            ("/tracker/pose".to_owned(), 4),
        ]
    );
    assert_eq!(summary.last_step, Some(step_msg(3)));
    assert_eq!(summary.end, Some(end()));
    assert_eq!(summary.metadata, info(7).metadata());
    assert_eq!(summary.metadata["requested_start"], "1 -0.5 0.25");

    // The images are the frame's own bytes: an Image's CDR is the same
    // whether encoded from the owned message or the view.
    let buf = std::fs::read(&path).expect("read");
    let colors: Vec<Vec<u8>> = mcap::MessageStream::new(&buf)
        .expect("stream")
        .map(|m| m.expect("message"))
        .filter(|m| m.channel.topic == "/camera/color/image_raw")
        .map(|m| m.data.into_owned())
        .collect();
    let expected: Vec<Vec<u8>> = (0..=3)
        .map(|s| codec::encode(&frame(s).color).expect("encode"))
        .collect();
    assert_eq!(colors, expected);
}

#[test]
fn a_crash_keeps_every_flushed_step_and_recover_makes_a_complete_file() {
    let dir = tempdir("crash");
    let path = dir.join("ep-000007.mcap");
    let mut file = EpisodeFile::create(&path, &info(7), Some(Compression::Zstd)).expect("create");
    write_steps(&mut file, 2);
    // kill -9 now: what is on disk is the .partial as it stands.
    let crashed = dir.join("crashed.mcap.partial");
    std::fs::copy(partial_path(&path), &crashed).expect("copy");
    // A step in progress (not flushed) is in no complete chunk.
    file.write(Channel::Color, 1, 1, &frame(3).color.view())
        .expect("color");
    drop(file);

    let summary = read::summarize(&crashed).expect("partial summary");
    assert!(!summary.complete, "no footer after a crash");
    assert_eq!(summary.last_step, Some(step_msg(2)));
    assert_eq!(summary.end, None);
    assert_eq!(summary.messages["/offworld/step"], 3);
    assert_eq!(summary.metadata, info(7).metadata());

    let (recovered, kept) = read::recover(&crashed, None).expect("recover");
    assert_eq!(recovered, dir.join("crashed.mcap"));
    // Episode info + 3 × (colour, depth, pose, step) + 2 commands.
    assert_eq!(kept, 1 + 3 * 4 + 2);
    let again = read::summarize(&recovered).expect("recovered summary");
    assert!(again.complete);
    assert_eq!(again.messages, summary.messages);
    assert_eq!(again.metadata, summary.metadata);
    // Never overwrites.
    assert!(matches!(
        read::recover(&crashed, None),
        Err(offworld_recorder::RecordError::Io { .. })
    ));
    assert!(matches!(
        read::recover(&recovered, None),
        Err(offworld_recorder::RecordError::Invalid { .. })
    ));
}

#[test]
fn an_episode_file_is_never_overwritten() {
    // A site that started over with a new database reuses episode ids.
    let dir = tempdir("twice");
    let path = dir.join("ep-000001.mcap");
    let first = EpisodeFile::create(&path, &info(1), Some(Compression::Zstd)).expect("create");
    let second = EpisodeFile::create(&path, &info(1), Some(Compression::Zstd)).expect("create");
    assert_eq!(second.path(), dir.join("ep-000001.1.mcap"));
    assert_eq!(first.finish(&end(), false).expect("finish"), path);
    assert_eq!(
        second.finish(&end(), false).expect("finish"),
        dir.join("ep-000001.1.mcap")
    );
    let third = EpisodeFile::create(&path, &info(1), Some(Compression::Zstd)).expect("create");
    assert_eq!(third.path(), dir.join("ep-000001.2.mcap"));
    // Finished under a name another file took meanwhile: linked beside it.
    std::fs::write(dir.join("ep-000001.2.mcap"), b"someone else's").expect("write");
    let kept = third.finish(&end(), false).expect("finish");
    assert_eq!(kept, dir.join("ep-000001.2.1.mcap"));
    assert_eq!(
        std::fs::read(dir.join("ep-000001.2.mcap")).expect("read"),
        b"someone else's"
    );
}

#[test]
fn an_unwritable_directory_is_refused_at_the_start() {
    let dir = tempdir("unwritable");
    let file = dir.join("a-file");
    std::fs::write(&file, b"x").expect("write");
    // A directory below a regular file cannot exist (root ignores modes).
    let err = offworld_recorder::RecordTo::check(&file.join("runs")).expect_err("refused");
    assert!(
        matches!(err, offworld_recorder::RecordError::Unwritable { .. }),
        "{err}"
    );
    assert!(err.to_string().starts_with("cannot record into "), "{err}");
    offworld_recorder::RecordTo::check(&dir.join("runs")).expect("a fresh directory is fine");
}

fn tempdir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("offworld-recorder-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("tempdir");
    assert!(Path::new(&dir).is_dir());
    dir
}
