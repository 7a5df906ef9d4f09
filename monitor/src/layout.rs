//! The default viewer layout: one tab per env with its 3D scene, camera
//! views and time series, plus a tab with the monitor's own health.

use offworld_runtime::EnvId;
use rerun::blueprint::{
    Blueprint, ContainerLike, Horizontal, Spatial2DView, Spatial3DView, Tabs, TextLogView,
    TimeSeriesView, Vertical,
};

use crate::paths::{self, env_path, env_root};

fn abs(path: String) -> String {
    format!("/{path}")
}

fn env_tab(env: &EnvId) -> ContainerLike {
    let root = abs(env_root(env));
    let p = |rel: &str| abs(env_path(env, rel));
    // Overhead images have no pinhole: they belong to 2D views only.
    let scene = Spatial3DView::new(format!("{env} 3D"))
        .with_origin(root.as_str())
        .with_contents([
            format!("+ {root}/**"),
            format!("- {}/**", p(paths::OVERHEAD)),
            format!("- {}/**", p("metrics")),
            format!("- {}", p(paths::EVENTS)),
        ]);
    let cameras = Vertical::new([
        Spatial2DView::new("colour")
            .with_origin(p(paths::CAMERA).as_str())
            .with_contents([p(paths::COLOR)])
            .into(),
        Spatial2DView::new("depth")
            .with_origin(p(paths::CAMERA).as_str())
            .with_contents([p(paths::DEPTH)])
            .into(),
        Spatial2DView::new("overhead")
            .with_origin(p(paths::OVERHEAD).as_str())
            .into(),
    ]);
    let series = Vertical::new([
        TimeSeriesView::new("commands")
            .with_contents([p(paths::LINEAR_X), p(paths::ANGULAR_Z)])
            .into(),
        TimeSeriesView::new("reward / return")
            .with_contents([p(paths::REWARD), p(paths::RETURN)])
            .into(),
        TimeSeriesView::new("episodes")
            .with_contents([p(paths::SUCCESS), p(paths::EPISODE_LENGTH)])
            .into(),
        TextLogView::new("events")
            .with_origin(p(paths::EVENTS).as_str())
            .into(),
    ]);
    Horizontal::new([scene.into(), cameras.into(), series.into()])
        .with_name(env.to_string())
        .with_column_shares([0.5, 0.2, 0.3])
        .into()
}

/// The layout for the envs seen so far (one tab each, in order).
pub fn blueprint<'a>(envs: impl IntoIterator<Item = &'a EnvId>) -> Blueprint {
    let mut tabs: Vec<ContainerLike> = envs.into_iter().map(env_tab).collect();
    tabs.push(
        Vertical::new([
            TimeSeriesView::new("monitor health")
                .with_origin("/monitor")
                .into(),
            TextLogView::new("site events")
                .with_origin(abs(paths::SITE_EVENTS.to_owned()).as_str())
                .into(),
        ])
        .with_name("monitor")
        .into(),
    );
    Blueprint::new(Tabs::new(tabs)).with_auto_views(false)
}
