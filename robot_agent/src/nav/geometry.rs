//! Planar map geometry: the enclosure's inner wall faces and the obstacle
//! footprints (monolith, boulders) as axis-aligned rectangles, with the
//! clearance queries the grid, the planner and the tests share. Exact
//! (analytic) so that the grid's guarantees can be checked against it.

use offworld_runtime::WorldSpec;

use super::NavError;

/// A point on the ground plane, world frame, m.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    /// m.
    pub x: f64,
    /// m.
    pub y: f64,
}

impl Point {
    /// The point (`x`, `y`).
    pub const fn new(x: f64, y: f64) -> Self {
        Self { x, y }
    }

    /// Euclidean distance to `other`, m.
    pub fn distance(self, other: Point) -> f64 {
        (other.x - self.x).hypot(other.y - self.y)
    }

    /// Direction from `self` towards `other`, rad (world frame).
    pub fn bearing_to(self, other: Point) -> f64 {
        (other.y - self.y).atan2(other.x - self.x)
    }

    /// Both coordinates are finite.
    pub fn is_finite(self) -> bool {
        self.x.is_finite() && self.y.is_finite()
    }

    /// `self + t (other − self)`.
    pub(crate) fn lerp(self, other: Point, t: f64) -> Point {
        Point::new(
            self.x + (other.x - self.x) * t,
            self.y + (other.y - self.y) * t,
        )
    }
}

/// `angle` wrapped to (−π, π].
pub(crate) fn wrap_angle(angle: f64) -> f64 {
    use std::f64::consts::{PI, TAU};
    let wrapped = (angle + PI).rem_euclid(TAU) - PI;
    // rem_euclid maps +π to −π; keep +π so that "half a turn left" stays left.
    if wrapped <= -PI {
        PI
    } else {
        wrapped
    }
}

/// An axis-aligned rectangle, m.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Rect {
    pub min: Point,
    pub max: Point,
}

impl Rect {
    /// The rectangle of full size `size_x` × `size_y` centred on (`cx`, `cy`).
    pub fn centred(cx: f64, cy: f64, size_x: f64, size_y: f64) -> Self {
        let (hx, hy) = (size_x.abs() * 0.5, size_y.abs() * 0.5);
        Self {
            min: Point::new(cx - hx, cy - hy),
            max: Point::new(cx + hx, cy + hy),
        }
    }

    /// `p` is inside or on the boundary.
    pub fn contains(&self, p: Point) -> bool {
        p.x >= self.min.x && p.x <= self.max.x && p.y >= self.min.y && p.y <= self.max.y
    }

    /// Distance from `p` to the rectangle, 0 inside.
    pub fn distance_to_point(&self, p: Point) -> f64 {
        let dx = (self.min.x - p.x).max(p.x - self.max.x).max(0.0);
        let dy = (self.min.y - p.y).max(p.y - self.max.y).max(0.0);
        dx.hypot(dy)
    }

    /// Smallest distance between any point of `self` and any point of
    /// `other`, 0 when they touch or overlap.
    pub fn gap_to(&self, other: &Rect) -> f64 {
        let dx = (other.min.x - self.max.x)
            .max(self.min.x - other.max.x)
            .max(0.0);
        let dy = (other.min.y - self.max.y)
            .max(self.min.y - other.max.y)
            .max(0.0);
        dx.hypot(dy)
    }

    fn is_finite(&self) -> bool {
        self.min.is_finite() && self.max.is_finite()
    }
}

/// What the robot must not touch: the enclosure interior (bounded by the
/// inner wall faces) and the obstacle footprints inside it.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct MapGeometry {
    /// Inner wall faces.
    pub interior: Rect,
    /// Monolith first, then the boulders, in world-file order.
    pub obstacles: Vec<Rect>,
}

impl MapGeometry {
    /// The footprints of `world`: boulders are axis-aligned boxes (as the
    /// world file and the spawn sampler treat them), the monolith its box.
    pub fn from_world(world: &WorldSpec) -> Result<Self, NavError> {
        let e = &world.enclosure;
        let interior = Rect {
            min: Point::new(f64::from(e.x_min), f64::from(e.y_min)),
            max: Point::new(f64::from(e.x_max), f64::from(e.y_max)),
        };
        if !interior.is_finite()
            || interior.min.x >= interior.max.x
            || interior.min.y >= interior.max.y
        {
            return Err(NavError::InvalidMap("enclosure is empty or not finite"));
        }
        let m = &world.monolith;
        let monolith = Rect::centred(
            f64::from(m.center[0]),
            f64::from(m.center[1]),
            f64::from(m.size[0]),
            f64::from(m.size[1]),
        );
        let boulders = world.boulders.iter().map(|b| {
            Rect::centred(
                f64::from(b.center[0]),
                f64::from(b.center[1]),
                f64::from(b.size[0]),
                f64::from(b.size[1]),
            )
        });
        let obstacles: Vec<Rect> = std::iter::once(monolith).chain(boulders).collect();
        if !obstacles.iter().all(Rect::is_finite) {
            return Err(NavError::InvalidMap("an obstacle footprint is not finite"));
        }
        Ok(Self {
            interior,
            obstacles,
        })
    }

    /// Distance from `p` to the nearest wall face or obstacle footprint, m;
    /// 0 or less when `p` is outside the interior or inside a footprint.
    pub fn clearance(&self, p: Point) -> f64 {
        let i = &self.interior;
        let walls = (p.x - i.min.x)
            .min(i.max.x - p.x)
            .min(p.y - i.min.y)
            .min(i.max.y - p.y);
        self.obstacles
            .iter()
            .map(|o| o.distance_to_point(p))
            .fold(walls, f64::min)
    }

    /// Smallest clearance of any point of `rect`, m (0 or less when part of
    /// it is outside the interior or touches a footprint).
    pub fn rect_clearance(&self, rect: &Rect) -> f64 {
        let i = &self.interior;
        let walls = (rect.min.x - i.min.x)
            .min(i.max.x - rect.max.x)
            .min(rect.min.y - i.min.y)
            .min(i.max.y - rect.max.y);
        self.obstacles
            .iter()
            .map(|o| o.gap_to(rect))
            .fold(walls, f64::min)
    }

    /// `p` is strictly inside the inner wall faces.
    pub fn inside_enclosure(&self, p: Point) -> bool {
        let i = &self.interior;
        p.x > i.min.x && p.x < i.max.x && p.y > i.min.y && p.y < i.max.y
    }

    /// `p` lies in (or on) an obstacle footprint.
    pub fn inside_obstacle(&self, p: Point) -> bool {
        self.obstacles.iter().any(|o| o.contains(p))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    #[test]
    fn wrap_angle_maps_into_half_open_interval() {
        assert!((wrap_angle(3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(-3.0 * PI) - PI).abs() < 1e-12);
        assert!((wrap_angle(2.0 * PI + 0.25) - 0.25).abs() < 1e-12);
        assert!((wrap_angle(-0.5) + 0.5).abs() < 1e-12);
    }

    #[test]
    fn clearance_is_exact_for_walls_and_boxes() {
        let world = WorldSpec::builtin("monolith_obstacle").expect("world");
        let map = MapGeometry::from_world(&world).expect("map");
        assert_eq!(map.obstacles.len(), 15);
        // 0.1 m right of the last boulder's right face (x = 0.029 + 0.13).
        let p = Point::new(0.029 + 0.13 + 0.1, -0.903);
        assert!((map.clearance(p) - 0.1).abs() < 1e-6);
        assert!(map.inside_obstacle(Point::new(0.029, -0.903)));
        assert!(map.clearance(Point::new(0.029, -0.903)) <= 0.0);
        // Near the top wall, far from everything else.
        assert!((map.clearance(Point::new(1.5, 1.235 - 0.07)) - 0.07).abs() < 1e-6);
        assert!(!map.inside_enclosure(Point::new(2.1, 0.0)));
        let cell = Rect::centred(0.029 + 0.13 + 0.2, -0.903, 0.1, 0.1);
        assert!((map.rect_clearance(&cell) - 0.15).abs() < 1e-6);
    }
}
