//! Invariants of the tracker agent's input parsers: the tracker line
//! protocol read from stdin / TCP / UDP / replay files (`LineDecoder`,
//! `parse_line`), the calibration TOML and the reference / samples TOML of
//! `tracker_agent calibrate` (with the solver they feed).
//!
//! Shared by the fuzz targets and `tracker_agent/tests/integration/fuzz_corpus.rs`.

use offworld_tracker_agent::calibration::{
    calibrate_from_samples, rosbot_mount, Calibration, ReferenceFile,
};
use offworld_tracker_agent::protocol::{
    parse_line, LineDecoder, ProtocolError, ProtocolErrorKind, TrackerSample, MAX_LINE_BYTES,
};

type Outcome = Result<TrackerSample, ProtocolError>;

/// What the decoder must produce for `stream`: every `\n`-terminated line,
/// and the unterminated rest when flushed, numbered from 1; overlong lines
/// are `TooLong`, others are decoded as UTF-8 and parsed, blank and comment
/// lines produce nothing.
fn expected(stream: &[u8]) -> Vec<Outcome> {
    let mut lines: Vec<&[u8]> = stream.split(|b| *b == b'\n').collect();
    if lines.last().is_some_and(|rest| rest.is_empty()) {
        lines.pop();
    }
    let mut out = Vec::new();
    for (line, no) in lines.into_iter().zip(1u64..) {
        let error = |kind| Some(Err(ProtocolError { line: no, kind }));
        let outcome = if line.len() > MAX_LINE_BYTES {
            error(ProtocolErrorKind::TooLong { bytes: line.len() })
        } else {
            match std::str::from_utf8(line) {
                Ok(text) => parse_line(text, no).transpose(),
                Err(_) => error(ProtocolErrorKind::NotUtf8),
            }
        };
        out.extend(outcome);
    }
    out
}

fn decode(chunks: &[&[u8]]) -> Vec<Outcome> {
    let mut decoder = LineDecoder::new();
    let mut out = Vec::new();
    for chunk in chunks {
        decoder.push(chunk, &mut out);
    }
    decoder.flush(&mut out);
    assert!(!decoder.has_partial(), "a partial line survived the flush");
    out
}

/// A parsed sample is finite with a unit rotation, and formats back to a
/// line that parses to exactly the same sample.
fn sample(s: &TrackerSample) {
    let t = s.pose.translation.vector;
    assert!(
        s.timestamp_s.is_finite() && t.iter().all(|x| x.is_finite()),
        "non-finite sample {s:?}"
    );
    let norm = s.pose.rotation.quaternion().norm();
    assert!((norm - 1.0).abs() < 1e-12, "rotation norm {norm} in {s:?}");
    let line = s.to_line();
    // `to_line` writes every digit (1e300 takes 301 characters): a line
    // over the protocol's limit cannot be read back, by design of the limit.
    if line.len() <= MAX_LINE_BYTES {
        assert_eq!(
            parse_line(&line, 1),
            Ok(Some(s.clone())),
            "{line:?} does not parse back"
        );
    }
}

/// The line protocol: input `[cut, stream…]`. The stream is decoded whole
/// and split at `cut` (any chunking gives the same outcomes), and compared
/// with [`parse_line`] applied line by line.
pub fn tracker_line(data: &[u8]) {
    let Some((&cut, stream)) = data.split_first() else {
        return;
    };
    let whole = decode(&[stream]);
    let at = usize::from(cut) * stream.len() / 255;
    let (a, b) = stream.split_at(at);
    assert_eq!(
        decode(&[a, b]),
        whole,
        "chunking at {at} changed the outcome"
    );
    assert_eq!(expected(stream), whole, "decoder and parse_line disagree");
    let mut last = 0;
    for outcome in &whole {
        let line = match outcome {
            Ok(s) => {
                sample(s);
                continue;
            }
            Err(e) => e.line,
        };
        assert!(line > last, "line numbers must increase");
        last = line;
    }
}

/// Calibration files. Input `[kind, text…]`: an even `kind` reads `text`
/// as the calibration file, an odd one as a reference / samples file (then
/// also solved, as `tracker_agent calibrate --samples` does).
pub fn tracker_calibration(data: &[u8]) {
    let Some((&kind, text)) = data.split_first() else {
        return;
    };
    let Ok(text) = std::str::from_utf8(text) else {
        return;
    };
    if kind % 2 == 0 {
        calibration(text);
    } else {
        reference(text);
    }
}

fn close(a: &Calibration, b: &Calibration) -> bool {
    let near = |x: f64, y: f64| (x - y).abs() <= 1e-9 * x.abs().max(1.0);
    [
        (&a.world_from_tracking, &b.world_from_tracking),
        (&a.tracker_in_base_link, &b.tracker_in_base_link),
    ]
    .iter()
    .all(|(p, q)| {
        p.translation
            .vector
            .iter()
            .zip(q.translation.vector.iter())
            .chain(
                p.rotation
                    .quaternion()
                    .coords
                    .iter()
                    .zip(q.rotation.quaternion().coords.iter()),
            )
            .all(|(x, y)| near(*x, *y))
    })
}

/// A calibration that loads is finite with unit rotations, saves, and
/// loads back equal (but for components under 1e-12, saved as 0); saving
/// that again gives the same text.
fn calibration(text: &str) {
    let Ok(loaded) = Calibration::from_toml_str(text) else {
        return;
    };
    for iso in [loaded.world_from_tracking, loaded.tracker_in_base_link] {
        assert!(iso.translation.vector.iter().all(|x| x.is_finite()));
        let norm = iso.rotation.quaternion().norm();
        assert!((norm - 1.0).abs() < 1e-12, "rotation norm {norm}");
    }
    let saved = loaded
        .to_toml_string()
        .unwrap_or_else(|e| panic!("a loaded calibration does not save: {e}"));
    let reloaded = Calibration::from_toml_str(&saved)
        .unwrap_or_else(|e| panic!("a saved calibration does not load: {e}\n{saved}"));
    assert!(
        close(&loaded, &reloaded),
        "save and load changed {loaded:?} into {reloaded:?}"
    );
    let again = reloaded.to_toml_string().expect("saves again");
    let third = Calibration::from_toml_str(&again).expect("loads again");
    assert!(close(&reloaded, &third), "saving is not stable");
}

/// A reference file that loads has finite world points and saves to a
/// text that loads back and saves identically; solving it never panics,
/// and a solution fits its points with finite, consistent residuals.
fn reference(text: &str) {
    let Ok(file) = ReferenceFile::from_toml_str(text) else {
        return;
    };
    assert!(file
        .world_points()
        .iter()
        .all(|p| p.coords.iter().all(|x| x.is_finite())));
    let saved = file
        .to_toml_string()
        .unwrap_or_else(|e| panic!("a loaded reference file does not save: {e}"));
    let reloaded = ReferenceFile::from_toml_str(&saved)
        .unwrap_or_else(|e| panic!("a saved reference file does not load: {e}\n{saved}"));
    assert_eq!(
        reloaded.to_toml_string().ok().as_deref(),
        Some(saved.as_str()),
        "saving is not stable"
    );
    let Ok(solution) = calibrate_from_samples(&file, &rosbot_mount()) else {
        return;
    };
    assert_eq!(solution.residuals_m.len(), file.point.len());
    let rotation = solution.world_from_tracking.rotation.quaternion().norm();
    assert!(
        (rotation - 1.0).abs() < 1e-9,
        "solved rotation norm {rotation}"
    );
    assert!(
        solution.rms_residual_m.is_finite()
            && solution.max_residual_m.is_finite()
            && solution.rms_residual_m <= solution.max_residual_m * (1.0 + 1e-12),
        "residuals {solution:?}"
    );
}

/// Seeds of [`tracker_line`].
pub fn tracker_line_seeds() -> Vec<Vec<u8>> {
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let streams = [
        "LHR-1A2B3C4D 1718000000.004 1.250 -0.300 0.182 0.0 0.0 0.3826834 0.9238795\n".to_owned(),
        "# header\n1 0 0 0 0 0 0 1\nbad line\n\n2 1 1 1 0 0 0 1\r\n3 2 2 2 0 0 0 1".to_owned(),
        format!("dev 2e-3 1E1\t0 0   0 0 {h} {h}\n1 2 3 NaN 0 0 0 1\n1 0 0 0 0 0 0 1.005\n"),
        format!("{}\n1 0 0 0 0 0 0 1\n", "9".repeat(MAX_LINE_BYTES + 1)),
        "\u{fffd}\u{85} 0 0 0 0 0 0 1\n-inf 1 2 3 0 0 0 1\n1 2 x 3 0 0 0 1\n".to_owned(),
    ];
    streams
        .iter()
        .zip([0u8, 100, 200, 255, 17])
        .map(|(stream, cut)| {
            let mut out = vec![cut];
            out.extend(stream.as_bytes());
            out
        })
        .collect()
}

/// Seeds of [`tracker_calibration`].
pub fn tracker_calibration_seeds() -> Vec<Vec<u8>> {
    let calibration = "# solved\n\
        [world_from_tracking]    # maps tracking-frame coordinates into the world frame\n\
        translation = [0.5, -1.25, 0.0]\n\
        rotation = [0.0, 0.0, 0.3826834323650898, 0.9238795325112867]\n\
        [tracker_in_base_link]\n\
        translation = [-0.03, 0.0, 0.14]\n\
        rotation = [0.0, 0.0, 0.0, 1.0]\n";
    let samples = "[[point]]\nname = \"corner A\"\nworld = [0.0, 0.0, 0.0]\n\
        device_translation = [1.0, 2.0, 0.14]\ndevice_rotation = [0.0, 0.0, 0.0, 1.0]\n\
        [[point]]\nworld = [1.0, 0.0, 0.0]\n\
        device_translation = [2.0, 2.0, 0.14]\ndevice_rotation = [0.0, 0.0, 0.0, 1.0]\n\
        [[point]]\nworld = [0.0, 1.5, 0.0]\n\
        device_translation = [1.0, 3.5, 0.14]\ndevice_rotation = [0.0, 0.0, 0.0, 1.0]\n";
    let reference =
        "[[point]]\nworld = [0.0, 0.0, 0.0]\n[[point]]\nname = \"b\"\nworld = [1, 2, 3]\n";
    [(0u8, calibration), (1, samples), (3, reference)]
        .iter()
        .map(|(kind, text)| {
            let mut out = vec![*kind];
            out.extend(text.as_bytes());
            out
        })
        .collect()
}
