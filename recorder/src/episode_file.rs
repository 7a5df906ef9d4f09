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

/// The file's name while its episode is being written.
pub fn partial_path(path: &Path) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(".partial");
    PathBuf::from(name)
}

/// An episode file being written. Dropped without [`EpisodeFile::finish`],
/// it stays a `.partial` readable up to its last flushed step.
pub struct EpisodeFile {
    writer: Writer<BufWriter<File>>,
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
        let io = |e: std::io::Error| RecordError::io(path, e);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent).map_err(io)?;
        }
        let partial = partial_path(path);
        let file = File::create_new(&partial).map_err(io)?;
        let mut writer = WriteOptions::new()
            .profile("ros2")
            .library(concat!("offworld-recorder/", env!("CARGO_PKG_VERSION")))
            .compression(compression)
            .compression_level(1)
            // One chunk per step: no zstd worker threads per chunk.
            .compression_threads(0)
            .create(BufWriter::new(file))
            .map_err(|e| RecordError::mcap(path, e))?;
        let mut channels = [0u16; Channel::ALL.len()];
        for (slot, channel) in channels.iter_mut().zip(Channel::ALL) {
            let name = channel.type_name();
            let text = schema::full_text(name)
                .ok_or_else(|| RecordError::Schema(format!("no message definition for {name}")))?;
            let schema = writer
                .add_schema(name, "ros2msg", text.as_bytes())
                .map_err(|e| RecordError::mcap(path, e))?;
            let metadata = BTreeMap::from([
                ("offered_qos_profiles".to_owned(), OFFERED_QOS.to_owned()),
                ("topic_type_hash".to_owned(), String::new()),
            ]);
            *slot = writer
                .add_channel(schema, channel.topic(), "cdr", &metadata)
                .map_err(|e| RecordError::mcap(path, e))?;
        }
        writer
            .write_metadata(&Metadata {
                name: METADATA_NAME.to_owned(),
                metadata: info.metadata(),
            })
            .map_err(|e| RecordError::mcap(path, e))?;
        let mut file = Self {
            writer,
            path: path.to_owned(),
            partial,
            channels,
            sequence: 0,
        };
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
        self.writer
            .write_to_known_channel(&header, data)
            .map_err(|e| RecordError::mcap(&self.path, e))
    }

    /// Ends a step: its messages become a complete chunk on disk (a crash
    /// from now on loses nothing of it).
    pub fn end_step(&mut self) -> Result<(), RecordError> {
        self.writer
            .flush()
            .map_err(|e| RecordError::mcap(&self.path, e))
    }

    /// Writes `end`, finishes the file (summary and footer), syncs it if
    /// `sync` (so a power cut cannot lose it once renamed) and gives it its
    /// final name; returns that name. Without `sync` the rename is still
    /// atomic for readers and survives the process being killed.
    pub fn finish(mut self, end: &EpisodeEnd, sync: bool) -> Result<PathBuf, RecordError> {
        let at = stamp_ns(&end.header.stamp);
        self.write(Channel::EpisodeEnd, at, now_ns(), end)?;
        self.writer
            .finish()
            .map_err(|e| RecordError::mcap(&self.path, e))?;
        let Self {
            writer,
            path,
            partial,
            ..
        } = self;
        let io = |e: std::io::Error| RecordError::io(&path, e);
        let file = writer
            .into_inner()
            .into_inner()
            .map_err(|e| io(e.into_error()))?;
        if sync {
            file.sync_all().map_err(io)?;
        }
        std::fs::rename(&partial, &path).map_err(io)?;
        // The rename itself survives a power cut only once the directory is synced.
        if let (true, Some(parent)) = (sync, path.parent()) {
            File::open(parent).and_then(|d| d.sync_all()).map_err(io)?;
        }
        Ok(path)
    }
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
