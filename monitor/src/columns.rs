//! Column batching for every row with a time the monitor logs (images,
//! poses, scalars, event lines, trajectories): rows gather per entity and go to
//! rerun as one chunk per entity every flush period (`send_columns`),
//! instead of one `log` call, one serialisation and one channel message per
//! row. At a thousand steps a second this is most of the monitor's CPU
//! saved: each chunk costs rerun a fixed encoding (its arrow schema) on its
//! way to a file or a viewer, whatever its rows.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use rerun::components::ImageFormat;
use rerun::{
    Color, DepthImage, LineStrips3D, RecordingStream, RecordingStreamError, Scalars,
    SerializedComponentColumn, TextLog, TimeColumn, Transform3D,
};

use crate::paths;

/// Where a row sits on the timelines (`wall_time` always, the others when
/// known).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Stamp {
    /// `step` timeline.
    pub step: Option<i64>,
    /// `sim_time` timeline, ns.
    pub sim_nanos: Option<i64>,
    /// `wall_time` timeline, ns since the epoch.
    pub wall_nanos: i64,
}

/// One row of one entity.
pub(crate) enum Row {
    /// A `Scalars` value.
    Scalar(f64),
    /// A `Transform3D` (translation, quaternion x y z w).
    Transform([f32; 3], [f32; 4]),
    /// An `Image`.
    Image(Vec<u8>, ImageFormat),
    /// A `DepthImage` with its depth scale (units per metre).
    Depth(Vec<u8>, ImageFormat, f32),
    /// A `TextLog` line and its level (a `rerun::TextLogLevel` constant).
    Text(String, &'static str),
    /// A `LineStrips3D` of one strip, drawn as a trajectory.
    Trajectory(Vec<[f32; 3]>),
}

/// How a trajectory is drawn: a thick orange line (RGB) just above the
/// ground …
const TRAJECTORY_RGB: [u8; 3] = [235, 120, 30];
/// … of this radius, scene units (m).
const TRAJECTORY_RADIUS: f32 = 0.008;

impl Row {
    fn kind(&self) -> u8 {
        match self {
            Row::Scalar(_) => 0,
            Row::Transform(..) => 1,
            Row::Image(..) => 2,
            Row::Depth(..) => 3,
            Row::Text(..) => 4,
            Row::Trajectory(_) => 5,
        }
    }

    fn bytes(&self) -> usize {
        match self {
            Row::Image(b, _) | Row::Depth(b, _, _) => b.len(),
            Row::Text(text, _) => text.len(),
            Row::Trajectory(points) => points.len() * 12,
            _ => 32,
        }
    }
}

/// Rows of one entity, one kind and one set of timelines (a chunk's time
/// columns cannot have holes).
#[derive(Clone, Hash, PartialEq, Eq)]
struct Key {
    path: String,
    kind: u8,
    step: bool,
    sim: bool,
}

#[derive(Default)]
struct Group {
    steps: Vec<i64>,
    sims: Vec<i64>,
    walls: Vec<i64>,
    rows: Vec<Row>,
}

/// Pending rows, flushed as columns.
pub(crate) struct Columns {
    groups: HashMap<Key, Group>,
    order: Vec<Key>,
    bytes: usize,
    oldest: Option<Instant>,
    period: Duration,
    max_bytes: usize,
}

impl Columns {
    /// Flushes rows at most `period` old, or sooner past `max_bytes`.
    pub fn new(period: Duration, max_bytes: usize) -> Self {
        Self {
            groups: HashMap::new(),
            order: Vec::new(),
            bytes: 0,
            oldest: None,
            period,
            max_bytes,
        }
    }

    /// Queues one row for `path`.
    pub fn push(&mut self, path: String, stamp: Stamp, row: Row) {
        let key = Key {
            path,
            kind: row.kind(),
            step: stamp.step.is_some(),
            sim: stamp.sim_nanos.is_some(),
        };
        self.bytes += row.bytes();
        self.oldest.get_or_insert_with(Instant::now);
        if !self.groups.contains_key(&key) {
            self.order.push(key.clone());
        }
        let group = self.groups.entry(key).or_default();
        group.steps.extend(stamp.step);
        group.sims.extend(stamp.sim_nanos);
        group.walls.push(stamp.wall_nanos);
        group.rows.push(row);
    }

    /// Whether the pending rows should go now.
    pub fn due(&self) -> bool {
        self.bytes >= self.max_bytes || self.oldest.is_some_and(|t| t.elapsed() >= self.period)
    }

    /// Sends every pending row, one chunk per group. Returns the rows that
    /// could not be sent (their error is the last one seen).
    pub fn flush(&mut self, rec: &RecordingStream) -> Result<(), (usize, RecordingStreamError)> {
        self.bytes = 0;
        self.oldest = None;
        let mut failed = None;
        for key in std::mem::take(&mut self.order) {
            let Some(group) = self.groups.remove(&key) else {
                continue;
            };
            let rows = group.rows.len();
            if let Err(e) = send(rec, &key, group) {
                let count = failed.as_ref().map_or(0, |(n, _)| *n);
                failed = Some((count + rows, e));
            }
        }
        self.groups.clear();
        match failed {
            Some(f) => Err(f),
            None => Ok(()),
        }
    }
}

fn send(rec: &RecordingStream, key: &Key, group: Group) -> Result<(), RecordingStreamError> {
    let Group {
        steps,
        sims,
        walls,
        rows,
    } = group;
    let mut indexes = vec![TimeColumn::new_timestamp_nanos_since_epoch(
        paths::TIMELINE_WALL_TIME,
        walls,
    )];
    if key.step {
        indexes.push(TimeColumn::new_sequence(paths::TIMELINE_STEP, steps));
    }
    if key.sim {
        indexes.push(TimeColumn::new_duration_nanos(
            paths::TIMELINE_SIM_TIME,
            sims,
        ));
    }
    let columns: Vec<SerializedComponentColumn> = match key.kind {
        0 => {
            let values = rows.into_iter().filter_map(|r| match r {
                Row::Scalar(v) => Some(v),
                _ => None,
            });
            Scalars::new(values).columns_of_unit_batches()?.collect()
        }
        1 => {
            let (mut translations, mut rotations) = (Vec::new(), Vec::new());
            for row in rows {
                if let Row::Transform(t, q) = row {
                    translations.push(t);
                    rotations.push(rerun::Quaternion::from_xyzw(q));
                }
            }
            Transform3D::update_fields()
                .with_many_translation(translations)
                .with_many_quaternion(rotations)
                .columns_of_unit_batches()?
                .collect()
        }
        2 => {
            let (mut buffers, mut formats) = (Vec::new(), Vec::new());
            for row in rows {
                if let Row::Image(b, f) = row {
                    buffers.push(b);
                    formats.push(f);
                }
            }
            rerun::Image::update_fields()
                .with_many_buffer(buffers)
                .with_many_format(formats)
                .columns_of_unit_batches()?
                .collect()
        }
        4 => {
            let (mut texts, mut levels) = (Vec::new(), Vec::new());
            for row in rows {
                if let Row::Text(text, level) = row {
                    texts.push(text);
                    levels.push(level);
                }
            }
            TextLog::update_fields()
                .with_many_text(texts)
                .with_many_level(levels)
                .columns_of_unit_batches()?
                .collect()
        }
        5 => {
            let strips: Vec<Vec<[f32; 3]>> = rows
                .into_iter()
                .filter_map(|r| match r {
                    Row::Trajectory(points) => Some(points),
                    _ => None,
                })
                .collect();
            let n = strips.len();
            LineStrips3D::update_fields()
                .with_strips(strips)
                .with_colors(vec![
                    Color::from_rgb(
                        TRAJECTORY_RGB[0],
                        TRAJECTORY_RGB[1],
                        TRAJECTORY_RGB[2]
                    );
                    n
                ])
                .with_radii(vec![rerun::Radius::new_scene_units(TRAJECTORY_RADIUS); n])
                .columns_of_unit_batches()?
                .collect()
        }
        _ => {
            let (mut buffers, mut formats, mut meters) = (Vec::new(), Vec::new(), Vec::new());
            for row in rows {
                if let Row::Depth(b, f, m) = row {
                    buffers.push(b);
                    formats.push(f);
                    meters.push(m);
                }
            }
            DepthImage::update_fields()
                .with_many_buffer(buffers)
                .with_many_format(formats)
                .with_many_meter(meters)
                .columns_of_unit_batches()?
                .collect()
        }
    };
    rec.send_columns(key.path.as_str(), indexes, columns)
}
