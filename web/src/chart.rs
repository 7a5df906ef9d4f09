//! The learning curve: episode return over episodes, drawn on the server
//! as inline SVG (no script, no chart library). Styled by the stylesheet
//! (`svg.curve …`): the pages' Content Security Policy allows no inline
//! style.

use maud::{html, Markup};
use offworld_runtime::msg::EpisodeRecordEntry;

const WIDTH: f64 = 720.0;
const HEIGHT: f64 = 260.0;
const LEFT: f64 = 60.0;
const RIGHT: f64 = 16.0;
const TOP: f64 = 14.0;
const BOTTOM: f64 = 38.0;
/// Points drawn at most (more episodes are sampled evenly).
const MAX_POINTS: usize = 2000;
/// Episodes marked with a dot (success or not) at most.
const MAX_DOTS: usize = 200;

/// The curve of `episodes` (finished ones, in order): each return, and
/// its trailing mean over a tenth of the episodes once there are five.
pub fn learning_curve(episodes: &[&EpisodeRecordEntry]) -> Markup {
    if episodes.is_empty() {
        return html! { p.empty #no-curve { "The curve starts with the first finished episode." } };
    }
    let stride = episodes.len().div_ceil(MAX_POINTS).max(1);
    let shown: Vec<(u64, f64, bool)> = episodes
        .iter()
        .step_by(stride)
        .map(|e| (e.index, finite(e.episode_return), e.success))
        .collect();
    let (x0, x1) = (
        shown.first().map_or(0, |p| p.0),
        shown.last().map_or(0, |p| p.0),
    );
    let (mut y0, mut y1) = shown
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.1), hi.max(p.1))
        });
    if y1 - y0 < 1e-9 {
        (y0, y1) = (y0 - 1.0, y1 + 1.0);
    }
    let x = |i: u64| {
        if x1 == x0 {
            LEFT + (WIDTH - LEFT - RIGHT) / 2.0
        } else {
            LEFT + (i - x0) as f64 / (x1 - x0) as f64 * (WIDTH - LEFT - RIGHT)
        }
    };
    let y = |v: f64| TOP + (y1 - v) / (y1 - y0) * (HEIGHT - TOP - BOTTOM);
    let line = |points: &mut dyn Iterator<Item = (u64, f64)>| {
        points
            .map(|(i, v)| format!("{:.1},{:.1}", x(i), y(v)))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let returns = line(&mut shown.iter().map(|p| (p.0, p.1)));
    let window = (shown.len() / 10).max(2);
    let means = (shown.len() >= 5).then(|| {
        let mut sum = 0.0;
        let mean: Vec<(u64, f64)> = shown
            .iter()
            .enumerate()
            .map(|(k, p)| {
                sum += p.1;
                if k >= window {
                    sum -= shown[k - window].1;
                }
                (p.0, sum / (k + 1).min(window) as f64)
            })
            .collect();
        line(&mut mean.into_iter())
    });
    let bottom = HEIGHT - BOTTOM;
    let mid = (y0 + y1) / 2.0;
    html! {
        figure.curve {
            svg.curve viewBox=(format!("0 0 {WIDTH} {HEIGHT}")) role="img"
                data-points=(shown.len()) aria-labelledby="curve-title" {
                title #curve-title { "Episode return over " (episodes.len()) " episodes" }
                rect.plot x=(LEFT) y=(TOP) width=(WIDTH - LEFT - RIGHT) height=(bottom - TOP) {}
                @if y0 < 0.0 && y1 > 0.0 {
                    line.zero x1=(LEFT) x2=(WIDTH - RIGHT) y1=(fmt(y(0.0))) y2=(fmt(y(0.0))) {}
                }
                @for v in [y0, mid, y1] {
                    line.grid x1=(LEFT) x2=(WIDTH - RIGHT) y1=(fmt(y(v))) y2=(fmt(y(v))) {}
                    text.tick x=(LEFT - 6.0) y=(fmt(y(v) + 4.0)) text-anchor="end" { (format!("{v:.2}")) }
                }
                text.tick x=(fmt(x(x0))) y=(bottom + 16.0) text-anchor="middle" { (x0) }
                @if x1 != x0 {
                    text.tick x=(fmt(x(x1))) y=(bottom + 16.0) text-anchor="middle" { (x1) }
                }
                text.axis x=(fmt(LEFT + (WIDTH - LEFT - RIGHT) / 2.0)) y=(HEIGHT - 4.0) text-anchor="middle" { "episode" }
                text.axis x="12" y=(fmt(TOP + (bottom - TOP) / 2.0)) text-anchor="middle"
                    transform=(format!("rotate(-90 12 {})", fmt(TOP + (bottom - TOP) / 2.0))) { "return" }
                polyline.returns points=(returns) {}
                @if let Some(means) = &means {
                    polyline.mean points=(means) {}
                }
                @if shown.len() <= MAX_DOTS {
                    @for (i, v, success) in &shown {
                        circle.{(if *success { "success" } else { "failure" })} cx=(fmt(x(*i))) cy=(fmt(y(*v))) r="3" {
                            title { "episode " (i) ": " (format!("{v:.3}")) @if *success { " (success)" } }
                        }
                    }
                }
            }
            figcaption {
                "Return of each finished episode"
                @if means.is_some() { "; the darker line is its mean over the last " (window) " episodes" }
                @if stride > 1 { " (every " (stride) "th episode drawn)" }
                "."
            }
        }
    }
}

fn finite(v: f64) -> f64 {
    if v.is_finite() {
        v
    } else {
        0.0
    }
}

fn fmt(v: f64) -> String {
    format!("{v:.1}")
}

#[cfg(test)]
mod tests {
    use super::*;
    use offworld_runtime::msg::ResetAccuracy;

    fn episode(index: u64, episode_return: f64) -> EpisodeRecordEntry {
        EpisodeRecordEntry {
            index,
            seeded: false,
            seed: 0,
            steps: 3,
            episode_return,
            success: episode_return > 0.0,
            end_reason: "step_limit".into(),
            started_unix_ms: 0,
            ended_unix_ms: 0,
            reset: ResetAccuracy::default(),
            recordings: Vec::new(),
        }
    }

    #[test]
    fn the_curve_has_a_point_per_episode_inside_the_plot() {
        let episodes: Vec<_> = (0..12)
            .map(|i| episode(i, f64::from(i as u32) - 4.0))
            .collect();
        let refs: Vec<_> = episodes.iter().collect();
        let svg = learning_curve(&refs).into_string();
        assert!(svg.contains("data-points=\"12\""), "{svg}");
        let points = svg
            .split("class=\"returns\" points=\"")
            .nth(1)
            .and_then(|rest| rest.split('"').next())
            .expect("polyline");
        let parsed: Vec<(f64, f64)> = points
            .split(' ')
            .map(|p| {
                let (x, y) = p.split_once(',').expect("x,y");
                (x.parse().expect("x"), y.parse().expect("y"))
            })
            .collect();
        assert_eq!(parsed.len(), 12);
        assert_eq!(
            parsed[0],
            (LEFT, HEIGHT - BOTTOM),
            "first: lowest return, left"
        );
        assert_eq!(parsed[11], (WIDTH - RIGHT, TOP), "last: highest, right");
        assert!(svg.contains("class=\"mean\""));
        assert!(svg.contains("class=\"zero\""));
        assert_eq!(svg.matches("<circle").count(), 12);
    }

    #[test]
    fn one_flat_or_no_episode_still_draws() {
        let one = [episode(0, 1.0)];
        let svg = learning_curve(&one.iter().collect::<Vec<_>>()).into_string();
        assert!(
            svg.contains("data-points=\"1\"") && !svg.contains("NaN"),
            "{svg}"
        );
        assert!(learning_curve(&[]).into_string().contains("no-curve"));
    }
}
