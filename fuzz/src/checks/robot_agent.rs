//! Invariants of the files the robot side reads: the robot agent's
//! configuration (`AgentConfig` TOML, with the base guard's section), its
//! e-stop latch file, and world files (`WorldSpec` TOML, as the sim twin
//! and the agent's reset planner load them).
//!
//! Shared by the fuzz targets and `robot_agent/tests/integration/fuzz_corpus.rs`.

use offworld_robot_agent::nav::{NavConfig, OccupancyGrid, Point};
use offworld_robot_agent::AgentConfig;
use offworld_runtime::msg::EStopState;
use offworld_runtime::WorldSpec;

/// Robot files. Input `[kind, text…]`: an even `kind` reads `text` as the
/// agent's configuration file, an odd one as its e-stop latch file.
pub fn robot_config(data: &[u8]) {
    let Some((&kind, text)) = data.split_first() else {
        return;
    };
    let Ok(text) = std::str::from_utf8(text) else {
        return;
    };
    if kind % 2 == 0 {
        agent_config(text);
    } else {
        latch(text);
    }
}

/// What `AgentConfig::load` does after reading the file.
fn load(text: &str) -> Result<AgentConfig, String> {
    let config: AgentConfig = toml::from_str(text).map_err(|e| e.to_string())?;
    config.validate().map_err(|e| e.to_string())?;
    Ok(config)
}

/// A configuration that parses writes back to TOML that parses to the same
/// configuration (compared as text, so NaN equals itself) and validates
/// alike; a valid one yields its graph, watchdog and base check.
fn agent_config(text: &str) {
    let Ok(parsed) = toml::from_str::<AgentConfig>(text) else {
        return;
    };
    let written = toml::to_string(&parsed)
        .unwrap_or_else(|e| panic!("a parsed configuration does not write: {e}\n{parsed:?}"));
    let reparsed: AgentConfig = toml::from_str(&written)
        .unwrap_or_else(|e| panic!("a written configuration does not parse: {e}\n{written}"));
    assert_eq!(
        toml::to_string(&reparsed).ok().as_deref(),
        Some(written.as_str()),
        "writing is not stable"
    );
    let valid = parsed.validate().map_err(|e| e.to_string());
    assert_eq!(
        reparsed.validate().map_err(|e| e.to_string()),
        valid,
        "validation changed by a round trip"
    );
    if valid.is_ok() {
        assert!(load(text).is_ok(), "AgentConfig::load would refuse it");
        assert!(
            parsed.graph().is_ok(),
            "valid configuration without a graph"
        );
        assert!(!parsed.watchdog().is_zero(), "a zero watchdog window");
        assert!(parsed.control_hz.is_finite() && parsed.control_hz > 0.0);
        let _ = parsed.base_check();
    }
}

/// A latch file that parses writes back to the same state.
fn latch(text: &str) {
    let Ok(state) = toml::from_str::<EStopState>(text) else {
        return;
    };
    let written = toml::to_string(&state)
        .unwrap_or_else(|e| panic!("a parsed latch does not write: {e}\n{state:?}"));
    let reread: EStopState = toml::from_str(&written)
        .unwrap_or_else(|e| panic!("a written latch does not parse: {e}\n{written}"));
    assert_eq!(reread, state, "latch round trip");
    assert_eq!(state.refusal().is_some(), state.engaged());
}

/// Largest grid (cells at 1 m) the world check rasterises: the fuzzer's
/// time goes to parsing, not to big maps.
const MAX_CHECKED_CELLS: f64 = 2_500.0;

/// World files: one that loads satisfies what validation promises; the
/// robot agent's planner map built from it (coarse, 1 m cells) is bounded
/// and has no free cell outside the enclosure.
pub fn world_toml(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(world) = WorldSpec::from_toml(text) else {
        return;
    };
    let e = &world.enclosure;
    assert!(e.x_min < e.x_max && e.y_min < e.y_max, "empty enclosure");
    let t = &world.terrain;
    assert!((2..=4096).contains(&t.cells_x) && (2..=4096).contains(&t.cells_y));
    assert!(!t.wavelengths.is_empty() && t.wavelengths.len() == t.weights.len());
    let c = &world.camera;
    assert!((1..=4096).contains(&c.width) && (1..=4096).contains(&c.height));
    assert!(c.hfov > 0.0 && c.hfov < 3.0 && c.min_range > 0.0 && c.min_range < c.max_range);
    let width = f64::from(e.x_max) - f64::from(e.x_min);
    let depth = f64::from(e.y_max) - f64::from(e.y_min);
    let cells = width.ceil() * depth.ceil();
    if cells.is_nan() || cells > MAX_CHECKED_CELLS {
        return;
    }
    let config = NavConfig {
        resolution: 1.0,
        ..NavConfig::default()
    };
    let Ok(grid) = OccupancyGrid::from_world(&world, &config) else {
        return;
    };
    let (cols, rows) = grid.size();
    assert!(
        cols >= 1 && rows >= 1 && (cols * rows) as f64 <= MAX_CHECKED_CELLS + 1.0,
        "grid {cols}x{rows} for {width}x{depth} m"
    );
    // (Poses are checked finite before they reach the map; a NaN one is
    // simply never free.)
    assert!(!grid.is_free_at(Point::new(f64::NAN, 0.0)), "NaN is free");
    let outside = [
        Point::new(f64::from(e.x_min) - 1.0, f64::from(e.y_min) - 1.0),
        Point::new(f64::from(e.x_max) + 1.0, f64::from(e.y_max) + 1.0),
    ];
    for p in outside {
        assert!(!grid.is_free_at(p), "{p:?} outside the enclosure is free");
        let clearance = grid.clearance_at(p);
        assert!(
            clearance <= 0.0,
            "{p:?} outside the enclosure has clearance {clearance}"
        );
    }
}

/// Seeds of [`robot_config`].
pub fn robot_config_seeds() -> Vec<Vec<u8>> {
    let example = include_str!("../../../robot_agent/robot.example.toml");
    let bridge = "key_style = { style = \"bridge\", prefix = \"site_a\" }\n\
        ros_namespace = \"/rosbot\"\nestop_latch = \"/var/lib/offworld/agent.estop\"\n\
        require_base_guard = false\n[nav]\nresolution = 0.05\n[guard]\nrate_hz = 50.0\n";
    let latch = "[site]\nengaged = true\nreason = \"fire alarm\"\n\
        [site.changed]\nsec = 1700000123\nnanosec = 456789\n\
        [env]\nengaged = false\nreason = \"\"\n[env.changed]\nsec = 0\nnanosec = 0\n";
    [(0u8, example), (2, bridge), (4, ""), (1, latch)]
        .iter()
        .map(|(kind, text)| {
            let mut out = vec![*kind];
            out.extend(text.as_bytes());
            out
        })
        .collect()
}

/// Seeds of [`world_toml`]: the built-in worlds.
pub fn world_toml_seeds() -> Vec<Vec<u8>> {
    [
        include_str!("../../../runtime/worlds/monolith.toml"),
        include_str!("../../../runtime/worlds/monolith_obstacle.toml"),
    ]
    .iter()
    .map(|text| text.as_bytes().to_vec())
    .collect()
}
