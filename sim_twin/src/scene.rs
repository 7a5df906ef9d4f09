//! The static scene: terrain plus the upright boxes (walls, monolith,
//! boulders) that physics collides with and the camera sees.

use std::sync::Arc;

use crate::terrain::Terrain;
use crate::world::WorldSpec;

/// What a surface is (for shading and for telling things apart in tests).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum SurfaceKind {
    /// The lunar floor.
    Terrain,
    /// An enclosure wall.
    Wall,
    /// The goal beacon.
    Monolith,
    /// An obstacle.
    Boulder,
}

/// An axis-aligned, upright box.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneBox {
    /// Minimum corner, m.
    pub min: [f32; 3],
    /// Maximum corner, m.
    pub max: [f32; 3],
    /// Grey-level reflectance.
    pub albedo: f32,
    /// What it is.
    pub kind: SurfaceKind,
}

impl SceneBox {
    fn centered(center: [f32; 3], size: [f32; 3], albedo: f32, kind: SurfaceKind) -> Self {
        Self {
            min: std::array::from_fn(|i| center[i] - size[i] * 0.5),
            max: std::array::from_fn(|i| center[i] + size[i] * 0.5),
            albedo,
            kind,
        }
    }

    /// Centre, m.
    pub fn center(&self) -> [f32; 3] {
        std::array::from_fn(|i| 0.5 * (self.min[i] + self.max[i]))
    }

    /// Half extents, m.
    pub fn half_extents(&self) -> [f32; 3] {
        std::array::from_fn(|i| 0.5 * (self.max[i] - self.min[i]))
    }
}

/// Terrain and boxes of one world, shared by physics and rendering.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The world definition it was built from.
    pub world: WorldSpec,
    /// The floor.
    pub terrain: Arc<Terrain>,
    /// Walls, monolith, boulders.
    pub boxes: Vec<SceneBox>,
}

/// How deep boulders sit in the ground below the terrain at their centre, m.
const BOULDER_EMBED: f32 = 0.03;

impl Scene {
    /// Builds the scene of a world (terrain generated from its seed).
    pub fn build(world: &WorldSpec) -> Self {
        let terrain = Terrain::generate(&world.terrain, &world.enclosure);
        Self::with_terrain(world, terrain)
    }

    /// Builds the scene over a given terrain (e.g. flat, for calibration tests).
    pub fn with_terrain(world: &WorldSpec, terrain: Terrain) -> Self {
        let e = &world.enclosure;
        let (t, h) = (e.wall_thickness, e.wall_height);
        let wall = |min: [f32; 3], max: [f32; 3]| SceneBox {
            min,
            max,
            albedo: e.wall_albedo,
            kind: SurfaceKind::Wall,
        };
        // Walls stand on the lowest ground (terrain heights are ≥ 0).
        let floor = 0.0;
        let mut boxes = vec![
            wall([e.x_min - t, e.y_min - t, floor], [e.x_min, e.y_max + t, h]),
            wall([e.x_max, e.y_min - t, floor], [e.x_max + t, e.y_max + t, h]),
            wall([e.x_min, e.y_min - t, floor], [e.x_max, e.y_min, h]),
            wall([e.x_min, e.y_max, floor], [e.x_max, e.y_max + t, h]),
            SceneBox::centered(
                world.monolith.center,
                world.monolith.size,
                world.monolith.albedo,
                SurfaceKind::Monolith,
            ),
        ];
        for b in &world.boulders {
            let base = terrain.height_at(b.center[0], b.center[1]) - BOULDER_EMBED;
            let center = [b.center[0], b.center[1], base + b.size[2] * 0.5];
            boxes.push(SceneBox::centered(
                center,
                b.size,
                b.albedo,
                SurfaceKind::Boulder,
            ));
        }
        Self {
            world: world.clone(),
            terrain: Arc::new(terrain),
            boxes,
        }
    }

    /// The monolith box.
    pub fn monolith(&self) -> &SceneBox {
        // Built at index 4 by `with_terrain`.
        &self.boxes[4]
    }
}
