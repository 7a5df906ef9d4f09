//! The simulator facade: physics + camera + tracker for one enclosure,
//! deterministic for a seed and a command sequence. No networking here (see
//! [`crate::node`]).

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rand_distr::StandardNormal;

use offworld_runtime::Resolution;

use crate::camera::{CameraPose, ColumnRenderer, ExactRenderer, Intrinsics, PixelsMut, RgbdFrame};
use crate::error::SimError;
use crate::physics::{BodyPose, PlanarPose, RobotPhysics};
use crate::profile::{DepthProfile, TwinProfile};
use crate::scene::Scene;
use crate::tracker::{SimTracker, TrackerConfig};
use crate::world::{LightSpec, WorldSpec};

/// Longest single motion accepted, s.
pub const MAX_MOTION_S: f32 = 10.0;

/// Domain randomisation, all off by default; seeded.
///
/// `depth_noise` and `depth_dropout` are the same sensor model as the twin
/// profile's [`DepthProfile`] (kept here for the CLI flags and existing
/// callers): a twin takes each from whichever of the two sets it, and
/// refuses a config where both set the same one.
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

/// The most threads a frame may be rendered on (flags and
/// `OFFWORLD_RENDER_THREADS` accept 1 to this).
pub const RENDER_THREADS_LIMIT: u16 = 64;

/// Everything a twin is made from.
#[derive(Debug, Clone, PartialEq)]
pub struct TwinConfig {
    /// The enclosure.
    pub world: WorldSpec,
    /// Rendered size (the native camera resampled); `None` = native 320×240.
    pub resolution: Option<Resolution>,
    /// The tracker.
    pub tracker: TrackerConfig,
    /// Randomisation knobs.
    pub randomization: Randomization,
    /// Where the robot starts.
    pub start: PlanarPose,
    /// The physical robot this twin stands for (default: the nominal twin).
    pub profile: TwinProfile,
    /// Threads a frame is rendered on (1: the twin's own; see
    /// [`ColumnRenderer::with_threads`]).
    pub render_threads: usize,
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
            profile: TwinProfile::default(),
            render_threads: 1,
        })
    }
}

/// One simulated enclosure.
pub struct SimTwin {
    base_scene: Scene,
    scene: Scene,
    physics: RobotPhysics,
    renderer: ColumnRenderer,
    /// The per-pixel renderer, used instead of `renderer` when the profile
    /// tilts the camera (the column walk is exact only for a level camera).
    exact: Option<ExactRenderer>,
    frame: RgbdFrame,
    tracker: SimTracker,
    randomization: Randomization,
    profile: TwinProfile,
    /// The camera mount in base_link with the profile's height offset, m.
    mount: [f32; 3],
    /// The profile's camera yaw and pitch offsets, rad.
    yaw_offset: f32,
    pitch_offset: f32,
    /// The depth model in force (the profile's or the randomisation's).
    depth: DepthProfile,
    rng: ChaCha8Rng,
    slip: f32,
}

impl SimTwin {
    /// Builds the twin (terrain, physics world, renderer).
    pub fn new(config: TwinConfig) -> Result<Self, SimError> {
        let Resolution {
            width: w,
            height: h,
        } = config.resolution.unwrap_or(Resolution::new(
            config.world.camera.width,
            config.world.camera.height,
        ));
        if w == 0 || h == 0 || w > 4096 || h > 4096 {
            return Err(SimError::BadCommand(format!(
                "resolution {w}x{h} out of range"
            )));
        }
        let profile = config.profile;
        profile.validate()?;
        let depth = depth_model(&config.randomization, &profile.depth)?;
        let scene = Scene::build(&config.world);
        let intrinsics = Intrinsics::resized(&config.world.camera, w, h);
        if !(1..=usize::from(RENDER_THREADS_LIMIT)).contains(&config.render_threads) {
            return Err(SimError::BadCommand(format!(
                "render threads {} out of range 1–{RENDER_THREADS_LIMIT}",
                config.render_threads
            )));
        }
        let renderer = ColumnRenderer::new(intrinsics, &config.world.light)
            .with_threads(config.render_threads)
            .map_err(|e| SimError::Threads(e.to_string()))?;
        let exact = (profile.camera.pitch_deg != 0.0)
            .then(|| ExactRenderer::new(intrinsics, &config.world.light, &scene));
        let mut physics = RobotPhysics::new(&scene, config.start);
        physics.set_profile(profile.motion);
        let [mx, my, mz] = config.world.camera.mount;
        Ok(Self {
            base_scene: scene.clone(),
            scene,
            physics,
            renderer,
            exact,
            frame: RgbdFrame::new(w, h),
            tracker: SimTracker::new(config.tracker),
            randomization: config.randomization,
            profile,
            mount: [mx, my, mz + profile.camera.height_offset_m],
            yaw_offset: profile.camera.yaw_deg.to_radians(),
            pitch_offset: profile.camera.pitch_deg.to_radians(),
            depth,
            rng: ChaCha8Rng::seed_from_u64(config.randomization.seed),
            slip: 0.0,
        })
    }

    /// The profile this twin was built with.
    pub fn profile(&self) -> &TwinProfile {
        &self.profile
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
        let intrinsics = *self.renderer.intrinsics();
        self.renderer.set_light(&scene.world.light);
        if self.exact.is_some() {
            self.exact = Some(ExactRenderer::new(intrinsics, &scene.world.light, &scene));
        }
        self.scene = scene;
    }

    /// The camera's pose: the mount (with the profile's offsets) on the
    /// chassis, the chassis' pitch and roll included. What is rendered
    /// treats the chassis as level (see [`crate::camera`]): only the
    /// profile's mount pitch tilts the view.
    pub fn camera_pose(&self) -> CameraPose {
        let body = self.physics.body_pose();
        CameraPose {
            position: self.physics.to_world(self.mount),
            yaw: body.yaw + self.yaw_offset,
            pitch: body.pitch + self.pitch_offset,
            roll: body.roll,
        }
    }

    /// The pose rendered: [`Self::camera_pose`] on a level chassis.
    fn view_pose(&self) -> CameraPose {
        let body = self.physics.body_pose();
        CameraPose {
            position: self.physics.to_world(self.mount),
            yaw: body.yaw + self.yaw_offset,
            pitch: self.pitch_offset,
            roll: 0.0,
        }
    }

    /// Renders the current view (with noise if enabled).
    pub fn render(&mut self) -> &RgbdFrame {
        let pose = self.view_pose();
        match &self.exact {
            Some(exact) => {
                exact.render_into(&pose, &mut self.frame.pixels_mut());
            }
            None => self.renderer.render(&self.scene, &pose, &mut self.frame),
        }
        perturb_depth(&self.depth, &mut self.rng, &mut self.frame.depth);
        &self.frame
    }

    /// [`Self::render`] into `pixels` (e.g. a message's pixel fields), which
    /// must have the camera's resolution; false, writing nothing, if not.
    pub fn render_into(&mut self, mut pixels: PixelsMut<'_>) -> bool {
        let pose = self.view_pose();
        let rendered = match &self.exact {
            Some(exact) => exact.render_into(&pose, &mut pixels),
            None => self.renderer.render_into(&self.scene, &pose, &mut pixels),
        };
        if !rendered {
            return false;
        }
        perturb_depth(&self.depth, &mut self.rng, pixels.depth);
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

/// The depth model: each knob from whichever of the randomisation and the
/// profile sets it (both setting one is a config error: which would win is
/// not obvious).
fn depth_model(r: &Randomization, profile: &DepthProfile) -> Result<DepthProfile, SimError> {
    let pick = |name: &str, randomized: f32, profiled: f32| {
        if randomized != 0.0 && profiled != 0.0 {
            return Err(SimError::BadCommand(format!(
                "depth {name} is set by both the randomisation ({randomized}) and the twin profile ({profiled}): set one"
            )));
        }
        Ok(if profiled != 0.0 {
            profiled
        } else {
            randomized
        })
    };
    Ok(DepthProfile {
        noise: pick("noise", r.depth_noise, profile.noise)?,
        dropout: pick("dropout", r.depth_dropout, profile.dropout)?,
    })
}

/// Depth noise and dropout, if enabled.
fn perturb_depth(model: &DepthProfile, rng: &mut ChaCha8Rng, depth: &mut [f32]) {
    if model.noise <= 0.0 && model.dropout <= 0.0 {
        return;
    }
    for d in depth {
        if model.dropout > 0.0 && rng.random::<f32>() < model.dropout {
            *d = f32::NAN;
        } else if model.noise > 0.0 && d.is_finite() {
            *d *= 1.0 + model.noise * rng.sample::<f32, _>(StandardNormal);
        }
    }
}
