//! The camera: the fast level renderer against the exact parry reference,
//! geometry, golden low-resolution frames, determinism and noise knobs.

use offworld_runtime::Resolution;

use offworld_sim_twin::camera::{CameraPose, ColumnRenderer, ExactRenderer, Intrinsics, RgbdFrame};
use offworld_sim_twin::scene::Scene;
use offworld_sim_twin::terrain::Terrain;
use offworld_sim_twin::{PlanarPose, Randomization, SimTwin, TwinConfig, WorldSpec};
use rand::{Rng, SeedableRng};

fn agree(a: &RgbdFrame, b: &RgbdFrame) -> (usize, usize) {
    let mut bad = 0;
    for i in 0..a.depth.len() {
        let (da, db) = (a.depth[i], b.depth[i]);
        let depth_ok = (da.is_nan() && db.is_nan()) || (da - db).abs() <= 0.002 + 0.002 * db.abs();
        let grey_ok = a.rgb[i * 3].abs_diff(b.rgb[i * 3]) <= 2;
        if !(depth_ok && grey_ok) {
            bad += 1;
        }
    }
    (bad, a.depth.len())
}

#[test]
fn fast_renderer_matches_exact_reference_for_a_level_camera() {
    let world = WorldSpec::builtin("monolith_obstacle").expect("world");
    let scene = Scene::build(&world);
    let intr = Intrinsics::resized(&world.camera, 80, 60);
    let mut fast = ColumnRenderer::new(intr, &world.light);
    let exact = ExactRenderer::new(intr, &world.light, &scene);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
    let mut frame = RgbdFrame::new(80, 60);
    let (mut bad, mut total) = (0, 0);
    for _ in 0..16 {
        let (x, y) = (rng.random_range(-1.5..1.7), rng.random_range(-1.3..0.9));
        let inside_a_box = scene.boxes.iter().any(|b| {
            x >= b.min[0] - 0.01
                && x <= b.max[0] + 0.01
                && y >= b.min[1] - 0.01
                && y <= b.max[1] + 0.01
        });
        if inside_a_box {
            continue; // a camera inside a boulder sees nothing comparable
        }
        let z = scene.terrain.height_at(x, y) + rng.random_range(0.1..0.3);
        let pose = CameraPose::level([x, y, z], rng.random_range(0.0..std::f32::consts::TAU));
        fast.render(&scene, &pose, &mut frame);
        let reference = exact.render(&pose);
        let (b, t) = agree(&frame, &reference);
        bad += b;
        total += t;
    }
    // Only silhouette pixels whose centre ray grazes an edge may differ.
    assert!(bad * 1000 <= total, "{bad} of {total} pixels disagree");
}

/// A pose where the column walk's skip-ahead used to step back to a cell
/// it had just left, forever (found by a soak: the twin's worker hung at
/// 100 % CPU and stopped answering). The render must finish, and agree
/// with the exact reference.
#[test]
fn a_column_walk_that_used_to_loop_forever_finishes_and_is_exact() {
    let world = WorldSpec::builtin("monolith").expect("world");
    let scene = Scene::build(&world);
    let intr = Intrinsics::resized(&world.camera, 84, 84);
    let pose = CameraPose::level(
        [
            f32::from_bits(3_204_819_284),
            f32::from_bits(1_066_958_835),
            f32::from_bits(1_053_088_554),
        ],
        f32::from_bits(3_192_415_392),
    );
    let (done, rendered) = std::sync::mpsc::channel();
    {
        let (scene, light) = (scene.clone(), world.light.clone());
        // A thread, so that a regression fails the test instead of hanging it.
        std::thread::spawn(move || {
            let mut fast = ColumnRenderer::new(intr, &light);
            let mut frame = RgbdFrame::new(84, 84);
            fast.render(&scene, &pose, &mut frame);
            let _ = done.send(frame);
        });
    }
    let frame = rendered
        .recv_timeout(std::time::Duration::from_secs(60))
        .expect("the render never finished: the column walk loops");
    let reference = ExactRenderer::new(intr, &world.light, &scene).render(&pose);
    let (bad, total) = agree(&frame, &reference);
    assert!(bad * 1000 <= total, "{bad} of {total} pixels disagree");
}

#[test]
fn monolith_seen_at_its_distance_at_the_image_centre() {
    let world = WorldSpec::builtin("monolith").expect("world");
    let scene = Scene::with_terrain(&world, Terrain::flat(&world.enclosure, 8, 6, 0.05));
    let m = scene.monolith();
    let front = m.min[0];
    for (w, h) in [(320, 240), (84, 84)] {
        let intr = Intrinsics::resized(&world.camera, w, h);
        let mut renderer = ColumnRenderer::new(intr, &world.light);
        let mut frame = RgbdFrame::new(w, h);
        for distance in [0.5f32, 1.0, 1.8] {
            let camera_x = front - distance;
            let pose = CameraPose::level([camera_x, m.center()[1], 0.05 + 0.04 + 0.096], 0.0);
            renderer.render(&scene, &pose, &mut frame);
            let centre = frame.depth_at(w / 2, h / 2);
            assert!(
                (centre - distance).abs() < 1e-3,
                "{w}x{h}: {centre} at {distance}"
            );
            // Dark monolith: albedo 0.1 → a grey level of at most 26.
            let grey = frame.rgb[((h / 2 * w + w / 2) * 3) as usize];
            assert!(grey <= 26, "monolith grey {grey}");
        }
    }
}

#[test]
fn native_intrinsics_are_the_reference_camera() {
    let world = WorldSpec::builtin("monolith").expect("world");
    let intr = Intrinsics::native(&world.camera);
    assert_eq!(
        (intr.width, intr.height, intr.cx, intr.cy),
        (320, 240, 160.0, 120.0)
    );
    assert!((intr.fx - 277.1).abs() < 0.1 && (intr.fy - 277.1).abs() < 0.1);
    // 84×84 is the native view resized: anisotropic focal lengths.
    let small = Intrinsics::resized(&world.camera, 84, 84);
    assert!((small.fx - 277.1 * 84.0 / 320.0).abs() < 0.05);
    assert!((small.fy - 277.1 * 84.0 / 240.0).abs() < 0.05);
}

fn twin(world: &str, res: Resolution, randomization: Randomization) -> SimTwin {
    let mut config = TwinConfig::builtin(world).expect("world");
    config.resolution = Some(res);
    config.randomization = randomization;
    SimTwin::new(config).expect("twin")
}

fn frame_bytes(twin: &mut SimTwin) -> (Vec<u8>, Vec<u8>) {
    let f = twin.render();
    (f.rgb.clone(), f.depth_bytes())
}

#[test]
fn same_seed_and_commands_give_byte_identical_frames() {
    let noisy = Randomization {
        seed: 11,
        depth_noise: 0.01,
        depth_dropout: 0.02,
        light_jitter: 0.2,
        albedo_jitter: 0.2,
        max_slip: 0.1,
    };
    for randomization in [Randomization::default(), noisy] {
        let run = || {
            let mut t = twin("monolith_obstacle", Resolution::new(84, 84), randomization);
            let mut frames = vec![frame_bytes(&mut t)];
            t.teleport(PlanarPose {
                x: 0.9,
                y: 0.6,
                yaw: 2.0,
            })
            .expect("teleport");
            for (v, w, d) in [
                (0.1, 0.0, 0.6),
                (0.07, 1.25, 1.2),
                (0.07, -1.25, 1.2),
                (-0.1, 0.0, 0.6),
            ] {
                t.execute(v, w, d).expect("motion");
                frames.push(frame_bytes(&mut t));
            }
            frames
        };
        let (a, b) = (run(), run());
        assert_eq!(a, b, "{randomization:?}");
        assert_ne!(a[0], a[1], "the view changes when the robot moves");
    }
}

#[test]
fn noise_knobs_are_off_by_default_and_change_frames_when_on() {
    let mut clean = twin(
        "monolith",
        Resolution::new(84, 84),
        Randomization::default(),
    );
    let mut noisy = twin(
        "monolith",
        Resolution::new(84, 84),
        Randomization {
            seed: 1,
            depth_noise: 0.05,
            depth_dropout: 0.1,
            ..Randomization::default()
        },
    );
    let (c, n) = (clean.render().clone(), noisy.render().clone());
    assert_eq!(c.rgb, n.rgb, "depth noise leaves colour alone");
    let dropped = n
        .depth
        .iter()
        .zip(&c.depth)
        .filter(|(n, c)| n.is_nan() && !c.is_nan())
        .count();
    let valid = c.depth.iter().filter(|d| !d.is_nan()).count();
    let share = dropped as f32 / valid as f32;
    assert!((share - 0.1).abs() < 0.03, "dropout share {share}");
    assert_ne!(c.depth_bytes(), n.depth_bytes());
}

#[test]
fn bad_commands_are_typed_errors_and_change_nothing() {
    let mut t = twin(
        "monolith",
        Resolution::new(32, 24),
        Randomization::default(),
    );
    let before = t.ground_truth();
    for (v, w, d) in [
        (f64::NAN, 0.0, 1.0),
        (0.1, f64::INFINITY, 1.0),
        (0.1, 0.0, -1.0),
        (0.1, 0.0, 1e9),
    ] {
        assert!(matches!(
            t.execute(v, w, d),
            Err(offworld_sim_twin::SimError::BadCommand(_))
        ));
    }
    assert!(t
        .teleport(PlanarPose {
            x: 9.0,
            y: 0.0,
            yaw: 0.0
        })
        .is_err());
    assert!(t
        .teleport(PlanarPose {
            x: f32::NAN,
            y: 0.0,
            yaw: 0.0
        })
        .is_err());
    assert_eq!(t.ground_truth(), before);
}

/// Golden 32×24 frames at fixed poses: depth in mm and grey level, one
/// pixel per line. Regenerate with `UPDATE_GOLDEN=1` after an intended change.
#[test]
fn golden_low_resolution_frames() {
    let poses = [
        (
            "obstacle_west",
            "monolith_obstacle",
            PlanarPose {
                x: -1.2,
                y: 0.2,
                yaw: -0.3,
            },
        ),
        (
            "open_east",
            "monolith",
            PlanarPose {
                x: 1.2,
                y: -0.8,
                yaw: 2.6,
            },
        ),
        (
            "open_corner",
            "monolith",
            PlanarPose {
                x: -1.4,
                y: -1.2,
                yaw: 0.8,
            },
        ),
    ];
    let dir = offworld_test_support::package_dir().join("tests/golden");
    for (name, world, pose) in poses {
        let mut config = TwinConfig::builtin(world).expect("world");
        config.resolution = Some(Resolution::new(32, 24));
        config.start = pose;
        let mut t = SimTwin::new(config).expect("twin");
        let f = t.render();
        let text: String = f
            .depth
            .iter()
            .enumerate()
            .map(|(i, d)| {
                let mm = if d.is_nan() {
                    -1
                } else {
                    (d * 1000.0).round() as i64
                };
                format!("{mm} {}\n", f.rgb[i * 3])
            })
            .collect();
        let path = dir.join(format!("{name}.txt"));
        if std::env::var_os("UPDATE_GOLDEN").is_some() {
            std::fs::write(&path, &text).expect("write golden");
            continue;
        }
        let golden =
            std::fs::read_to_string(&path).expect("golden file (UPDATE_GOLDEN=1 to create)");
        let mut mismatches = 0;
        for (got, want) in text.lines().zip(golden.lines()) {
            let parse = |l: &str| -> (i64, i64) {
                let mut it = l.split(' ').map(|x| x.parse::<i64>().expect("int"));
                (it.next().expect("mm"), it.next().expect("grey"))
            };
            let ((gd, gg), (wd, wg)) = (parse(got), parse(want));
            if (gd - wd).abs() > 1 || (gg - wg).abs() > 1 {
                mismatches += 1;
            }
        }
        assert_eq!(golden.lines().count(), 32 * 24, "{name}");
        assert_eq!(
            mismatches, 0,
            "{name}: {mismatches} pixels differ from the golden frame"
        );
    }
}

/// A frame is the same bits on any number of threads: each column is
/// walked by one thread, whichever takes its band. Sizes with a partial
/// last band and with fewer columns than one band; poses beside boulders
/// and out of the range (NaN depth).
#[test]
fn a_frame_is_the_same_on_any_number_of_threads() {
    let world = WorldSpec::builtin("monolith_obstacle").expect("world");
    let scene = Scene::build(&world);
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(17);
    let poses: Vec<CameraPose> = (0..6)
        .map(|_| {
            let (x, y) = (rng.random_range(-1.5..1.7), rng.random_range(-1.3..0.9));
            let z = scene.terrain.height_at(x, y) + 0.2;
            CameraPose::level([x, y, z], rng.random_range(0.0..std::f32::consts::TAU))
        })
        .collect();
    let bits = |f: &RgbdFrame| f.depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>();
    for (w, h) in [(320, 240), (84, 84), (37, 29), (5, 3)] {
        let intr = Intrinsics::resized(&world.camera, w, h);
        let mut one = ColumnRenderer::new(intr, &world.light);
        assert_eq!(one.threads(), 1);
        for threads in [2, 3] {
            let mut many = ColumnRenderer::new(intr, &world.light)
                .with_threads(threads)
                .expect("threads");
            assert_eq!(many.threads(), threads);
            for pose in &poses {
                let (mut a, mut b) = (RgbdFrame::new(w, h), RgbdFrame::new(w, h));
                one.render(&scene, pose, &mut a);
                many.render(&scene, pose, &mut b);
                assert!(
                    a.rgb == b.rgb,
                    "{w}x{h} on {threads} threads: colour differs"
                );
                assert!(
                    bits(&a) == bits(&b),
                    "{w}x{h} on {threads} threads: depth differs"
                );
            }
        }
    }
}
