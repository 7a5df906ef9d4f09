//! Sim twin throughput, single thread: full env steps (one discrete action
//! of physics + one RGBD render), render-only, a frame's wire payload
//! (rendered in place vs rendered then encoded), physics-only, a twin
//! profile's tilted camera (the per-pixel renderer), and RSS; then env
//! steps and renders with each frame rendered on all the machine's cores
//! (`TwinConfig::render_threads`).
//!
//! `cargo bench --bench twin_step`
//!
//! Wall clock on a shared machine moves by several percent from run to
//! run; instructions do not: `TWIN_STEP_INSTRUCTIONS=1` counts instructions
//! per env step, per render and per physics action under callgrind (the
//! bench re-runs itself for a few and for many units of each; see
//! `offworld_test_support::callgrind`). One unit alone, for a whole-process
//! timer or a profiler: `TWIN_STEP_ONLY=render-320x240 TWIN_STEP_COUNT=2000
//! [TWIN_STEP_THREADS=2]` (units: `step-` / `render-` + `320x240` / `84x84`,
//! `physics`).

use std::time::Instant;

use offworld_runtime::codec;
use offworld_runtime::msg::{CameraFrameView, PixelEncoding, Time};
use offworld_runtime::Resolution;
use offworld_sim_twin::frame_payload::FramePayloads;
use offworld_sim_twin::ros_out::frame_images;
use offworld_sim_twin::{CameraProfile, PlanarPose, SimTwin, TwinConfig, TwinProfile};
use offworld_test_support::callgrind;

/// The discrete action table (linear, angular, duration).
const ACTIONS: [(f64, f64, f64); 4] = [
    (0.07, 1.25, 1.2),
    (0.07, -1.25, 1.2),
    (0.1, 0.0, 0.6),
    (-0.1, 0.0, 0.6),
];

fn twin(world: &str, res: Resolution) -> SimTwin {
    profiled(world, res, TwinProfile::default())
}

/// `TWIN_STEP_THREADS` (default 1): the render threads of a
/// `TWIN_STEP_ONLY` run.
fn only_threads() -> usize {
    std::env::var("TWIN_STEP_THREADS")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(1)
}

/// A twin of `world` at `res` with the default profile, one render thread.
fn config(world: &str, res: Resolution) -> TwinConfig {
    let mut config = TwinConfig::builtin(world).expect("world");
    config.resolution = Some(res);
    config
}

fn profiled(world: &str, res: Resolution, profile: TwinProfile) -> SimTwin {
    SimTwin::new(TwinConfig {
        profile,
        ..config(world, res)
    })
    .expect("twin")
}

/// A twin rendering each frame on `threads` threads.
fn threaded(world: &str, res: Resolution, threads: usize) -> SimTwin {
    SimTwin::new(TwinConfig {
        render_threads: threads,
        ..config(world, res)
    })
    .expect("twin")
}

/// Median rate over `runs` runs of `n` iterations each.
fn rate(runs: usize, n: usize, mut f: impl FnMut(usize)) -> f64 {
    let mut rates: Vec<f64> = (0..runs)
        .map(|r| {
            let start = Instant::now();
            for i in 0..n {
                f(r * n + i);
            }
            n as f64 / start.elapsed().as_secs_f64()
        })
        .collect();
    rates.sort_by(f64::total_cmp);
    rates[runs / 2]
}

/// A reproducible pseudo-random action stream that keeps the robot inside.
fn env_step(t: &mut SimTwin, i: usize) {
    // Re-spawn every 100 steps like an episode reset.
    if i.is_multiple_of(100) {
        let k = (i / 100) as f32;
        t.teleport(PlanarPose {
            x: -1.0 + (k * 0.37) % 2.0,
            y: -1.0 + (k * 0.53) % 1.6,
            yaw: k,
        })
        .expect("spawn");
    }
    let (v, w, d) = ACTIONS[(i * 7 + i / 3) % 4];
    t.execute(v, w, d).expect("motion");
    t.render();
}

fn rss_mb() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// What an instruction count measures: one unit of each.
const UNITS: [(&str, &str); 5] = [
    ("step-320x240", "env step 320x240 RGBD (physics + render)"),
    ("step-84x84", "env step 84x84 RGBD (physics + render)"),
    ("render-320x240", "render 320x240"),
    ("render-84x84", "render 84x84"),
    ("physics", "physics, one discrete action"),
];

/// Does `n` units of `unit` and nothing else (the run callgrind counts).
fn only(world: &str, unit: &str, n: usize) {
    let resolution = |r: &str| match r {
        "320x240" => Resolution::new(320, 240),
        _ => Resolution::new(84, 84),
    };
    let made = |world: &str, res| threaded(world, res, only_threads());
    match unit.split_once('-') {
        Some(("step", r)) => {
            let mut t = made(world, resolution(r));
            (0..n).for_each(|i| env_step(&mut t, i));
        }
        Some(("render", r)) => {
            let mut t = made(world, resolution(r));
            (0..n).for_each(|_| {
                std::hint::black_box(t.render());
            });
        }
        _ => {
            let mut t = made(world, resolution("84x84"));
            for i in 0..n {
                let (v, w, d) = ACTIONS[i % 4];
                t.execute(v, w, d).expect("motion");
            }
        }
    }
}

fn instructions(world: &str) {
    const FEW: usize = 20;
    const MANY: usize = 200;
    println!(
        "sim_twin instructions, world `{world}` (callgrind; {MANY} units = {} − {FEW}):",
        FEW + MANY
    );
    let exe = std::env::current_exe().expect("this bench's path");
    for (unit, what) in UNITS {
        let per_unit = callgrind::per_unit(
            |n| {
                let mut run = callgrind::command(&exe);
                run.arg(world)
                    .env("TWIN_STEP_ONLY", unit)
                    .env("TWIN_STEP_COUNT", n.to_string())
                    .env_remove("TWIN_STEP_INSTRUCTIONS");
                run
            },
            FEW,
            MANY,
        );
        match per_unit {
            Ok(count) => println!("  {what:<42}: {count:>12.0} instructions"),
            Err(e) => {
                eprintln!("{what}: {e}");
                std::process::exit(1);
            }
        }
    }
}

fn main() {
    let world = std::env::args()
        .nth(1)
        .filter(|a| !a.starts_with('-'))
        .unwrap_or_else(|| "monolith_obstacle".into());
    if let Ok(unit) = std::env::var("TWIN_STEP_ONLY") {
        let n = std::env::var("TWIN_STEP_COUNT")
            .ok()
            .and_then(|n| n.parse().ok())
            .unwrap_or(100);
        return only(&world, &unit, n);
    }
    if std::env::var_os("TWIN_STEP_INSTRUCTIONS").is_some() {
        return instructions(&world);
    }
    println!("sim_twin bench, world `{world}`, single thread (unless said), median of 5 runs");
    let rss_before = rss_mb();
    let mut full = twin(&world, Resolution::new(320, 240));
    let rss_after = rss_mb();
    let steps_full = rate(5, 400, |i| env_step(&mut full, i));
    let mut small = twin(&world, Resolution::new(84, 84));
    let steps_small = rate(5, 1000, |i| env_step(&mut small, i));
    let render_full = rate(5, 400, |_| {
        full.render();
    });
    let render_small = rate(5, 2000, |_| {
        small.render();
    });
    let payloads = FramePayloads::new();
    let in_place = rate(5, 400, |i| {
        let payload = payloads.render(&mut full, i as u64, Time::default());
        std::hint::black_box(payload.expect("payload"));
    });
    let mut scratch = Vec::new();
    let encoded = rate(5, 400, |i| {
        let (color, depth) = frame_images(
            full.render(),
            Time::default(),
            PixelEncoding::Depth32FC1,
            &mut scratch,
        );
        let view = CameraFrameView {
            seq: i as u64,
            color,
            depth,
        };
        std::hint::black_box(codec::encode(&view).expect("encode"));
    });
    let physics = rate(5, 1000, |i| {
        let (v, w, d) = ACTIONS[i % 4];
        small.execute(v, w, d).expect("motion");
    });
    // A profile with a tilted camera renders per pixel (ExactRenderer).
    let tilted = TwinProfile {
        camera: CameraProfile {
            pitch_deg: 5.0,
            ..CameraProfile::default()
        },
        ..TwinProfile::default()
    };
    let mut tilted_full = profiled(&world, Resolution::new(320, 240), tilted);
    let tilted_render_full = rate(5, 10, |_| {
        tilted_full.render();
    });
    let mut tilted_small = profiled(&world, Resolution::new(84, 84), tilted);
    let tilted_render_small = rate(5, 50, |_| {
        tilted_small.render();
    });
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut spread_full = threaded(&world, Resolution::new(320, 240), cores);
    let spread_steps_full = rate(5, 400, |i| env_step(&mut spread_full, i));
    let spread_render_full = rate(5, 400, |_| {
        spread_full.render();
    });
    let mut spread_small = threaded(&world, Resolution::new(84, 84), cores);
    let spread_steps_small = rate(5, 1000, |i| env_step(&mut spread_small, i));
    println!("env steps/s  320x240 RGBD : {steps_full:8.0}");
    println!("env steps/s  84x84 RGBD   : {steps_small:8.0}");
    println!("render fps   320x240      : {render_full:8.0}");
    println!("render fps   84x84        : {render_small:8.0}");
    println!("render fps   320x240, camera pitched (exact renderer) : {tilted_render_full:8.1}");
    println!("render fps   84x84, camera pitched (exact renderer)   : {tilted_render_small:8.1}");
    println!("frame payloads/s 320x240, rendered in place  : {in_place:8.0}");
    println!("frame payloads/s 320x240, rendered + encoded : {encoded:8.0}");
    println!("physics actions/s         : {physics:8.0}");
    println!("rendered on {cores} threads (`render_threads`, the machine's cores):");
    println!("env steps/s  320x240 RGBD : {spread_steps_full:8.0}");
    println!("env steps/s  84x84 RGBD   : {spread_steps_small:8.0}");
    println!("render fps   320x240      : {spread_render_full:8.0}");
    println!(
        "RSS: {rss_after:.1} MB after building one twin ({:.1} MB for the twin), {:.1} MB now",
        rss_after - rss_before,
        rss_mb()
    );
}
