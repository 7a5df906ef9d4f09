//! Twin identification: the profile that makes the twin replay recorded
//! episodes best, fitted with a derivative-free optimiser (`argmin`'s
//! Nelder–Mead) on the replay error.
//!
//! The parameters come apart into three fits, each on the data that sees
//! them:
//! 1. **motion gains** (linear, angular): one-step replays — each step
//!    from the recorded pose before it, with its recorded command — scored
//!    by the distance (and heading, at 0.3 m per rad) from the recorded
//!    pose after it;
//! 2. **camera mount** (height, pitch, yaw): depth rendered at recorded
//!    poses against the recorded depth (pixels valid in one image only
//!    count as a 0.5 m miss);
//! 3. **depth noise and dropout**: measured directly at the fitted
//!    camera — the share of pixels the twin sees and the camera lost, and
//!    the robust spread of the relative depth residual.
//!
//! Before these, **latency and settle time**, which shape *when* the robot
//! moves more than where a step ends, are fitted to the wheel-odometry
//! time series ([`crate::timing`]) when the episodes hold one (a robot
//! agent streams its odometry); else they are kept from the starting
//! profile. The motion gains are then fitted with the fitted servo.

use offworld_runtime::Resolution;
use std::cell::RefCell;

use argmin::core::{CostFunction, Error as ArgminError, Executor, State};
use argmin::solver::neldermead::NelderMead;
use offworld_runtime::msg::Pose2D;
use offworld_sim_twin::twin::MAX_MOTION_S;
use offworld_sim_twin::{PlanarPose, SimTwin, TwinConfig, TwinProfile};

use crate::recorded::RecordedEpisode;
use crate::replay::yaw_error;
use crate::timing::TimingData;
use crate::ParityError;

/// Fewer episodes than this are refused: a fit to one or two runs learns
/// their noise.
pub const MIN_EPISODES: usize = 3;
/// Fewer moving steps in all than this are refused.
pub const MIN_STEPS: usize = 20;
/// Metres of position error that weigh as much as one radian of heading.
const YAW_WEIGHT_M: f64 = 0.3;
/// What a pixel valid in one image and not the other costs, m.
const VALIDITY_MISS_M: f64 = 0.5;
/// The cost of a candidate outside the profile's valid ranges.
const OUT_OF_RANGE: f64 = 1e6;

/// How the fit runs.
#[derive(Debug, Clone, Copy)]
pub struct IdentifyOptions {
    /// Nelder–Mead iterations per fit, at most.
    pub max_iters: u64,
    /// Steps (evenly spread over all episodes) whose depth the camera fit
    /// renders.
    pub camera_steps: usize,
}

impl Default for IdentifyOptions {
    fn default() -> Self {
        Self {
            max_iters: 150,
            camera_steps: 24,
        }
    }
}

/// What identification found.
#[derive(Debug, Clone)]
pub struct Identified {
    /// The fitted profile.
    pub profile: TwinProfile,
    /// Mean one-step position error with the starting profile, m.
    pub position_error_before_m: f64,
    /// The same with the fitted profile, m.
    pub position_error_after_m: f64,
    /// Mean depth cost at the recorded poses before and after, m.
    pub depth_cost_before_m: f64,
    /// After.
    pub depth_cost_after_m: f64,
    /// The latency and settle-time fit, when the episodes hold an
    /// odometry time series.
    pub timing: Option<TimingFitted>,
    /// Moving steps the motion fit used.
    pub steps: usize,
    /// Nelder–Mead iterations of both fits.
    pub iterations: u64,
}

/// How well the servo's timing matches the odometry.
#[derive(Debug, Clone, Copy)]
pub struct TimingFitted {
    /// Odometry samples used.
    pub samples: usize,
    /// RMS speed error with the starting profile, m/s (yaw rate weighted).
    pub speed_error_before: f64,
    /// The same with the fitted latency and settle time.
    pub speed_error_after: f64,
}

/// The servo's speed error of `profile`'s latency and settle time.
struct TimingFit<'a> {
    data: &'a TimingData,
    base: TwinProfile,
}

impl Fit for TimingFit<'_> {
    fn profile(&self, p: &[f64]) -> TwinProfile {
        let mut profile = self.base;
        profile.motion.latency_s = p[0] as f32;
        profile.motion.settle_time_s = Some(p[1] as f32);
        profile
    }

    fn score(&self, profile: &TwinProfile) -> f64 {
        self.data.cost(profile)
    }
}

/// One moving step: from where, with which command, to where.
#[derive(Debug, Clone, Copy)]
struct Transition {
    episode: usize,
    /// The step's index in its episode (for errors).
    step: u32,
    before: Pose2D,
    after: Pose2D,
    linear: f64,
    angular: f64,
    duration: f64,
}

fn planar(p: &Pose2D) -> PlanarPose {
    PlanarPose {
        x: p.x as f32,
        y: p.y as f32,
        yaw: p.yaw as f32,
    }
}

fn unusable(episode: &RecordedEpisode, reason: String) -> ParityError {
    ParityError::Unusable {
        path: episode.path.clone(),
        reason,
    }
}

/// Checks that `episodes` can be fitted together: enough of them, one env
/// and world, enough motion.
fn check(episodes: &[RecordedEpisode]) -> Result<Vec<Transition>, ParityError> {
    let Some(first) = episodes.first() else {
        return Err(ParityError::TooFew {
            reason: "no episodes".into(),
        });
    };
    if episodes.len() < MIN_EPISODES {
        return Err(ParityError::TooFew {
            reason: format!(
                "{} episodes: identification needs at least {MIN_EPISODES}",
                episodes.len()
            ),
        });
    }
    for e in episodes {
        if e.info.env_id != first.info.env_id || e.info.world != first.info.world {
            return Err(unusable(
                e,
                format!(
                    "recorded on {} in world {}, but {} was recorded on {} in world {}: \
                     identify one robot in one world at a time",
                    e.info.env_id,
                    e.info.world,
                    first.path.display(),
                    first.info.env_id,
                    first.info.world
                ),
            ));
        }
    }
    let mut transitions = Vec::new();
    for (i, e) in episodes.iter().enumerate() {
        for w in e.steps.windows(2) {
            let s = &w[1].step;
            let (a, b) = (w[0].pose, w[1].pose);
            let finite = [
                s.linear_x,
                s.angular_z,
                s.duration_s,
                a.x,
                a.y,
                a.yaw,
                b.x,
                b.y,
                b.yaw,
            ]
            .iter()
            .all(|v| v.is_finite());
            // One bad step would make every candidate fail alike and the
            // fit stop where it started: refuse it, naming it.
            if !finite || !(0.0..=f64::from(MAX_MOTION_S)).contains(&s.duration_s) {
                return Err(unusable(
                    e,
                    format!(
                        "step {}: command ({}, {}) for {} s or its poses cannot be replayed",
                        s.step, s.linear_x, s.angular_z, s.duration_s
                    ),
                ));
            }
            if s.duration_s > 0.0 && (s.linear_x != 0.0 || s.angular_z != 0.0) {
                transitions.push(Transition {
                    episode: i,
                    step: s.step,
                    before: w[0].pose,
                    after: w[1].pose,
                    linear: s.linear_x,
                    angular: s.angular_z,
                    duration: s.duration_s,
                });
            }
        }
    }
    if transitions.len() < MIN_STEPS {
        return Err(ParityError::TooFew {
            reason: format!(
                "{} moving steps in {} episodes: identification needs at least {MIN_STEPS}",
                transitions.len(),
                episodes.len()
            ),
        });
    }
    Ok(transitions)
}

fn twin_for(
    episode: &RecordedEpisode,
    profile: TwinProfile,
    resolution: Resolution,
) -> Result<SimTwin, ParityError> {
    let mut config = TwinConfig::builtin(&episode.info.world).map_err(|e| ParityError::Twin {
        path: episode.path.clone(),
        reason: e.to_string(),
    })?;
    config.resolution = Some(resolution);
    config.profile = profile;
    config.start = planar(&episode.steps[0].pose);
    SimTwin::new(config).map_err(|e| ParityError::Twin {
        path: episode.path.clone(),
        reason: e.to_string(),
    })
}

/// The one-step motion error of `profile`'s motion over `transitions`.
struct MotionFit<'a> {
    transitions: &'a [Transition],
    /// Each episode's file (for errors).
    paths: Vec<std::path::PathBuf>,
    base: TwinProfile,
    /// One twin per episode (only physics is used).
    twins: RefCell<Vec<SimTwin>>,
}

impl MotionFit<'_> {
    fn profile(&self, p: &[f64]) -> TwinProfile {
        let mut profile = self.base;
        profile.motion.linear_gain = p[0] as f32;
        profile.motion.angular_gain = p[1] as f32;
        profile
    }

    /// Mean squared error (m²) and mean position error (m) of `profile`;
    /// the first step the twin refuses (a pose outside the enclosure, …).
    fn errors(&self, profile: &TwinProfile) -> Result<(f64, f64), ParityError> {
        let mut twins = self.twins.borrow_mut();
        for twin in twins.iter_mut() {
            twin.physics_mut().set_profile(profile.motion);
        }
        let (mut sq, mut dist) = (0.0, 0.0);
        for t in self.transitions {
            let twin = &mut twins[t.episode];
            twin.teleport(planar(&t.before))
                .and_then(|()| twin.execute(t.linear, t.angular, t.duration).map(drop))
                .map_err(|e| ParityError::Twin {
                    path: self.paths[t.episode].clone(),
                    reason: format!("step {}: {e}", t.step),
                })?;
            let p = twin.ground_truth();
            let d =
                (f64::from(p.position[0]) - t.after.x).hypot(f64::from(p.position[1]) - t.after.y);
            let yaw = yaw_error(f64::from(p.yaw), t.after.yaw) * YAW_WEIGHT_M;
            sq += d * d + yaw * yaw;
            dist += d;
        }
        let n = self.transitions.len() as f64;
        Ok((sq / n, dist / n))
    }
}

impl Fit for MotionFit<'_> {
    fn profile(&self, p: &[f64]) -> TwinProfile {
        self.profile(p)
    }

    fn score(&self, profile: &TwinProfile) -> f64 {
        self.errors(profile).map_or(OUT_OF_RANGE, |(sq, _)| sq)
    }
}

/// One of the fits: a candidate's parameters as a profile, and its cost.
trait Fit {
    fn profile(&self, p: &[f64]) -> TwinProfile;
    fn score(&self, profile: &TwinProfile) -> f64;
}

/// A [`Fit`] as argmin's cost function: a candidate outside the profile's
/// valid ranges costs [`OUT_OF_RANGE`].
struct Scored<'a, F>(&'a F);

impl<F: Fit> CostFunction for Scored<'_, F> {
    type Param = Vec<f64>;
    type Output = f64;

    fn cost(&self, p: &Self::Param) -> Result<f64, ArgminError> {
        let profile = self.0.profile(p);
        if profile.validate().is_err() {
            return Ok(OUT_OF_RANGE);
        }
        Ok(self.0.score(&profile))
    }
}

/// A recorded depth image at a recorded pose.
struct DepthView<'a> {
    episode: &'a RecordedEpisode,
    pose: Pose2D,
    metres: &'a [f32],
    resolution: Resolution,
}

/// The depth error of `profile`'s camera at recorded poses.
struct CameraFit<'a> {
    views: Vec<DepthView<'a>>,
    base: TwinProfile,
}

impl CameraFit<'_> {
    fn profile(&self, p: &[f64]) -> TwinProfile {
        let mut profile = self.base;
        profile.camera.height_offset_m = p[0] as f32;
        profile.camera.pitch_deg = p[1] as f32;
        profile.camera.yaw_deg = p[2] as f32;
        profile
    }

    /// Renders every view with `profile` (noise-free) and hands each
    /// (twin, robot) depth pair to `each`.
    fn render(
        &self,
        profile: &TwinProfile,
        mut each: impl FnMut(&[f32], &[f32]),
    ) -> Result<(), ParityError> {
        let mut clean = *profile;
        clean.depth.noise = 0.0;
        clean.depth.dropout = 0.0;
        let mut twin: Option<(usize, SimTwin)> = None;
        for view in &self.views {
            let key = view.episode as *const RecordedEpisode as usize;
            if twin.as_ref().map(|(k, _)| *k) != Some(key) {
                twin = Some((key, twin_for(view.episode, clean, view.resolution)?));
            }
            let Some((_, t)) = twin.as_mut() else {
                continue;
            };
            t.teleport(planar(&view.pose))
                .map_err(|e| ParityError::Twin {
                    path: view.episode.path.clone(),
                    reason: e.to_string(),
                })?;
            each(&t.render().depth, view.metres);
        }
        Ok(())
    }

    fn cost_of(&self, profile: &TwinProfile) -> f64 {
        let (mut sum, mut n) = (0.0f64, 0usize);
        let rendered = self.render(profile, |twin, robot| {
            for (&t, &r) in twin.iter().zip(robot) {
                sum += match (t.is_finite(), r.is_finite()) {
                    (true, true) => f64::from((t - r).abs()),
                    (true, false) | (false, true) => VALIDITY_MISS_M,
                    (false, false) => 0.0,
                };
                n += 1;
            }
        });
        if rendered.is_err() || n == 0 {
            return OUT_OF_RANGE;
        }
        sum / n as f64
    }

    /// Dropout (share of the twin's valid pixels the camera lost) and
    /// noise (robust spread of the relative residual) at `profile`.
    fn depth_noise(&self, profile: &TwinProfile) -> Result<(f32, f32), ParityError> {
        let (mut twin_valid, mut lost) = (0usize, 0usize);
        let mut residuals = Vec::new();
        self.render(profile, |twin, robot| {
            for (&t, &r) in twin.iter().zip(robot) {
                if !t.is_finite() {
                    continue;
                }
                twin_valid += 1;
                if r.is_finite() {
                    residuals.push(f64::from((r - t) / t).abs());
                } else {
                    lost += 1;
                }
            }
        })?;
        let dropout = if twin_valid == 0 {
            0.0
        } else {
            lost as f64 / twin_valid as f64
        };
        residuals.sort_by(f64::total_cmp);
        // The median absolute deviation of a normal is 0.6745 σ.
        let noise = residuals
            .get(residuals.len() / 2)
            .map_or(0.0, |mad| mad / 0.674_489_75);
        Ok((dropout as f32, noise as f32))
    }
}

impl Fit for CameraFit<'_> {
    fn profile(&self, p: &[f64]) -> TwinProfile {
        self.profile(p)
    }

    fn score(&self, profile: &TwinProfile) -> f64 {
        self.cost_of(profile)
    }
}

/// Nelder–Mead from `start` with a first simplex of `steps` along each axis.
fn minimise<C>(
    problem: C,
    start: Vec<f64>,
    steps: &[f64],
    max_iters: u64,
) -> Result<(Vec<f64>, u64), ParityError>
where
    C: CostFunction<Param = Vec<f64>, Output = f64>,
{
    let mut simplex = vec![start.clone()];
    for (i, step) in steps.iter().enumerate() {
        let mut vertex = start.clone();
        vertex[i] += step;
        simplex.push(vertex);
    }
    let solver = NelderMead::new(simplex)
        .with_sd_tolerance(1e-12)
        .map_err(|e| ParityError::Fit(e.to_string()))?;
    let result = Executor::new(problem, solver)
        .configure(|state| state.max_iters(max_iters))
        .run()
        .map_err(|e| ParityError::Fit(e.to_string()))?;
    let state = result.state();
    let best = state
        .get_best_param()
        .cloned()
        .ok_or_else(|| ParityError::Fit("the optimiser found no parameters".into()))?;
    Ok((best, state.get_iter()))
}

/// Fits a profile to `episodes`, starting from `start`.
pub fn identify(
    episodes: &[RecordedEpisode],
    start: &TwinProfile,
    options: &IdentifyOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<Identified, ParityError> {
    let transitions = check(episodes)?;
    let world =
        offworld_runtime::world::WorldSpec::builtin(&episodes[0].info.world).map_err(|e| {
            ParityError::Twin {
                path: episodes[0].path.clone(),
                reason: e.to_string(),
            }
        })?;
    let (timed, timing, timing_iters) = match TimingData::from_episodes(episodes, &world.robot) {
        None => {
            progress(&format!(
                "timing: no odometry time series (fewer than {} samples per moving step): \
                 latency {} s and settle time kept from the starting profile",
                crate::timing::MIN_SAMPLES_PER_STEP,
                start.motion.latency_s
            ));
            (*start, None, 0)
        }
        Some(data) => {
            let fit = TimingFit {
                data: &data,
                base: *start,
            };
            let nominal_settle = world.robot.max_linear_speed / world.robot.max_linear_accel;
            let settle = start.motion.settle_time_s.unwrap_or(nominal_settle);
            let before = data.cost(start).sqrt();
            let (best, iters) = minimise(
                Scored(&fit),
                vec![f64::from(start.motion.latency_s), f64::from(settle)],
                &[0.05, 0.2],
                options.max_iters,
            )?;
            let fitted = fit.profile(&best);
            let after = data.cost(&fitted).sqrt();
            progress(&format!(
                "timing: {} odometry samples over {} moving steps: latency {:.3} s, settle time {:.3} s; \
                 speed error {:.3} → {:.3} m/s",
                data.samples(),
                data.moving_steps(),
                fitted.motion.latency_s,
                fitted.motion.settle_time_s.unwrap_or(nominal_settle),
                before,
                after
            ));
            let summary = TimingFitted {
                samples: data.samples(),
                speed_error_before: before,
                speed_error_after: after,
            };
            (fitted, Some(summary), iters)
        }
    };
    let motion = MotionFit {
        transitions: &transitions,
        paths: episodes.iter().map(|e| e.path.clone()).collect(),
        base: timed,
        twins: RefCell::new(
            episodes
                .iter()
                .map(|e| twin_for(e, timed, Resolution::new(4, 3)))
                .collect::<Result<_, _>>()?,
        ),
    };
    // The starting profile must replay every step: a step the twin
    // refuses is an error naming it, not a flat cost.
    let (_, position_error_before_m) = motion.errors(start)?;
    progress(&format!(
        "motion: {} moving steps, mean one-step error {:.2} cm with the starting profile",
        transitions.len(),
        position_error_before_m * 100.0
    ));
    let m = &timed.motion;
    let (gains, motion_iters) = minimise(
        Scored(&motion),
        vec![f64::from(m.linear_gain), f64::from(m.angular_gain)],
        &[0.1, 0.1],
        options.max_iters,
    )?;
    let mut profile = motion.profile(&gains);
    let (_, position_error_after_m) = motion.errors(&profile)?;
    progress(&format!(
        "motion: linear gain {:.4}, angular gain {:.4}: mean one-step error {:.2} cm",
        profile.motion.linear_gain,
        profile.motion.angular_gain,
        position_error_after_m * 100.0
    ));

    let with_depth: Vec<DepthView<'_>> = episodes
        .iter()
        .flat_map(|e| {
            // One camera size per episode (its first depth image's): the
            // twin is built once per episode at that size.
            let size = e
                .steps
                .iter()
                .find_map(|s| s.depth.as_ref().map(|d| (d.width, d.height)));
            e.steps.iter().filter_map(move |s| {
                s.depth
                    .as_ref()
                    .filter(|d| Some((d.width, d.height)) == size)
                    .map(|d| DepthView {
                        episode: e,
                        pose: s.pose,
                        metres: &d.metres,
                        resolution: Resolution::new(d.width, d.height),
                    })
            })
        })
        .collect();
    if with_depth.is_empty() {
        return Err(ParityError::TooFew {
            reason: "no depth images: the camera cannot be fitted".into(),
        });
    }
    let stride = with_depth.len().div_ceil(options.camera_steps.max(1));
    let camera = CameraFit {
        views: with_depth.into_iter().step_by(stride.max(1)).collect(),
        base: profile,
    };
    let depth_cost_before_m = camera.cost_of(&profile);
    progress(&format!(
        "camera: {} depth images, cost {:.2} cm with the starting mount",
        camera.views.len(),
        depth_cost_before_m * 100.0
    ));
    let c = &start.camera;
    let (mount, camera_iters) = minimise(
        Scored(&camera),
        vec![
            f64::from(c.height_offset_m),
            f64::from(c.pitch_deg),
            f64::from(c.yaw_deg),
        ],
        &[0.01, 1.0, 1.0],
        options.max_iters,
    )?;
    profile = camera.profile(&mount);
    let depth_cost_after_m = camera.cost_of(&profile);
    let (dropout, noise) = camera.depth_noise(&profile)?;
    if dropout >= 0.99 {
        return Err(ParityError::TooFew {
            reason: format!(
                "the recorded depth is missing where the twin sees something at {:.1} % of pixels: \
                 a covered or failed depth camera cannot be fitted",
                dropout * 100.0
            ),
        });
    }
    profile.depth.dropout = dropout;
    // The profile's range: a larger spread is a camera the twin cannot model.
    profile.depth.noise = noise.min(0.5);
    progress(&format!(
        "camera: height {:+.4} m, pitch {:+.3}°, yaw {:+.3}°: cost {:.2} cm; depth noise {:.4}, dropout {:.4}",
        profile.camera.height_offset_m,
        profile.camera.pitch_deg,
        profile.camera.yaw_deg,
        depth_cost_after_m * 100.0,
        noise,
        dropout
    ));
    profile
        .validate()
        .map_err(|e| ParityError::Fit(e.to_string()))?;
    Ok(Identified {
        profile,
        position_error_before_m,
        position_error_after_m,
        depth_cost_before_m,
        depth_cost_after_m,
        timing,
        steps: transitions.len(),
        iterations: timing_iters + motion_iters + camera_iters,
    })
}
