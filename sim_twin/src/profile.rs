//! The twin profile: the parameters that make the simulated twin match one
//! physical robot (traction, command latency, servo ramp, camera mount,
//! depth sensor), kept as a small TOML file (`docs/twin-profile.md`).
//!
//! The default profile is the nominal twin: a twin built with it behaves
//! bit for bit like one built before profiles existed.

use std::io::Write;
use std::path::Path;

use atomic_write_file::AtomicWriteFile;
use serde::{Deserialize, Serialize};

use crate::error::SimError;

/// The version of the profile file format this build reads and writes
/// (the file's top-level `format` key).
pub const PROFILE_FORMAT: u32 = 1;

/// How one simulated twin differs from the nominal one.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TwinProfile {
    /// The base: traction, latency, servo ramp.
    pub motion: MotionProfile,
    /// The camera mount.
    pub camera: CameraProfile,
    /// The depth sensor's noise.
    pub depth: DepthProfile,
}

/// How the base answers a velocity command.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionProfile {
    /// Achieved forward speed over the wheels' speed (traction; 1 = none
    /// lost). Wheel odometry keeps reporting the wheels' speed, as a real
    /// skid-steer's encoders do. In (0, 3].
    pub linear_gain: f32,
    /// Achieved yaw rate over the wheels' yaw rate (skid-steer turns slip
    /// more than they drive straight). In (0, 3].
    pub angular_gain: f32,
    /// The base applies a velocity command this long after it is given, s,
    /// to the physics step (1/60 s). In [0, 1].
    pub latency_s: f32,
    /// Time the servo takes to ramp from the top forward speed to rest, s;
    /// `None` = the world's robot (`max_linear_speed / max_linear_accel`).
    /// Scales both acceleration limits (forward and turning) alike.
    /// In (0, 5].
    pub settle_time_s: Option<f32>,
}

impl MotionProfile {
    /// The servo's acceleration limits (m/s², rad/s²) for `robot`: its own,
    /// scaled by nominal settle time (`max_linear_speed / max_linear_accel`)
    /// over this profile's, when it sets one.
    pub fn accel_limits(&self, robot: &offworld_runtime::world::RobotSpec) -> (f32, f32) {
        match self.settle_time_s {
            None => (robot.max_linear_accel, robot.max_angular_accel),
            Some(t) => {
                let nominal = robot.max_linear_speed / robot.max_linear_accel;
                let scale = nominal / t;
                (
                    robot.max_linear_accel * scale,
                    robot.max_angular_accel * scale,
                )
            }
        }
    }
}

impl Default for MotionProfile {
    fn default() -> Self {
        Self {
            linear_gain: 1.0,
            angular_gain: 1.0,
            latency_s: 0.0,
            settle_time_s: None,
        }
    }
}

/// Offsets of the camera mount from the world's nominal mount
/// (`CameraSpec::mount`, a level camera looking along base_link's +x).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraProfile {
    /// Added to the mount's height, m. Within ±0.5.
    pub height_offset_m: f32,
    /// Nose-down tilt, degrees. Within ±30. A tilted camera is rendered by
    /// the per-pixel [`ExactRenderer`](crate::camera::ExactRenderer)
    /// instead of the level-camera column walk, about 75× slower: 51 ms a
    /// frame at 320×240 instead of 0.65 ms, 4.6 ms at 84×84 instead of
    /// 0.07 ms (`cargo bench --bench twin_step`, one
    /// core); see `docs/twin-profile.md`.
    pub pitch_deg: f32,
    /// Added to the camera's heading (left positive), degrees. Within ±30.
    pub yaw_deg: f32,
}

/// The depth sensor's imperfections (the same model as
/// [`Randomization`](crate::Randomization)'s depth knobs).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DepthProfile {
    /// Noise: standard deviation as a fraction of depth. In [0, 0.5].
    pub noise: f32,
    /// Fraction of depth pixels dropped (no return). In [0, 1).
    pub dropout: f32,
}

/// The file: the profile plus its format version.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ProfileFile {
    // Checked before deserializing (see `parse`); here so it is not unknown.
    #[allow(dead_code)]
    #[serde(default)]
    format: Option<toml::Value>,
    #[serde(default)]
    motion: MotionProfile,
    #[serde(default)]
    camera: CameraProfile,
    #[serde(default)]
    depth: DepthProfile,
}

#[derive(Serialize)]
struct ProfileFileRef<'a> {
    format: u32,
    motion: &'a MotionProfile,
    camera: &'a CameraProfile,
    depth: &'a DepthProfile,
}

impl TwinProfile {
    /// Reads and validates a profile file. Errors name the file and the
    /// field (unknown, mistyped, out of range) and the format version if
    /// it is not [`PROFILE_FORMAT`].
    pub fn load(path: &Path) -> Result<Self, SimError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| profile_error(Some(path), None, format!("cannot read: {e}")))?;
        Self::parse(&text).map_err(|e| e.in_file(path))
    }

    /// Parses and validates a profile's TOML text (errors without a file).
    pub fn parse(text: &str) -> Result<Self, SimError> {
        // The version first: a newer file's other fields may be unknown here.
        let table: toml::Table = toml::from_str(text).map_err(|e| toml_error(text, &e))?;
        match table.get("format") {
            None => {} // a hand-written file may leave it out: format 1
            Some(toml::Value::Integer(v)) if *v == i64::from(PROFILE_FORMAT) => {}
            Some(v) => {
                return Err(profile_error(
                    None,
                    Some("format"),
                    format!(
                        "format {v} is not supported: this build reads format {PROFILE_FORMAT}"
                    ),
                ))
            }
        }
        let file: ProfileFile = toml::from_str(text).map_err(|e| toml_error(text, &e))?;
        let profile = Self {
            motion: file.motion,
            camera: file.camera,
            depth: file.depth,
        };
        profile.validate()?;
        Ok(profile)
    }

    /// Checks every value's range (see each field); the error names the
    /// first field out of range.
    pub fn validate(&self) -> Result<(), SimError> {
        let m = &self.motion;
        let c = &self.camera;
        let d = &self.depth;
        check(
            "motion.linear_gain",
            m.linear_gain,
            |v| v > 0.0 && v <= 3.0,
            "(0, 3]",
        )?;
        check(
            "motion.angular_gain",
            m.angular_gain,
            |v| v > 0.0 && v <= 3.0,
            "(0, 3]",
        )?;
        check(
            "motion.latency_s",
            m.latency_s,
            |v| (0.0..=1.0).contains(&v),
            "[0, 1] s",
        )?;
        if let Some(t) = m.settle_time_s {
            check(
                "motion.settle_time_s",
                t,
                |v| v > 0.0 && v <= 5.0,
                "(0, 5] s",
            )?;
        }
        check(
            "camera.height_offset_m",
            c.height_offset_m,
            |v| v.abs() <= 0.5,
            "[-0.5, 0.5] m",
        )?;
        check(
            "camera.pitch_deg",
            c.pitch_deg,
            |v| v.abs() <= 30.0,
            "[-30, 30]°",
        )?;
        check(
            "camera.yaw_deg",
            c.yaw_deg,
            |v| v.abs() <= 30.0,
            "[-30, 30]°",
        )?;
        check(
            "depth.noise",
            d.noise,
            |v| (0.0..=0.5).contains(&v),
            "[0, 0.5]",
        )?;
        check(
            "depth.dropout",
            d.dropout,
            |v| (0.0..1.0).contains(&v),
            "[0, 1)",
        )?;
        Ok(())
    }

    /// The profile as a profile file's text (with its format version).
    pub fn to_toml(&self) -> Result<String, SimError> {
        let file = ProfileFileRef {
            format: PROFILE_FORMAT,
            motion: &self.motion,
            camera: &self.camera,
            depth: &self.depth,
        };
        let body = toml::to_string(&file)
            .map_err(|e| profile_error(None, None, format!("cannot encode: {e}")))?;
        Ok(format!(
            "# OffWorld twin profile: the sim twin's parameters for one robot (docs/twin-profile.md).\n{body}"
        ))
    }

    /// Writes the profile to `path` atomically: a temporary file in the
    /// same directory, synced, renamed over `path`, then the directory
    /// synced, so a crash leaves the old file or the new one, never a part.
    pub fn save(&self, path: &Path) -> Result<(), SimError> {
        self.validate().map_err(|e| e.in_file(path))?;
        let text = self.to_toml()?;
        let write = || -> std::io::Result<()> {
            let mut file = AtomicWriteFile::open(path)?;
            file.write_all(text.as_bytes())?;
            file.commit()
        };
        write().map_err(|e| profile_error(Some(path), None, format!("cannot write: {e}")))
    }
}

impl SimError {
    /// A profile error without a file, placed in `path`.
    fn in_file(self, path: &Path) -> Self {
        match self {
            SimError::Profile { field, reason, .. } => SimError::Profile {
                path: Some(path.to_path_buf()),
                field,
                reason,
            },
            other => other,
        }
    }
}

fn profile_error(path: Option<&Path>, field: Option<&str>, reason: String) -> SimError {
    SimError::Profile {
        path: path.map(Path::to_path_buf),
        field: field.map(str::to_owned),
        reason,
    }
}

fn check(field: &str, value: f32, ok: impl Fn(f32) -> bool, range: &str) -> Result<(), SimError> {
    if !value.is_finite() {
        return Err(profile_error(
            None,
            Some(field),
            format!("{value} is not finite"),
        ));
    }
    if !ok(value) {
        return Err(profile_error(
            None,
            Some(field),
            format!("{value} is outside {range}"),
        ));
    }
    Ok(())
}

/// A TOML error with the field it is about, found from the error's place
/// in `text` (toml's own messages name only the last key, or none).
fn toml_error(text: &str, e: &toml::de::Error) -> SimError {
    let at = e.span().map(|s| s.start);
    let field = at.and_then(|at| field_at(text, at));
    let line = at.map(|at| text[..at.min(text.len())].matches('\n').count() + 1);
    let reason = match line {
        Some(line) => format!("{} (line {line})", e.message()),
        None => e.message().to_owned(),
    };
    profile_error(None, field.as_deref(), reason)
}

/// The dotted name of the key on the line holding byte `at` (with its
/// `[table]`), or the table named on that line.
fn field_at(text: &str, at: usize) -> Option<String> {
    let start = text.get(..at)?.rfind('\n').map_or(0, |i| i + 1);
    let line = text[start..].lines().next().unwrap_or("");
    let header = |l: &str| {
        let l = l.trim();
        (l.starts_with('[') && !l.starts_with("[[")).then(|| {
            l.trim_start_matches('[')
                .split(']')
                .next()
                .unwrap_or("")
                .trim()
                .to_owned()
        })
    };
    if let Some(table) = header(line) {
        return Some(table);
    }
    let key = line
        .split('=')
        .next()?
        .trim()
        .trim_matches(['"', '\''])
        .to_owned();
    if key.is_empty() || !line.contains('=') {
        return None;
    }
    let table = text[..start].lines().rev().find_map(header);
    Some(match table {
        Some(t) if !t.is_empty() => format!("{t}.{key}"),
        _ => key,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn field_at_names_dotted_keys_and_tables() {
        let text = "format = 1\n[motion]\nlinear_gain = 2\n[camera]\n";
        assert_eq!(field_at(text, 0).as_deref(), Some("format"));
        let at = text.find("linear_gain").expect("key") + 14;
        assert_eq!(field_at(text, at).as_deref(), Some("motion.linear_gain"));
        let at = text.find("camera").expect("table");
        assert_eq!(field_at(text, at).as_deref(), Some("camera"));
    }
}
