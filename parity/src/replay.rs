//! A recorded episode replayed in the twin: the same world, the twin at the
//! episode's first pose, the recorded commands with their durations; the
//! gap measured at every step.
//!
//! Two twins replay each episode, because the gap has two parts a
//! researcher wants apart:
//! - **open loop**: one twin runs the whole command sequence from the first
//!   pose, as a policy trained in sim would experience it (errors
//!   accumulate);
//! - **one step**: a second twin starts each step from the recorded pose
//!   before it, so each step's error is the motion model's alone; its
//!   camera renders at the recorded pose, so image errors are the sensor
//!   model's alone.

use offworld_env_controller::episode::judge;
use offworld_env_controller::Task;
use offworld_runtime::msg::Pose2D;
use offworld_runtime::Resolution;
use offworld_sim_twin::camera::RgbdFrame;
use offworld_sim_twin::{PlanarPose, SimTwin, TwinConfig, TwinProfile};

use crate::recorded::{ColorImage, DepthImage, RecordedEpisode, RecordedStep, ResetRecord};
use crate::ParityError;

/// The gap at one step (after its command).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepGap {
    /// The step's index (1 = the first command).
    pub step: u32,
    /// Recorded seconds into the episode (from the reset's frame).
    pub time_s: f64,
    /// Where the robot was (recorded) and where each twin put it.
    pub recorded: Pose2D,
    /// The open-loop twin's pose.
    pub open_loop: Pose2D,
    /// The open-loop twin's planar distance from the recorded pose, m.
    pub open_loop_position_m: f64,
    /// Its absolute heading error, rad.
    pub open_loop_yaw_rad: f64,
    /// The one-step twin's planar distance from the recorded pose, m.
    pub one_step_position_m: f64,
    /// Its absolute heading error, rad.
    pub one_step_yaw_rad: f64,
    /// Depth at the recorded pose: mean |twin − robot| over pixels valid
    /// in both, m (NaN when no image or no pixel valid in both).
    pub depth_mae_m: f64,
    /// Fraction of pixels valid in one image and not the other.
    pub depth_validity_disagreement: f64,
    /// Colour at the recorded pose: mean |twin − robot| per channel, 0–255.
    pub color_mae: f64,
    /// The recorded reward and the open-loop twin's, judged by the task.
    pub reward: (f64, f64),
    /// The recorded termination and the open-loop twin's.
    pub terminated: (bool, bool),
}

/// An episode's replay.
#[derive(Debug, Clone)]
pub struct EpisodeReplay {
    /// The episode file.
    pub path: std::path::PathBuf,
    /// Its env, task and world.
    pub env_id: String,
    /// Task name.
    pub task: String,
    /// World name.
    pub world: String,
    /// `robot` or `twin`: what recorded it.
    pub embodiment: String,
    /// The pose the episode started from (recorded; both twins start there).
    pub start: Pose2D,
    /// How well its reset placed the robot.
    pub reset: ResetRecord,
    /// The gap after each command.
    pub steps: Vec<StepGap>,
}

fn planar(p: &Pose2D) -> PlanarPose {
    PlanarPose {
        x: p.x as f32,
        y: p.y as f32,
        yaw: p.yaw as f32,
    }
}

fn pose_of(twin: &SimTwin) -> Pose2D {
    let p = twin.ground_truth();
    Pose2D {
        x: f64::from(p.position[0]),
        y: f64::from(p.position[1]),
        yaw: f64::from(p.yaw),
    }
}

/// Absolute heading difference wrapped to [0, π].
pub fn yaw_error(a: f64, b: f64) -> f64 {
    let turn = (a - b).rem_euclid(std::f64::consts::TAU);
    turn.min(std::f64::consts::TAU - turn)
}

fn position_error(a: &Pose2D, b: &Pose2D) -> f64 {
    (a.x - b.x).hypot(a.y - b.y)
}

/// Mean |twin − robot| over pixels valid in both, and the fraction where
/// validity disagrees.
pub fn depth_gap(twin: &[f32], robot: &[f32]) -> (f64, f64) {
    let (mut sum, mut both, mut disagree) = (0.0f64, 0usize, 0usize);
    for (&t, &r) in twin.iter().zip(robot) {
        match (t.is_finite(), r.is_finite()) {
            (true, true) => {
                sum += f64::from((t - r).abs());
                both += 1;
            }
            (true, false) | (false, true) => disagree += 1,
            (false, false) => {}
        }
    }
    let n = twin.len().min(robot.len()).max(1);
    let mae = if both == 0 {
        f64::NAN
    } else {
        sum / both as f64
    };
    (mae, disagree as f64 / n as f64)
}

/// Mean absolute difference per channel, 0–255.
pub fn color_gap(twin: &[u8], robot: &[u8]) -> f64 {
    let n = twin.len().min(robot.len());
    if n == 0 {
        return f64::NAN;
    }
    let sum: u64 = twin
        .iter()
        .zip(robot)
        .map(|(&a, &b)| u64::from(a.abs_diff(b)))
        .sum();
    sum as f64 / n as f64
}

/// The image size the episode's camera recorded (depth first, else colour).
fn resolution(episode: &RecordedEpisode) -> Option<Resolution> {
    episode.steps.iter().find_map(|s| {
        s.depth
            .as_ref()
            .map(|d: &DepthImage| Resolution::new(d.width, d.height))
            .or_else(|| {
                s.color
                    .as_ref()
                    .map(|c: &ColorImage| Resolution::new(c.width, c.height))
            })
    })
}

/// Replays `episode` in twins built with `profile`.
pub fn replay(
    episode: &RecordedEpisode,
    profile: &TwinProfile,
) -> Result<EpisodeReplay, ParityError> {
    replay_with(episode, profile, |_, _, _| {})
}

/// [`replay`], handing each step to `visit` as it is replayed: the recorded
/// step, the one-step twin's frame at the recorded pose, and the gap.
pub fn replay_with(
    episode: &RecordedEpisode,
    profile: &TwinProfile,
    mut visit: impl FnMut(&RecordedStep, &RgbdFrame, &StepGap),
) -> Result<EpisodeReplay, ParityError> {
    let path = &episode.path;
    let twin_error = |e: offworld_sim_twin::SimError| ParityError::Twin {
        path: path.clone(),
        reason: e.to_string(),
    };
    let info = &episode.info;
    let task = Task::by_name(&info.task).map_err(|e| ParityError::Unusable {
        path: path.clone(),
        reason: format!("task {:?}: {e}", info.task),
    })?;
    if task.world.name != info.world {
        return Err(ParityError::Unusable {
            path: path.clone(),
            reason: format!(
                "recorded in world {:?}, but its task {} runs in {:?}",
                info.world, info.task, task.world.name
            ),
        });
    }
    let mut config = TwinConfig::builtin(&info.world).map_err(twin_error)?;
    config.resolution = resolution(episode);
    config.profile = *profile;
    let start = episode.steps[0].pose;
    config.start = planar(&start);
    let mut open_loop = SimTwin::new(config.clone()).map_err(twin_error)?;
    let mut one_step = SimTwin::new(config).map_err(twin_error)?;
    open_loop.teleport(planar(&start)).map_err(twin_error)?;
    let t0 = episode.steps[0].step.header.stamp;
    let t0 = f64::from(t0.sec) + f64::from(t0.nanosec) * 1e-9;
    let mut steps = Vec::with_capacity(episode.steps.len());
    for pair in episode.steps.windows(2) {
        let (before, after) = (&pair[0], &pair[1]);
        let s = &after.step;
        open_loop
            .execute(s.linear_x, s.angular_z, s.duration_s)
            .map_err(twin_error)?;
        one_step
            .teleport(planar(&before.pose))
            .map_err(twin_error)?;
        one_step
            .execute(s.linear_x, s.angular_z, s.duration_s)
            .map_err(twin_error)?;
        let twin_pose = pose_of(&open_loop);
        let step_pose = pose_of(&one_step);
        // The sensor model alone: render where the robot was.
        one_step.teleport(planar(&after.pose)).map_err(twin_error)?;
        let frame = one_step.render();
        // Compared pixel for pixel only at the twin's size (the recorded
        // depth's): another size (a colour camera of its own) is not measured.
        let same_size = |w: u32, h: u32| (w, h) == (frame.width, frame.height);
        let (depth_mae_m, depth_validity_disagreement) = match &after.depth {
            Some(d) if same_size(d.width, d.height) => depth_gap(&frame.depth, &d.metres),
            _ => (f64::NAN, f64::NAN),
        };
        let color_mae = match &after.color {
            Some(c) if same_size(c.width, c.height) => color_gap(&frame.rgb, &c.rgb),
            _ => f64::NAN,
        };
        let judged = judge(&task, twin_pose.x, twin_pose.y, s.step);
        let stamp = f64::from(s.header.stamp.sec) + f64::from(s.header.stamp.nanosec) * 1e-9;
        let gap = StepGap {
            step: s.step,
            time_s: stamp - t0,
            recorded: after.pose,
            open_loop: twin_pose,
            open_loop_position_m: position_error(&twin_pose, &after.pose),
            open_loop_yaw_rad: yaw_error(twin_pose.yaw, after.pose.yaw),
            one_step_position_m: position_error(&step_pose, &after.pose),
            one_step_yaw_rad: yaw_error(step_pose.yaw, after.pose.yaw),
            depth_mae_m,
            depth_validity_disagreement,
            color_mae,
            reward: (s.reward, judged.reward),
            terminated: (s.terminated, judged.terminated),
        };
        visit(after, frame, &gap);
        steps.push(gap);
    }
    Ok(EpisodeReplay {
        path: path.clone(),
        env_id: info.env_id.clone(),
        task: info.task.clone(),
        world: info.world.clone(),
        embodiment: info.embodiment.clone(),
        start,
        reset: episode.reset,
        steps,
    })
}
