//! The tracker line protocol: one timestamped device pose per line.
//!
//! ```text
//! [<device_id>] <timestamp_s> <x> <y> <z> <qx> <qy> <qz> <qw>
//! ```
//!
//! - UTF-8, one pose per line, `\n` terminated (a trailing `\r` is ignored);
//!   tokens are separated by any whitespace.
//! - Eight numbers, optionally preceded by one non-numeric device id token
//!   (e.g. `LHR-1A2B3C4D`).
//! - Position in metres in the tracking (lighthouse) frame; orientation of
//!   the tracker device in that frame as a Hamilton unit quaternion in
//!   `x y z w` order (the ROS order).
//! - The timestamp is in seconds of the source's clock, monotonic per device
//!   (it may be unix time).
//! - Blank lines and lines starting with `#` are ignored.
//!
//! A malformed line is a [`ProtocolError`] carrying its line number and a
//! [`ProtocolErrorKind`]; readers count it and go on with the next line.

use std::fmt;

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

/// How far a quaternion's norm may be from 1 before the line is rejected
/// (within it, the quaternion is normalised).
pub const QUATERNION_NORM_TOLERANCE: f64 = 0.01;

/// Longest accepted line, bytes (a real line is under 150).
pub const MAX_LINE_BYTES: usize = 1024;

/// Numbers on a line (timestamp, position, quaternion).
const NUMBERS: usize = 8;

/// One pose of one tracker device, as read from a source.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackerSample {
    /// The device id token, if the line carried one.
    pub device: Option<String>,
    /// Source clock, seconds.
    pub timestamp_s: f64,
    /// The device's pose in the tracking frame (`device_in_tracking`).
    pub pose: Isometry3<f64>,
}

impl TrackerSample {
    /// A sample from a position and a unit quaternion.
    pub fn new(
        device: Option<&str>,
        timestamp_s: f64,
        translation: [f64; 3],
        rotation: UnitQuaternion<f64>,
    ) -> Self {
        Self {
            device: device.map(str::to_owned),
            timestamp_s,
            pose: Isometry3::from_parts(
                Translation3::new(translation[0], translation[1], translation[2]),
                rotation,
            ),
        }
    }

    /// Formats this sample as one protocol line (no trailing newline);
    /// numbers are written in full precision, so parsing it back is exact.
    pub fn to_line(&self) -> String {
        let t = &self.pose.translation.vector;
        let q = self.pose.rotation.quaternion();
        let numbers = format!(
            "{} {} {} {} {} {} {} {}",
            self.timestamp_s, t.x, t.y, t.z, q.i, q.j, q.k, q.w
        );
        match &self.device {
            Some(id) => format!("{id} {numbers}"),
            None => numbers,
        }
    }
}

/// What is wrong with a line.
#[derive(Debug, Clone, PartialEq)]
pub enum ProtocolErrorKind {
    /// Not 8 numbers (plus an optional device id).
    TokenCount {
        /// Tokens found.
        found: usize,
    },
    /// A token that should be a number is not one.
    NotANumber {
        /// Which field (`timestamp`, `x`, …, `qw`).
        field: &'static str,
        /// The offending token.
        token: String,
    },
    /// A number is NaN or infinite.
    NonFinite {
        /// Which field.
        field: &'static str,
    },
    /// The quaternion's norm is farther than [`QUATERNION_NORM_TOLERANCE`]
    /// from 1.
    QuaternionNorm {
        /// The norm found.
        norm: f64,
    },
    /// Longer than [`MAX_LINE_BYTES`].
    TooLong {
        /// Bytes seen (at least).
        bytes: usize,
    },
    /// Not valid UTF-8.
    NotUtf8,
}

impl fmt::Display for ProtocolErrorKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::TokenCount { found } => write!(
                f,
                "expected 8 numbers optionally preceded by a device id, found {found} tokens"
            ),
            Self::NotANumber { field, token } => write!(f, "{field} `{token}` is not a number"),
            Self::NonFinite { field } => write!(f, "{field} is not finite"),
            Self::QuaternionNorm { norm } => write!(
                f,
                "quaternion norm {norm} is not within {QUATERNION_NORM_TOLERANCE} of 1"
            ),
            Self::TooLong { bytes } => {
                write!(f, "line of {bytes} bytes exceeds {MAX_LINE_BYTES}")
            }
            Self::NotUtf8 => write!(f, "line is not valid UTF-8"),
        }
    }
}

/// A malformed line: counted and skipped, never the end of a stream.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("line {line}: {kind}")]
pub struct ProtocolError {
    /// 1-based line number within the stream (or connection, or file).
    pub line: u64,
    /// What is wrong.
    pub kind: ProtocolErrorKind,
}

const FIELDS: [&str; NUMBERS] = ["timestamp", "x", "y", "z", "qx", "qy", "qz", "qw"];

/// Parses one line. `Ok(None)` for blank and comment lines.
pub fn parse_line(line: &str, line_no: u64) -> Result<Option<TrackerSample>, ProtocolError> {
    let err = |kind| ProtocolError {
        line: line_no,
        kind,
    };
    let trimmed = line.trim();
    if trimmed.is_empty() || trimmed.starts_with('#') {
        return Ok(None);
    }
    if line.len() > MAX_LINE_BYTES {
        return Err(err(ProtocolErrorKind::TooLong { bytes: line.len() }));
    }
    let tokens: Vec<&str> = trimmed.split_whitespace().collect();
    let is_number = |token: &&str| token.parse::<f64>().is_ok();
    let (device, numbers) = match tokens.len() {
        // A device id followed by only 7 numbers: a missing number, not a
        // bad timestamp.
        NUMBERS if !is_number(&tokens[0]) && tokens[1..].iter().all(is_number) => {
            return Err(err(ProtocolErrorKind::TokenCount {
                found: tokens.len(),
            }))
        }
        NUMBERS => (None, &tokens[..]),
        n if n == NUMBERS + 1 && !is_number(&tokens[0]) => (Some(tokens[0]), &tokens[1..]),
        found => return Err(err(ProtocolErrorKind::TokenCount { found })),
    };
    let mut values = [0.0_f64; NUMBERS];
    for ((value, token), field) in values.iter_mut().zip(numbers).zip(FIELDS) {
        let parsed: f64 = token.parse().map_err(|_| {
            err(ProtocolErrorKind::NotANumber {
                field,
                token: (*token).to_owned(),
            })
        })?;
        if !parsed.is_finite() {
            return Err(err(ProtocolErrorKind::NonFinite { field }));
        }
        *value = parsed;
    }
    let [timestamp_s, x, y, z, qx, qy, qz, qw] = values;
    let quaternion = Quaternion::new(qw, qx, qy, qz);
    let norm = quaternion.norm();
    if (norm - 1.0).abs() > QUATERNION_NORM_TOLERANCE {
        return Err(err(ProtocolErrorKind::QuaternionNorm { norm }));
    }
    Ok(Some(TrackerSample::new(
        device,
        timestamp_s,
        [x, y, z],
        normalize(quaternion),
    )))
}

/// Normalises a quaternion, leaving one that is already unit to machine
/// precision untouched (so formatting and parsing back is exact).
pub(crate) fn normalize(q: Quaternion<f64>) -> UnitQuaternion<f64> {
    if (q.norm() - 1.0).abs() <= 4.0 * f64::EPSILON {
        UnitQuaternion::new_unchecked(q)
    } else {
        UnitQuaternion::new_normalize(q)
    }
}

/// Splits a byte stream into protocol lines and parses them, with bounded
/// memory: a line longer than [`MAX_LINE_BYTES`] is reported as
/// [`ProtocolErrorKind::TooLong`] and its bytes are dropped up to the next
/// newline.
#[derive(Debug, Default)]
pub struct LineDecoder {
    buffer: Vec<u8>,
    /// Bytes of an overlong line seen so far (skipping to its newline).
    skipping: Option<usize>,
    line_no: u64,
}

impl LineDecoder {
    /// A decoder at line 0.
    pub fn new() -> Self {
        Self::default()
    }

    /// Lines completed so far.
    pub fn line_no(&self) -> u64 {
        self.line_no
    }

    /// Whether a partial line is buffered.
    pub fn has_partial(&self) -> bool {
        !self.buffer.is_empty() || self.skipping.is_some()
    }

    /// Forgets any partial line and restarts numbering (a new connection).
    pub fn reset(&mut self) {
        self.buffer.clear();
        self.skipping = None;
        self.line_no = 0;
    }

    /// Feeds bytes; every completed line's outcome is appended to `out`
    /// (blank and comment lines produce nothing).
    pub fn push(&mut self, bytes: &[u8], out: &mut Vec<Result<TrackerSample, ProtocolError>>) {
        let mut rest = bytes;
        while !rest.is_empty() {
            let newline = rest.iter().position(|b| *b == b'\n');
            let (chunk, complete) = match newline {
                Some(i) => (&rest[..i], true),
                None => (rest, false),
            };
            rest = match newline {
                Some(i) => &rest[i + 1..],
                None => &[],
            };
            if let Some(seen) = self.skipping.as_mut() {
                *seen += chunk.len();
                if complete {
                    let bytes = *seen;
                    self.skipping = None;
                    self.line_no += 1;
                    out.push(Err(ProtocolError {
                        line: self.line_no,
                        kind: ProtocolErrorKind::TooLong { bytes },
                    }));
                }
                continue;
            }
            if self.buffer.len() + chunk.len() > MAX_LINE_BYTES {
                let seen = self.buffer.len() + chunk.len();
                self.buffer.clear();
                if complete {
                    self.line_no += 1;
                    out.push(Err(ProtocolError {
                        line: self.line_no,
                        kind: ProtocolErrorKind::TooLong { bytes: seen },
                    }));
                } else {
                    self.skipping = Some(seen);
                }
                continue;
            }
            self.buffer.extend_from_slice(chunk);
            if complete {
                self.finish_line(out);
            }
        }
    }

    /// Ends the stream or a datagram: a buffered partial line counts as a
    /// complete line.
    pub fn flush(&mut self, out: &mut Vec<Result<TrackerSample, ProtocolError>>) {
        if let Some(bytes) = self.skipping.take() {
            self.line_no += 1;
            out.push(Err(ProtocolError {
                line: self.line_no,
                kind: ProtocolErrorKind::TooLong { bytes },
            }));
        } else if !self.buffer.is_empty() {
            self.finish_line(out);
        }
    }

    fn finish_line(&mut self, out: &mut Vec<Result<TrackerSample, ProtocolError>>) {
        self.line_no += 1;
        let bytes = std::mem::take(&mut self.buffer);
        match std::str::from_utf8(&bytes) {
            Ok(line) => match parse_line(line, self.line_no) {
                Ok(Some(sample)) => out.push(Ok(sample)),
                Ok(None) => {}
                Err(e) => out.push(Err(e)),
            },
            Err(_) => out.push(Err(ProtocolError {
                line: self.line_no,
                kind: ProtocolErrorKind::NotUtf8,
            })),
        }
        // Keep the allocation for the next line.
        self.buffer = bytes;
        self.buffer.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kind(line: &str) -> ProtocolErrorKind {
        match parse_line(line, 7) {
            Err(e) => {
                assert_eq!(e.line, 7, "{line:?}");
                e.kind
            }
            Ok(other) => panic!("{line:?} parsed as {other:?}"),
        }
    }

    #[test]
    fn valid_lines_parse_with_and_without_a_device_id() {
        let s = parse_line("1.5 1 2 3 0 0 0 1", 1)
            .expect("valid")
            .expect("a sample");
        assert_eq!(s.device, None);
        assert_eq!(s.timestamp_s, 1.5);
        assert_eq!(s.pose.translation.vector.as_slice(), &[1.0, 2.0, 3.0]);
        assert_eq!(s.pose.rotation, UnitQuaternion::identity());

        let h = std::f64::consts::FRAC_1_SQRT_2;
        let line = format!("LHR-1A2B3C4D 1718000000.25 -0.5 0.25 0.125 0 0 {h} {h}");
        let s = parse_line(&line, 2).expect("valid").expect("a sample");
        assert_eq!(s.device.as_deref(), Some("LHR-1A2B3C4D"));
        assert_eq!(s.timestamp_s, 1_718_000_000.25);
        assert_eq!(s.pose.translation.vector.as_slice(), &[-0.5, 0.25, 0.125]);
        let q = s.pose.rotation.quaternion();
        // x y z w order on the line.
        assert!((q.k - h).abs() < 1e-15 && (q.w - h).abs() < 1e-15 && q.i == 0.0 && q.j == 0.0);

        // Tabs, repeated spaces, CR (from a CRLF stream) and exponents.
        let s = parse_line("\tdev  2e-3 1E1\t0 0   0 0 0 1\r", 3)
            .expect("valid")
            .expect("a sample");
        assert_eq!(s.device.as_deref(), Some("dev"));
        assert_eq!(s.timestamp_s, 0.002);
        assert_eq!(s.pose.translation.vector.x, 10.0);

        // A norm slightly off 1 is normalised.
        let s = parse_line("0 0 0 0 0 0 0 1.005", 4)
            .expect("valid")
            .expect("a sample");
        assert!((s.pose.rotation.quaternion().norm() - 1.0).abs() < 1e-15);
    }

    #[test]
    fn blank_and_comment_lines_are_ignored() {
        for line in [
            "",
            "   ",
            "\r",
            "# recorded 2024-06-01",
            "   # indented comment",
        ] {
            assert_eq!(parse_line(line, 1), Ok(None), "{line:?}");
        }
    }

    #[test]
    fn every_malformed_kind_is_reported_with_its_line() {
        use ProtocolErrorKind as K;
        let table: Vec<(&str, ProtocolErrorKind)> = vec![
            ("1 2 3 4 5 6 7", K::TokenCount { found: 7 }),
            ("1 2 3 4 5 6 7 8 9", K::TokenCount { found: 9 }),
            ("LHR-1 1 2 3 0 0 0 1", K::TokenCount { found: 8 }),
            ("LHR-1 extra 1 2 3 0 0 0 0 1", K::TokenCount { found: 10 }),
            ("1", K::TokenCount { found: 1 }),
            (
                "1 2 x 3 0 0 0 1",
                K::NotANumber {
                    field: "y",
                    token: "x".into(),
                },
            ),
            (
                "dev t 1 2 3 0 0 0 1",
                K::NotANumber {
                    field: "timestamp",
                    token: "t".into(),
                },
            ),
            (
                "1 2 3 4 0 0 0 1,0",
                K::NotANumber {
                    field: "qw",
                    token: "1,0".into(),
                },
            ),
            ("1 2 3 NaN 0 0 0 1", K::NonFinite { field: "z" }),
            ("1 inf 3 4 0 0 0 1", K::NonFinite { field: "x" }),
            (
                "-infinity 1 2 3 0 0 0 1",
                K::NonFinite { field: "timestamp" },
            ),
            ("1 0 0 0 0 0 0 nan", K::NonFinite { field: "qw" }),
            ("1 0 0 0 0 0 0 2", K::QuaternionNorm { norm: 2.0 }),
            ("1 0 0 0 0 0 0 0", K::QuaternionNorm { norm: 0.0 }),
            (
                "1 0 0 0 0 0 0.5 0.5",
                K::QuaternionNorm {
                    norm: 0.5_f64.sqrt(),
                },
            ),
        ];
        for (line, expected) in table {
            assert_eq!(kind(line), expected, "{line:?}");
        }
        let long = format!("1 2 3 4 0 0 0 1 {}", "0".repeat(MAX_LINE_BYTES));
        assert_eq!(kind(&long), K::TooLong { bytes: long.len() });
        // Errors print their line number and reason.
        let e = parse_line("1 2 x 3 0 0 0 1", 42).expect_err("malformed");
        assert_eq!(e.to_string(), "line 42: y `x` is not a number");
    }

    #[test]
    fn formatted_lines_parse_back_exactly() {
        let rotation = UnitQuaternion::from_euler_angles(0.1, -0.7, 2.9);
        for device in [None, Some("LHR-0000ABCD")] {
            let sample = TrackerSample::new(
                device,
                1_718_000_123.456_789,
                [0.1 + 0.2, -1.0 / 3.0, 1e-7],
                rotation,
            );
            let parsed = parse_line(&sample.to_line(), 1)
                .expect("valid")
                .expect("a sample");
            assert_eq!(parsed, sample);
        }
    }

    fn decode(chunks: &[&[u8]], flush: bool) -> Vec<Result<TrackerSample, ProtocolError>> {
        let mut decoder = LineDecoder::new();
        let mut out = Vec::new();
        for chunk in chunks {
            decoder.push(chunk, &mut out);
        }
        if flush {
            decoder.flush(&mut out);
        }
        out
    }

    #[test]
    fn the_decoder_splits_streams_at_any_boundary() {
        let text = b"# header\n1 0 0 0 0 0 0 1\nbad line\n\n2 1 1 1 0 0 0 1\r\n3 2 2 2 0 0 0 1";
        let whole = decode(&[text], true);
        for split in 0..text.len() {
            let (a, b) = text.split_at(split);
            assert_eq!(decode(&[a, b], true), whole, "split at {split}");
        }
        let summary: Vec<Result<f64, (u64, usize)>> = whole
            .iter()
            .map(|r| match r {
                Ok(s) => Ok(s.timestamp_s),
                Err(e) => Err((
                    e.line,
                    match e.kind {
                        ProtocolErrorKind::TokenCount { found } => found,
                        _ => usize::MAX,
                    },
                )),
            })
            .collect();
        assert_eq!(summary, vec![Ok(1.0), Err((3, 2)), Ok(2.0), Ok(3.0)]);
        // Without a flush the unterminated last line is still pending.
        assert_eq!(decode(&[text], false).len(), 3);
    }

    #[test]
    fn overlong_and_non_utf8_lines_are_skipped_with_bounded_memory() {
        let long = vec![b'9'; 3 * MAX_LINE_BYTES];
        let mut decoder = LineDecoder::new();
        let mut out = Vec::new();
        // An overlong line arriving in pieces, then valid lines.
        for piece in long.chunks(100) {
            decoder.push(piece, &mut out);
            assert!(decoder.buffer.len() <= MAX_LINE_BYTES);
        }
        decoder.push(b"\n1 0 0 0 0 0 0 1\n", &mut out);
        decoder.push(b"\xff\xfe 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n", &mut out);
        assert_eq!(out.len(), 4);
        assert_eq!(
            out[0],
            Err(ProtocolError {
                line: 1,
                kind: ProtocolErrorKind::TooLong { bytes: long.len() }
            })
        );
        assert_eq!(out[1].as_ref().map(|s| s.timestamp_s), Ok(1.0));
        assert_eq!(
            out[2],
            Err(ProtocolError {
                line: 3,
                kind: ProtocolErrorKind::NotUtf8
            })
        );
        assert_eq!(out[3].as_ref().map(|s| s.timestamp_s), Ok(2.0));
        assert_eq!(decoder.line_no(), 4);
    }
}
