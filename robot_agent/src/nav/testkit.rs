//! Test support shared by the nav tests: built-in worlds, a seeded
//! spawn sampler (same rules as the controller's `SpawnSampler`), a
//! unicycle robot model with acceleration limits, and an exact check of
//! the robot's footprint against walls and obstacle footprints.

use offworld_runtime::msg::Pose2D;
use offworld_runtime::WorldSpec;

use super::geometry::{MapGeometry, Point};
use super::{NavConfig, OccupancyGrid};

/// A built-in world.
pub fn world(name: &str) -> WorldSpec {
    WorldSpec::builtin(name).expect("built-in world")
}

/// The default-config grid of a built-in world.
pub fn grid(name: &str) -> OccupancyGrid {
    OccupancyGrid::from_world(&world(name), &NavConfig::default()).expect("grid")
}

/// A pose.
pub fn pose(x: f64, y: f64, yaw: f64) -> Pose2D {
    Pose2D { x, y, yaw }
}

/// Knuth's MMIX linear congruential generator: tiny, seeded, reproducible.
pub struct Lcg(u64);

impl Lcg {
    /// A generator seeded with `seed`.
    pub fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }

    /// Uniform in [0, 1), from the top 53 bits.
    pub fn next_f64(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Uniform in [lo, hi).
    pub fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.next_f64()
    }
}

/// `n` valid spawn poses of `world`: uniform in the spawn region, at least
/// the task's distances from the monolith centre and from every boulder
/// footprint, uniform heading (the controller's rejection rules).
pub fn spawn_poses(world: &WorldSpec, n: usize, seed: u64) -> Vec<Pose2D> {
    let t = &world.task;
    let m = world.monolith.center;
    let mut rng = Lcg::new(seed);
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        let x = rng.range(f64::from(t.spawn_x[0]), f64::from(t.spawn_x[1]));
        let y = rng.range(f64::from(t.spawn_y[0]), f64::from(t.spawn_y[1]));
        let yaw = rng.range(0.0, std::f64::consts::TAU);
        if (x - f64::from(m[0])).hypot(y - f64::from(m[1]))
            < f64::from(t.spawn_min_monolith_distance)
        {
            continue;
        }
        let clear = world.boulders.iter().all(|b| {
            let dx = ((x - f64::from(b.center[0])).abs() - f64::from(b.size[0]) * 0.5).max(0.0);
            let dy = ((y - f64::from(b.center[1])).abs() - f64::from(b.size[1]) * 0.5).max(0.0);
            dx.hypot(dy) >= f64::from(t.spawn_min_boulder_distance)
        });
        if clear {
            out.push(pose(x, y, yaw));
        }
    }
    out
}

/// A kinematic unicycle whose velocities follow the commands within
/// acceleration limits (1 m/s², 5 rad/s²).
pub struct Unicycle {
    /// Current pose.
    pub pose: Pose2D,
    linear: f64,
    angular: f64,
}

impl Unicycle {
    /// Linear acceleration limit, m/s².
    pub const LINEAR_ACCEL: f64 = 1.0;
    /// Angular acceleration limit, rad/s².
    pub const ANGULAR_ACCEL: f64 = 5.0;

    /// At rest at `pose`.
    pub fn new(pose: Pose2D) -> Self {
        Self {
            pose,
            linear: 0.0,
            angular: 0.0,
        }
    }

    /// Advances `dt` seconds under the command (`linear`, `angular`).
    pub fn step(&mut self, linear: f64, angular: f64, dt: f64) {
        let dv = Self::LINEAR_ACCEL * dt;
        let dw = Self::ANGULAR_ACCEL * dt;
        self.linear += (linear - self.linear).clamp(-dv, dv);
        self.angular += (angular - self.angular).clamp(-dw, dw);
        self.pose.x += self.linear * self.pose.yaw.cos() * dt;
        self.pose.y += self.linear * self.pose.yaw.sin() * dt;
        self.pose.yaw += self.angular * dt;
    }
}

/// Corners of the robot footprint (`size` = full x × y extent in
/// base_link) at `pose`.
fn footprint_corners(pose: Pose2D, size: [f64; 2]) -> [Point; 4] {
    let (hx, hy) = (size[0] * 0.5, size[1] * 0.5);
    let (s, c) = pose.yaw.sin_cos();
    [(hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy)]
        .map(|(bx, by)| Point::new(pose.x + c * bx - s * by, pose.y + s * bx + c * by))
}

/// Smallest separation between the robot footprint at `pose` and every
/// wall face and obstacle footprint, m; 0 or less means overlap. Exact for
/// convex polygons: the footprint and an axis-aligned box are disjoint iff
/// one of the four edge normals separates them (separating axis theorem);
/// the reported figure is the largest such separation, a lower bound of
/// the true distance that is positive exactly when they are disjoint.
pub fn footprint_separation(map: &MapGeometry, pose: Pose2D, size: [f64; 2]) -> f64 {
    let corners = footprint_corners(pose, size);
    let i = &map.interior;
    let walls = corners
        .iter()
        .map(|p| {
            (p.x - i.min.x)
                .min(i.max.x - p.x)
                .min(p.y - i.min.y)
                .min(i.max.y - p.y)
        })
        .fold(f64::INFINITY, f64::min);
    let (s, c) = pose.yaw.sin_cos();
    let axes = [(1.0, 0.0), (0.0, 1.0), (c, s), (-s, c)];
    map.obstacles
        .iter()
        .map(|o| {
            let box_corners = [
                o.min,
                Point::new(o.max.x, o.min.y),
                o.max,
                Point::new(o.min.x, o.max.y),
            ];
            axes.iter()
                .map(|&(ax, ay)| {
                    let project = |ps: &[Point]| {
                        ps.iter()
                            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
                                let d = p.x * ax + p.y * ay;
                                (lo.min(d), hi.max(d))
                            })
                    };
                    let (a_lo, a_hi) = project(&corners);
                    let (b_lo, b_hi) = project(&box_corners);
                    (b_lo - a_hi).max(a_lo - b_hi)
                })
                .fold(f64::NEG_INFINITY, f64::max)
        })
        .fold(walls, f64::min)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn footprint_separation_detects_overlap_and_clearance() {
        let world = world("monolith_obstacle");
        let map = MapGeometry::from_world(&world).expect("map");
        let size = [0.2, 0.235];
        // Facing the boulder at (0.762, −0.241) whose left face is x = 0.632.
        let near = pose(0.632 - 0.1 - 0.02, -0.241, 0.0);
        assert!((footprint_separation(&map, near, size) - 0.02).abs() < 1e-6);
        let touching = pose(0.632 - 0.1 + 0.01, -0.241, 0.0);
        assert!(footprint_separation(&map, touching, size) < 0.0);
        // Turned 90°, the 0.235 side faces the boulder.
        let turned = pose(0.632 - 0.11, -0.241, std::f64::consts::FRAC_PI_2);
        assert!(footprint_separation(&map, turned, size) < 0.0);
        // Into the wall.
        assert!(footprint_separation(&map, pose(2.0, 0.9, 0.0), size) < 0.0);
    }
}
