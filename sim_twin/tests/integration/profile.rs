//! The twin profile: the default is the nominal twin bit for bit; each
//! field changes what it says and nothing else; files load, fail and
//! round-trip as documented.

use offworld_runtime::Resolution;
use offworld_test_support::ScratchDir;
use std::path::{Path, PathBuf};

use offworld_sim_twin::camera::{CameraPose, ColumnRenderer, ExactRenderer, RgbdFrame};
use offworld_sim_twin::physics::{RobotPhysics, DT};
use offworld_sim_twin::scene::Scene;
use offworld_sim_twin::terrain::Terrain;
use offworld_sim_twin::{
    CameraProfile, DepthProfile, MotionProfile, PlanarPose, Randomization, SimError, SimTwin,
    TwinConfig, TwinProfile, WorldSpec,
};

fn twin_with(world: &str, res: Resolution, profile: TwinProfile) -> SimTwin {
    let mut config = TwinConfig::builtin(world).expect("world");
    config.resolution = Some(res);
    config.profile = profile;
    SimTwin::new(config).expect("twin")
}

fn with_motion(motion: MotionProfile) -> TwinProfile {
    TwinProfile {
        motion,
        ..TwinProfile::default()
    }
}

fn with_camera(camera: CameraProfile) -> TwinProfile {
    TwinProfile {
        camera,
        ..TwinProfile::default()
    }
}

fn planar_distance(a: PlanarPose, b: PlanarPose) -> f32 {
    ((b.x - a.x).powi(2) + (b.y - a.y).powi(2)).sqrt()
}

/// Commands, a teleport and renders; every pose, odometry, time and frame
/// checksum as bits.
fn scenario(world: &str, randomization: Randomization, profile: TwinProfile) -> Vec<u32> {
    let mut config = TwinConfig::builtin(world).expect("world");
    config.resolution = Some(Resolution::new(64, 48));
    config.randomization = randomization;
    config.profile = profile;
    let mut twin = SimTwin::new(config).expect("twin");
    let mut bits = Vec::new();
    let mut record = |twin: &mut SimTwin, t: f32| {
        let p = twin.ground_truth();
        bits.extend(p.position.iter().chain(&p.orientation).map(|v| v.to_bits()));
        let o = twin.physics().odometry();
        bits.extend([o.x, o.y, o.yaw, t].map(f32::to_bits));
        let f = twin.render();
        let depth: f64 = f
            .depth
            .iter()
            .filter(|d| d.is_finite())
            .map(|&d| f64::from(d))
            .sum();
        let grey: u64 = f.rgb.iter().map(|&g| u64::from(g)).sum();
        bits.push((depth as f32).to_bits());
        bits.push(grey as u32);
    };
    for (v, w, d) in [
        (0.3, 0.0, 1.0),
        (0.1, 1.0, 0.8),
        (-0.2, -0.5, 0.5),
        (0.7, 2.5, 2.0),
    ] {
        let t = twin.execute(v, w, d).expect("execute");
        record(&mut twin, t);
    }
    twin.teleport(PlanarPose {
        x: 0.5,
        y: -0.4,
        yaw: 2.0,
    })
    .expect("teleport");
    for (v, w, d) in [(0.5, -0.3, 1.5), (0.0, 0.0, 0.0), (0.2, 0.0, 0.05)] {
        let t = twin.execute(v, w, d).expect("execute");
        record(&mut twin, t);
    }
    bits
}

/// [`scenario`] pinned: first run by the twin as it was before profiles
/// existed (the same program built against that source), then once more
/// when a teleport began to put base_link exactly on the asked-for pose
/// after settling (the settled tilt used to move it up to ~1 cm), and
/// when the physics went from rapier's default four solver iterations a
/// substep to one (docs/performance.md, "The twin's physics"), and when
/// substeps away from every box stopped going through rapier (last-place
/// differences; "Free motion").
const BEFORE_OBSTACLE: [u32; 91] = [
    3207814869, 1057090148, 1035480707, 1026450090, 1019823223, 983889953, 1065332922, 1050253717,
    0, 0, 1067170748, 1166578188, 693027, 3206568288, 1057662668, 1035366824, 1032768832,
    3163956475, 1053386471, 1063953190, 1052660874, 1022916628, 1061997771, 1063675495, 2147483648,
    285696, 3207935000, 1056173208, 1035092354, 1029441544, 1013852387, 1049376242, 1064684835,
    1049997448, 3170262937, 1057803471, 1059481191, 1155290589, 418107, 3207203545, 1058148829,
    1035935778, 1026551926, 997155256, 1055679497, 1063440406, 3170995596, 3188481774, 1085381013,
    1075838977, 1127143586, 327006, 1052794079, 1051500540, 1038421466, 1008860399, 3172360420,
    1060295258, 1060564623, 1052548690, 3208882212, 1084437273, 1072483534, 2147483648, 285696,
    1052794021, 1051500731, 1038423397, 1008895982, 3172365039, 1060295234, 1060564624, 1052548690,
    3208882212, 1084437273, 1015580809, 2147483648, 285696, 1052796266, 1051627947, 1038440805,
    1009163106, 3172398197, 1060295056, 1060564632, 1052596249, 3208940460, 1084437273, 1039068912,
    2147483648, 285696,
];
/// The same with depth noise, dropout and slip (seed 7) on `monolith`.
const BEFORE_NOISY: [u32; 91] = [
    3207814869, 1057090148, 1035480707, 1026450090, 1019823223, 983889953, 1065332922, 1050253717,
    0, 0, 1067170748, 1167427814, 780141, 3206568288, 1057662668, 1035366824, 1032768832,
    3163956475, 1053386471, 1063953190, 1052660874, 1022916628, 1061997771, 1063675495, 1158684765,
    755364, 3207935000, 1056173208, 1035092354, 1029441544, 1013852387, 1049376242, 1064684835,
    1049997448, 3170262937, 1057803471, 1059481191, 1162606039, 769737, 3213025259, 1052549644,
    1038042685, 1004528744, 3169695953, 1051604193, 3211827939, 3170995596, 3188481774, 1085381013,
    1075838977, 1168478513, 826971, 1052777799, 1051377283, 1038402344, 1008626534, 3172339465,
    1060308362, 1060551916, 1052516581, 3208822513, 1084441862, 1072483534, 1157638319, 743355,
    1052777743, 1051377464, 1038404186, 1008660467, 3172343832, 1060308340, 1060551917, 1052516581,
    3208822513, 1084441862, 1015580809, 1157546219, 743355, 1052779703, 1051504624, 1038421338,
    1008920345, 3172374524, 1060308169, 1060551930, 1052564395, 3208880707, 1084441862, 1039068912,
    1157486757, 743241,
];

fn noisy() -> Randomization {
    Randomization {
        seed: 7,
        depth_noise: 0.01,
        depth_dropout: 0.02,
        max_slip: 0.1,
        ..Randomization::default()
    }
}

#[test]
fn default_profile_is_the_twin_as_before_bit_for_bit() {
    // Every default spelled out, as a file would.
    let explicit = TwinProfile::parse(
        "format = 1\n[motion]\nlinear_gain = 1.0\nangular_gain = 1.0\nlatency_s = 0.0\n\
         [camera]\nheight_offset_m = 0.0\npitch_deg = 0.0\nyaw_deg = 0.0\n\
         [depth]\nnoise = 0.0\ndropout = 0.0\n",
    )
    .expect("profile");
    assert_eq!(explicit, TwinProfile::default());
    let none = Randomization::default();
    for profile in [TwinProfile::default(), explicit] {
        assert_eq!(
            scenario("monolith_obstacle", none, profile),
            BEFORE_OBSTACLE
        );
        assert_eq!(scenario("monolith", noisy(), profile), BEFORE_NOISY);
    }
}

#[test]
fn linear_gain_shortens_the_drive_but_not_the_odometry() {
    let run = |gain: f32| {
        let mut twin = twin_with(
            "monolith",
            Resolution::new(32, 24),
            with_motion(MotionProfile {
                linear_gain: gain,
                ..MotionProfile::default()
            }),
        );
        let start = twin.physics().planar_pose();
        twin.execute(0.3, 0.0, 1.0).expect("execute");
        let odom = twin.physics().odometry();
        let origin = PlanarPose {
            x: 0.0,
            y: 0.0,
            yaw: 0.0,
        };
        (
            planar_distance(start, twin.physics().planar_pose()),
            planar_distance(origin, odom),
        )
    };
    let (nominal, nominal_odom) = run(1.0);
    let (slipping, slipping_odom) = run(0.8);
    let ratio = slipping / nominal;
    assert!(
        (ratio - 0.8).abs() < 0.008,
        "ratio {ratio} ({slipping} / {nominal} m)"
    );
    // The wheels turned as much: odometry cannot see the lost traction.
    assert_eq!(slipping_odom, nominal_odom);
    assert!(
        (nominal_odom - 0.3).abs() < 0.003,
        "odometry {nominal_odom}"
    );
}

#[test]
fn angular_gain_shortens_the_turn_but_not_the_odometry() {
    let run = |gain: f32| {
        let mut twin = twin_with(
            "monolith",
            Resolution::new(32, 24),
            with_motion(MotionProfile {
                angular_gain: gain,
                ..MotionProfile::default()
            }),
        );
        let start = twin.physics().planar_pose().yaw;
        twin.execute(0.0, 1.0, 1.0).expect("execute");
        (
            twin.physics().planar_pose().yaw - start,
            twin.physics().odometry().yaw,
        )
    };
    let (nominal, nominal_odom) = run(1.0);
    let (slipping, slipping_odom) = run(0.7);
    let ratio = slipping / nominal;
    assert!(
        (ratio - 0.7).abs() < 0.007,
        "ratio {ratio} ({slipping} / {nominal} rad)"
    );
    assert_eq!(slipping_odom, nominal_odom);
    assert!((nominal_odom - 1.0).abs() < 0.01, "odometry {nominal_odom}");
}

#[test]
fn latency_delays_the_motion_without_changing_it() {
    let lagging = with_motion(MotionProfile {
        latency_s: 0.2,
        ..MotionProfile::default()
    });
    let mut nominal = twin_with("monolith", Resolution::new(32, 24), TwinProfile::default());
    let mut late = twin_with("monolith", Resolution::new(32, 24), lagging);
    for (v, w, d) in [(0.3, 0.0, 1.0), (0.2, 0.8, 0.5), (0.1, 0.0, 0.1)] {
        let t_nominal = nominal.execute(v, w, d).expect("execute");
        let t_late = late.execute(v, w, d).expect("execute");
        // 0.2 s is 12 substeps exactly.
        let extra = t_late - t_nominal;
        assert!((extra - 12.0 * DT).abs() < 1e-4, "took {extra} s longer");
        let (a, b) = (nominal.ground_truth(), late.ground_truth());
        let apart = planar_distance(
            nominal.physics().planar_pose(),
            late.physics().planar_pose(),
        );
        assert!(apart < 0.001, "{apart} m apart: {a:?} vs {b:?}");
        assert!((a.yaw - b.yaw).abs() < 0.001);
        // The wheels did the same: odometry agrees to float rounding.
        let (oa, ob) = (nominal.physics().odometry(), late.physics().odometry());
        assert!(planar_distance(oa, ob) < 1e-5 && (oa.yaw - ob.yaw).abs() < 1e-5);
    }

    // Substep by substep: the previous target (zero) holds for 12 steps.
    let world = WorldSpec::builtin("monolith").expect("world");
    let scene = Scene::with_terrain(&world, Terrain::flat(&world.enclosure, 8, 6, 0.05));
    let mut physics = RobotPhysics::new(
        &scene,
        PlanarPose {
            x: -1.0,
            y: 0.5,
            yaw: 0.0,
        },
    );
    physics.set_profile(lagging.motion);
    physics.set_targets(0.3, 0.0);
    // Repeats of the newest target are not queued twice (a teleop repeats).
    physics.set_targets(0.3, 0.0);
    for _ in 0..12 {
        physics.substep();
        assert_eq!(physics.servo().linear, 0.0);
        assert!(physics.targets_pending());
    }
    physics.substep();
    assert!(physics.servo().linear > 0.0);
    assert!(!physics.targets_pending());
}

#[test]
fn settle_time_scales_the_servo_ramp() {
    let stop_time = |settle: Option<f32>| {
        let mut twin = twin_with(
            "monolith",
            Resolution::new(32, 24),
            with_motion(MotionProfile {
                settle_time_s: settle,
                ..MotionProfile::default()
            }),
        );
        // From full speed (0.7 m/s): the time after the command, less the
        // one resting step, is the servo's time to zero.
        let taken = twin.execute(0.7, 0.0, 1.0).expect("execute");
        (taken - 1.0 - DT, twin.physics().accel_limits())
    };
    let (nominal, nominal_limits) = stop_time(None);
    // The world's robot: 0.7 m/s at 1.5 m/s² stops in 0.467 s (28 steps,
    // one more for float rounding).
    assert!(
        (nominal - 0.7 / 1.5).abs() <= DT + 1e-4,
        "stops in {nominal} s"
    );
    assert_eq!(nominal_limits, (1.5, 12.0));
    let (slow, slow_limits) = stop_time(Some(2.0 * 0.7 / 1.5));
    assert!(
        (slow - 2.0 * 0.7 / 1.5).abs() <= DT + 1e-4,
        "stops in {slow} s"
    );
    let ratio = slow / nominal;
    assert!((ratio - 2.0).abs() < 0.05, "{slow} s / {nominal} s");
    assert!((slow_limits.0 - 0.75).abs() < 1e-5 && (slow_limits.1 - 6.0).abs() < 1e-4);
}

#[test]
fn camera_yaw_turns_the_view_about_the_camera() {
    let mut nominal = twin_with("monolith", Resolution::new(64, 48), TwinProfile::default());
    let yawed_profile = with_camera(CameraProfile {
        yaw_deg: 5.0,
        ..CameraProfile::default()
    });
    let mut yawed = twin_with("monolith", Resolution::new(64, 48), yawed_profile);
    let frame = yawed.render().clone();
    assert_ne!(frame, *nominal.render());
    // The nominal camera turned by 5° in place, rendered by the column walk.
    let base = nominal.camera_pose();
    let turned = CameraPose::level(base.position, base.yaw + 5f32.to_radians());
    let mut renderer = ColumnRenderer::new(*nominal.intrinsics(), &nominal.scene().world.light);
    let mut expected = RgbdFrame::new(64, 48);
    renderer.render(nominal.scene(), &turned, &mut expected);
    assert_eq!(frame, expected);
    let pose = yawed.camera_pose();
    assert_eq!(pose.position, base.position);
    assert!((pose.yaw - turned.yaw).abs() < 1e-6);
}

#[test]
fn camera_height_moves_the_floor_the_expected_way() {
    // A flat floor: a level camera h above it sees row v's floor at h / slope(v).
    let mut config = TwinConfig::builtin("monolith").expect("world");
    config.world.terrain.max_height = 0.0;
    config.world.terrain.mean_height = 0.0;
    config.resolution = Some(Resolution::new(64, 48));
    let mut nominal = SimTwin::new(config.clone()).expect("twin");
    let raised = TwinConfig {
        profile: with_camera(CameraProfile {
            height_offset_m: 0.1,
            ..CameraProfile::default()
        }),
        ..config.clone()
    };
    let mut raised = SimTwin::new(raised).expect("twin");
    // The same as a world whose mount is 0.1 m higher, bit for bit.
    let mut mount_world = config.clone();
    mount_world.world.camera.mount[2] += 0.1;
    let mut higher_mount = SimTwin::new(mount_world).expect("twin");
    assert_eq!(raised.render(), higher_mount.render());

    let bottom = 47;
    let slope = nominal.intrinsics().row_slope(bottom);
    for (twin, offset) in [(&mut nominal, 0.0), (&mut raised, 0.1)] {
        let pose = twin.camera_pose();
        let ground = twin
            .scene()
            .terrain
            .height_at(pose.position[0], pose.position[1]);
        let h = pose.position[2] - ground;
        // base_link at wheel-radius height (0.04 m) + the mount's 0.096 m.
        assert!((h - (0.136 + offset)).abs() < 0.01, "camera {h} m up");
        let depth = twin.render().depth_at(32, bottom);
        let expected = h / slope;
        assert!(
            (depth - expected).abs() < 0.01 * expected,
            "bottom row at {depth} m, expected {expected} m"
        );
    }
    // The horizon stays at the centre row (a level camera): the rows above
    // it see the far walls in both.
    let top = nominal.render().depth_at(32, 10);
    assert!(top > 1.0, "top rows see the far wall, {top} m");
}

#[test]
fn camera_pitch_renders_exactly_and_sees_the_floor_nearer() {
    let pitched_profile = with_camera(CameraProfile {
        pitch_deg: 10.0,
        ..CameraProfile::default()
    });
    let mut nominal = twin_with("monolith", Resolution::new(64, 48), TwinProfile::default());
    let mut pitched = twin_with("monolith", Resolution::new(64, 48), pitched_profile);
    let frame = pitched.render().clone();
    // The per-pixel renderer, tilted 10° nose down on a level chassis.
    let base = nominal.camera_pose();
    let tilted = CameraPose {
        position: base.position,
        yaw: base.yaw,
        pitch: 10f32.to_radians(),
        roll: 0.0,
    };
    let exact = ExactRenderer::new(
        *nominal.intrinsics(),
        &nominal.scene().world.light,
        nominal.scene(),
    );
    assert_eq!(frame, exact.render(&tilted));
    // The message path renders the same.
    let mut rgb = vec![0; 64 * 48 * 3];
    let mut depth = vec![0.0; 64 * 48];
    assert!(pitched.render_into(offworld_sim_twin::camera::PixelsMut {
        rgb: &mut rgb,
        depth: &mut depth,
    }));
    assert_eq!(rgb, frame.rgb);
    assert_eq!(
        depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>(),
        frame.depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>()
    );
    let level = nominal.render().clone();
    let bottom_mean = |f: &RgbdFrame| {
        let row: Vec<f32> = (0..64)
            .map(|u| f.depth_at(u, 47))
            .filter(|d| d.is_finite())
            .collect();
        row.iter().sum::<f32>() / row.len() as f32
    };
    let (tilted_floor, level_floor) = (bottom_mean(&frame), bottom_mean(&level));
    assert!(
        tilted_floor < 0.8 * level_floor,
        "bottom row at {tilted_floor} m tilted, {level_floor} m level"
    );
}

#[test]
fn profile_depth_noise_is_the_randomization_model() {
    let mut config = TwinConfig::builtin("monolith").expect("world");
    config.resolution = Some(Resolution::new(64, 48));
    config.randomization.seed = 5;
    let mut by_profile = config.clone();
    by_profile.profile.depth = DepthProfile {
        noise: 0.02,
        dropout: 0.1,
    };
    let mut by_randomization = config.clone();
    by_randomization.randomization.depth_noise = 0.02;
    by_randomization.randomization.depth_dropout = 0.1;
    let mut a = SimTwin::new(by_profile.clone()).expect("twin");
    let mut b = SimTwin::new(by_randomization).expect("twin");
    let (fa, fb) = (a.render().clone(), b.render().clone());
    assert_eq!(fa.depth_bytes(), fb.depth_bytes());
    assert!(fa.depth.iter().filter(|d| d.is_nan()).count() > 64 * 48 / 20);
    // Both at once: which would win is not obvious, so it is refused.
    by_profile.randomization.depth_noise = 0.01;
    let err = SimTwin::new(by_profile).err().expect("refused");
    assert!(err.to_string().contains("depth noise"), "{err}");
}

/// A fresh directory, removed at the end of the test.
fn scratch_dir(name: &str) -> ScratchDir {
    ScratchDir::new(&format!("twin-profile-{name}"))
}

fn load_error(dir: &Path, name: &str, text: &str) -> (PathBuf, SimError) {
    let path = dir.join(name);
    std::fs::write(&path, text).expect("write");
    let err = TwinProfile::load(&path).expect_err("must not load");
    (path, err)
}

#[test]
fn load_errors_name_the_file_and_the_field() {
    let dir = scratch_dir("errors");
    let cases = [
        (
            "unknown.toml",
            "[motion]\nlinear_gan = 1.0\n",
            "motion.linear_gan",
        ),
        (
            "table.toml",
            "format = 1\n[motoin]\nlinear_gain = 1.0\n",
            "motoin",
        ),
        ("top.toml", "colour = 1\n", "colour"),
        (
            "range.toml",
            "[motion]\nlinear_gain = 5.0\n",
            "motion.linear_gain",
        ),
        (
            "zero.toml",
            "[motion]\nangular_gain = 0.0\n",
            "motion.angular_gain",
        ),
        (
            "latency.toml",
            "[motion]\nlatency_s = 1.5\n",
            "motion.latency_s",
        ),
        (
            "settle.toml",
            "[motion]\nsettle_time_s = 0.0\n",
            "motion.settle_time_s",
        ),
        ("nan.toml", "[depth]\nnoise = nan\n", "depth.noise"),
        ("inf.toml", "[camera]\nyaw_deg = inf\n", "camera.yaw_deg"),
        (
            "pitch.toml",
            "[camera]\npitch_deg = -31.0\n",
            "camera.pitch_deg",
        ),
        (
            "height.toml",
            "[camera]\nheight_offset_m = 0.6\n",
            "camera.height_offset_m",
        ),
        ("dropout.toml", "[depth]\ndropout = 1.0\n", "depth.dropout"),
        (
            "type.toml",
            "[camera]\npitch_deg = \"down\"\n",
            "camera.pitch_deg",
        ),
        (
            "dotted.toml",
            "motion.latency_s = -0.1\n",
            "motion.latency_s",
        ),
        (
            "version.toml",
            "format = 2\n[motion]\nnew_thing = 1\n",
            "format",
        ),
        ("version_type.toml", "format = \"1\"\n", "format"),
    ];
    for (name, text, field) in cases {
        let (path, err) = load_error(&dir, name, text);
        let message = err.to_string();
        assert!(
            message.contains(&path.display().to_string()) && message.contains(field),
            "{name}: {message}"
        );
        match err {
            SimError::Profile {
                path: Some(p),
                field: Some(f),
                ..
            } => {
                assert_eq!(p, path);
                assert_eq!(f, field);
            }
            other => panic!("{name}: {other:?}"),
        }
    }
    let (_, err) = load_error(&dir, "version_msg.toml", "format = 2\n");
    assert!(err.to_string().contains("reads format 1"), "{err}");
    let missing = dir.join("missing.toml");
    let err = TwinProfile::load(&missing).expect_err("missing");
    assert!(
        err.to_string().contains(&missing.display().to_string()),
        "{err}"
    );
    // Over the wire these are the caller's fault.
    let wire = offworld_runtime::WireError::from(load_error(&dir, "w.toml", "x = 1\n").1);
    assert_eq!(wire.code, offworld_runtime::ErrorCode::BadRequest);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn save_then_load_round_trips() {
    let dir = scratch_dir("round-trip");
    let profile = TwinProfile {
        motion: MotionProfile {
            linear_gain: 0.83,
            angular_gain: 0.71,
            latency_s: 0.12,
            settle_time_s: Some(0.9),
        },
        camera: CameraProfile {
            height_offset_m: -0.013,
            pitch_deg: 2.5,
            yaw_deg: -1.25,
        },
        depth: DepthProfile {
            noise: 0.011,
            dropout: 0.03,
        },
    };
    let path = dir.join("robot-a.toml");
    std::fs::write(&path, "old contents").expect("write");
    profile.save(&path).expect("save");
    let text = std::fs::read_to_string(&path).expect("read");
    assert!(text.starts_with("# "), "{text}");
    assert!(text.contains("format = 1"), "{text}");
    assert_eq!(TwinProfile::load(&path).expect("load"), profile);
    // Only the file itself: the temporary file was renamed over it.
    let names: Vec<_> = std::fs::read_dir(&dir)
        .expect("dir")
        .map(|e| e.expect("entry").file_name())
        .collect();
    assert_eq!(names, [std::ffi::OsString::from("robot-a.toml")]);
    // The default too (no settle time written: the world's).
    TwinProfile::default().save(&path).expect("save");
    assert_eq!(
        TwinProfile::load(&path).expect("load"),
        TwinProfile::default()
    );
    // An invalid profile is not written.
    let bad = with_motion(MotionProfile {
        linear_gain: f32::NAN,
        ..MotionProfile::default()
    });
    let err = bad.save(&path).expect_err("invalid");
    assert!(err.to_string().contains("motion.linear_gain"), "{err}");
    assert_eq!(
        TwinProfile::load(&path).expect("load"),
        TwinProfile::default()
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn sim_twin_cli_takes_a_profile() {
    let dir = scratch_dir("cli");
    let bin = env!("CARGO_BIN_EXE_sim_twin");
    let good = dir.join("good.toml");
    TwinProfile::default().save(&good).expect("save");
    // The depth flags say what the profile's [depth] says: not both.
    let out = std::process::Command::new(bin)
        .arg("--profile")
        .arg(&good)
        .args(["--depth-noise", "0.01"])
        .output()
        .expect("run");
    assert_eq!(out.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&out.stderr).contains("cannot be used with"));
    // A bad file fails before anything starts, naming the file and field.
    let bad = dir.join("bad.toml");
    std::fs::write(&bad, "[motion]\nlinear_gain = 9.0\n").expect("write");
    let out = std::process::Command::new(bin)
        .arg("--profile")
        .arg(&bad)
        .output()
        .expect("run");
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains(&bad.display().to_string()) && stderr.contains("motion.linear_gain"),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_documented_example_loads() {
    let doc = include_str!("../../../docs/twin-profile.md");
    let start = doc.find("```toml\n").expect("example") + "```toml\n".len();
    let text = &doc[start..start + doc[start..].find("```").expect("end")];
    let profile = TwinProfile::parse(text).expect("the example parses");
    assert_eq!(profile.motion.settle_time_s, Some(0.6));
    assert_eq!(profile.camera.yaw_deg, -1.5);
    // What `to_toml` writes starts with the same header line.
    let written = profile.to_toml().expect("toml");
    assert_eq!(written.lines().next(), text.lines().next());
    assert_eq!(TwinProfile::parse(&written).expect("parse"), profile);
}
