//! Physics sanity of the ROSbot on flat ground and against walls, and
//! determinism.

use offworld_sim_twin::physics::{PlanarPose, RobotPhysics};
use offworld_sim_twin::scene::Scene;
use offworld_sim_twin::terrain::Terrain;
use offworld_sim_twin::WorldSpec;

fn flat_scene(world: &str) -> Scene {
    let world = WorldSpec::builtin(world).expect("world");
    let flat = Terrain::flat(&world.enclosure, 8, 6, 0.05);
    Scene::with_terrain(&world, flat)
}

fn angle_diff(a: f32, b: f32) -> f32 {
    let d = (a - b).rem_euclid(std::f32::consts::TAU);
    if d > std::f32::consts::PI {
        d - std::f32::consts::TAU
    } else {
        d
    }
}

const START: PlanarPose = PlanarPose {
    x: -1.0,
    y: 0.5,
    yaw: 0.3,
};

#[test]
fn forward_moves_six_centimetres() {
    let mut robot = RobotPhysics::new(&flat_scene("monolith"), START);
    let before = robot.planar_pose();
    robot.drive(0.10, 0.0, 0.6);
    let after = robot.planar_pose();
    let (dx, dy) = (after.x - before.x, after.y - before.y);
    let moved = (dx * dx + dy * dy).sqrt();
    // 0.1 m/s × 0.6 s = 0.06 m; acceleration ramps in and out cancel to
    // within 2 mm (the ramp lasts 0.1/1.5 s at each end).
    assert!((moved - 0.06).abs() < 0.002, "moved {moved}");
    // Straight ahead along the heading.
    assert!(angle_diff(dy.atan2(dx), START.yaw).abs() < 0.02);
    assert!(angle_diff(after.yaw, before.yaw).abs() < 0.01);
    // Stopped, on its wheels: base_link at ground + wheel radius (+ spring sag ≈ 0).
    let z = robot.body_pose().position[2];
    assert!((z - (0.05 + 0.04)).abs() < 0.005, "z {z}");
}

#[test]
fn backward_moves_six_centimetres_back() {
    let mut robot = RobotPhysics::new(&flat_scene("monolith"), START);
    let before = robot.planar_pose();
    robot.drive(-0.10, 0.0, 0.6);
    let after = robot.planar_pose();
    let along = (after.x - before.x) * START.yaw.cos() + (after.y - before.y) * START.yaw.sin();
    assert!((along + 0.06).abs() < 0.002, "moved {along}");
}

#[test]
fn left_turns_one_and_a_half_radians() {
    let mut robot = RobotPhysics::new(&flat_scene("monolith"), START);
    let before = robot.planar_pose();
    robot.drive(0.07, 1.25, 1.2);
    let turned = angle_diff(robot.planar_pose().yaw, before.yaw);
    // 1.25 rad/s × 1.2 s = 1.5 rad; ramps cancel to within 0.02 rad.
    assert!((turned - 1.5).abs() < 0.02, "turned {turned}");
    let mut robot = RobotPhysics::new(&flat_scene("monolith"), START);
    robot.drive(0.07, -1.25, 1.2);
    let turned = angle_diff(robot.planar_pose().yaw, before.yaw);
    assert!((turned + 1.5).abs() < 0.02, "turned {turned}");
}

#[test]
fn driving_into_a_wall_stays_outside_it() {
    let scene = flat_scene("monolith");
    let x_max = scene.world.enclosure.x_max;
    let half_length = scene.world.robot.size[0] * 0.5;
    // Facing the +x wall from 0.5 m away, drive 3 m worth at top speed.
    let mut robot = RobotPhysics::new(
        &scene,
        PlanarPose {
            x: x_max - 0.5,
            y: 0.0,
            yaw: 0.0,
        },
    );
    for _ in 0..6 {
        robot.drive(0.7, 0.0, 1.0);
    }
    let nose = robot.planar_pose().x + half_length;
    assert!(nose <= x_max + 0.01, "nose at {nose}, wall at {x_max}");
    assert!(nose > x_max - 0.05, "stopped short at {nose}");
    // Still upright.
    let p = robot.body_pose();
    assert!(p.pitch.abs() < 0.2 && p.roll.abs() < 0.2, "{p:?}");
}

#[test]
fn boulders_block_the_robot() {
    let scene = flat_scene("monolith_obstacle");
    // Boulder at (0.762, -0.241): approach from -x.
    let mut robot = RobotPhysics::new(
        &scene,
        PlanarPose {
            x: 0.2,
            y: -0.241,
            yaw: 0.0,
        },
    );
    robot.drive(0.5, 0.0, 3.0);
    let nose = robot.planar_pose().x + 0.1;
    let boulder_face = 0.762 - 0.13;
    assert!(
        nose <= boulder_face + 0.01,
        "drove into the boulder: nose {nose}"
    );
}

#[test]
fn same_commands_same_trajectory_bit_for_bit() {
    let world = WorldSpec::builtin("monolith_obstacle").expect("world");
    let scene = Scene::build(&world);
    let run = || {
        let mut robot = RobotPhysics::new(&scene, START);
        let mut trace = Vec::new();
        for (v, w, d) in [
            (0.1, 0.0, 0.6),
            (0.07, 1.25, 1.2),
            (0.7, -2.5, 1.0),
            (-0.1, 0.0, 0.6),
        ] {
            robot.drive(v, w, d);
            trace.push(robot.body_pose().position.map(f32::to_bits));
        }
        robot.teleport(PlanarPose {
            x: 0.5,
            y: 0.5,
            yaw: 1.0,
        });
        robot.drive(0.1, 0.0, 0.6);
        trace.push(robot.body_pose().position.map(f32::to_bits));
        trace
    };
    assert_eq!(run(), run());
    // Teleport rebuilds the world: after it, history does not matter.
    let mut fresh = RobotPhysics::new(
        &scene,
        PlanarPose {
            x: 0.5,
            y: 0.5,
            yaw: 1.0,
        },
    );
    let mut used = RobotPhysics::new(&scene, START);
    used.drive(0.5, 1.0, 2.0);
    used.teleport(PlanarPose {
        x: 0.5,
        y: 0.5,
        yaw: 1.0,
    });
    fresh.drive(0.1, 0.0, 0.6);
    used.drive(0.1, 0.0, 0.6);
    assert_eq!(fresh.body_pose(), used.body_pose());
}

#[test]
fn rough_terrain_keeps_the_robot_on_its_wheels() {
    let world = WorldSpec::builtin("monolith").expect("world");
    let scene = Scene::build(&world);
    let mut robot = RobotPhysics::new(
        &scene,
        PlanarPose {
            x: -1.2,
            y: -1.0,
            yaw: 0.4,
        },
    );
    for i in 0..40 {
        let w = if i % 3 == 0 { 1.25 } else { 0.0 };
        robot.drive(0.3, w, 1.0);
        let p = robot.body_pose();
        assert!(
            p.pitch.abs() < 0.35 && p.roll.abs() < 0.35,
            "tipping at step {i}: {p:?}"
        );
        let ground = scene.terrain.height_at(p.position[0], p.position[1]);
        assert!(
            (p.position[2] - ground - 0.04).abs() < 0.05,
            "floating/sinking at {i}: {p:?}"
        );
    }
}
