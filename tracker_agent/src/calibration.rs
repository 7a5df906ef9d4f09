//! The two rigid transforms that turn a tracker device pose into the robot's
//! base_link pose in the world frame, their TOML file, and the solver that
//! finds `world_from_tracking` from reference points.
//!
//! ```text
//! base_link_in_world = world_from_tracking * device_in_tracking * tracker_in_base_link⁻¹
//! ```
//!
//! The config file:
//!
//! ```toml
//! [world_from_tracking]        # maps tracking-frame coordinates into the world frame
//! translation = [0.0, 0.0, 0.0]
//! rotation = [0.0, 0.0, 0.0, 1.0]   # qx, qy, qz, qw
//! [tracker_in_base_link]       # the tracker device's pose in base_link (mount)
//! translation = [-0.03, 0.0, 0.14]
//! rotation = [0.0, 0.0, 0.0, 1.0]
//! ```

use std::io::Write;
use std::path::Path;

use atomic_write_file::AtomicWriteFile;
use nalgebra::{
    Isometry3, Matrix3, Point3, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3,
};
use serde::{Deserialize, Serialize};

/// How far a config quaternion's norm may be from 1 (it is then normalised).
pub const ROTATION_NORM_TOLERANCE: f64 = 0.01;

/// Reference points whose RMS distance from their best-fit line is below
/// this (metres) are collinear: the rotation about that line is unknown.
pub const MIN_OFF_LINE_SPREAD_M: f64 = 0.02;

/// …or below this fraction of their RMS spread along the line.
pub const MIN_OFF_LINE_RATIO: f64 = 0.05;

/// Fewest reference points the solver accepts.
pub const MIN_POINTS: usize = 3;

/// What can be wrong with a calibration or its inputs.
#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    /// A file could not be read or written.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        #[source]
        error: std::io::Error,
    },
    /// A file is not valid TOML of the expected shape.
    #[error("{path}: {message}")]
    Parse {
        /// The file (or `<string>`).
        path: String,
        /// The parser's message.
        message: String,
    },
    /// A transform has a NaN or infinite component.
    #[error("{field}: not finite")]
    NonFinite {
        /// Which transform and part.
        field: String,
    },
    /// A rotation quaternion is too far from unit length.
    #[error("{field}: quaternion norm {norm} is not within {ROTATION_NORM_TOLERANCE} of 1")]
    NotUnit {
        /// Which transform.
        field: String,
        /// Its norm.
        norm: f64,
    },
    /// Fewer than [`MIN_POINTS`] reference points.
    #[error("calibration needs at least {MIN_POINTS} reference points, got {0}")]
    TooFewPoints(usize),
    /// The reference points (nearly) lie on a line.
    #[error(
        "reference points are (nearly) collinear: {off_line_m:.4} m RMS off their common line \
         (need ≥ {MIN_OFF_LINE_SPREAD_M} m and ≥ {MIN_OFF_LINE_RATIO} × their spread along it); \
         add a point off the line"
    )]
    Collinear {
        /// RMS distance of the points from their best-fit line, m.
        off_line_m: f64,
    },
    /// World and measured point lists differ in length, or files disagree.
    #[error("mismatched inputs: {0}")]
    Mismatch(String),
}

/// A rigid transform as written in the config file.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransformToml {
    /// Metres.
    pub translation: [f64; 3],
    /// Unit quaternion, `[qx, qy, qz, qw]`.
    pub rotation: [f64; 4],
}

impl TransformToml {
    /// Checks and converts to an isometry (the quaternion is normalised).
    pub fn to_isometry(&self, field: &str) -> Result<Isometry3<f64>, CalibrationError> {
        Ok(Isometry3::from_parts(
            Translation3::from(vector(self.translation, &format!("{field}.translation"))?),
            unit_quaternion(self.rotation, &format!("{field}.rotation"))?,
        ))
    }

    /// The file form of an isometry; components below 1e-12 in magnitude
    /// (round-off of a solve) are written as 0.
    pub fn from_isometry(iso: &Isometry3<f64>) -> Self {
        let snap = |x: f64| if x.abs() < 1e-12 { 0.0 } else { x };
        let t = iso.translation.vector;
        let q = iso.rotation.quaternion();
        Self {
            translation: [t.x, t.y, t.z].map(snap),
            rotation: [q.i, q.j, q.k, q.w].map(snap),
        }
    }
}

/// Checks a `[x, y, z]` for finiteness.
pub fn vector(v: [f64; 3], field: &str) -> Result<Vector3<f64>, CalibrationError> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(Vector3::new(v[0], v[1], v[2]))
    } else {
        Err(CalibrationError::NonFinite {
            field: field.to_owned(),
        })
    }
}

/// Checks a `[qx, qy, qz, qw]` and normalises it.
pub fn unit_quaternion(q: [f64; 4], field: &str) -> Result<UnitQuaternion<f64>, CalibrationError> {
    if !q.iter().all(|x| x.is_finite()) {
        return Err(CalibrationError::NonFinite {
            field: field.to_owned(),
        });
    }
    let quaternion = Quaternion::new(q[3], q[0], q[1], q[2]);
    let norm = quaternion.norm();
    if (norm - 1.0).abs() > ROTATION_NORM_TOLERANCE {
        return Err(CalibrationError::NotUnit {
            field: field.to_owned(),
            norm,
        });
    }
    Ok(crate::protocol::normalize(quaternion))
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CalibrationFile {
    world_from_tracking: TransformToml,
    tracker_in_base_link: TransformToml,
}

/// The ROSbot mount: the tracker 3 cm behind and 14 cm above base_link,
/// axes aligned.
pub fn rosbot_mount() -> Isometry3<f64> {
    Isometry3::translation(-0.03, 0.0, 0.14)
}

/// The tracker's calibration: where the tracking frame sits in the world,
/// and where the tracker sits on the robot.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Calibration {
    /// Maps tracking-frame coordinates into the world frame.
    pub world_from_tracking: Isometry3<f64>,
    /// The tracker device's pose in base_link (the mount).
    pub tracker_in_base_link: Isometry3<f64>,
}

impl Default for Calibration {
    /// Identity world transform, ROSbot mount.
    fn default() -> Self {
        Self {
            world_from_tracking: Isometry3::identity(),
            tracker_in_base_link: rosbot_mount(),
        }
    }
}

impl Calibration {
    /// base_link's pose in the world given the device's pose in the
    /// tracking frame.
    pub fn base_link_in_world(&self, device_in_tracking: &Isometry3<f64>) -> Isometry3<f64> {
        self.world_from_tracking
            * base_link_in_tracking(device_in_tracking, &self.tracker_in_base_link)
    }

    /// Parses and validates the TOML form.
    pub fn from_toml_str(text: &str) -> Result<Self, CalibrationError> {
        Self::parse(text, "<string>")
    }

    fn parse(text: &str, path: &str) -> Result<Self, CalibrationError> {
        let file: CalibrationFile = toml::from_str(text).map_err(|e| CalibrationError::Parse {
            path: path.to_owned(),
            message: e.to_string(),
        })?;
        Ok(Self {
            world_from_tracking: file
                .world_from_tracking
                .to_isometry("world_from_tracking")?,
            tracker_in_base_link: file
                .tracker_in_base_link
                .to_isometry("tracker_in_base_link")?,
        })
    }

    /// Loads and validates a config file.
    pub fn load(path: &Path) -> Result<Self, CalibrationError> {
        Self::parse(&read_text(path)?, &path.display().to_string())
    }

    /// The TOML form (numbers in full precision: loading it back is exact,
    /// but for components below 1e-12, written as 0).
    pub fn to_toml_string(&self) -> Result<String, CalibrationError> {
        let file = CalibrationFile {
            world_from_tracking: TransformToml::from_isometry(&self.world_from_tracking),
            tracker_in_base_link: TransformToml::from_isometry(&self.tracker_in_base_link),
        };
        let body = toml::to_string(&file).map_err(|e| CalibrationError::Parse {
            path: "<string>".to_owned(),
            message: e.to_string(),
        })?;
        Ok(body
            .replace(
                "[world_from_tracking]\n",
                "[world_from_tracking]    # maps tracking-frame coordinates into the world frame\n",
            )
            .replace(
                "[tracker_in_base_link]\n",
                "[tracker_in_base_link]   # the tracker device's pose in base_link (mount)\n",
            ))
    }

    /// Writes the config file, preceded by `comment` lines (each prefixed
    /// with `# `).
    pub fn save(&self, path: &Path, comment: &str) -> Result<(), CalibrationError> {
        let mut text = String::new();
        for line in comment.lines() {
            text.push_str("# ");
            text.push_str(line);
            text.push('\n');
        }
        text.push_str(&self.to_toml_string()?);
        write_durably(path, &text)
    }
}

/// Writes `text` to `path` so that a crash or power cut leaves the old file
/// or the new one, never a part: a tracker agent must not start from a
/// truncated calibration (temporary file, fsync, rename, directory fsync).
fn write_durably(path: &Path, text: &str) -> Result<(), CalibrationError> {
    let io = |error| CalibrationError::Io {
        path: path.display().to_string(),
        error,
    };
    let mut file = AtomicWriteFile::open(path).map_err(io)?;
    file.write_all(text.as_bytes()).map_err(io)?;
    file.commit().map_err(io)
}

/// base_link's pose in the tracking frame given the device's pose there and
/// the mount: `device_in_tracking * tracker_in_base_link⁻¹`.
pub fn base_link_in_tracking(
    device_in_tracking: &Isometry3<f64>,
    tracker_in_base_link: &Isometry3<f64>,
) -> Isometry3<f64> {
    device_in_tracking * tracker_in_base_link.inverse()
}

/// A solved `world_from_tracking` and how well it fits.
#[derive(Debug, Clone, PartialEq)]
pub struct Solution {
    /// The least-squares rigid transform.
    pub world_from_tracking: Isometry3<f64>,
    /// RMS distance between mapped and surveyed points, m.
    pub rms_residual_m: f64,
    /// Largest such distance, m.
    pub max_residual_m: f64,
    /// Per-point distance, m, in input order.
    pub residuals_m: Vec<f64>,
}

/// Solves the rigid transform mapping `tracking[i]` onto `world[i]` in the
/// least-squares sense (Kabsch: SVD of the cross-covariance, with the
/// reflection case corrected so the result is a proper rotation).
///
/// Needs ≥ [`MIN_POINTS`] points that are not (nearly) collinear; coplanar
/// points (all marks on the floor) are fine.
pub fn solve_world_from_tracking(
    tracking: &[Point3<f64>],
    world: &[Point3<f64>],
) -> Result<Solution, CalibrationError> {
    if tracking.len() != world.len() {
        return Err(CalibrationError::Mismatch(format!(
            "{} measured points for {} reference points",
            tracking.len(),
            world.len()
        )));
    }
    let n = world.len();
    if n < MIN_POINTS {
        return Err(CalibrationError::TooFewPoints(n));
    }
    for (i, p) in tracking.iter().chain(world).enumerate() {
        if !p.coords.iter().all(|x| x.is_finite()) {
            return Err(CalibrationError::NonFinite {
                field: format!("point {}", i % n + 1),
            });
        }
    }
    check_not_collinear(world)?;
    check_not_collinear(tracking)?;

    let centroid = |points: &[Point3<f64>]| -> Vector3<f64> {
        points.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n as f64
    };
    let (ct, cw) = (centroid(tracking), centroid(world));
    // H = Σ (t_i − c_t)(w_i − c_w)ᵀ ;  R = V diag(1, 1, d) Uᵀ.
    let h: Matrix3<f64> = tracking
        .iter()
        .zip(world)
        .map(|(t, w)| (t.coords - ct) * (w.coords - cw).transpose())
        .sum();
    let svd = h.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(CalibrationError::Collinear { off_line_m: 0.0 });
    };
    let v = v_t.transpose();
    // Singular values are sorted in decreasing order: the last column is
    // the one to flip when V Uᵀ is a reflection.
    let d = (v * u.transpose()).determinant().signum();
    let correction = Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d));
    let r = v * correction * u.transpose();
    let rotation = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(r));
    let translation = cw - rotation * ct;
    let world_from_tracking = Isometry3::from_parts(Translation3::from(translation), rotation);
    let residuals_m: Vec<f64> = tracking
        .iter()
        .zip(world)
        .map(|(t, w)| (world_from_tracking * t - w).norm())
        .collect();
    let rms_residual_m = (residuals_m.iter().map(|r| r * r).sum::<f64>() / n as f64).sqrt();
    let max_residual_m = residuals_m.iter().copied().fold(0.0, f64::max);
    Ok(Solution {
        world_from_tracking,
        rms_residual_m,
        max_residual_m,
        residuals_m,
    })
}

/// Rejects point sets that (nearly) lie on one line.
fn check_not_collinear(points: &[Point3<f64>]) -> Result<(), CalibrationError> {
    let n = points.len() as f64;
    let c = points.iter().map(|p| p.coords).sum::<Vector3<f64>>() / n;
    let scatter: Matrix3<f64> = points
        .iter()
        .map(|p| (p.coords - c) * (p.coords - c).transpose())
        .sum();
    let mut eig: Vec<f64> = scatter
        .symmetric_eigen()
        .eigenvalues
        .iter()
        .map(|e| e.max(0.0))
        .collect();
    eig.sort_by(|a, b| b.total_cmp(a));
    let along = (eig[0] / n).sqrt();
    let off_line_m = ((eig[1] + eig[2]) / n).sqrt();
    if off_line_m < MIN_OFF_LINE_SPREAD_M || off_line_m < MIN_OFF_LINE_RATIO * along {
        return Err(CalibrationError::Collinear { off_line_m });
    }
    Ok(())
}

/// One surveyed mark: base_link origin's world position there.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferencePoint {
    /// Optional label used in prompts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub name: Option<String>,
    /// World position of base_link's origin at this mark, m.
    pub world: [f64; 3],
    /// Measured device position in the tracking frame (offline mode).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device_translation: Option<[f64; 3]>,
    /// Measured device rotation `[qx, qy, qz, qw]` (offline mode).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device_rotation: Option<[f64; 4]>,
}

impl ReferencePoint {
    /// A label for prompts and reports.
    pub fn label(&self, index: usize) -> String {
        match &self.name {
            Some(name) => format!("point {} ({name})", index + 1),
            None => format!("point {}", index + 1),
        }
    }

    /// The measured device pose, if both parts are present and valid.
    pub fn device_pose(&self, index: usize) -> Result<Isometry3<f64>, CalibrationError> {
        let field = self.label(index);
        let (Some(t), Some(q)) = (self.device_translation, self.device_rotation) else {
            return Err(CalibrationError::Mismatch(format!(
                "{field} has no device_translation and device_rotation"
            )));
        };
        Ok(Isometry3::from_parts(
            Translation3::from(vector(t, &format!("{field}.device_translation"))?),
            unit_quaternion(q, &format!("{field}.device_rotation"))?,
        ))
    }
}

/// A reference (or samples) file: `[[point]]` tables.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferenceFile {
    /// The marks, in order.
    #[serde(default)]
    pub point: Vec<ReferencePoint>,
}

impl ReferenceFile {
    /// Parses the TOML form.
    pub fn from_toml_str(text: &str) -> Result<Self, CalibrationError> {
        Self::parse(text, "<string>")
    }

    fn parse(text: &str, path: &str) -> Result<Self, CalibrationError> {
        let file: ReferenceFile = toml::from_str(text).map_err(|e| CalibrationError::Parse {
            path: path.to_owned(),
            message: e.to_string(),
        })?;
        for (i, p) in file.point.iter().enumerate() {
            vector(p.world, &format!("{}.world", p.label(i)))?;
        }
        Ok(file)
    }

    /// Loads a reference or samples file.
    pub fn load(path: &Path) -> Result<Self, CalibrationError> {
        Self::parse(&read_text(path)?, &path.display().to_string())
    }

    /// The TOML form.
    pub fn to_toml_string(&self) -> Result<String, CalibrationError> {
        toml::to_string(self).map_err(|e| CalibrationError::Parse {
            path: "<string>".to_owned(),
            message: e.to_string(),
        })
    }

    /// Writes the file (see [`write_durably`]).
    pub fn save(&self, path: &Path) -> Result<(), CalibrationError> {
        write_durably(path, &self.to_toml_string()?)
    }

    /// World positions, in order.
    pub fn world_points(&self) -> Vec<Point3<f64>> {
        self.point.iter().map(|p| Point3::from(p.world)).collect()
    }
}

/// Solves `world_from_tracking` from measured device poses at the marks:
/// each base_link origin in the tracking frame is
/// `device_in_tracking * tracker_in_base_link⁻¹ * 0`.
pub fn calibrate_from_device_poses(
    world: &[Point3<f64>],
    device_in_tracking: &[Isometry3<f64>],
    tracker_in_base_link: &Isometry3<f64>,
) -> Result<Solution, CalibrationError> {
    let tracking: Vec<Point3<f64>> = device_in_tracking
        .iter()
        .map(|d| base_link_in_tracking(d, tracker_in_base_link) * Point3::origin())
        .collect();
    solve_world_from_tracking(&tracking, world)
}

/// Offline calibration from a samples file (every point has its device
/// pose).
pub fn calibrate_from_samples(
    samples: &ReferenceFile,
    tracker_in_base_link: &Isometry3<f64>,
) -> Result<Solution, CalibrationError> {
    let devices = samples
        .point
        .iter()
        .enumerate()
        .map(|(i, p)| p.device_pose(i))
        .collect::<Result<Vec<_>, _>>()?;
    calibrate_from_device_poses(&samples.world_points(), &devices, tracker_in_base_link)
}

/// Averages device poses measured at one mark: mean position, and the
/// normalised sum of sign-aligned quaternions (accurate for the small
/// spread of a robot standing still). `None` for no poses.
pub fn average_poses(poses: &[Isometry3<f64>]) -> Option<Isometry3<f64>> {
    let first = poses.first()?;
    let n = poses.len() as f64;
    let translation = poses
        .iter()
        .map(|p| p.translation.vector)
        .sum::<Vector3<f64>>()
        / n;
    let reference = first.rotation.quaternion().coords;
    let sum = poses
        .iter()
        .map(|p| {
            let q = p.rotation.quaternion().coords;
            if q.dot(&reference) < 0.0 {
                -q
            } else {
                q
            }
        })
        .sum::<nalgebra::Vector4<f64>>();
    let rotation = UnitQuaternion::try_new(Quaternion::from(sum), 1e-12)?;
    Some(Isometry3::from_parts(
        Translation3::from(translation),
        rotation,
    ))
}

/// RMS distance of positions from their mean, m (how still the robot was).
pub fn position_spread(poses: &[Isometry3<f64>]) -> f64 {
    if poses.is_empty() {
        return 0.0;
    }
    let n = poses.len() as f64;
    let mean = poses
        .iter()
        .map(|p| p.translation.vector)
        .sum::<Vector3<f64>>()
        / n;
    (poses
        .iter()
        .map(|p| (p.translation.vector - mean).norm_squared())
        .sum::<f64>()
        / n)
        .sqrt()
}

/// A config or reference file's text, with its path in the error.
fn read_text(path: &Path) -> Result<String, CalibrationError> {
    std::fs::read_to_string(path).map_err(|error| CalibrationError::Io {
        path: path.display().to_string(),
        error,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;
    use rand_distr::StandardNormal;

    /// A lighthouse frame tilted by 20° and 11° and turned by 120°, its
    /// origin 2.4 m above the floor.
    fn true_world_from_tracking() -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(1.2, -0.7, 2.4),
            UnitQuaternion::from_euler_angles(0.35, -0.2, 2.1),
        )
    }

    /// Marks on the floor of a 2.5 m × 2 m enclosure, and the robot's yaw
    /// at each.
    const MARKS: [([f64; 3], f64); 6] = [
        ([0.0, 0.0, 0.0], 0.0),
        ([2.5, 0.0, 0.0], 1.0),
        ([2.5, 2.0, 0.0], 2.0),
        ([0.0, 2.0, 0.0], -1.5),
        ([1.2, 0.9, 0.0], 0.4),
        ([0.6, 1.5, 0.0], -2.8),
    ];

    fn base_link_at(world: [f64; 3], yaw: f64) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(world[0], world[1], world[2]),
            UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        )
    }

    /// Device poses in the tracking frame at each mark, with Gaussian noise
    /// (position σ per axis, rotation σ per axis-angle component).
    fn measure(
        world_from_tracking: &Isometry3<f64>,
        mount: &Isometry3<f64>,
        sigma_m: f64,
        sigma_rad: f64,
        rng: &mut ChaCha8Rng,
    ) -> Vec<Isometry3<f64>> {
        let mut gauss = |sigma: f64| sigma * rng.sample::<f64, _>(StandardNormal);
        MARKS
            .iter()
            .map(|(world, yaw)| {
                let device = world_from_tracking.inverse() * base_link_at(*world, *yaw) * mount;
                let dt = Vector3::new(gauss(sigma_m), gauss(sigma_m), gauss(sigma_m));
                let dr = UnitQuaternion::from_scaled_axis(Vector3::new(
                    gauss(sigma_rad),
                    gauss(sigma_rad),
                    gauss(sigma_rad),
                ));
                Isometry3::from_parts(
                    Translation3::from(device.translation.vector + dt),
                    dr * device.rotation,
                )
            })
            .collect()
    }

    fn world_points() -> Vec<Point3<f64>> {
        MARKS.iter().map(|(w, _)| Point3::from(*w)).collect()
    }

    #[test]
    fn noise_free_points_give_the_exact_transform() {
        let truth = true_world_from_tracking();
        let mount = rosbot_mount();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let devices = measure(&truth, &mount, 0.0, 0.0, &mut rng);
        let solution =
            calibrate_from_device_poses(&world_points(), &devices, &mount).expect("solvable");
        let est = solution.world_from_tracking;
        assert!((est.translation.vector - truth.translation.vector).norm() < 1e-9);
        assert!(est.rotation.angle_to(&truth.rotation) < 1e-9);
        assert!(solution.rms_residual_m < 1e-9);
        assert_eq!(solution.residuals_m.len(), MARKS.len());
    }

    /// Stated tolerance: with 2 mm (σ per axis) position noise and 0.2°
    /// rotation noise on the device poses at 6 floor marks, over 20 noise
    /// draws the solved rotation is within 0.5°, the marks map within 5 mm
    /// RMS of their surveyed positions (every one within 1 cm), and the
    /// enclosure's centre within 5 mm.
    #[test]
    fn noisy_points_recover_a_tilted_transform_within_tolerance() {
        let truth = true_world_from_tracking();
        let mount = rosbot_mount();
        let mut worst_angle = 0.0_f64;
        let mut worst_rms = 0.0_f64;
        let mut worst_mark = 0.0_f64;
        let mut worst_centre = 0.0_f64;
        let centre = Point3::new(1.25, 1.0, 0.0);
        for seed in 0..20 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let devices = measure(&truth, &mount, 0.002, 0.2_f64.to_radians(), &mut rng);
            let solution =
                calibrate_from_device_poses(&world_points(), &devices, &mount).expect("solvable");
            let est = solution.world_from_tracking;
            worst_angle = worst_angle.max(est.rotation.angle_to(&truth.rotation));
            let errors: Vec<f64> = world_points()
                .iter()
                .map(|world| (est * (truth.inverse() * world) - world).norm())
                .collect();
            let rms = (errors.iter().map(|e| e * e).sum::<f64>() / errors.len() as f64).sqrt();
            worst_rms = worst_rms.max(rms);
            worst_mark = errors.iter().copied().fold(worst_mark, f64::max);
            worst_centre = worst_centre.max((est * (truth.inverse() * centre) - centre).norm());
            assert!(solution.rms_residual_m < 0.005, "seed {seed}: {solution:?}");
            assert!(solution.rms_residual_m > 0.0);
        }
        eprintln!(
            "worst of 20: rotation {:.3}°, marks {:.2} mm RMS / {:.2} mm max, centre {:.2} mm",
            worst_angle.to_degrees(),
            worst_rms * 1e3,
            worst_mark * 1e3,
            worst_centre * 1e3
        );
        assert!(worst_angle.to_degrees() < 0.5);
        assert!(worst_rms < 0.005);
        assert!(worst_mark < 0.01);
        assert!(worst_centre < 0.005);
    }

    /// Random frames with coplanar marks: half the SVDs need the
    /// reflection fix; every solution must still be exact.
    #[test]
    fn coplanar_points_always_give_a_proper_rotation() {
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let world = world_points();
        for _ in 0..50 {
            let truth = Isometry3::from_parts(
                Translation3::new(
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                    rng.random_range(-3.0..3.0),
                ),
                UnitQuaternion::from_euler_angles(
                    rng.random_range(-3.1..3.1),
                    rng.random_range(-1.5..1.5),
                    rng.random_range(-3.1..3.1),
                ),
            );
            let tracking: Vec<_> = world.iter().map(|w| truth.inverse() * w).collect();
            let solution = solve_world_from_tracking(&tracking, &world).expect("solvable");
            assert!(
                solution
                    .world_from_tracking
                    .rotation
                    .angle_to(&truth.rotation)
                    < 1e-9,
                "{truth:?}"
            );
            assert!(solution.rms_residual_m < 1e-9);
        }
        // A mirrored point set has no proper fit: the solver still returns
        // a rotation (and a large residual) instead of a reflection.
        let world = vec![
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(1.0, 0.0, 0.0),
            Point3::new(0.0, 1.0, 0.0),
            Point3::new(0.0, 0.0, 1.0),
        ];
        let mirrored: Vec<_> = world.iter().map(|p| Point3::new(-p.x, p.y, p.z)).collect();
        let solution = solve_world_from_tracking(&mirrored, &world).expect("solvable");
        let r = solution.world_from_tracking.rotation.to_rotation_matrix();
        assert!((r.matrix().determinant() - 1.0).abs() < 1e-9);
        assert!(solution.rms_residual_m > 0.1);
    }

    #[test]
    fn too_few_or_collinear_points_are_typed_errors() {
        let two = [Point3::new(0.0, 0.0, 0.0), Point3::new(1.0, 0.0, 0.0)];
        assert!(matches!(
            solve_world_from_tracking(&two, &two),
            Err(CalibrationError::TooFewPoints(2))
        ));
        let line = [
            Point3::new(0.0, 0.0, 0.0),
            Point3::new(1.0, 0.0, 0.0),
            Point3::new(2.0, 0.001, 0.0),
            Point3::new(3.0, 0.0, 0.0),
        ];
        match solve_world_from_tracking(&line, &line) {
            Err(CalibrationError::Collinear { off_line_m }) => assert!(off_line_m < 0.001),
            other => panic!("expected Collinear, got {other:?}"),
        }
        let same = [Point3::new(1.0, 2.0, 0.0); 4];
        assert!(matches!(
            solve_world_from_tracking(&same, &same),
            Err(CalibrationError::Collinear { .. })
        ));
        assert!(matches!(
            solve_world_from_tracking(&line[..3], &line),
            Err(CalibrationError::Mismatch(_))
        ));
        let bad = [
            Point3::new(f64::NAN, 0.0, 0.0),
            Point3::new(1.0, 0.0, 0.0),
            Point3::new(0.0, 1.0, 0.0),
        ];
        assert!(matches!(
            solve_world_from_tracking(&bad, &bad),
            Err(CalibrationError::NonFinite { .. })
        ));
    }

    #[test]
    fn base_link_pose_composes_the_mount() {
        // Identity world transform: a device 14 cm up, facing +y, carries
        // base_link 3 cm ahead of it along +y (the tracker sits behind).
        let calibration = Calibration::default();
        let device = Isometry3::from_parts(
            Translation3::new(1.0, 2.0, 0.14),
            UnitQuaternion::from_euler_angles(0.0, 0.0, std::f64::consts::FRAC_PI_2),
        );
        let base = calibration.base_link_in_world(&device);
        assert!((base.translation.vector - Vector3::new(1.0, 2.03, 0.0)).norm() < 1e-12);
        assert!(base.rotation.angle_to(&device.rotation) < 1e-12);

        // General case: world * device * mount⁻¹, and back.
        let calibration = Calibration {
            world_from_tracking: true_world_from_tracking(),
            tracker_in_base_link: Isometry3::from_parts(
                Translation3::new(-0.03, 0.01, 0.14),
                UnitQuaternion::from_euler_angles(0.0, 0.0, 0.5),
            ),
        };
        let truth = base_link_at([0.7, 1.1, 0.0], -0.9);
        let device =
            calibration.world_from_tracking.inverse() * truth * calibration.tracker_in_base_link;
        let base = calibration.base_link_in_world(&device);
        assert!((base.translation.vector - truth.translation.vector).norm() < 1e-12);
        assert!(base.rotation.angle_to(&truth.rotation) < 1e-12);
    }

    #[test]
    fn config_toml_round_trips_and_validates() {
        let calibration = Calibration {
            world_from_tracking: true_world_from_tracking(),
            tracker_in_base_link: rosbot_mount(),
        };
        let text = calibration.to_toml_string().expect("serialises");
        assert!(text.contains("[world_from_tracking]"));
        assert!(text.contains("[tracker_in_base_link]"));
        assert_eq!(
            Calibration::from_toml_str(&text).expect("parses"),
            calibration
        );

        // Saved whole, over an older (longer) file, leaving nothing beside it.
        let dir = std::env::temp_dir().join(format!(
            "tracker_agent_calib_{}_{:?}",
            std::process::id(),
            std::thread::current().id()
        ));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("calibration.toml");
        std::fs::write(&path, "# an older calibration\n".repeat(200)).expect("old file");
        calibration
            .save(&path, "a comment\nover two lines")
            .expect("saved");
        let written = std::fs::read_to_string(&path).expect("readable");
        assert!(written.starts_with("# a comment\n# over two lines\n"));
        assert!(!written.contains("older"), "{written}");
        assert_eq!(Calibration::load(&path).expect("loads"), calibration);
        let names: Vec<_> = std::fs::read_dir(&dir)
            .expect("list")
            .map(|e| e.expect("entry").file_name())
            .collect();
        assert_eq!(names, ["calibration.toml"], "no temporary file left");
        // A directory that does not exist: an error naming the file.
        let missing = dir.join("no/such/dir/calibration.toml");
        let e = calibration.save(&missing, "x").expect_err("no directory");
        assert!(e.to_string().contains("calibration.toml"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);

        // The documented example, with a hand-typed quaternion.
        let example = "[world_from_tracking]\ntranslation = [1, 2, 3]\nrotation = [0.0, 0.0, 0.7071, 0.7071]\n\
                       [tracker_in_base_link]\ntranslation = [-0.03, 0.0, 0.14]\nrotation = [0.0, 0.0, 0.0, 1.0]\n";
        let parsed = Calibration::from_toml_str(example).expect("parses");
        assert!(
            (parsed.world_from_tracking.rotation.angle() - std::f64::consts::FRAC_PI_2).abs()
                < 1e-9
        );
        assert_eq!(parsed.tracker_in_base_link, rosbot_mount());

        let broken = |from: &str, to: &str| Calibration::from_toml_str(&example.replace(from, to));
        assert!(matches!(
            broken("[0.0, 0.0, 0.7071, 0.7071]", "[0.0, 0.0, 0.0, 0.9]"),
            Err(CalibrationError::NotUnit { .. })
        ));
        assert!(matches!(
            broken("[1, 2, 3]", "[1, nan, 3]"),
            Err(CalibrationError::NonFinite { .. })
        ));
        assert!(matches!(
            broken("[1, 2, 3]", "[1, 2]"),
            Err(CalibrationError::Parse { .. })
        ));
        assert!(matches!(
            broken("[tracker_in_base_link]", "[tracker_in_base]"),
            Err(CalibrationError::Parse { .. })
        ));
        assert!(matches!(
            Calibration::load(std::path::Path::new("/nonexistent/tracker.toml")),
            Err(CalibrationError::Io { .. })
        ));
    }

    #[test]
    fn samples_files_round_trip_and_calibrate() {
        let truth = true_world_from_tracking();
        let mount = rosbot_mount();
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let devices = measure(&truth, &mount, 0.0, 0.0, &mut rng);
        let samples = ReferenceFile {
            point: MARKS
                .iter()
                .zip(&devices)
                .enumerate()
                .map(|(i, ((world, _), d))| {
                    let TransformToml {
                        translation,
                        rotation,
                    } = TransformToml::from_isometry(d);
                    ReferencePoint {
                        name: (i == 0).then(|| "door".to_owned()),
                        world: *world,
                        device_translation: Some(translation),
                        device_rotation: Some(rotation),
                    }
                })
                .collect(),
        };
        let text = samples.to_toml_string().expect("serialises");
        let parsed = ReferenceFile::from_toml_str(&text).expect("parses");
        assert_eq!(parsed, samples);
        let solution = calibrate_from_samples(&parsed, &mount).expect("solvable");
        assert!(
            solution
                .world_from_tracking
                .rotation
                .angle_to(&truth.rotation)
                < 1e-9
        );

        // A plain reference file has no device poses.
        let reference = ReferenceFile::from_toml_str(
            "[[point]]\nworld = [0, 0, 0]\n[[point]]\nname = \"b\"\nworld = [1, 0, 0]\n",
        )
        .expect("parses");
        assert_eq!(reference.point.len(), 2);
        assert_eq!(reference.point[1].label(1), "point 2 (b)");
        assert!(matches!(
            calibrate_from_samples(&reference, &mount),
            Err(CalibrationError::Mismatch(_))
        ));
        assert!(matches!(
            ReferenceFile::from_toml_str("[[point]]\nwhere = [0, 0, 0]\n"),
            Err(CalibrationError::Parse { .. })
        ));
    }

    #[test]
    fn averaging_poses_is_exact_for_identical_poses_and_sign_safe() {
        let pose = base_link_at([1.0, 2.0, 3.0], 0.3);
        let mut flipped = pose;
        // −q is the same rotation.
        flipped.rotation = UnitQuaternion::new_unchecked(-pose.rotation.into_inner());
        let avg = average_poses(&[pose, flipped, pose]).expect("poses");
        assert!((avg.translation.vector - pose.translation.vector).norm() < 1e-12);
        assert!(avg.rotation.angle_to(&pose.rotation) < 1e-9);
        assert_eq!(average_poses(&[]), None);
        assert_eq!(position_spread(&[pose, pose]), 0.0);
    }
}
