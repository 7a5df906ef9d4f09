//! Column batching for the high-rate data (images, poses, scalars): rows
//! gather per entity and go to rerun as one chunk per entity every flush
//! period (`send_columns`), instead of one `log` call, one serialisation
//! and one channel message per row. At a thousand steps a second this is
//! most of the monitor's CPU saved.

use std::collections::HashMap;
use std::time::{Duration, Instant};

use rerun::components::ImageFormat;
use rerun::{
    DepthImage, RecordingStream, RecordingStreamError, Scalars, SerializedComponentColumn,
    TimeColumn, Transform3D,
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
}

impl Row {
    fn kind(&self) -> u8 {
        match self {
            Row::Scalar(_) => 0,
            Row::Transform(..) => 1,
            Row::Image(..) => 2,
            Row::Depth(..) => 3,
        }
    }

    fn bytes(&self) -> usize {
        match self {
            Row::Image(b, _) | Row::Depth(b, _, _) => b.len(),
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
