//! The enclosure's overhead camera, simulated: a top-down orthographic
//! colour view of the floor (shaded by height), walls, monolith, boulders
//! and the robot, like the ceiling cameras users of the original service
//! watched through. For spectators and monitors, never for the agent.

use crate::physics::BodyPose;
use crate::scene::{Scene, SurfaceKind};
use offworld_runtime::preview::Watch;

/// An overhead view's pixel grid over the enclosure (walls included).
#[derive(Debug, Clone)]
pub struct OverheadCamera {
    width: u32,
    height: u32,
    /// World x, y of pixel (0, 0)'s centre's corner and metres per pixel.
    origin: [f32; 2],
    scale: f32,
    /// The static background (floor and boxes), rendered once.
    background: Vec<u8>,
}

const ROBOT: [u8; 3] = [230, 120, 30];
const ROBOT_NOSE: [u8; 3] = [255, 230, 60];
const MONOLITH: [u8; 3] = [20, 20, 30];

impl OverheadCamera {
    /// A camera `width` pixels wide covering the enclosure and its walls
    /// (the height follows the enclosure's aspect ratio).
    pub fn new(scene: &Scene, width: u32) -> Self {
        let e = &scene.world.enclosure;
        let t = e.wall_thickness;
        let (x0, x1, y0, y1) = (e.x_min - t, e.x_max + t, e.y_min - t, e.y_max + t);
        let width = width.clamp(16, 2048);
        let scale = (x1 - x0) / width as f32;
        let height = ((y1 - y0) / scale).ceil().max(1.0) as u32;
        let mut camera = Self {
            width,
            height,
            origin: [x0, y1],
            scale,
            background: Vec::new(),
        };
        camera.background = camera.render_background(scene);
        camera
    }

    /// Image width, px.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height, px.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// World (x, y) at the centre of pixel (column, row); row 0 is the far
    /// (+y) wall, so the image reads like a map with +x to the right.
    pub fn world_at(&self, column: u32, row: u32) -> (f32, f32) {
        (
            self.origin[0] + (column as f32 + 0.5) * self.scale,
            self.origin[1] - (row as f32 + 0.5) * self.scale,
        )
    }

    fn render_background(&self, scene: &Scene) -> Vec<u8> {
        let max_h = scene.world.terrain.max_height.max(1e-3);
        let mut rgb = Vec::with_capacity((self.width * self.height * 3) as usize);
        for row in 0..self.height {
            for column in 0..self.width {
                let (x, y) = self.world_at(column, row);
                let top = scene
                    .boxes
                    .iter()
                    .find(|b| x >= b.min[0] && x <= b.max[0] && y >= b.min[1] && y <= b.max[1]);
                let pixel = match top {
                    Some(b) if b.kind == SurfaceKind::Monolith => MONOLITH,
                    Some(b) => {
                        let g = (255.0 * b.albedo.clamp(0.0, 1.0)) as u8;
                        [g, g, g]
                    }
                    None => {
                        // Higher ground is lighter: the relief reads at a glance.
                        let h = scene.terrain.height_at(x, y) / max_h;
                        let g = 70.0 + 120.0 * h.clamp(0.0, 1.0);
                        [g as u8, (g * 0.97) as u8, (g * 0.92) as u8]
                    }
                };
                rgb.extend_from_slice(&pixel);
            }
        }
        rgb
    }

    /// Renders the view with the robot's footprint at `robot` into `rgb`
    /// (resized as needed; `width × height × 3` bytes, row-major).
    pub fn render(&self, scene: &Scene, robot: &BodyPose, rgb: &mut Vec<u8>) {
        rgb.clear();
        rgb.extend_from_slice(&self.background);
        let [length, width, _] = scene.world.robot.size;
        let (hx, hy) = (0.5 * length, 0.5 * width);
        let (sin, cos) = robot.yaw.sin_cos();
        let [rx, ry, _] = robot.position;
        let reach = hx.hypot(hy);
        let to_px = |v: f32, o: f32, sign: f32| ((v - o) * sign / self.scale).floor() as i64;
        let c0 = to_px(rx - reach, self.origin[0], 1.0).max(0);
        let c1 = to_px(rx + reach, self.origin[0], 1.0).min(i64::from(self.width) - 1);
        let r0 = to_px(ry + reach, self.origin[1], -1.0).max(0);
        let r1 = to_px(ry - reach, self.origin[1], -1.0).min(i64::from(self.height) - 1);
        for row in r0..=r1 {
            for column in c0..=c1 {
                let (x, y) = self.world_at(column as u32, row as u32);
                // Into the robot's frame.
                let (dx, dy) = (x - rx, y - ry);
                let (fx, fy) = (cos * dx + sin * dy, -sin * dx + cos * dy);
                if fx.abs() <= hx && fy.abs() <= hy {
                    let colour = if fx > 0.6 * hx { ROBOT_NOSE } else { ROBOT };
                    let at = ((row as u32 * self.width + column as u32) * 3) as usize;
                    rgb[at..at + 3].copy_from_slice(&colour);
                }
            }
        }
    }
}

/// The overhead camera's frames for an env's `overhead/<camera>` key, as
/// `sensor_msgs/Image` rgb8: rate-limited by the wall clock (spectators do
/// not need more, and the step path must not pay for it), and rendered only
/// while someone watches. They are put through the key's
/// [`ViewerCopy`](offworld_runtime::preview::ViewerCopy), whose
/// [`Watch`] this follows.
pub struct OverheadStream {
    camera: OverheadCamera,
    watch: Watch,
    period: std::time::Duration,
    last: Option<std::time::Instant>,
    image: offworld_runtime::msg::Image,
}

impl OverheadStream {
    /// Default frame rate, Hz.
    pub const DEFAULT_HZ: f64 = 2.0;

    /// At most `hz` frames per second, while `watch` says someone watches.
    pub fn new(scene: &Scene, watch: Watch, hz: f64) -> Self {
        let camera = OverheadCamera::new(scene, 320);
        let mut image = offworld_runtime::msg::Image::packed(
            offworld_runtime::msg::Header::new(offworld_runtime::msg::Time::default(), "overhead"),
            camera.width(),
            camera.height(),
            offworld_runtime::msg::PixelEncoding::Rgb8,
            Vec::new(),
        );
        image
            .data
            .reserve((camera.width() * camera.height() * 3) as usize);
        Self {
            camera,
            watch,
            period: std::time::Duration::from_secs_f64(1.0 / hz.clamp(0.01, 60.0)),
            last: None,
            image,
        }
    }

    /// Whether anyone watches now: a caller skips even the robot's pose
    /// for [`OverheadStream::maybe_encode`] when nobody does.
    pub fn watched(&self) -> bool {
        self.watch.watched()
    }

    /// A frame (CDR `sensor_msgs/Image`) if someone watches and the last
    /// one is older than the period. Unwatched, it costs one atomic load:
    /// no render, no encoding.
    pub fn maybe_encode(&mut self, scene: &Scene, robot: &BodyPose) -> Option<Vec<u8>> {
        if !self.watched() {
            return None;
        }
        let now = std::time::Instant::now();
        if self
            .last
            .is_some_and(|t| now.duration_since(t) < self.period)
        {
            return None;
        }
        self.last = Some(now);
        self.image.header.stamp = offworld_runtime::msg::Time::now();
        self.camera.render(scene, robot, &mut self.image.data);
        offworld_runtime::codec::encode(&self.image)
            .map_err(|e| tracing::error!("cannot encode the overhead view: {e}"))
            .ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::WorldSpec;

    fn pixel(camera: &OverheadCamera, rgb: &[u8], x: f32, y: f32) -> [u8; 3] {
        let column = ((x - camera.origin[0]) / camera.scale) as u32;
        let row = ((camera.origin[1] - y) / camera.scale) as u32;
        let at = ((row * camera.width + column) * 3) as usize;
        [rgb[at], rgb[at + 1], rgb[at + 2]]
    }

    #[test]
    fn shows_the_monolith_boulders_and_the_robot_where_they_are() -> Result<(), crate::SimError> {
        let world = WorldSpec::builtin("monolith_obstacle")?;
        let scene = Scene::build(&world);
        let camera = OverheadCamera::new(&scene, 320);
        assert_eq!(camera.width(), 320);
        assert!(camera.height() > 200 && camera.height() < 260, "4:3-ish");
        let robot = BodyPose {
            position: [1.0, 0.5, 0.1],
            orientation: [0.0, 0.0, 0.0, 1.0],
            yaw: 0.0,
            pitch: 0.0,
            roll: 0.0,
        };
        let mut rgb = Vec::new();
        camera.render(&scene, &robot, &mut rgb);
        assert_eq!(rgb.len(), (camera.width() * camera.height() * 3) as usize);
        let m = &world.monolith.center;
        assert_eq!(pixel(&camera, &rgb, m[0], m[1]), MONOLITH);
        assert_eq!(pixel(&camera, &rgb, 1.0, 0.5), ROBOT);
        assert_eq!(
            pixel(&camera, &rgb, 1.09, 0.5),
            ROBOT_NOSE,
            "nose points +x"
        );
        let b = &world.boulders[0];
        let g = (255.0 * b.albedo) as u8;
        assert_eq!(pixel(&camera, &rgb, b.center[0], b.center[1]), [g, g, g]);
        // The robot leaves no trace when it moves on.
        let moved = BodyPose {
            position: [-1.0, -0.8, 0.1],
            ..robot
        };
        camera.render(&scene, &moved, &mut rgb);
        assert_ne!(pixel(&camera, &rgb, 1.0, 0.5), ROBOT);
        assert_eq!(pixel(&camera, &rgb, -1.0, -0.8), ROBOT);
        Ok(())
    }
}
