//! World definitions: the enclosure, task geometry, terrain, robot, camera
//! and light, read from TOML data files (`runtime/worlds/*.toml`). No
//! geometry lives in code. Shared by the sim twin (physics, rendering), the
//! controller (task), the robot agent (map for reset navigation) and monitors.

use std::path::Path;

use serde::Deserialize;

/// A world file that cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WorldError {
    /// No built-in world of that name.
    #[error("unknown world `{0}` (built-in: monolith, monolith_obstacle)")]
    Unknown(String),
    /// A world file is unreadable or invalid.
    #[error("invalid world: {0}")]
    Invalid(String),
}

/// The built-in worlds, shipped as data files in the crate.
const BUILTIN: [(&str, &str); 2] = [
    ("monolith", include_str!("../worlds/monolith.toml")),
    (
        "monolith_obstacle",
        include_str!("../worlds/monolith_obstacle.toml"),
    ),
];

/// A whole world file.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorldSpec {
    /// World name (`monolith`, `monolith_obstacle`).
    pub name: String,
    /// Walls.
    pub enclosure: EnclosureSpec,
    /// The goal.
    pub monolith: BoxSpec,
    /// Task geometry (boundary, spawn region, success radius).
    pub task: TaskGeometry,
    /// Ground relief.
    pub terrain: TerrainSpec,
    /// The ROSbot.
    pub robot: RobotSpec,
    /// The RGBD camera.
    pub camera: CameraSpec,
    /// Shading.
    pub light: LightSpec,
    /// Obstacles (empty in the open world).
    #[serde(default)]
    pub boulders: Vec<BoulderSpec>,
}

/// Inner faces of the four walls.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct EnclosureSpec {
    pub x_min: f32,
    pub x_max: f32,
    pub y_min: f32,
    pub y_max: f32,
    pub wall_height: f32,
    pub wall_thickness: f32,
    pub wall_albedo: f32,
}

/// An upright box given by centre and full size.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoxSpec {
    /// Centre, m.
    pub center: [f32; 3],
    /// Full extents, m.
    pub size: [f32; 3],
    /// Grey-level reflectance 0–1.
    pub albedo: f32,
}

/// A boulder resting on the terrain.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoulderSpec {
    /// Ground-plane centre, m.
    pub center: [f32; 2],
    /// Full extents, m.
    pub size: [f32; 3],
    /// Grey-level reflectance 0–1.
    pub albedo: f32,
}

/// Boundary, spawn region, success radius.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct TaskGeometry {
    pub boundary_x: [f32; 2],
    pub boundary_y: [f32; 2],
    pub success_radius: f32,
    pub spawn_x: [f32; 2],
    pub spawn_y: [f32; 2],
    pub spawn_min_monolith_distance: f32,
    pub spawn_min_boulder_distance: f32,
}

/// Procedural terrain parameters.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TerrainSpec {
    /// Seed of the relief (the terrain is part of the world, not the episode).
    pub seed: u64,
    /// Grid cells along x.
    pub cells_x: usize,
    /// Grid cells along y.
    pub cells_y: usize,
    /// Highest point, m (lowest is 0).
    pub max_height: f32,
    /// Target mean height, m.
    pub mean_height: f32,
    /// Noise octave feature sizes, m.
    pub wavelengths: Vec<f32>,
    /// Octave weights.
    pub weights: Vec<f32>,
    /// Ground friction coefficient.
    pub friction: f32,
    /// Grey-level reflectance 0–1.
    pub albedo: f32,
}

/// The robot.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
#[allow(missing_docs)]
pub struct RobotSpec {
    pub size: [f32; 3],
    pub base_mass: f32,
    pub wheel_mass: f32,
    pub wheel_radius: f32,
    pub wheel_base: f32,
    pub track_width: f32,
    pub ground_clearance: f32,
    pub max_linear_accel: f32,
    pub max_angular_accel: f32,
    pub max_linear_speed: f32,
    pub max_angular_speed: f32,
    /// Vive tracker position in base_link, m.
    pub tracker_offset: [f32; 3],
}

impl RobotSpec {
    /// Total mass, kg.
    pub fn mass(&self) -> f32 {
        self.base_mass + 4.0 * self.wheel_mass
    }
}

/// The camera.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// Columns.
    pub width: u32,
    /// Rows.
    pub height: u32,
    /// Horizontal field of view, rad.
    pub hfov: f32,
    /// Optical centre in base_link (x forward, y left, z up), m; no tilt.
    pub mount: [f32; 3],
    /// Nearer returns are invalid, m.
    pub min_range: f32,
    /// Farther returns are invalid, m.
    pub max_range: f32,
}

/// One directional light plus ambient.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LightSpec {
    /// Direction towards the light (normalised on use).
    pub direction: [f32; 3],
    /// Ambient term.
    pub ambient: f32,
    /// Diffuse term.
    pub diffuse: f32,
}

impl WorldSpec {
    /// Names of the built-in worlds.
    pub fn builtin_names() -> impl Iterator<Item = &'static str> {
        BUILTIN.iter().map(|(name, _)| *name)
    }

    /// A built-in world by name.
    pub fn builtin(name: &str) -> Result<Self, WorldError> {
        let (_, text) = BUILTIN
            .iter()
            .find(|(n, _)| *n == name)
            .ok_or_else(|| WorldError::Unknown(name.to_owned()))?;
        Self::from_toml(text)
    }

    /// Loads a world file.
    pub fn load(path: &Path) -> Result<Self, WorldError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| WorldError::Invalid(format!("{}: {e}", path.display())))?;
        Self::from_toml(&text)
    }

    /// Parses and validates world TOML.
    pub fn from_toml(text: &str) -> Result<Self, WorldError> {
        let spec: WorldSpec =
            toml::from_str(text).map_err(|e| WorldError::Invalid(e.to_string()))?;
        spec.validate()?;
        Ok(spec)
    }

    fn validate(&self) -> Result<(), WorldError> {
        let bad = |what: &str| Err(WorldError::Invalid(format!("{}: {what}", self.name)));
        let e = &self.enclosure;
        if !(e.x_min < e.x_max && e.y_min < e.y_max) {
            return bad("enclosure min must be below max");
        }
        let t = &self.terrain;
        if t.cells_x < 2 || t.cells_y < 2 || t.cells_x > 4096 || t.cells_y > 4096 {
            return bad("terrain cells must be in 2..=4096");
        }
        if t.wavelengths.len() != t.weights.len() || t.wavelengths.is_empty() {
            return bad("terrain wavelengths and weights must pair up");
        }
        if !(t.max_height >= 0.0 && t.mean_height >= 0.0 && t.mean_height <= t.max_height) {
            return bad("terrain heights must satisfy 0 <= mean <= max");
        }
        let c = &self.camera;
        if c.width == 0 || c.height == 0 || c.width > 4096 || c.height > 4096 {
            return bad("camera size must be in 1..=4096");
        }
        if !(c.hfov > 0.0 && c.hfov < 3.0 && c.min_range > 0.0 && c.min_range < c.max_range) {
            return bad("camera fov/range out of bounds");
        }
        if self.robot.mass() <= 0.0 || self.robot.max_linear_accel <= 0.0 {
            return bad("robot mass and accelerations must be positive");
        }
        Ok(())
    }
}

impl CameraSpec {
    /// Focal length in pixels (fx = fy): `width / 2 / tan(hfov / 2)`.
    pub fn focal_px(&self) -> f32 {
        self.width as f32 * 0.5 / (self.hfov * 0.5).tan()
    }

    /// This camera at another resolution, same field of view.
    pub fn with_resolution(&self, width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            ..self.clone()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn builtin_worlds_load_with_reference_figures() {
        let open = WorldSpec::builtin("monolith").expect("monolith");
        assert!(open.boulders.is_empty());
        assert_eq!(open.monolith.center, [0.0109, -0.2034, 0.2838]);
        assert_eq!(open.task.success_radius, 0.40);
        let obstacle = WorldSpec::builtin("monolith_obstacle").expect("obstacle");
        assert_eq!(obstacle.boulders.len(), 14);
        assert_eq!(obstacle.boulders[13].center, [0.029, -0.903]);
        // fx = fy ≈ 277.1 px at 320 px and 1.047 rad.
        assert!((open.camera.focal_px() - 277.1).abs() < 0.1);
    }

    #[test]
    fn bad_world_files_are_typed_errors() {
        assert!(matches!(
            WorldSpec::builtin("mars"),
            Err(WorldError::Unknown(_))
        ));
        assert!(matches!(
            WorldSpec::from_toml("name = 1"),
            Err(WorldError::Invalid(_))
        ));
        let text = include_str!("../worlds/monolith.toml").replace("cells_x = 64", "cells_x = 1");
        assert!(matches!(
            WorldSpec::from_toml(&text),
            Err(WorldError::Invalid(_))
        ));
        let text = include_str!("../worlds/monolith.toml").replace("[light]", "[light]\nbogus = 1");
        assert!(matches!(
            WorldSpec::from_toml(&text),
            Err(WorldError::Invalid(_))
        ));
    }
}
