//! The replay as PNG figures for a paper's appendix (`parity replay
//! --plots DIR`), linked from the Markdown report:
//!
//! ```text
//! trajectories.png        every episode over the enclosure map: recorded (solid)
//!                         and the open-loop twin (dashed), walls, monolith and its
//!                         success radius, boulders, task boundary, start markers
//! trajectory-NNN.png      one episode (NNN: its index in the report), zoomed on
//!                         its trajectories
//! pose-error.png          position (cm) and heading (°) error over the steps, open
//!                         loop and one step; depth MAE (cm) and validity
//!                         disagreement (%): per episode, and their mean per step
//! depth-error-K.png       the K-th worst step by depth MAE: recorded depth | twin
//!                         depth at the recorded pose | |twin − robot|, colour scales in m
//! ```
//!
//! Drawn with plotters' bitmap backend into memory and encoded with `png`:
//! no system font or image library; text uses a font compiled in
//! (`parity/fonts/`, a subset of DejaVu Sans). The same replay gives
//! byte-identical files.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use offworld_runtime::world::WorldSpec;
use offworld_sim_twin::camera::RgbdFrame;
use plotters::coord::Shift;
use plotters::element::DashedPathElement;
use plotters::prelude::*;
use plotters::style::colors::colormaps::ViridisRGB;
use plotters::style::text_anchor::{HPos, Pos, VPos};

use crate::recorded::RecordedStep;
use crate::replay::{EpisodeReplay, StepGap};
use crate::report::Stats;
use crate::ParityError;

/// How many of the worst depth steps get an image.
pub const WORST_DEPTH_STEPS: usize = 5;
/// The map figures' size, px.
pub const MAP_SIZE: (u32, u32) = (960, 680);
/// The error-over-steps figure's size, px.
pub const ERROR_SIZE: (u32, u32) = (1100, 900);
/// A depth comparison figure's size, px.
pub const DEPTH_SIZE: (u32, u32) = (1260, 500);

/// The family name the compiled-in font is registered under.
const FONT: &str = "parity-sans";
static FONT_BYTES: &[u8] = include_bytes!("../fonts/ParityPlotSans.ttf");

const RECORDED: RGBColor = RGBColor(31, 119, 180);
const TWIN: RGBColor = RGBColor(255, 127, 14);
const ONE_STEP: RGBColor = RGBColor(44, 160, 44);
const DEPTH: RGBColor = RGBColor(148, 103, 189);
const WALL: RGBColor = RGBColor(120, 120, 120);
const BOULDER: RGBColor = RGBColor(166, 118, 76);
const NO_RETURN: RGBColor = RGBColor(200, 200, 200);
const ONE_ONLY: RGBColor = RGBColor(90, 200, 255);

/// A step kept for its depth images: the recorded depth and the twin's at
/// the recorded pose.
#[derive(Debug, Clone)]
pub struct KeptDepth {
    /// The episode's index in the replay (the report's order).
    pub episode: usize,
    /// The episode file.
    pub file: PathBuf,
    /// The step's gap.
    pub gap: StepGap,
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// The recorded depth, m (NaN: no return).
    pub recorded: Vec<f32>,
    /// The twin's depth at the recorded pose, m.
    pub twin: Vec<f32>,
}

/// The worst steps by depth MAE, kept while replaying (hand each step of
/// `replay_with` to [`WorstDepth::visit`]); only their images are copied.
#[derive(Debug, Clone)]
pub struct WorstDepth {
    capacity: usize,
    kept: Vec<KeptDepth>,
}

impl Default for WorstDepth {
    fn default() -> Self {
        Self::new(WORST_DEPTH_STEPS)
    }
}

impl WorstDepth {
    /// Keeps the `capacity` worst steps.
    pub fn new(capacity: usize) -> Self {
        Self {
            capacity,
            kept: Vec::with_capacity(capacity + 1),
        }
    }

    /// Looks at one replayed step of episode `episode` (file `file`). Steps
    /// without a measured depth error (no depth recorded, another size, no
    /// pixel valid in both) are skipped.
    pub fn visit(
        &mut self,
        episode: usize,
        file: &Path,
        recorded: &RecordedStep,
        twin: &RgbdFrame,
        gap: &StepGap,
    ) {
        let Some(depth) = &recorded.depth else {
            return;
        };
        let mae = gap.depth_mae_m;
        if !mae.is_finite()
            || self.capacity == 0
            || (depth.width, depth.height) != (twin.width, twin.height)
            || depth.metres.len() != twin.depth.len()
            || depth.metres.len() != (depth.width as usize) * (depth.height as usize)
        {
            return;
        }
        if self.kept.len() == self.capacity
            && self.kept.last().is_some_and(|w| w.gap.depth_mae_m >= mae)
        {
            return;
        }
        // Ties keep the earlier step first.
        let at = self.kept.partition_point(|k| k.gap.depth_mae_m >= mae);
        self.kept.insert(
            at,
            KeptDepth {
                episode,
                file: file.to_owned(),
                gap: *gap,
                width: depth.width,
                height: depth.height,
                recorded: depth.metres.clone(),
                twin: twin.depth.clone(),
            },
        );
        self.kept.truncate(self.capacity);
    }

    /// The kept steps, worst first.
    pub fn steps(&self) -> &[KeptDepth] {
        &self.kept
    }
}

/// One written figure.
#[derive(Debug, Clone, PartialEq)]
pub struct Figure {
    /// The file written.
    pub path: PathBuf,
    /// How the report links it (the link base joined with its name).
    pub link: String,
}

/// A depth comparison figure and the step it shows.
#[derive(Debug, Clone)]
pub struct DepthFigure {
    /// The figure.
    pub figure: Figure,
    /// The episode's index in the replay.
    pub episode: usize,
    /// The episode file.
    pub file: PathBuf,
    /// The step's gap.
    pub gap: StepGap,
}

/// Every figure of a replay.
#[derive(Debug, Clone)]
pub struct Figures {
    /// All episodes over the map (none when no episode has a step).
    pub trajectories: Option<Figure>,
    /// One per episode, in the replay's order.
    pub episode_trajectories: Vec<Figure>,
    /// Errors over the steps (none when no episode has a step).
    pub errors: Option<Figure>,
    /// The worst depth steps, worst first.
    pub depth: Vec<DepthFigure>,
}

fn output_error(path: &Path, reason: impl std::fmt::Display) -> ParityError {
    ParityError::Output {
        path: path.to_owned(),
        reason: reason.to_string(),
    }
}

fn register_font() -> Result<(), String> {
    static REGISTERED: OnceLock<Result<(), String>> = OnceLock::new();
    REGISTERED
        .get_or_init(|| {
            plotters::style::register_font(FONT, FontStyle::Normal, FONT_BYTES)
                .map_err(|_| "the compiled-in plot font is not a valid font".to_owned())
        })
        .clone()
}

/// Draws `draw` into a `size` RGB canvas and writes it as a PNG to `path`.
fn render(
    path: &Path,
    size: (u32, u32),
    draw: impl FnOnce(&DrawingArea<BitMapBackend<'_>, Shift>) -> Result<(), String>,
) -> Result<(), ParityError> {
    register_font().map_err(|e| output_error(path, e))?;
    let mut pixels = vec![255u8; size.0 as usize * size.1 as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut pixels, size).into_drawing_area();
        root.fill(&WHITE).map_err(|e| output_error(path, e))?;
        draw(&root).map_err(|e| output_error(path, e))?;
        root.present().map_err(|e| output_error(path, e))?;
    }
    let mut bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut bytes, size.0, size.1);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        // Figures are mostly flat colour: a few ms more for a third smaller.
        encoder.set_compression(png::Compression::High);
        let mut writer = encoder.write_header().map_err(|e| output_error(path, e))?;
        writer
            .write_image_data(&pixels)
            .map_err(|e| output_error(path, e))?;
        writer.finish().map_err(|e| output_error(path, e))?;
    }
    std::fs::write(path, bytes).map_err(|e| output_error(path, e))
}

/// `?` for plotters' errors inside a drawing closure.
fn e<T, E: std::fmt::Display>(r: Result<T, E>) -> Result<T, String> {
    r.map_err(|e| e.to_string())
}

fn font(size: u32) -> TextStyle<'static> {
    (FONT, size).into_font().into()
}

fn text(size: u32) -> (&'static str, u32) {
    (FONT, size)
}

fn file_name(path: &Path) -> String {
    path.file_name().map_or_else(
        || path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    )
}

/// How a Markdown file at `report` (`None`: standard output, read from
/// the current directory) reaches the directory `dir`: a relative path
/// with `/` separators where both are on one tree, else `dir` absolute.
/// Call it once `dir` exists.
pub fn link_base(report: Option<&Path>, dir: &Path) -> String {
    let from = report
        .and_then(Path::parent)
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let resolve = |p: &Path| std::fs::canonicalize(p).or_else(|_| std::path::absolute(p));
    let (Ok(from), Ok(to)) = (resolve(from), resolve(dir)) else {
        return dir.display().to_string();
    };
    let (a, b): (Vec<_>, Vec<_>) = (from.components().collect(), to.components().collect());
    let common = a.iter().zip(&b).take_while(|(x, y)| x == y).count();
    if common == 0 {
        return to.display().to_string();
    }
    let parts: Vec<String> = std::iter::repeat_n("..".to_owned(), a.len() - common)
        .chain(
            b[common..]
                .iter()
                .map(|c| c.as_os_str().to_string_lossy().into_owned()),
        )
        .collect();
    if parts.is_empty() {
        ".".to_owned()
    } else {
        parts.join("/")
    }
}

/// The world the episodes were recorded in (the first episode's), if it is
/// a built-in one.
fn world_of(replays: &[EpisodeReplay]) -> Option<WorldSpec> {
    replays
        .first()
        .and_then(|r| WorldSpec::builtin(&r.world).ok())
}

/// Writes every figure of `replays` into `dir` (created if missing); the
/// report links them as `link_base/<name>` (`link_base` empty: the name
/// alone).
pub fn write(
    dir: &Path,
    link_base: &str,
    replays: &[EpisodeReplay],
    worst: &WorstDepth,
) -> Result<Figures, ParityError> {
    std::fs::create_dir_all(dir).map_err(|e| output_error(dir, e))?;
    let figure = |name: &str| Figure {
        path: dir.join(name),
        link: if link_base.is_empty() || link_base == "." {
            name.to_owned()
        } else {
            format!("{}/{name}", link_base.trim_end_matches('/'))
        },
    };
    let world = world_of(replays);
    let with_steps = replays.iter().any(|r| !r.steps.is_empty());
    let mut figures = Figures {
        trajectories: None,
        episode_trajectories: Vec::with_capacity(replays.len()),
        errors: None,
        depth: Vec::new(),
    };
    if with_steps {
        let all = figure("trajectories.png");
        let title = format!(
            "Trajectories: {} episodes, recorded vs open-loop twin",
            replays.len()
        );
        let indexed: Vec<(usize, &EpisodeReplay)> = replays.iter().enumerate().collect();
        render(&all.path, MAP_SIZE, |root| {
            map(root, &title, world.as_ref(), &indexed, false)
        })?;
        figures.trajectories = Some(all);
    }
    for (i, r) in replays.iter().enumerate() {
        let one = figure(&format!("trajectory-{i:03}.png"));
        let title = format!(
            "Episode {i}: {} ({} steps)",
            file_name(&r.path),
            r.steps.len()
        );
        render(&one.path, MAP_SIZE, |root| {
            let world = WorldSpec::builtin(&r.world).ok();
            map(root, &title, world.as_ref(), &[(i, r)], true)
        })?;
        figures.episode_trajectories.push(one);
    }
    if with_steps {
        let errors = figure("pose-error.png");
        render(&errors.path, ERROR_SIZE, |root| error_panels(root, replays))?;
        figures.errors = Some(errors);
    }
    for (rank, kept) in worst.steps().iter().enumerate() {
        let one = figure(&format!("depth-error-{}.png", rank + 1));
        render(&one.path, DEPTH_SIZE, |root| depth_panels(root, rank, kept))?;
        figures.depth.push(DepthFigure {
            figure: one,
            episode: kept.episode,
            file: kept.file.clone(),
            gap: kept.gap,
        });
    }
    Ok(figures)
}

// ---------------------------------------------------------------- the map

/// Extends `[lo, hi]` to hold `v` (finite values only).
fn grow(range: &mut (f64, f64), v: f64) {
    if v.is_finite() {
        range.0 = range.0.min(v);
        range.1 = range.1.max(v);
    }
}

/// Ground-plane rectangle from a centre and full size.
fn rect(cx: f64, cy: f64, sx: f64, sy: f64) -> [(f64, f64); 2] {
    [
        (cx - sx / 2.0, cy - sy / 2.0),
        (cx + sx / 2.0, cy + sy / 2.0),
    ]
}

/// Splits a polyline at non-finite points.
fn finite_runs(points: impl IntoIterator<Item = (f64, f64)>) -> Vec<Vec<(f64, f64)>> {
    let mut runs = vec![Vec::new()];
    for p in points {
        if p.0.is_finite() && p.1.is_finite() {
            if let Some(run) = runs.last_mut() {
                run.push(p);
            }
        } else if runs.last().is_some_and(|r| !r.is_empty()) {
            runs.push(Vec::new());
        }
    }
    runs.retain(|r| !r.is_empty());
    runs
}

/// The smallest span, m, of a map zoomed on one episode.
const ZOOM_SPAN: f64 = 1.2;

/// Draws `episodes` over `world`'s map: the whole enclosure, or (`zoom`)
/// the region around the trajectories.
fn map(
    root: &DrawingArea<BitMapBackend<'_>, Shift>,
    title: &str,
    world: Option<&WorldSpec>,
    episodes: &[(usize, &EpisodeReplay)],
    zoom: bool,
) -> Result<(), String> {
    // What has to be visible: the walls, and every finite pose.
    let (mut xs, mut ys) = (
        (f64::INFINITY, f64::NEG_INFINITY),
        (f64::INFINITY, f64::NEG_INFINITY),
    );
    if let (Some(w), false) = (world, zoom) {
        let e = &w.enclosure;
        let t = f64::from(e.wall_thickness);
        grow(&mut xs, f64::from(e.x_min) - t);
        grow(&mut xs, f64::from(e.x_max) + t);
        grow(&mut ys, f64::from(e.y_min) - t);
        grow(&mut ys, f64::from(e.y_max) + t);
    }
    for (_, r) in episodes {
        grow(&mut xs, r.start.x);
        grow(&mut ys, r.start.y);
        for s in &r.steps {
            for p in [s.recorded, s.open_loop] {
                grow(&mut xs, p.x);
                grow(&mut ys, p.y);
            }
        }
    }
    if !xs.0.is_finite() || !ys.0.is_finite() {
        (xs, ys) = ((-1.0, 1.0), (-1.0, 1.0));
    }
    if zoom {
        // Around the trajectories, at least `ZOOM_SPAN` across.
        for range in [&mut xs, &mut ys] {
            let grow_by = (ZOOM_SPAN - (range.1 - range.0)).max(0.0) / 2.0 + 0.25;
            *range = (range.0 - grow_by, range.1 + grow_by);
        }
    }
    let pad = 0.15;
    let (mut x0, mut x1, mut y0, mut y1) = (xs.0 - pad, xs.1 + pad, ys.0 - pad, ys.1 + pad);
    // One metre is as many pixels across as up: the plot's pixel size is
    // the figure less the margins, the caption and the label areas below.
    let (margin, caption, x_labels, y_labels, legend) = (16, 40, 50, 64, 190);
    let (w, h) = root.dim_in_pixel();
    let pw = f64::from(w.saturating_sub(2 * margin + y_labels + legend).max(1));
    let ph = f64::from(h.saturating_sub(2 * margin + caption + x_labels).max(1));
    let per_px = ((x1 - x0) / pw).max((y1 - y0) / ph);
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    (x0, x1) = (cx - pw * per_px / 2.0, cx + pw * per_px / 2.0);
    (y0, y1) = (cy - ph * per_px / 2.0, cy + ph * per_px / 2.0);
    // The legend sits right of the map.
    let (plot_area, legend_area) = root.split_horizontally(w.saturating_sub(legend));
    let mut chart = e(ChartBuilder::on(&plot_area)
        .caption(title, text(22))
        .margin(margin)
        .x_label_area_size(x_labels)
        .y_label_area_size(y_labels)
        .build_cartesian_2d(x0..x1, y0..y1))?;
    e(chart
        .configure_mesh()
        .x_desc("x, m (world frame)")
        .y_desc("y, m")
        .label_style(text(15))
        .axis_desc_style(text(16))
        .max_light_lines(1)
        .light_line_style(RGBColor(240, 240, 240))
        .bold_line_style(RGBColor(215, 215, 215))
        .draw())?;
    let mut keys: Vec<(String, ShapeStyle, bool)> = Vec::new();
    if let Some(w) = world {
        let en = &w.enclosure;
        let t = f64::from(en.wall_thickness);
        let (ix0, ix1, iy0, iy1) = (
            f64::from(en.x_min),
            f64::from(en.x_max),
            f64::from(en.y_min),
            f64::from(en.y_max),
        );
        let walls = [
            [(ix0 - t, iy0 - t), (ix1 + t, iy0)],
            [(ix0 - t, iy1), (ix1 + t, iy1 + t)],
            [(ix0 - t, iy0), (ix0, iy1)],
            [(ix1, iy0), (ix1 + t, iy1)],
        ];
        e(chart.draw_series(walls.iter().map(|r| Rectangle::new(*r, WALL.filled()))))?;
        keys.push(("walls".into(), WALL.filled(), true));
        let task = &w.task;
        let boundary = [
            (f64::from(task.boundary_x[0]), f64::from(task.boundary_y[0])),
            (f64::from(task.boundary_x[1]), f64::from(task.boundary_y[0])),
            (f64::from(task.boundary_x[1]), f64::from(task.boundary_y[1])),
            (f64::from(task.boundary_x[0]), f64::from(task.boundary_y[1])),
            (f64::from(task.boundary_x[0]), f64::from(task.boundary_y[0])),
        ];
        let boundary_style = RGBColor(150, 150, 150).stroke_width(1);
        e(chart.draw_series(DashedLineSeries::new(boundary, 6, 5, boundary_style)))?;
        keys.push(("task boundary".into(), boundary_style, false));
        let boulders = w.boulders.iter().map(|b| {
            Rectangle::new(
                rect(
                    f64::from(b.center[0]),
                    f64::from(b.center[1]),
                    f64::from(b.size[0]),
                    f64::from(b.size[1]),
                ),
                BOULDER.filled(),
            )
        });
        if !w.boulders.is_empty() {
            e(chart.draw_series(boulders))?;
            keys.push(("boulders".into(), BOULDER.filled(), true));
        }
        let m = &w.monolith;
        let (mx, my) = (f64::from(m.center[0]), f64::from(m.center[1]));
        let radius = f64::from(task.success_radius);
        let circle: Vec<(f64, f64)> = (0..=96)
            .map(|k| {
                let a = f64::from(k) / 96.0 * std::f64::consts::TAU;
                (mx + radius * a.cos(), my + radius * a.sin())
            })
            .collect();
        let success_style = RGBColor(0, 150, 80).stroke_width(2);
        e(chart.draw_series(DashedLineSeries::new(circle, 4, 4, success_style)))?;
        keys.push(("success radius".into(), success_style, false));
        e(chart.draw_series(std::iter::once(Rectangle::new(
            rect(mx, my, f64::from(m.size[0]).max(0.03), f64::from(m.size[1])),
            BLACK.filled(),
        ))))?;
        keys.push(("monolith".into(), BLACK.filled(), true));
    }
    let many = episodes.len() > 1;
    let line = if many { 2 } else { 3 };
    for (_, r) in episodes {
        let recorded = std::iter::once((r.start.x, r.start.y))
            .chain(r.steps.iter().map(|s| (s.recorded.x, s.recorded.y)));
        for run in finite_runs(recorded) {
            e(chart.draw_series(LineSeries::new(run, RECORDED.stroke_width(line))))?;
        }
        let twin = std::iter::once((r.start.x, r.start.y))
            .chain(r.steps.iter().map(|s| (s.open_loop.x, s.open_loop.y)));
        for run in finite_runs(twin) {
            e(chart.draw_series(DashedLineSeries::new(run, 7, 4, TWIN.stroke_width(line))))?;
        }
        if r.start.x.is_finite() && r.start.y.is_finite() {
            // The start, and the heading it faced.
            let yaw = if r.start.yaw.is_finite() {
                r.start.yaw
            } else {
                0.0
            };
            let tip = (r.start.x + 0.18 * yaw.cos(), r.start.y + 0.18 * yaw.sin());
            e(chart.draw_series(std::iter::once(PathElement::new(
                vec![(r.start.x, r.start.y), tip],
                BLACK.stroke_width(2),
            ))))?;
            e(chart.draw_series(std::iter::once(Circle::new(
                (r.start.x, r.start.y),
                6,
                RGBColor(255, 255, 255).filled(),
            ))))?;
            e(chart.draw_series(std::iter::once(Circle::new(
                (r.start.x, r.start.y),
                6,
                BLACK.stroke_width(2),
            ))))?;
        }
        if let Some(last) = r.steps.last() {
            for (p, color) in [(last.recorded, RECORDED), (last.open_loop, TWIN)] {
                if p.x.is_finite() && p.y.is_finite() {
                    e(chart.draw_series(std::iter::once(Cross::new(
                        (p.x, p.y),
                        6,
                        color.stroke_width(3),
                    ))))?;
                }
            }
        }
    }
    if many {
        // Which episode each start is (its index in the report's table),
        // over every line.
        let labels = episodes
            .iter()
            .filter(|(_, r)| r.start.x.is_finite() && r.start.y.is_finite())
            .map(|(index, r)| {
                EmptyElement::at((r.start.x, r.start.y))
                    + Text::new(index.to_string(), (-20, -24), font(16))
            });
        e(chart.draw_series(labels))?;
    }
    // The legend, drawn by hand right of the map (plotters' own would sit
    // on the map).
    let mut rows: Vec<(String, ShapeStyle, u8)> = vec![
        ("recorded (robot)".into(), RECORDED.stroke_width(3), 0),
        ("open-loop twin".into(), TWIN.stroke_width(3), 1),
        ("start, heading".into(), BLACK.stroke_width(2), 2),
        ("end (recorded, twin)".into(), RECORDED.stroke_width(3), 3),
    ];
    rows.extend(
        keys.into_iter()
            .map(|(k, s, filled)| (k, s, if filled { 4 } else { 5 })),
    );
    let legend_area = legend_area.margin(margin + caption, 0, 0, 8);
    for (i, (label, style, kind)) in rows.iter().enumerate() {
        let y = 14 + 26 * i as i32;
        match kind {
            0 | 5 => e(legend_area.draw(&PathElement::new(vec![(0, y), (28, y)], *style)))?,
            1 => e(legend_area.draw(&DashedPathElement::new(vec![(0, y), (28, y)], 7, 4, *style)))?,
            2 => {
                e(legend_area.draw(&PathElement::new(vec![(14, y), (28, y)], *style)))?;
                e(legend_area.draw(&Circle::new((14, y), 6, WHITE.filled())))?;
                e(legend_area.draw(&Circle::new((14, y), 6, *style)))?;
            }
            3 => {
                e(legend_area.draw(&Cross::new((7, y), 6, RECORDED.stroke_width(3))))?;
                e(legend_area.draw(&Cross::new((22, y), 6, TWIN.stroke_width(3))))?;
            }
            _ => e(legend_area.draw(&Rectangle::new([(2, y - 7), (26, y + 7)], *style)))?,
        }
        e(legend_area.draw(&Text::new(label.as_str(), (36, y - 9), font(15))))?;
    }
    Ok(())
}

// ------------------------------------------------------ errors over steps

/// Per-step values of one error, one series per episode.
struct Series {
    per_episode: Vec<Vec<(u32, f64)>>,
}

impl Series {
    fn of(replays: &[EpisodeReplay], value: impl Fn(&StepGap) -> f64) -> Self {
        Self {
            per_episode: replays
                .iter()
                .map(|r| r.steps.iter().map(|s| (s.step, value(s))).collect())
                .collect(),
        }
    }

    /// The mean over the episodes at each step that has a finite value.
    fn mean(&self) -> Vec<(u32, f64)> {
        let mut by_step: std::collections::BTreeMap<u32, Vec<f64>> = Default::default();
        for (step, v) in self.per_episode.iter().flatten() {
            by_step.entry(*step).or_default().push(*v);
        }
        by_step
            .into_iter()
            .map(|(step, values)| (step, Stats::of(values).mean))
            .collect()
    }

    fn max(&self) -> f64 {
        self.per_episode
            .iter()
            .flatten()
            .map(|(_, v)| *v)
            .filter(|v| v.is_finite())
            .fold(0.0, f64::max)
    }
}

fn error_panels(
    root: &DrawingArea<BitMapBackend<'_>, Shift>,
    replays: &[EpisodeReplay],
) -> Result<(), String> {
    let root = e(root.titled(
        &format!(
            "Error over the steps: {} episodes (thin: each episode, bold: mean per step)",
            replays.len()
        ),
        text(22),
    ))?;
    let panels = root.split_evenly((3, 2));
    let cm = |x: f64| x * 100.0;
    let specs: [(&str, &str, RGBColor, Series); 6] = [
        (
            "Position error, open loop",
            "position error, cm",
            TWIN,
            Series::of(replays, |s| cm(s.open_loop_position_m)),
        ),
        (
            "Position error, one step",
            "position error, cm",
            ONE_STEP,
            Series::of(replays, |s| cm(s.one_step_position_m)),
        ),
        (
            "Heading error, open loop",
            "heading error, °",
            TWIN,
            Series::of(replays, |s| s.open_loop_yaw_rad.to_degrees()),
        ),
        (
            "Heading error, one step",
            "heading error, °",
            ONE_STEP,
            Series::of(replays, |s| s.one_step_yaw_rad.to_degrees()),
        ),
        (
            "Depth MAE at the recorded pose",
            "depth MAE, cm",
            DEPTH,
            Series::of(replays, |s| cm(s.depth_mae_m)),
        ),
        (
            "Depth validity disagreement",
            "valid in one image only, %",
            DEPTH,
            Series::of(replays, |s| s.depth_validity_disagreement * 100.0),
        ),
    ];
    let last_step = replays
        .iter()
        .filter_map(|r| r.steps.iter().map(|s| s.step).max())
        .max()
        .unwrap_or(1)
        .max(2);
    for (area, (title, unit, color, series)) in panels.iter().zip(specs) {
        let top = series.max();
        let top = if top > 0.0 { top * 1.08 } else { 1.0 };
        let mut chart = e(ChartBuilder::on(area)
            .caption(title, text(18))
            .margin(12)
            .x_label_area_size(44)
            .y_label_area_size(72)
            .build_cartesian_2d(1u32..last_step, 0.0..top))?;
        e(chart
            .configure_mesh()
            .x_desc("step")
            .y_desc(unit)
            .label_style(text(14))
            .axis_desc_style(text(15))
            .max_light_lines(1)
            .light_line_style(RGBColor(240, 240, 240))
            .bold_line_style(RGBColor(218, 218, 218))
            .draw())?;
        let thin = color.mix(0.35).stroke_width(1);
        for episode in &series.per_episode {
            for run in finite_runs(episode.iter().map(|(s, v)| (f64::from(*s), *v))) {
                let points = run.into_iter().map(|(s, v)| (s as u32, v));
                e(chart.draw_series(LineSeries::new(points, thin)))?;
            }
        }
        let mean = series.mean();
        for run in finite_runs(mean.iter().map(|(s, v)| (f64::from(*s), *v))) {
            let points: Vec<(u32, f64)> = run.into_iter().map(|(s, v)| (s as u32, v)).collect();
            e(chart.draw_series(LineSeries::new(points.clone(), color.stroke_width(3))))?;
            if points.len() == 1 {
                e(chart.draw_series(
                    points
                        .into_iter()
                        .map(|p| Circle::new(p, 4, color.filled())),
                ))?;
            }
        }
    }
    Ok(())
}

// ------------------------------------------------------ depth comparison

/// A perceptual black → purple → orange → yellow scale (inferno's anchors).
fn inferno(t: f64) -> RGBColor {
    const ANCHORS: [(u8, u8, u8); 6] = [
        (0, 0, 4),
        (66, 10, 104),
        (147, 38, 103),
        (221, 81, 58),
        (252, 165, 10),
        (252, 255, 164),
    ];
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = t * (ANCHORS.len() - 1) as f64;
    let i = (x.floor() as usize).min(ANCHORS.len() - 2);
    let f = x - i as f64;
    let lerp = |a: u8, b: u8| (f64::from(a) + (f64::from(b) - f64::from(a)) * f).round() as u8;
    let (a, b) = (ANCHORS[i], ANCHORS[i + 1]);
    RGBColor(lerp(a.0, b.0), lerp(a.1, b.1), lerp(a.2, b.2))
}

fn viridis(t: f64) -> RGBColor {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    ViridisRGB::get_color(t as f32)
}

/// The smallest and largest finite value, or `None`.
fn finite_range(values: impl IntoIterator<Item = f32>) -> Option<(f64, f64)> {
    let mut range = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values {
        grow(&mut range, f64::from(v));
    }
    range.0.is_finite().then_some(range)
}

/// A scale's range, never empty.
fn widen((lo, hi): (f64, f64)) -> (f64, f64) {
    if hi - lo > 1e-6 {
        (lo, hi)
    } else {
        (lo, lo + 0.01)
    }
}

/// Draws `pixel(i)` (row-major `width`×`height`) scaled to fit `area`,
/// nearest neighbour, centred across, at the top; an empty image draws
/// nothing.
fn image(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    width: u32,
    height: u32,
    pixel: impl Fn(usize) -> RGBColor,
) -> Result<(), String> {
    if width == 0 || height == 0 {
        return Ok(());
    }
    let (aw, ah) = area.dim_in_pixel();
    let scale = (f64::from(aw) / f64::from(width)).min(f64::from(ah) / f64::from(height));
    let (dw, dh) = (
        (f64::from(width) * scale).floor() as u32,
        (f64::from(height) * scale).floor() as u32,
    );
    let (ox, oy) = ((aw - dw.min(aw)) / 2, 0);
    for y in 0..dh {
        let sy = ((f64::from(y) / scale) as u32).min(height - 1);
        for x in 0..dw {
            let sx = ((f64::from(x) / scale) as u32).min(width - 1);
            let color = pixel(sy as usize * width as usize + sx as usize);
            e(area.draw_pixel(((ox + x) as i32, (oy + y) as i32), &color))?;
        }
    }
    e(area.draw(&Rectangle::new(
        [
            (ox as i32 - 1, oy as i32 - 1),
            ((ox + dw) as i32, (oy + dh) as i32),
        ],
        BLACK.stroke_width(1),
    )))?;
    Ok(())
}

/// A horizontal colour bar over `[lo, hi]` with its axis labelled `desc`.
fn colour_bar(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    (lo, hi): (f64, f64),
    desc: &str,
    colour: impl Fn(f64) -> RGBColor,
) -> Result<(), String> {
    let mut chart = e(ChartBuilder::on(area)
        .margin_left(24)
        .margin_right(24)
        .x_label_area_size(44)
        .build_cartesian_2d(lo..hi, 0.0..1.0))?;
    e(chart
        .configure_mesh()
        .disable_mesh()
        .disable_y_axis()
        .x_labels(6)
        .x_desc(desc)
        .label_style(text(13))
        .axis_desc_style(text(14))
        .draw())?;
    let n = 128;
    e(chart.draw_series((0..n).map(|k| {
        let a = lo + (hi - lo) * f64::from(k) / f64::from(n);
        let b = lo + (hi - lo) * f64::from(k + 1) / f64::from(n);
        Rectangle::new(
            [(a, 0.0), (b, 1.0)],
            colour(f64::from(k) / f64::from(n - 1)).filled(),
        )
    })))?;
    Ok(())
}

/// A panel's colour of pixel `i`.
type PixelColour<'a> = Box<dyn Fn(usize) -> RGBColor + 'a>;

fn depth_panels(
    root: &DrawingArea<BitMapBackend<'_>, Shift>,
    rank: usize,
    kept: &KeptDepth,
) -> Result<(), String> {
    let gap = &kept.gap;
    let title = format!(
        "Depth, worst step {}: episode {} ({}) step {} — MAE {:.2} cm, validity disagrees on {:.1} % of pixels",
        rank + 1,
        kept.episode,
        file_name(&kept.file),
        gap.step,
        gap.depth_mae_m * 100.0,
        gap.depth_validity_disagreement * 100.0,
    );
    let root = e(root.titled(&title, text(19)))?;
    let (panels, note) = root.split_vertically(root.dim_in_pixel().1.saturating_sub(30));
    let columns = panels.split_evenly((1, 3));
    let depth =
        widen(finite_range(kept.recorded.iter().chain(&kept.twin).copied()).unwrap_or((0.0, 1.0)));
    let error: Vec<f32> = kept
        .recorded
        .iter()
        .zip(&kept.twin)
        .map(|(r, t)| (t - r).abs())
        .collect();
    let error_range = widen((
        0.0,
        finite_range(error.iter().copied()).map_or(0.01, |r| r.1),
    ));
    let depth_colour = |v: f32| {
        if v.is_finite() {
            viridis((f64::from(v) - depth.0) / (depth.1 - depth.0))
        } else {
            NO_RETURN
        }
    };
    let views: [(&str, PixelColour<'_>); 3] = [
        (
            "recorded (robot)",
            Box::new(|i| kept.recorded.get(i).map_or(NO_RETURN, |v| depth_colour(*v))),
        ),
        (
            "twin at the recorded pose",
            Box::new(|i| kept.twin.get(i).map_or(NO_RETURN, |v| depth_colour(*v))),
        ),
        (
            "|twin − robot|",
            Box::new(|i| {
                let (Some(r), Some(t)) = (kept.recorded.get(i), kept.twin.get(i)) else {
                    return NO_RETURN;
                };
                match (r.is_finite(), t.is_finite()) {
                    (true, true) => inferno(f64::from((t - r).abs()) / error_range.1),
                    (false, false) => NO_RETURN,
                    _ => ONE_ONLY,
                }
            }),
        ),
    ];
    for (k, (column, (label, pixel))) in columns.iter().zip(views).enumerate() {
        let column = column.margin(6, 0, 10, 10);
        let (head, rest) = column.split_vertically(30);
        e(head.draw(&Text::new(
            label,
            (head.dim_in_pixel().0 as i32 / 2, 6),
            font(17).pos(Pos::new(HPos::Center, VPos::Top)),
        )))?;
        // The image as wide as the column allows, its colour bar under it.
        let (rw, rh) = rest.dim_in_pixel();
        let bar_height = 84;
        let fit = (f64::from(rw) * f64::from(kept.height) / f64::from(kept.width.max(1)))
            .min(f64::from(rh.saturating_sub(bar_height)));
        let (picture, bar) = rest.split_vertically(fit.max(1.0) as u32 + 2);
        image(&picture, kept.width, kept.height, pixel)?;
        let (bar, _) = bar.margin(8, 0, 0, 0).split_vertically(bar_height - 8);
        if k < 2 {
            colour_bar(&bar, depth, "depth, m", viridis)?;
        } else {
            colour_bar(&bar, error_range, "|error|, m", inferno)?;
        }
    }
    // What the two flat colours mean.
    let note = note.margin(0, 0, 16, 0);
    e(note.draw(&Rectangle::new([(0, 4), (16, 18)], NO_RETURN.filled())))?;
    e(note.draw(&Text::new(
        "no return (both, or this image)",
        (22, 3),
        font(14),
    )))?;
    e(note.draw(&Rectangle::new([(300, 4), (316, 18)], ONE_ONLY.filled())))?;
    e(note.draw(&Text::new(
        "valid in one image only (error panel)",
        (322, 3),
        font(14),
    )))?;
    Ok(())
}
