//! Robot physics in rapier3d: a rigid chassis (mass, inertia, gravity) that
//! collides with walls, monolith and boulders, carried over the terrain by
//! four wheel suspensions (spring-damper on a vertical ray to the exact
//! terrain surface), driven by a skid-steer velocity servo with acceleration
//! limits.
//!
//! Why not rigid wheel–terrain contact: one contact manifold per heightfield
//! triangle under the robot costs 5–10× more per substep (see
//! `../shared/reference/sim-performance-facts.md`). The suspension is
//! rapier dynamics all the same (forces integrated by the solver), and the
//! wheel rays only see terrain, so a wheel touching a boulder cannot tip the
//! chassis: the chassis box collides with boulders instead.

use std::collections::VecDeque;
use std::sync::Arc;

use rapier3d::prelude::*;

use crate::profile::MotionProfile;
use crate::scene::Scene;
use crate::terrain::Terrain;
use crate::world::RobotSpec;

/// Physics time step, s.
pub const DT: f32 = 1.0 / 60.0;
/// Substeps of stillness used to let the suspension settle after a teleport.
const SETTLE_STEPS: usize = 20;
/// Suspension stiffness per wheel, N/m.
const SPRING_K: f32 = 2500.0;
/// Suspension damping per wheel, N·s/m.
const SPRING_C: f32 = 110.0;
/// Wheel travel below the rest position before the wheel loses the ground, m.
const TRAVEL: f32 = 0.04;
/// Substeps `drive` waits for the servo to stop beyond the ramp and the
/// latency (a guard: the ramp always ends).
const STOP_MARGIN_STEPS: usize = 600;
/// The chassis' angular damping, 1/s.
const ANGULAR_DAMPING: f32 = 2.0;
/// How close (m) the chassis' bounding box may come to a wall, the
/// monolith or a boulder before rapier steps it: rapier's default contact
/// prediction distance (2 cm) plus two substeps at top speed (≤ 0.7 m/s,
/// ~1.2 cm each), rounded up. Farther, rapier would make no contact, so the
/// chassis moves freely.
const CONTACT_MARGIN: f32 = 0.05;

/// A planar robot state in the world frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlanarPose {
    /// m.
    pub x: f32,
    /// m.
    pub y: f32,
    /// rad.
    pub yaw: f32,
}

/// The full body pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BodyPose {
    /// base_link origin in the world, m.
    pub position: [f32; 3],
    /// Orientation quaternion (x, y, z, w).
    pub orientation: [f32; 4],
    /// Heading, rad.
    pub yaw: f32,
    /// Nose-down pitch, rad.
    pub pitch: f32,
    /// Roll (right side down positive), rad.
    pub roll: f32,
}

/// What the servo is doing: commanded and current wheel-odometry speeds.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct ServoState {
    /// Target forward speed, m/s.
    pub target_linear: f32,
    /// Target yaw rate, rad/s.
    pub target_angular: f32,
    /// Ramped forward speed, m/s.
    pub linear: f32,
    /// Ramped yaw rate, rad/s.
    pub angular: f32,
}

/// The robot in its rapier world.
pub struct RobotPhysics {
    world: PhysicsWorld,
    robot: RigidBodyHandle,
    spec: RobotSpec,
    terrain: Arc<Terrain>,
    scene_boxes: Vec<crate::scene::SceneBox>,
    /// The chassis box: its centre in base_link and its half extents, m.
    chassis_offset: Vector,
    chassis_half: Vector,
    wheels: [Vector; 4],
    /// Static sag so that the chassis rests with base_link at wheel-radius height.
    sag: f32,
    servo: ServoState,
    /// Wheel odometry: the servo's speeds integrated (slip included, as on
    /// a real skid-steer robot), in the frame of the first pose.
    odom: PlanarPose,
    /// Simulated time since creation, s.
    time: f64,
    /// Substeps since creation (the latency queue's clock: exact, unlike `time`).
    steps: u64,
    /// How this robot's base differs from the nominal one.
    motion: MotionProfile,
    /// Acceleration limits after the profile's settle time, m/s², rad/s².
    linear_accel: f32,
    angular_accel: f32,
    /// The profile's latency in substeps.
    latency_steps: u64,
    /// Servo targets given but not yet applied (latency): (substep at which
    /// they apply, linear, angular), in order.
    pending: VecDeque<(u64, f32, f32)>,
}

impl RobotPhysics {
    /// A world for `scene` with the robot at `start`.
    pub fn new(scene: &Scene, start: PlanarPose) -> Self {
        let spec = scene.world.robot.clone();
        let (hw, ht) = (spec.wheel_base * 0.5, spec.track_width * 0.5);
        let sag = spec.mass() * 9.81 / (4.0 * SPRING_K);
        let mut physics = Self {
            world: PhysicsWorld::new(),
            robot: RigidBodyHandle::invalid(),
            spec,
            terrain: scene.terrain.clone(),
            scene_boxes: scene.boxes.clone(),
            chassis_offset: Vector::ZERO,
            chassis_half: Vector::ZERO,
            wheels: [
                Vector::new(hw, ht, 0.0),
                Vector::new(hw, -ht, 0.0),
                Vector::new(-hw, ht, 0.0),
                Vector::new(-hw, -ht, 0.0),
            ],
            sag,
            servo: ServoState::default(),
            odom: PlanarPose {
                x: 0.0,
                y: 0.0,
                yaw: 0.0,
            },
            time: 0.0,
            steps: 0,
            motion: MotionProfile::default(),
            linear_accel: 0.0,
            angular_accel: 0.0,
            latency_steps: 0,
            pending: VecDeque::new(),
        };
        physics.set_profile(MotionProfile::default());
        physics.teleport(start);
        physics
    }

    /// Makes the base behave per `motion` from now on (gains, latency,
    /// servo ramp); targets still waiting for the old latency apply at once.
    /// The default profile is the nominal base, bit for bit.
    pub fn set_profile(&mut self, motion: MotionProfile) {
        self.motion = motion;
        (self.linear_accel, self.angular_accel) = motion.accel_limits(&self.spec);
        self.latency_steps = (motion.latency_s.max(0.0) / DT).round() as u64;
        while let Some((_, linear, angular)) = self.pending.pop_front() {
            self.servo.target_linear = linear;
            self.servo.target_angular = angular;
        }
    }

    /// The base's profile.
    pub fn profile(&self) -> &MotionProfile {
        &self.motion
    }

    /// The acceleration limits in force (the world's robot scaled by the
    /// profile's settle time): (m/s², rad/s²).
    pub fn accel_limits(&self) -> (f32, f32) {
        (self.linear_accel, self.angular_accel)
    }

    /// Rebuilds the world with the robot resting at `pose`. Rebuilding (not
    /// moving) makes what follows independent of history: same pose + same
    /// commands → same result.
    pub fn teleport(&mut self, pose: PlanarPose) {
        let mut world = PhysicsWorld::new();
        world.gravity = Vector::new(0.0, 0.0, -9.81);
        world.integration_parameters.dt = DT;
        // One body, driven by a velocity servo and sliding against static
        // boxes: one solver iteration per substep holds it outside walls and
        // boulders (`tests/integration/physics.rs`) at 64 % of rapier's default four's
        // instructions (docs/performance.md, "The twin's physics"). Its
        // speeds (≤ 0.7 m/s driving, ~1 cm a substep; a settle after a
        // reset drops it millimetres) cannot tunnel through a 10 cm wall or
        // a boulder, and the terrain is not a collider (the wheel rays), so
        // continuous collision detection is off.
        world.integration_parameters.num_solver_iterations = 1;
        world.integration_parameters.max_ccd_substeps = 0;
        for b in &self.scene_boxes {
            let [hx, hy, hz] = b.half_extents();
            let [x, y, z] = b.center();
            world.insert(
                RigidBodyBuilder::fixed().translation(Vector::new(x, y, z)),
                ColliderBuilder::cuboid(hx, hy, hz).friction(0.5),
            );
        }
        let [sx, sy, sz] = self.spec.size;
        let r = self.spec.wheel_radius;
        let chassis_h = sz - self.spec.ground_clearance;
        // base_link is at axle height: the box spans from ground clearance
        // above the wheel bottoms to the top of the robot.
        let chassis_z = -r + self.spec.ground_clearance + chassis_h * 0.5;
        self.chassis_offset = Vector::new(0.0, 0.0, chassis_z);
        self.chassis_half = Vector::new(sx * 0.5, sy * 0.5, chassis_h * 0.5);
        let z = self.terrain.height_at(pose.x, pose.y) + r;
        let body = RigidBodyBuilder::dynamic()
            .pose(Pose::from_parts(
                Vector::new(pose.x, pose.y, z),
                Rotation::from_rotation_z(pose.yaw),
            ))
            .can_sleep(false)
            // Off so that free motion (`move_freely`) and rapier's steps
            // integrate the same equations: the chassis turns slowly about
            // its axes, and the gyroscopic torque of that is negligible.
            .gyroscopic_forces_enabled(false)
            .angular_damping(ANGULAR_DAMPING);
        let collider = ColliderBuilder::cuboid(sx * 0.5, sy * 0.5, chassis_h * 0.5)
            .translation(Vector::new(0.0, 0.0, chassis_z))
            .mass(self.spec.mass())
            .friction(0.3);
        let (robot, _) = world.insert(body, collider);
        self.world = world;
        self.robot = robot;
        self.servo = ServoState::default();
        self.pending.clear();
        for _ in 0..SETTLE_STEPS {
            self.substep();
        }
        // Settling tilts the chassis about its centre of mass, which moves
        // base_link sideways on a slope (up to ~1 cm): put it back where it
        // was asked for, keeping the settled height and tilt, so a reset
        // (and a parity replay from a recorded pose) starts exactly there.
        if let Some(body) = self.world.bodies.get_mut(self.robot) {
            let settled = *body.position();
            let forward = settled.rotation * Vector::X;
            let turn = Rotation::from_rotation_z(pose.yaw - forward.y.atan2(forward.x));
            body.set_position(
                Pose::from_parts(
                    Vector::new(pose.x, pose.y, settled.translation.z),
                    turn * settled.rotation,
                ),
                true,
            );
        }
    }

    /// Drives at (`linear`, `angular`) for `duration` s, then commands zero
    /// and runs until the servo has stopped. Speeds beyond the robot's limits
    /// are clamped. With a latency, the base starts (and stops) that much
    /// later. Returns the simulated time taken, s.
    pub fn drive(&mut self, linear: f32, angular: f32, duration: f32) -> f32 {
        let steps = (duration.max(0.0) / DT).round() as usize;
        self.set_targets(linear, angular);
        for _ in 0..steps {
            self.substep();
        }
        self.set_targets(0.0, 0.0);
        let (max_linear, max_angular) = (self.spec.max_linear_speed, self.spec.max_angular_speed);
        let ramp_s = (max_linear / self.linear_accel).max(max_angular / self.angular_accel);
        let max_stop =
            STOP_MARGIN_STEPS + self.latency_steps as usize + (ramp_s / DT).ceil() as usize;
        let mut stop_steps = 0;
        while (self.servo.linear != 0.0 || self.servo.angular != 0.0 || !self.pending.is_empty())
            && stop_steps < max_stop
        {
            self.substep();
            stop_steps += 1;
        }
        // One more step so the chassis comes to rest on its springs.
        self.substep();
        (steps + stop_steps + 1) as f32 * DT
    }

    /// Sets the servo targets without stepping (real-time mode steps
    /// itself); with the profile's latency they take effect that many
    /// substeps later, in the order given.
    pub fn set_targets(&mut self, linear: f32, angular: f32) {
        let linear = linear.clamp(-self.spec.max_linear_speed, self.spec.max_linear_speed);
        let angular = angular.clamp(-self.spec.max_angular_speed, self.spec.max_angular_speed);
        if self.latency_steps == 0 {
            self.servo.target_linear = linear;
            self.servo.target_angular = angular;
            return;
        }
        // A repeat of the newest target changes nothing: keeps the queue as
        // short as the distinct commands in flight (a teleop repeats its twist).
        let newest = self.pending.back().map_or(
            (self.servo.target_linear, self.servo.target_angular),
            |&(_, l, a)| (l, a),
        );
        if newest != (linear, angular) {
            self.pending
                .push_back((self.steps + self.latency_steps, linear, angular));
        }
    }

    /// Whether targets given are still waiting for the latency to pass.
    pub fn targets_pending(&self) -> bool {
        !self.pending.is_empty()
    }

    /// One fixed physics step.
    pub fn substep(&mut self) {
        while let Some(&(due, linear, angular)) = self.pending.front() {
            if due > self.steps {
                break;
            }
            self.pending.pop_front();
            self.servo.target_linear = linear;
            self.servo.target_angular = angular;
        }
        self.ramp_servo();
        let Some(body) = self.world.bodies.get_mut(self.robot) else {
            return;
        };
        let pose = *body.position();
        let mut grounded = 0;
        for wheel in self.wheels {
            let p = pose.transform_point(wheel);
            let ground = self.terrain.height_at(p.x, p.y);
            // Positive when the spring is compressed past its free length.
            let compression = ground + self.spec.wheel_radius + self.sag - p.z;
            if compression <= 0.0 || compression > TRAVEL + self.sag + 0.1 {
                continue;
            }
            grounded += 1;
            let vz = body.velocity_at_point(p).z;
            let force = (SPRING_K * compression - SPRING_C * vz).max(0.0);
            body.apply_impulse_at_point(Vector::new(0.0, 0.0, force * DT), p, true);
        }
        if grounded > 0 {
            // Traction: the wheels set the planar velocity (no lateral slip),
            // gravity and the springs own the vertical motion.
            let heading = pose.rotation * Vector::X;
            let flat = Vector::new(heading.x, heading.y, 0.0).normalize_or_zero();
            let v = body.linvel();
            // The profile's gains: the body keeps this fraction of the
            // wheels' speed (odometry, in `ramp_servo`, keeps the wheels').
            let planar = flat * (self.servo.linear * self.motion.linear_gain);
            body.set_linvel(Vector::new(planar.x, planar.y, v.z), true);
            let w = body.angvel();
            let yaw_rate = self.servo.angular * self.motion.angular_gain;
            body.set_angvel(Vector::new(w.x, w.y, yaw_rate), true);
        }
        if self.may_touch_a_box() {
            self.world.step();
        } else {
            self.move_freely();
        }
        self.time += f64::from(DT);
        self.steps += 1;
    }

    /// Whether the chassis is near enough a wall, the monolith or a boulder
    /// to touch one within a substep: its box's world bounds, grown by
    /// [`CONTACT_MARGIN`], overlap the other box.
    fn may_touch_a_box(&self) -> bool {
        let Some(body) = self.world.bodies.get(self.robot) else {
            return true;
        };
        let pose = body.position();
        let centre = pose.transform_point(self.chassis_offset);
        let (q, h) = (pose.rotation, self.chassis_half);
        let (x, y, z) = (
            (q * Vector::X).abs(),
            (q * Vector::Y).abs(),
            (q * Vector::Z).abs(),
        );
        let reach = x * h.x + y * h.y + z * h.z + Vector::splat(CONTACT_MARGIN);
        let (low, high) = ((centre - reach).to_array(), (centre + reach).to_array());
        self.scene_boxes
            .iter()
            .any(|b| (0..3).all(|i| low[i] <= b.max[i] && b.min[i] <= high[i]))
    }

    /// One substep of the chassis touching nothing, without rapier: what
    /// its solver does for a lone body (semi-implicit Euler: gravity into
    /// the velocity, the pose turned (linearised) and moved about the
    /// centre of mass, then the damping), at a small fraction of its fixed cost
    /// per step (docs/performance.md, "Free motion").
    fn move_freely(&mut self) {
        let gravity = self.world.gravity;
        let Some(body) = self.world.bodies.get_mut(self.robot) else {
            return;
        };
        let linvel = body.linvel() + gravity * (body.gravity_scale() * DT);
        let angvel = body.angvel();
        let pose = *body.position();
        let local_com = body.local_center_of_mass();
        let centre = pose.transform_point(local_com);
        // Rapier's solver turns a body by the linearised rotation
        // (`integrate_linearized`): identity + half the angle, normalised.
        let half_turn = angvel * (DT * 0.5);
        let turn = Rotation::from_xyzw(half_turn.x, half_turn.y, half_turn.z, 1.0);
        let rotation = (turn * pose.rotation).normalize();
        let translation = centre + linvel * DT - rotation * local_com;
        body.set_position(Pose::from_parts(translation, rotation), false);
        let damping = |rate: f32| 1.0 / (1.0 + DT * rate);
        body.set_linvel(linvel * damping(body.linear_damping()), false);
        body.set_angvel(angvel * damping(body.angular_damping()), false);
    }

    fn ramp_servo(&mut self) {
        let ramp = |current: f32, target: f32, max_delta: f32| {
            current + (target - current).clamp(-max_delta, max_delta)
        };
        let s = &mut self.servo;
        s.linear = ramp(s.linear, s.target_linear, self.linear_accel * DT);
        s.angular = ramp(s.angular, s.target_angular, self.angular_accel * DT);
        let o = &mut self.odom;
        o.yaw += s.angular * DT;
        o.x += s.linear * o.yaw.cos() * DT;
        o.y += s.linear * o.yaw.sin() * DT;
    }

    /// Wheel odometry pose (odom frame).
    pub fn odometry(&self) -> PlanarPose {
        self.odom
    }

    /// The robot's pose.
    pub fn body_pose(&self) -> BodyPose {
        let Some(body) = self.world.bodies.get(self.robot) else {
            return BodyPose {
                position: [0.0; 3],
                orientation: [0.0, 0.0, 0.0, 1.0],
                yaw: 0.0,
                pitch: 0.0,
                roll: 0.0,
            };
        };
        let pose = body.position();
        let t = pose.translation;
        let q = pose.rotation;
        let forward = q * Vector::X;
        let left = q * Vector::Y;
        let yaw = forward.y.atan2(forward.x);
        let pitch = (-forward.z).asin();
        let roll = (-left.z).asin();
        BodyPose {
            position: [t.x, t.y, t.z],
            orientation: [q.x, q.y, q.z, q.w],
            yaw,
            pitch,
            roll,
        }
    }

    /// Planar pose.
    pub fn planar_pose(&self) -> PlanarPose {
        let p = self.body_pose();
        PlanarPose {
            x: p.position[0],
            y: p.position[1],
            yaw: p.yaw,
        }
    }

    /// Transforms a point from base_link to the world.
    pub fn to_world(&self, local: [f32; 3]) -> [f32; 3] {
        self.world
            .bodies
            .get(self.robot)
            .map(|b| b.position().transform_point(Vector::from(local)).to_array())
            .unwrap_or(local)
    }

    /// The servo (wheel odometry) state.
    pub fn servo(&self) -> ServoState {
        self.servo
    }

    /// Simulated seconds since creation.
    pub fn time(&self) -> f64 {
        self.time
    }
}
