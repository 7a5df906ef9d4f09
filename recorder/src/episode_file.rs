//! One episode, one MCAP file: written as `….mcap.partial`, each step
//! flushed as its own chunk, finished, synced and renamed at the end.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use mcap::records::{MessageHeader, Metadata};
pub use mcap::Compression;
use mcap::{WriteOptions, Writer};
use offworld_runtime::codec;
use serde::Serialize;

use crate::msg::{EpisodeEnd, EpisodeInfo};
use crate::schema;
use crate::RecordError;

/// The topics of an episode file (see `docs/recording.md`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Channel {
    /// `/offworld/episode`: [`EpisodeInfo`].
    Episode,
    /// `/camera/color/image_raw`: `sensor_msgs/msg/Image`.
    Color,
    /// `/camera/depth/image_raw`: `sensor_msgs/msg/Image`.
    Depth,
    /// `/tracker/pose`: `geometry_msgs/msg/PoseStamped`.
    Pose,
    /// `/odom`: `nav_msgs/msg/Odometry`.
    Odom,
    /// `/cmd_vel`: `geometry_msgs/msg/Twist`.
    CmdVel,
    /// `/offworld/step`: [`crate::msg::Step`].
    Step,
    /// `/offworld/episode_end`: [`EpisodeEnd`].
    EpisodeEnd,
}

impl Channel {
    /// Every channel, in the order they are declared in a file.
    pub const ALL: [Channel; 8] = [
        Channel::Episode,
        Channel::Color,
        Channel::Depth,
        Channel::Pose,
        Channel::Odom,
        Channel::CmdVel,
        Channel::Step,
        Channel::EpisodeEnd,
    ];

    /// The ROS topic name.
    pub fn topic(self) -> &'static str {
        match self {
            Channel::Episode => "/offworld/episode",
            Channel::Color => "/camera/color/image_raw",
            Channel::Depth => "/camera/depth/image_raw",
            Channel::Pose => "/tracker/pose",
            Channel::Odom => "/odom",
            Channel::CmdVel => "/cmd_vel",
            Channel::Step => "/offworld/step",
            Channel::EpisodeEnd => "/offworld/episode_end",
        }
    }

    /// The ROS type, `pkg/msg/Type`.
    pub fn type_name(self) -> &'static str {
        match self {
            Channel::Episode => "offworld_msgs/msg/EpisodeInfo",
            Channel::Color | Channel::Depth => "sensor_msgs/msg/Image",
            Channel::Pose => "geometry_msgs/msg/PoseStamped",
            Channel::Odom => "nav_msgs/msg/Odometry",
            Channel::CmdVel => "geometry_msgs/msg/Twist",
            Channel::Step => "offworld_msgs/msg/Step",
            Channel::EpisodeEnd => "offworld_msgs/msg/EpisodeEnd",
        }
    }
}

/// The QoS rosbag2 records with each topic (its reader needs one; numeric
/// form, as rosbag2 reads files without its own metadata record): keep
/// last 10, reliable, volatile, automatic liveliness, no deadline.
const OFFERED_QOS: &str = "- history: 1\n  depth: 10\n  reliability: 1\n  durability: 2\n  deadline:\n    sec: 9223372036\n    nsec: 854775807\n  lifespan:\n    sec: 9223372036\n    nsec: 854775807\n  liveliness: 1\n  liveliness_lease_duration:\n    sec: 9223372036\n    nsec: 854775807\n  avoid_ros_namespace_conventions: false";

/// Name of the metadata record repeating [`EpisodeInfo`].
pub const METADATA_NAME: &str = "offworld.episode";

/// The metadata key of how long the episode's reset took, s (decimal):
/// with the requested start (`EpisodeInfo::requested_start`) and the reset
/// step's pose, the reset's accuracy.
pub const RESET_DURATION_NOTE: &str = "reset_duration_s";

/// How every episode file is written: the ROS 2 profile, our library
/// name, chunks compressed with `compression` (zstd at its fastest level,
/// without worker threads: a chunk may hold a single step).
pub(crate) fn write_options(compression: Option<Compression>) -> WriteOptions {
    WriteOptions::new()
        .profile("ros2")
        .library(concat!("offworld-recorder/", env!("CARGO_PKG_VERSION")))
        .compression(compression)
        .compression_level(1)
        .compression_threads(0)
}

/// The file's name while its episode is being written.
pub fn partial_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".partial");
    PathBuf::from(name)
}

/// An episode file being written. Dropped without [`EpisodeFile::finish`],
/// it stays a `.partial` readable up to its last flushed step.
///
/// After any write error the mcap writer is dropped and never called
/// again: the mcap crate can be left in a state where its next call (or
/// its own drop) panics, and a panic must not end the recorder.
pub struct EpisodeFile {
    writer: Option<Writer<BufWriter<File>>>,
    path: PathBuf,
    partial: PathBuf,
    channels: [u16; Channel::ALL.len()],
    sequence: u32,
}

impl EpisodeFile {
    /// Creates `path` (as its `.partial`; parent directories too) for the
    /// episode `info`, its chunks compressed with `compression`, and writes
    /// the episode's first message.
    pub fn create(
        path: &Path,
        info: &EpisodeInfo,
        compression: Option<Compression>,
    ) -> Result<Self, RecordError> {
        Self::create_annotated(path, info, &BTreeMap::new(), compression)
    }

    /// [`EpisodeFile::create`], with `notes` added to the `offworld.episode`
    /// metadata record (what `EpisodeInfo` cannot say, e.g. who recorded
    /// the file and which of its fields are unknown); `EpisodeInfo`'s own
    /// keys win over notes of the same name.
    pub fn create_annotated(
        path: &Path,
        info: &EpisodeInfo,
        notes: &BTreeMap<String, String>,
        compression: Option<Compression>,
    ) -> Result<Self, RecordError> {
        let io = |e: std::io::Error| RecordError::io(path, e);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(io)?;
        }
        // An episode id used before (a site that started over with a new
        // database) gets a name of its own: a recording is never replaced.
        let path = &unused_name(path);
        let partial = partial_path(path);
        let file = File::create_new(&partial).map_err(io)?;
        let writer = write_options(compression)
            .create(BufWriter::new(file))
            .map_err(|e| RecordError::mcap(path, e))?;
        let mut file = Self {
            writer: Some(writer),
            path: path.to_owned(),
            partial,
            channels: [0u16; Channel::ALL.len()],
            sequence: 0,
        };
        for (slot, channel) in Channel::ALL.into_iter().enumerate() {
            let name = channel.type_name();
            let text = schema::full_text(name)
                .ok_or_else(|| RecordError::Schema(format!("no message definition for {name}")))?;
            let schema = file.with_writer(|w| w.add_schema(name, "ros2msg", text.as_bytes()))?;
            let metadata = BTreeMap::from([
                ("offered_qos_profiles".to_owned(), OFFERED_QOS.to_owned()),
                ("topic_type_hash".to_owned(), String::new()),
            ]);
            file.channels[slot] =
                file.with_writer(|w| w.add_channel(schema, channel.topic(), "cdr", &metadata))?;
        }
        let mut metadata = notes.clone();
        metadata.extend(info.metadata());
        let metadata = Metadata {
            name: METADATA_NAME.to_owned(),
            metadata,
        };
        file.with_writer(|w| w.write_metadata(&metadata))?;
        let started = stamp_ns(&info.header.stamp);
        file.write(Channel::Episode, started, started, info)?;
        file.end_step()?;
        Ok(file)
    }

    /// The file's final path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Writes `msg` on `channel`, logged at `log_time_ns` (the capture
    /// time), received at `publish_time_ns`.
    pub fn write<T: Serialize>(
        &mut self,
        channel: Channel,
        log_time_ns: u64,
        publish_time_ns: u64,
        msg: &T,
    ) -> Result<(), RecordError> {
        let data = codec::encode(msg).map_err(|e| RecordError::Encode(e.to_string()))?;
        self.write_cdr(channel, log_time_ns, publish_time_ns, &data)
    }

    /// Writes an already encoded CDR message (encapsulation header first).
    pub fn write_cdr(
        &mut self,
        channel: Channel,
        log_time_ns: u64,
        publish_time_ns: u64,
        data: &[u8],
    ) -> Result<(), RecordError> {
        self.sequence = self.sequence.wrapping_add(1);
        let header = MessageHeader {
            channel_id: self.channels[channel as usize],
            sequence: self.sequence,
            log_time: log_time_ns,
            publish_time: publish_time_ns,
        };
        self.with_writer(|w| w.write_to_known_channel(&header, data))
    }

    /// Calls the mcap writer; on its first error drops it for good.
    fn with_writer<T>(
        &mut self,
        call: impl FnOnce(&mut Writer<BufWriter<File>>) -> mcap::McapResult<T>,
    ) -> Result<T, RecordError> {
        let Some(writer) = self.writer.as_mut() else {
            return Err(RecordError::Invalid {
                path: self.path.clone(),
                reason: "an earlier write failed: this file takes no more".into(),
            });
        };
        call(writer).map_err(|e| {
            drop_quietly(self.writer.take());
            RecordError::mcap(&self.path, e)
        })
    }

    /// Ends a step: its messages become a complete chunk on disk (a crash
    /// from now on loses nothing of it).
    pub fn end_step(&mut self) -> Result<(), RecordError> {
        self.with_writer(Writer::flush)
    }

    /// Writes `end`, finishes the file (summary and footer), syncs it if
    /// `sync` (so a power cut cannot lose it once renamed) and gives it its
    /// final name; returns that name. Without `sync` the rename is still
    /// atomic for readers and survives the process being killed.
    pub fn finish(mut self, end: &EpisodeEnd, sync: bool) -> Result<PathBuf, RecordError> {
        let at = stamp_ns(&end.header.stamp);
        self.write(Channel::EpisodeEnd, at, now_ns(), end)?;
        self.with_writer(|w| w.finish().map(drop))?;
        let (Some(writer), path, partial) =
            (self.writer.take(), self.path.clone(), self.partial.clone())
        else {
            return Err(invalid_state(&self.path));
        };
        let io = |e: std::io::Error| RecordError::io(&path, e);
        let file = writer
            .into_inner()
            .into_inner()
            .map_err(|e| io(e.into_error()))?;
        if sync {
            file.sync_all().map_err(io)?;
        }
        // Linked, not renamed: a link never replaces an existing file.
        let named = match std::fs::hard_link(&partial, &path) {
            Ok(()) => path.clone(),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                let other = unused_name(&path);
                std::fs::hard_link(&partial, &other).map_err(io)?;
                other
            }
            Err(e) => return Err(io(e)),
        };
        std::fs::remove_file(&partial).map_err(io)?;
        // The new name survives a power cut only once the directory is synced.
        if let (true, Some(parent)) = (sync, named.parent()) {
            File::open(parent).and_then(|d| d.sync_all()).map_err(io)?;
        }
        Ok(named)
    }
}

impl Drop for EpisodeFile {
    fn drop(&mut self) {
        // Unfinished: the mcap writer's own drop completes the .partial
        // (summary and footer) if it can.
        drop_quietly(self.writer.take());
    }
}

/// Drops an mcap writer, containing a panic of its drop (it finishes the
/// file, which panics in some states after an I/O error).
fn drop_quietly(writer: Option<Writer<BufWriter<File>>>) {
    if let Some(writer) = writer {
        let dropped = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| drop(writer)));
        if dropped.is_err() {
            tracing::debug!("the mcap writer panicked while dropped after an I/O error");
        }
    }
}

fn invalid_state(path: &Path) -> RecordError {
    RecordError::Invalid {
        path: path.to_owned(),
        reason: "the file was already finished or failed".into(),
    }
}

/// `path`, or if it or its `.partial` exists, the first free
/// `stem.N.mcap` beside it.
fn unused_name(path: &Path) -> PathBuf {
    let taken = |p: &Path| p.exists() || partial_path(p).exists();
    if !taken(path) {
        return path.to_owned();
    }
    let stem = path
        .file_stem()
        .unwrap_or_default()
        .to_string_lossy()
        .into_owned();
    (1u32..)
        .map(|n| path.with_file_name(format!("{stem}.{n}.mcap")))
        .find(|p| !taken(p))
        .unwrap_or_else(|| path.to_owned())
}

/// A ROS time in nanoseconds since the epoch (negative times clamp to 0).
pub fn stamp_ns(stamp: &offworld_runtime::msg::Time) -> u64 {
    u64::try_from(stamp.sec).unwrap_or(0) * 1_000_000_000 + u64::from(stamp.nanosec)
}

/// Wall-clock now, in nanoseconds since the epoch.
pub fn now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_nanos()).unwrap_or(u64::MAX))
}
