//! Reading episode files back: what a file holds, its messages in order,
//! and a crashed episode's `.partial` made into a complete file.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use enumset::enum_set;
use mcap::read::{LinearReader, MessageStream, Options};
use mcap::records::{Metadata, Record};
use offworld_runtime::codec;
use serde::de::DeserializeOwned;

use crate::episode_file::{write_options, Channel, Compression, METADATA_NAME};
use crate::msg::{EpisodeEnd, Step};
use crate::RecordError;

/// What an episode file holds.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeSummary {
    /// The file.
    pub path: PathBuf,
    /// Finished with its summary and footer (false: a `.partial` read up to
    /// its last complete chunk).
    pub complete: bool,
    /// The `offworld.episode` metadata record.
    pub metadata: BTreeMap<String, String>,
    /// Messages per topic.
    pub messages: BTreeMap<String, u64>,
    /// The last step recorded.
    pub last_step: Option<Step>,
    /// The episode's end record (absent after a crash).
    pub end: Option<EpisodeEnd>,
}

fn read_file(path: &Path) -> Result<Vec<u8>, RecordError> {
    std::fs::read(path).map_err(|e| RecordError::io(path, e))
}

fn invalid(path: &Path, reason: impl Into<String>) -> RecordError {
    RecordError::Invalid {
        path: path.to_owned(),
        reason: reason.into(),
    }
}

/// Reads `path` (a complete file, or a `.partial` up to its last complete
/// chunk).
pub fn summarize(path: &Path) -> Result<EpisodeSummary, RecordError> {
    let buf = read_file(path)?;
    let complete = MessageStream::new(&buf).is_ok_and(|mut s| s.all(|m| m.is_ok()));
    let mut summary = EpisodeSummary {
        path: path.to_owned(),
        complete,
        metadata: metadata(path, &buf)?,
        messages: BTreeMap::new(),
        last_step: None,
        end: None,
    };
    let stream = MessageStream::new_with_options(&buf, enum_set!(Options::IgnoreEndMagic))
        .map_err(|e| RecordError::mcap(path, e))?;
    for message in stream {
        // A .partial ends in a cut chunk: what came before it is the episode.
        let Ok(message) = message else { break };
        *summary
            .messages
            .entry(message.channel.topic.clone())
            .or_default() += 1;
        let topic = message.channel.topic.as_str();
        if topic == Channel::Step.topic() {
            summary.last_step = Some(decode_data(path, topic, &message.data)?);
        } else if topic == Channel::EpisodeEnd.topic() {
            summary.end = Some(decode_data(path, topic, &message.data)?);
        }
    }
    Ok(summary)
}

/// The file's `offworld.episode` metadata record.
fn metadata(path: &Path, buf: &[u8]) -> Result<BTreeMap<String, String>, RecordError> {
    Ok(metadata_records(path, buf)?
        .into_iter()
        .find(|m| m.name == METADATA_NAME)
        .map(|m| m.metadata)
        .unwrap_or_default())
}

/// Every metadata record before the file's end or cut.
fn metadata_records(path: &Path, buf: &[u8]) -> Result<Vec<Metadata>, RecordError> {
    let reader = LinearReader::new_with_options(buf, enum_set!(Options::IgnoreEndMagic))
        .map_err(|e| RecordError::mcap(path, e))?;
    Ok(reader
        .map_while(Result::ok)
        .filter_map(|record| match record {
            Record::Metadata(m) => Some(m),
            _ => None,
        })
        .collect())
}

/// Writes the complete steps of a crashed episode's `partial` file as a
/// complete file (its name without `.partial`, or `out`); returns that path
/// and the number of messages kept. The file has no `EpisodeEnd`: the
/// episode's end was never recorded.
pub fn recover(partial: &Path, out: Option<&Path>) -> Result<(PathBuf, u64), RecordError> {
    let target = match out {
        Some(out) => out.to_owned(),
        None => {
            let name = partial.to_string_lossy();
            let Some(stem) = name.strip_suffix(".partial") else {
                return Err(invalid(
                    partial,
                    "not a .partial file (give --out to recover it anyway)",
                ));
            };
            PathBuf::from(stem)
        }
    };
    let buf = read_file(partial)?;
    let file = std::fs::File::create_new(&target).map_err(|e| RecordError::io(&target, e))?;
    let mut writer = write_options(Some(Compression::Zstd))
        .create(std::io::BufWriter::new(file))
        .map_err(|e| RecordError::mcap(&target, e))?;
    for record in metadata_records(partial, &buf)? {
        writer
            .write_metadata(&record)
            .map_err(|e| RecordError::mcap(&target, e))?;
    }
    let stream = MessageStream::new_with_options(&buf, enum_set!(Options::IgnoreEndMagic))
        .map_err(|e| RecordError::mcap(partial, e))?;
    let mut kept = 0;
    for message in stream {
        let Ok(message) = message else { break };
        writer
            .write(&message)
            .map_err(|e| RecordError::mcap(&target, e))?;
        kept += 1;
    }
    writer.finish().map_err(|e| RecordError::mcap(&target, e))?;
    let file = writer
        .into_inner()
        .into_inner()
        .map_err(|e| RecordError::io(&target, e.into_error()))?;
    file.sync_all().map_err(|e| RecordError::io(&target, e))?;
    Ok((target, kept))
}

/// Every episode file under `path` (itself if a file), complete ones and
/// `.partial`s, sorted.
pub fn episode_files(path: &Path) -> Result<Vec<PathBuf>, RecordError> {
    let mut found = Vec::new();
    let mut pending = vec![path.to_owned()];
    while let Some(next) = pending.pop() {
        let meta = std::fs::metadata(&next).map_err(|e| RecordError::io(&next, e))?;
        if meta.is_file() {
            found.push(next);
            continue;
        }
        for entry in std::fs::read_dir(&next).map_err(|e| RecordError::io(&next, e))? {
            let entry = entry.map_err(|e| RecordError::io(&next, e))?;
            let p = entry.path();
            let name = p.to_string_lossy();
            // Not followed: a symlinked directory could loop.
            let kind = entry.file_type().map_err(|e| RecordError::io(&p, e))?;
            if kind.is_dir() {
                pending.push(p);
            } else if name.ends_with(".mcap") || name.ends_with(".mcap.partial") {
                found.push(p);
            }
        }
    }
    found.sort();
    Ok(found)
}

/// `data` (a message of `topic` in `path`) decoded from CDR.
fn decode_data<T: DeserializeOwned>(
    path: &Path,
    topic: &str,
    data: &[u8],
) -> Result<T, RecordError> {
    codec::decode(data).map_err(|e| invalid(path, format!("a bad {topic} message: {e}")))
}

/// Whether `path` is a `.partial`: an episode being written, or left so
/// by a crash (its end may be cut).
pub fn is_partial(path: &Path) -> bool {
    path.to_string_lossy().ends_with(".partial")
}

/// An episode file read into memory, to go through its messages.
#[derive(Debug, Clone)]
pub struct EpisodeData {
    path: PathBuf,
    buf: Vec<u8>,
}

/// One message of an episode file, as recorded.
#[derive(Debug, Clone)]
pub struct RecordedMessage {
    /// Its topic, if it is one of ours (other topics are passed on too).
    pub channel: Option<Channel>,
    /// Its topic's name.
    pub topic: String,
    /// The capture time (see `docs/recording.md`), ns.
    pub log_time_ns: u64,
    /// When the recorder received it, ns since the epoch.
    pub publish_time_ns: u64,
    /// The CDR message (encapsulation header first).
    pub data: Vec<u8>,
}

impl EpisodeData {
    /// Reads `path` (a complete file or a `.partial`).
    pub fn read(path: &Path) -> Result<Self, RecordError> {
        Ok(Self {
            path: path.to_owned(),
            buf: read_file(path)?,
        })
    }

    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The file's messages in file order: the order they were recorded
    /// in. A complete file must be whole: its first fault (a cut, a bad
    /// CRC, not MCAP at all) is an error naming it. A `.partial` is read
    /// up to its last complete chunk: the fault that ends it is its cut
    /// ([`Messages::cut`]), not an error.
    pub fn messages(&self) -> Result<Messages<'_>, RecordError> {
        let partial = is_partial(&self.path);
        let options = if partial {
            enum_set!(Options::IgnoreEndMagic)
        } else {
            enum_set!()
        };
        let stream = match MessageStream::new_with_options(&self.buf, options) {
            Ok(stream) => Some(stream),
            // Cut before its header was complete: nothing to read.
            Err(_) if partial => None,
            Err(e) => return Err(RecordError::mcap(&self.path, e)),
        };
        Ok(Messages {
            path: &self.path,
            cut: stream.is_none(),
            stream,
        })
    }

    /// The file's `offworld.episode` metadata record (env, experiment, seed,
    /// … and the notes its recorder added), empty if it has none.
    pub fn metadata(&self) -> Result<BTreeMap<String, String>, RecordError> {
        metadata(&self.path, &self.buf)
    }

    /// `message` (one of this file's) decoded from CDR; an error names the
    /// file and the topic.
    pub fn decode<T: DeserializeOwned>(&self, message: &RecordedMessage) -> Result<T, RecordError> {
        decode_data(&self.path, &message.topic, &message.data)
    }
}

/// The messages of an episode file, in file order ([`EpisodeData::messages`]).
pub struct Messages<'a> {
    path: &'a Path,
    stream: Option<MessageStream<'a>>,
    cut: bool,
}

impl Messages<'_> {
    /// Whether the file ended in a cut (a `.partial` read up to its last
    /// complete chunk) rather than with its end record.
    pub fn cut(&self) -> bool {
        self.cut
    }
}

impl Iterator for Messages<'_> {
    type Item = Result<RecordedMessage, RecordError>;

    fn next(&mut self) -> Option<Self::Item> {
        let next = self.stream.as_mut()?.next();
        match next {
            Some(Ok(message)) => Some(Ok(RecordedMessage {
                channel: Channel::ALL
                    .into_iter()
                    .find(|c| c.topic() == message.channel.topic),
                topic: message.channel.topic.clone(),
                log_time_ns: message.log_time,
                publish_time_ns: message.publish_time,
                data: message.data.into_owned(),
            })),
            Some(Err(e)) => {
                self.stream = None;
                if is_partial(self.path) {
                    self.cut = true;
                    None
                } else {
                    Some(Err(RecordError::mcap(self.path, e)))
                }
            }
            None => {
                self.stream = None;
                None
            }
        }
    }
}
