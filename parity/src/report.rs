//! The gap summed up: a Markdown report of episode replays, with the
//! figures a sim-to-real paper's appendix reports.

use std::fmt::Write as _;

use offworld_sim_twin::TwinProfile;

use crate::plots::Figures;
use crate::replay::{EpisodeReplay, StepGap};

/// Summary statistics of one error over many steps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stats {
    /// Values that were measured (NaN ones are skipped).
    pub count: usize,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub median: f64,
    /// 95th percentile (nearest rank).
    pub p95: f64,
    /// Maximum.
    pub max: f64,
}

impl Stats {
    /// Over `values`, skipping NaN; all NaN when none is left.
    pub fn of(values: impl IntoIterator<Item = f64>) -> Self {
        let mut v: Vec<f64> = values.into_iter().filter(|x| !x.is_nan()).collect();
        if v.is_empty() {
            return Self {
                count: 0,
                mean: f64::NAN,
                median: f64::NAN,
                p95: f64::NAN,
                max: f64::NAN,
            };
        }
        v.sort_by(f64::total_cmp);
        let rank = |q: f64| v[((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1];
        Self {
            count: v.len(),
            mean: v.iter().sum::<f64>() / v.len() as f64,
            median: rank(0.5),
            p95: rank(0.95),
            max: v[v.len() - 1],
        }
    }
}

/// The figures over every step of `replays`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Summary {
    /// Episodes replayed.
    pub episodes: usize,
    /// Steps compared.
    pub steps: usize,
    /// Open-loop position error, m.
    pub open_loop_position_m: Stats,
    /// Open-loop position error at each episode's last step, m.
    pub final_position_m: Stats,
    /// One-step position error, m.
    pub one_step_position_m: Stats,
    /// One-step heading error, rad.
    pub one_step_yaw_rad: Stats,
    /// Depth mean absolute error at the recorded pose, m.
    pub depth_mae_m: Stats,
    /// Fraction of pixels whose validity disagrees.
    pub depth_validity_disagreement: Stats,
    /// Colour mean absolute error, 0–255.
    pub color_mae: Stats,
    /// Fraction of steps whose reward agrees.
    pub reward_agreement: f64,
    /// Fraction of steps whose termination agrees.
    pub termination_agreement: f64,
}

fn all_steps(replays: &[EpisodeReplay]) -> impl Iterator<Item = &StepGap> + Clone {
    replays.iter().flat_map(|r| r.steps.iter())
}

impl Summary {
    /// Sums `replays` up.
    pub fn of(replays: &[EpisodeReplay]) -> Self {
        let steps = all_steps(replays);
        let n = steps.clone().count();
        let share = |agree: usize| {
            if n == 0 {
                f64::NAN
            } else {
                agree as f64 / n as f64
            }
        };
        Self {
            episodes: replays.len(),
            steps: n,
            open_loop_position_m: Stats::of(steps.clone().map(|s| s.open_loop_position_m)),
            final_position_m: Stats::of(
                replays
                    .iter()
                    .filter_map(|r| r.steps.last().map(|s| s.open_loop_position_m)),
            ),
            one_step_position_m: Stats::of(steps.clone().map(|s| s.one_step_position_m)),
            one_step_yaw_rad: Stats::of(steps.clone().map(|s| s.one_step_yaw_rad)),
            depth_mae_m: Stats::of(steps.clone().map(|s| s.depth_mae_m)),
            depth_validity_disagreement: Stats::of(
                steps.clone().map(|s| s.depth_validity_disagreement),
            ),
            color_mae: Stats::of(steps.clone().map(|s| s.color_mae)),
            reward_agreement: share(steps.clone().filter(|s| s.reward.0 == s.reward.1).count()),
            termination_agreement: share(
                steps.filter(|s| s.terminated.0 == s.terminated.1).count(),
            ),
        }
    }
}

fn cm(m: f64) -> String {
    if m.is_nan() {
        "–".into()
    } else {
        format!("{:.2}", m * 100.0)
    }
}

fn deg(rad: f64) -> String {
    if rad.is_nan() {
        "–".into()
    } else {
        format!("{:.2}", rad.to_degrees())
    }
}

fn num(x: f64, digits: usize) -> String {
    if x.is_nan() {
        "–".into()
    } else {
        format!("{x:.digits$}")
    }
}

fn pct(x: f64) -> String {
    if x.is_nan() {
        "–".into()
    } else {
        format!("{:.1} %", x * 100.0)
    }
}

/// A link target as Markdown reads it (`<…>` around one with spaces).
fn href(link: &str) -> String {
    if link.contains([' ', '(', ')']) {
        format!("<{link}>")
    } else {
        link.to_owned()
    }
}

fn stats_row(out: &mut String, what: &str, s: &Stats, fmt: fn(f64) -> String) {
    let _ = writeln!(
        out,
        "| {what} | {} | {} | {} | {} | {} |",
        fmt(s.mean),
        fmt(s.median),
        fmt(s.p95),
        fmt(s.max),
        s.count
    );
}

/// The report: what was replayed with which profile, the summary table,
/// one row per episode and the worst steps.
pub fn markdown(replays: &[EpisodeReplay], profile: &TwinProfile, profile_name: &str) -> String {
    markdown_with_figures(replays, profile, profile_name, None)
}

/// [`markdown`], linking the PNG figures of [`crate::plots::write`] where
/// they belong: the map and the errors over the steps under the summary,
/// each episode's map in its row, and a section of depth images of the
/// worst depth steps.
pub fn markdown_with_figures(
    replays: &[EpisodeReplay],
    profile: &TwinProfile,
    profile_name: &str,
    figures: Option<&Figures>,
) -> String {
    let summary = Summary::of(replays);
    let mut out = String::new();
    let _ = writeln!(out, "# Sim↔real parity\n");
    let _ = writeln!(
        out,
        "{} episodes, {} steps, replayed in the twin with the profile {profile_name} \
         (linear gain {}, angular gain {}, latency {} s, settle time {}, camera height {:+} m, \
         pitch {:+}°, yaw {:+}°, depth noise {}, dropout {}).\n",
        summary.episodes,
        summary.steps,
        profile.motion.linear_gain,
        profile.motion.angular_gain,
        profile.motion.latency_s,
        profile
            .motion
            .settle_time_s
            .map_or_else(|| "the world robot's".to_owned(), |t| format!("{t} s")),
        profile.camera.height_offset_m,
        profile.camera.pitch_deg,
        profile.camera.yaw_deg,
        profile.depth.noise,
        profile.depth.dropout,
    );
    let _ = writeln!(
        out,
        "Open loop: one twin runs each episode's commands from its first pose. \
         One step: each step starts from the recorded pose before it (the motion \
         model's error alone); images are rendered at the recorded pose (the \
         sensor model's error alone).\n"
    );
    let _ = writeln!(out, "| error | mean | median | p95 | max | steps |");
    let _ = writeln!(out, "|---|---:|---:|---:|---:|---:|");
    stats_row(
        &mut out,
        "open-loop position, cm",
        &summary.open_loop_position_m,
        cm,
    );
    stats_row(
        &mut out,
        "open-loop position at the episode's end, cm",
        &summary.final_position_m,
        cm,
    );
    stats_row(
        &mut out,
        "one-step position, cm",
        &summary.one_step_position_m,
        cm,
    );
    stats_row(
        &mut out,
        "one-step heading, °",
        &summary.one_step_yaw_rad,
        deg,
    );
    stats_row(&mut out, "depth MAE, cm", &summary.depth_mae_m, cm);
    stats_row(
        &mut out,
        "depth validity disagreement, %",
        &summary.depth_validity_disagreement,
        |x| num(x * 100.0, 2),
    );
    stats_row(&mut out, "colour MAE, 0–255", &summary.color_mae, |x| {
        num(x, 1)
    });
    let _ = writeln!(
        out,
        "\nReward agrees at {} of steps, termination at {}.\n",
        pct(summary.reward_agreement),
        pct(summary.termination_agreement)
    );
    if let Some(f) = figures.and_then(|f| f.trajectories.as_ref()) {
        let _ = writeln!(
            out,
            "![Trajectories over the enclosure map: recorded (solid blue) and the \
             open-loop twin (dashed orange)]({})\n",
            href(&f.link)
        );
    }
    if let Some(f) = figures.and_then(|f| f.errors.as_ref()) {
        let _ = writeln!(
            out,
            "![Position, heading and depth error over the steps, open loop and one step]({})\n",
            href(&f.link)
        );
    }
    resets(&mut out, replays);
    let maps = figures.map(|f| f.episode_trajectories.as_slice());
    let _ = writeln!(out, "## Episodes\n");
    let _ = writeln!(
        out,
        "| file | env | embodiment | steps | open-loop end, cm | one-step mean, cm | depth MAE, cm | reward agrees |{}",
        if maps.is_some() { " map |" } else { "" }
    );
    let _ = writeln!(
        out,
        "|---|---|---|---:|---:|---:|---:|---:|{}",
        if maps.is_some() { "---|" } else { "" }
    );
    for (i, r) in replays.iter().enumerate() {
        let s = Summary::of(std::slice::from_ref(r));
        let map = match maps {
            Some(maps) => maps.get(i).map_or_else(
                || " – |".to_owned(),
                |f| format!(" [map]({}) |", href(&f.link)),
            ),
            None => String::new(),
        };
        let _ = writeln!(
            out,
            "| {} | {} | {} | {} | {} | {} | {} | {} |{map}",
            r.path.file_name().map_or_else(
                || r.path.display().to_string(),
                |n| n.to_string_lossy().into_owned()
            ),
            r.env_id,
            r.embodiment,
            s.steps,
            cm(s.final_position_m.mean),
            cm(s.one_step_position_m.mean),
            cm(s.depth_mae_m.mean),
            pct(s.reward_agreement),
        );
    }
    let mut worst: Vec<(&EpisodeReplay, &StepGap)> = replays
        .iter()
        .flat_map(|r| r.steps.iter().map(move |s| (r, s)))
        .collect();
    worst.sort_by(|a, b| b.1.one_step_position_m.total_cmp(&a.1.one_step_position_m));
    let _ = writeln!(out, "\n## Worst steps (one-step position)\n");
    let _ = writeln!(
        out,
        "| file | step | t, s | recorded x, y, yaw | one-step, cm | heading, ° | depth MAE, cm |"
    );
    let _ = writeln!(out, "|---|---:|---:|---|---:|---:|---:|");
    for (r, s) in worst.into_iter().take(5) {
        let _ = writeln!(
            out,
            "| {} | {} | {:.2} | {:.3}, {:.3}, {:.1}° | {} | {} | {} |",
            r.path
                .file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
            s.step,
            s.time_s,
            s.recorded.x,
            s.recorded.y,
            s.recorded.yaw.to_degrees(),
            cm(s.one_step_position_m),
            deg(s.one_step_yaw_rad),
            cm(s.depth_mae_m),
        );
    }
    if let Some(figures) = figures {
        depth_section(&mut out, figures);
    }
    out
}

/// The worst depth steps, each with its recorded | twin | error image.
fn depth_section(out: &mut String, figures: &Figures) {
    let _ = writeln!(out, "\n## Depth error, worst steps\n");
    if figures.depth.is_empty() {
        let _ = writeln!(
            out,
            "No step has a depth error measured (no depth recorded at the twin's \
             resolution, or no pixel valid in both images)."
        );
        return;
    }
    let _ = writeln!(
        out,
        "The steps with the largest depth MAE: the recorded depth, the twin's \
         at the recorded pose, and |twin − robot| (grey: no return; blue: \
         valid in one image only).\n"
    );
    let _ = writeln!(
        out,
        "| rank | file | step | depth MAE, cm | validity disagreement | one-step, cm | image |"
    );
    let _ = writeln!(out, "|---:|---|---:|---:|---:|---:|---|");
    for (rank, d) in figures.depth.iter().enumerate() {
        let _ = writeln!(
            out,
            "| {} | {} | {} | {} | {} | {} | [depth]({}) |",
            rank + 1,
            d.file
                .file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
            d.gap.step,
            cm(d.gap.depth_mae_m),
            pct(d.gap.depth_validity_disagreement),
            cm(d.gap.one_step_position_m),
            href(&d.figure.link),
        );
    }
    for (rank, d) in figures.depth.iter().enumerate() {
        let _ = writeln!(
            out,
            "\n![Depth, worst step {}: recorded, twin, |error|]({})",
            rank + 1,
            href(&d.figure.link)
        );
    }
}

/// The resets' accuracy: where each episode was asked to start and where
/// it started, and how long its reset took.
fn resets(out: &mut String, replays: &[EpisodeReplay]) {
    if replays.is_empty() {
        return;
    }
    let position = Stats::of(replays.iter().map(|r| r.reset.position_error_m()));
    let heading = Stats::of(replays.iter().map(|r| r.reset.yaw_error_rad()));
    let duration = Stats::of(replays.iter().filter_map(|r| r.reset.duration_s));
    let _ = writeln!(out, "## Resets\n");
    let _ = writeln!(
        out,
        "How far each reset left the robot from the start pose it asked for \
         (a twin teleports: near zero; a robot drives there).\n"
    );
    let _ = writeln!(out, "| error | mean | median | p95 | max | episodes |");
    let _ = writeln!(out, "|---|---:|---:|---:|---:|---:|");
    stats_row(out, "position, cm", &position, cm);
    stats_row(out, "heading, °", &heading, deg);
    stats_row(out, "duration, s", &duration, |x| num(x, 2));
    let _ = writeln!(
        out,
        "\n| file | requested x, y, yaw | achieved x, y, yaw | position, cm | heading, ° | took, s |"
    );
    let _ = writeln!(out, "|---|---|---|---:|---:|---:|");
    for r in replays {
        let (q, a) = (r.reset.requested, r.reset.achieved);
        // Headings as (−180°, 180°]: a requested 247° is the achieved −113°.
        let wrap = |yaw: f64| {
            std::f64::consts::PI - (std::f64::consts::PI - yaw).rem_euclid(std::f64::consts::TAU)
        };
        let _ = writeln!(
            out,
            "| {} | {:.3}, {:.3}, {:.1}° | {:.3}, {:.3}, {:.1}° | {} | {} | {} |",
            r.path
                .file_name()
                .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
            q.x,
            q.y,
            wrap(q.yaw).to_degrees(),
            a.x,
            a.y,
            wrap(a.yaw).to_degrees(),
            cm(r.reset.position_error_m()),
            deg(r.reset.yaw_error_rad()),
            r.reset
                .duration_s
                .map_or_else(|| "–".to_owned(), |d| num(d, 2)),
        );
    }
    let _ = writeln!(out);
}
