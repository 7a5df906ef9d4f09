//! The simulator facade: physics + camera + tracker for one enclosure,
//! deterministic for a seed and a command sequence. No networking here (see
//! [`crate::node`]).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use crate::camera::{CameraPose, ColumnRenderer, Intrinsics, PixelsMut, RgbdFrame};
use crate::error::SimError;
use crate::physics::{BodyPose, PlanarPose, RobotPhysics};
use crate::scene::Scene;
use crate::tracker::{SimTracker, TrackerConfig};
use crate::world::{LightSpec, WorldSpec};

/// Longest single motion accepted, s.
pub const MAX_MOTION_S: f32 = 10.0;

/// Domain randomisation, all off by default; seeded.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Randomization {
    /// Seed of every random draw below.
    pub seed: u64,
    /// Depth noise: standard deviation as a fraction of depth (e.g. 0.01).
    pub depth_noise: f32,
    /// Fraction of depth pixels dropped to invalid (e.g. 0.02).
    pub depth_dropout: f32,
    /// Light intensity varies per episode by ± this fraction.
    pub light_jitter: f32,
    /// Surface albedo varies per episode by ± this fraction.
    pub albedo_jitter: f32,
    /// Wheel slip varies per episode in [0, this]: the fraction of commanded
    /// speed lost (a friction proxy).
    pub max_slip: f32,
}

/// Everything a twin is made from.
#[derive(Debug, Clone, PartialEq)]
pub struct TwinConfig {
    /// The enclosure.
    pub world: WorldSpec,
    /// Rendered size (the native camera resampled); `None` = native 320×240.
    pub resolution: Option<(u32, u32)>,
    /// The tracker.
    pub tracker: TrackerConfig,
    /// Randomisation knobs.
    pub randomization: Randomization,
    /// Where the robot starts.
    pub start: PlanarPose,
}

impl TwinConfig {
    /// A twin of a built-in world with defaults.
    pub fn builtin(world: &str) -> Result<Self, SimError> {
        Ok(Self {
            world: WorldSpec::builtin(world)?,
            resolution: None,
            tracker: TrackerConfig::default(),
            randomization: Randomization::default(),
            start: PlanarPose {
                x: -1.0,
                y: 0.5,
                yaw: 0.0,
            },
        })
    }
}

/// One simulated enclosure.
pub struct SimTwin {
    base_scene: Scene,
    scene: Scene,
    physics: RobotPhysics,
    renderer: ColumnRenderer,
    frame: RgbdFrame,
    tracker: SimTracker,
    randomization: Randomization,
    rng: ChaCha8Rng,
    slip: f32,
}

impl SimTwin {
    /// Builds the twin (terrain, physics world, renderer).
    pub fn new(config: TwinConfig) -> Result<Self, SimError> {
        let (w, h) = config
            .resolution
            .unwrap_or((config.world.camera.width, config.world.camera.height));
        if w == 0 || h == 0 || w > 4096 || h > 4096 {
            return Err(SimError::BadCommand(format!(
                "resolution {w}x{h} out of range"
            )));
        }
        let scene = Scene::build(&config.world);
        let intrinsics = Intrinsics::resized(&config.world.camera, w, h);
        let renderer = ColumnRenderer::new(intrinsics, &config.world.light);
        let physics = RobotPhysics::new(&scene, config.start);
        Ok(Self {
            base_scene: scene.clone(),
            scene,
            physics,
            renderer,
            frame: RgbdFrame::new(w, h),
            tracker: SimTracker::new(config.tracker),
            randomization: config.randomization,
            rng: ChaCha8Rng::seed_from_u64(config.randomization.seed),
            slip: 0.0,
        })
    }

    /// Executes one motion: drive for `duration` s, then stop. Rejects
    /// non-finite values and durations outside `[0, MAX_MOTION_S]`.
    /// Returns the simulated time taken, s.
    pub fn execute(&mut self, linear: f64, angular: f64, duration: f64) -> Result<f32, SimError> {
        if !(linear.is_finite() && angular.is_finite() && duration.is_finite()) {
            return Err(SimError::BadCommand("non-finite motion".into()));
        }
        if !(0.0..=f64::from(MAX_MOTION_S)).contains(&duration) {
            return Err(SimError::BadCommand(format!(
                "duration {duration} s outside [0, {MAX_MOTION_S}]"
            )));
        }
        let keep = 1.0 - self.slip;
        Ok(self
            .physics
            .drive(linear as f32 * keep, angular as f32 * keep, duration as f32))
    }

    /// Moves the robot to `pose` at once (sim-only reset) and draws the next
    /// episode's randomisation.
    pub fn teleport(&mut self, pose: PlanarPose) -> Result<(), SimError> {
        if !(pose.x.is_finite() && pose.y.is_finite() && pose.yaw.is_finite()) {
            return Err(SimError::BadCommand("non-finite pose".into()));
        }
        let e = &self.scene.world.enclosure;
        if pose.x <= e.x_min || pose.x >= e.x_max || pose.y <= e.y_min || pose.y >= e.y_max {
            return Err(SimError::BadCommand(format!(
                "pose ({}, {}) is outside the enclosure",
                pose.x, pose.y
            )));
        }
        self.randomize_episode();
        self.tracker.restart_noise([pose.x, pose.y, pose.yaw]);
        self.physics.teleport(pose);
        Ok(())
    }

    fn randomize_episode(&mut self) {
        let r = self.randomization;
        let mut jitter = |amount: f32| {
            if amount > 0.0 {
                1.0 + amount * (2.0 * self.rng.random::<f32>() - 1.0)
            } else {
                1.0
            }
        };
        let light = jitter(r.light_jitter);
        let albedo = jitter(r.albedo_jitter);
        self.slip = if r.max_slip > 0.0 {
            r.max_slip * self.rng.random::<f32>()
        } else {
            0.0
        };
        if light == 1.0 && albedo == 1.0 {
            return;
        }
        let mut scene = self.base_scene.clone();
        for b in &mut scene.boxes {
            b.albedo *= albedo;
        }
        scene.world.terrain.albedo *= albedo;
        let base: &LightSpec = &self.base_scene.world.light;
        scene.world.light.ambient = base.ambient * light;
        scene.world.light.diffuse = base.diffuse * light;
        self.renderer = ColumnRenderer::new(*self.renderer.intrinsics(), &scene.world.light);
        self.scene = scene;
    }

    /// The camera's pose (level: the chassis' pitch and roll are not
    /// rendered, see [`crate::camera`]).
    pub fn camera_pose(&self) -> CameraPose {
        let body = self.physics.body_pose();
        let position = self.physics.to_world(self.scene.world.camera.mount);
        CameraPose {
            position,
            yaw: body.yaw,
            pitch: body.pitch,
            roll: body.roll,
        }
    }

    /// Renders the current view (with noise if enabled).
    pub fn render(&mut self) -> &RgbdFrame {
        let pose = self.camera_pose();
        self.renderer.render(&self.scene, &pose, &mut self.frame);
        perturb_depth(&self.randomization, &mut self.rng, &mut self.frame.depth);
        &self.frame
    }

    /// [`Self::render`] into `pixels` (e.g. a message's pixel fields), which
    /// must have the camera's resolution; false, writing nothing, if not.
    pub fn render_into(&mut self, mut pixels: PixelsMut<'_>) -> bool {
        let pose = self.camera_pose();
        if !self.renderer.render_into(&self.scene, &pose, &mut pixels) {
            return false;
        }
        perturb_depth(&self.randomization, &mut self.rng, pixels.depth);
        true
    }

    /// Ground-truth base_link pose.
    pub fn ground_truth(&self) -> BodyPose {
        self.physics.body_pose()
    }

    /// What the tracker reports now.
    pub fn tracker_reading(&mut self) -> BodyPose {
        let truth = self.physics.body_pose();
        self.tracker.read(&truth)
    }

    /// Tracker settings.
    pub fn tracker_config(&self) -> &TrackerConfig {
        self.tracker.config()
    }

    /// The physics (wheel odometry, servo, time).
    pub fn physics(&self) -> &RobotPhysics {
        &self.physics
    }

    /// Mutable physics, for the real-time clock.
    pub fn physics_mut(&mut self) -> &mut RobotPhysics {
        &mut self.physics
    }

    /// The scene.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Intrinsics of rendered frames.
    pub fn intrinsics(&self) -> &Intrinsics {
        self.renderer.intrinsics()
    }
}

/// Depth noise and dropout, if enabled.
fn perturb_depth(r: &Randomization, rng: &mut ChaCha8Rng, depth: &mut [f32]) {
    if r.depth_noise <= 0.0 && r.depth_dropout <= 0.0 {
        return;
    }
    for d in depth {
        if r.depth_dropout > 0.0 && rng.random::<f32>() < r.depth_dropout {
            *d = f32::NAN;
        } else if r.depth_noise > 0.0 && d.is_finite() {
            *d *= 1.0 + r.depth_noise * rng.sample::<f32, _>(StandardNormal);
        }
    }
}
