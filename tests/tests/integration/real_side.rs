//! The real stack end to end on the emulated enclosure: env_controller,
//! robot_agent and tracker_agent as separate processes under `real/…`,
//! driving `offworld emulate-hardware` in real time over its ROS 2 topics
//! and raw tracker stream. This test process plays the researcher (a gym
//! client with a token) and, separately, an observer of the robot's
//! `cmd_vel` (what the motors were told).

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_runtime::codec;
use offworld_runtime::keys::{EnvId, Topic};
use offworld_runtime::msg::*;
use offworld_runtime::ros2::{RobotTopics, RosGraph, RosType};
use offworld_runtime::{ErrorCode, SessionConfig, WireError};
use offworld_tests::emulated::{EmulatedEnclosure, Options};
use zenoh::sample::Sample;
use zenoh::Session;

/// One emulated enclosure at a time: each runs four real-time processes,
/// and two at once starve each other on a 2-core machine (the watchdog then
/// rightly stops the robot).
static ONE_ENCLOSURE: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// The monolith's ground-plane centre (runtime/worlds/monolith.toml).
const MONOLITH: (f64, f64) = (0.0109, -0.2034);

fn open_request(token: &str, experiment: &str) -> OpenRequest {
    OpenRequest {
        token: token.to_owned(),
        experiment_name: experiment.to_owned(),
        algorithm_mode: AlgorithmMode::Test,
        ..OpenRequest::anonymous(ObsOptions {
            channels: Channels::Rgbd,
            height: 84,
            width: 84,
            depth_format: DepthFormat::Meters,
        })
    }
}

/// Opens the env once the deployment is up (bounded wait).
async fn open(deployment: &EmulatedEnclosure, experiment: &str) -> (Session, EnvClient) {
    let session = SessionConfig::connecting(&deployment.endpoint)
        .open()
        .await
        .expect("client session");
    // Controller, agents or tracker may still be starting.
    let client = EnvClient::open_when_ready(
        &session,
        &deployment.env,
        open_request(&deployment.token, experiment),
        ClientTimeouts::default(),
        Duration::from_secs(30),
    )
    .await
    .unwrap_or_else(|e| panic!("the emulated deployment did not come up within 30 s: {e}"));
    (session, client)
}

/// An observer on the robot computer's network (sees `cmd_vel`).
async fn robot_side(deployment: &EmulatedEnclosure) -> Session {
    let mut config = SessionConfig::connecting(&deployment.robot_endpoint);
    config.mode = offworld_runtime::session::Mode::Client;
    config.open().await.expect("robot-side session")
}

/// Resets, retrying while the tracker's first poses are still arriving.
async fn reset(gym: &mut EnvClient, seed: u64) -> ResetReply {
    let mut last = None;
    for _ in 0..50 {
        match gym.reset(Seed::Fixed(seed)).await {
            Ok(r) => return r,
            // Unavailable: tracker or agent still starting; Timeout: an
            // answer lost while the site was starved of CPU. Both are typed
            // and the next reset starts over.
            Err(e) if matches!(e.code, ErrorCode::Unavailable | ErrorCode::Timeout) => {
                last = Some(e);
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(e) => panic!("reset failed: {e}"),
        }
    }
    panic!("reset kept failing: {last:?}");
}

/// Every velocity the robot's base was told, with arrival times.
#[derive(Clone, Default)]
struct CmdVelLog(Arc<Mutex<Vec<(Instant, f64, f64)>>>);

impl CmdVelLog {
    async fn watch(session: &Session) -> (Self, zenoh::pubsub::Subscriber<()>) {
        let log = CmdVelLog::default();
        let key = RosGraph::new(Default::default(), "")
            .and_then(|g| g.subscription_key(&RobotTopics::default().cmd_vel, RosType::Twist))
            .expect("cmd_vel key");
        let sink = log.0.clone();
        let sub = session
            .declare_subscriber(key)
            .callback(move |s: Sample| {
                if let (Ok(t), Ok(mut v)) =
                    (codec::decode_payload::<Twist>(s.payload()), sink.lock())
                {
                    v.push((Instant::now(), t.linear.x, t.angular.z));
                }
            })
            .await
            .expect("cmd_vel subscriber");
        (log, sub)
    }

    fn snapshot(&self) -> Vec<(Instant, f64, f64)> {
        self.0.lock().map(|v| v.clone()).unwrap_or_default()
    }
}

/// Latest calibrated robot pose as published by the tracker agent.
async fn watch_pose(
    session: &Session,
    env: &EnvId,
) -> (Arc<Mutex<Option<Pose2D>>>, zenoh::pubsub::Subscriber<()>) {
    let latest = Arc::new(Mutex::new(None));
    let sink = latest.clone();
    let sub = session
        .declare_subscriber(env.key(Topic::Pose))
        .callback(move |s: Sample| {
            if let (Ok(p), Ok(mut v)) = (
                codec::decode_payload::<PoseStamped>(s.payload()),
                sink.lock(),
            ) {
                *v = Some(Pose2D {
                    x: p.pose.position.x,
                    y: p.pose.position.y,
                    yaw: p.pose.orientation.yaw(),
                });
            }
        })
        .await
        .expect("pose subscriber");
    (latest, sub)
}

fn wrap(a: f64) -> f64 {
    (a + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU) - std::f64::consts::PI
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_real_namespace_episode_runs_end_to_end_and_a_dead_controller_stops_the_robot() {
    let _one = ONE_ENCLOSURE.lock().await;
    let mut options = Options::new("MonolithContinuous").expect("options");
    let runs = std::env::temp_dir().join(format!(
        "offworld-real-runs-{}",
        offworld_runtime::keys::random_id()
    ));
    options.record = Some(runs.clone());
    let mut deployment = EmulatedEnclosure::start(&options).expect("deployment");
    deployment
        .ready(Duration::from_secs(60))
        .await
        .expect("deployment ready");
    let (session, mut gym) = open(&deployment, "emulated-e2e").await;
    let experiment_id = gym.opened().experiment.id;
    assert_eq!(gym.spec().task, "MonolithContinuous");
    let robot_side = robot_side(&deployment).await;
    let (pose, _pose_sub) = watch_pose(&robot_side, &deployment.env).await;
    let (cmd_vel, _cmd_sub) = CmdVelLog::watch(&robot_side).await;

    // Reset: the robot agent drives the robot to the sampled spawn pose.
    let started = Instant::now();
    let first = reset(&mut gym, 3).await;
    let reset_time = started.elapsed();
    assert_eq!(
        (
            first.observation.height,
            first.observation.width,
            first.observation.channels
        ),
        (84, 84, 4)
    );
    assert!(
        cmd_vel
            .snapshot()
            .iter()
            .any(|(_, v, w)| *v != 0.0 || *w != 0.0),
        "the reset drove the robot"
    );
    // Its accuracy is in the env's status: within the navigation's
    // tolerances (5 cm, 0.08 rad; twice that for the tracker's and the
    // settling's share), timed by the controller.
    let status = offworld_client::status(&session, &deployment.env, Duration::from_secs(5))
        .await
        .expect("status");
    let accuracy = status.last_reset;
    assert!(accuracy.measured, "{accuracy:?}");
    assert!(
        accuracy.position_error_m < 0.10 && accuracy.yaw_error_rad < 0.16,
        "{accuracy:?}"
    );
    assert!(
        accuracy.duration_s > 0.0 && accuracy.duration_s <= reset_time.as_secs_f64(),
        "{accuracy:?} vs {reset_time:?}"
    );
    if first.info.pose_shared {
        assert_eq!(
            (
                accuracy.achieved.x,
                accuracy.achieved.y,
                accuracy.achieved.yaw
            ),
            (first.info.x, first.info.y, first.info.yaw),
            "achieved = where the episode starts"
        );
    }

    // A scripted policy with privileged access to the tracker pose steers to
    // the monolith: the episode ends with the success reward.
    let mut steps = 0;
    let last = loop {
        let here = pose.lock().ok().and_then(|p| *p).expect("tracker pose");
        let (dx, dy) = (MONOLITH.0 - here.x, MONOLITH.1 - here.y);
        let error = wrap(dy.atan2(dx) - here.yaw);
        let distance = dx.hypot(dy);
        let turn = (1.5 * error / 2.5).clamp(-1.0, 1.0) as f32;
        let forward = if error.abs() < 0.4 {
            ((distance - 0.25).clamp(0.05, 0.3) / 0.7) as f32
        } else {
            0.0
        };
        let reply = gym
            .step(Action::Continuous(vec![forward, turn]))
            .await
            .expect("step");
        steps += 1;
        assert_eq!(reply.info.step, steps);
        // A real env keeps the ground truth to itself (no --share-real-pose).
        assert!(
            !reply.info.pose_shared && reply.info.x == 0.0,
            "{:?}",
            reply.info
        );
        if reply.terminated || reply.truncated {
            break reply;
        }
    };
    assert!(last.terminated, "reached the monolith, not the step limit");
    assert_eq!(last.reward, 1.0);
    assert!(last.info.is_success);
    assert_eq!(last.info.end_reason, "success");
    // The episode is on record: every step flushed, the file finished (the
    // writer runs beside the steps: a bounded wait for its last lines).
    let episode_dir = runs
        .join("real")
        .join(deployment.env.name())
        .join(format!("exp-{experiment_id:06}"));
    let first_file = episode_dir.join("ep-000000.mcap");
    for _ in 0..100 {
        if first_file.exists() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let recorded = offworld_recorder::read::summarize(&first_file).expect("the recorded episode");
    assert!(recorded.complete);
    assert_eq!(recorded.metadata["embodiment"], "robot");
    assert_eq!(recorded.messages["/offworld/step"], u64::from(steps) + 1);
    assert_eq!(recorded.messages["/cmd_vel"], u64::from(steps));
    let end = recorded.end.expect("the episode's end");
    assert_eq!((end.steps, end.end_reason.as_str()), (steps, "success"));
    eprintln!("emulated enclosure: reset drive {reset_time:?}, success in {steps} steps");

    // Next episode. Freeze the controller mid-motion (SIGSTOP: its session
    // and liveliness token stay, its heartbeats stop): the watchdog window
    // stops the robot.
    reset(&mut gym, 4).await;
    let stepping = tokio::spawn(async move {
        let result = gym.step(Action::Continuous(vec![0.0, 0.6])).await;
        (gym, result)
    });
    let latency = stop_latency(&cmd_vel, || deployment.signal_controller("STOP")).await;
    eprintln!("controller frozen mid-motion: commanded velocity zero after {latency:?}");
    // Within the 200 ms window after the last heartbeat (+ margin). No lower
    // bound: on a starved machine the last beats before the freeze may
    // already have been late, so the window can close sooner after it.
    assert!(
        latency < Duration::from_millis(500),
        "the heartbeat watchdog (200 ms) stopped the robot: {latency:?}"
    );
    deployment.signal_controller("CONT");
    let (mut gym, _cut_short) = stepping.await.expect("step task");

    // Kill it mid-motion (SIGKILL): its liveliness token vanishes at once.
    reset(&mut gym, 5).await;
    let stepping = tokio::spawn(async move {
        let result = gym.step(Action::Continuous(vec![0.0, 0.6])).await;
        (gym, result)
    });
    let latency = stop_latency(&cmd_vel, || deployment.kill_controller()).await;
    eprintln!("controller killed mid-motion: commanded velocity zero after {latency:?}");
    assert!(
        latency < Duration::from_millis(500),
        "stopped within the watchdog window (+ margin): {latency:?}"
    );
    let (_gym, result) = stepping.await.expect("step task");
    let err: WireError = result.expect_err("the step cannot succeed without its controller");
    assert!(
        matches!(err.code, ErrorCode::Timeout | ErrorCode::Unavailable),
        "{err}"
    );
    // Killed mid-episode: that episode is a .partial holding its reset
    // (flushed before the step began), the earlier ones complete.
    let files = offworld_recorder::read::episode_files(&runs).expect("files");
    let names: Vec<String> = files
        .iter()
        .filter_map(|f| f.file_name().map(|n| n.to_string_lossy().into_owned()))
        .collect();
    assert_eq!(
        names,
        ["ep-000000.mcap", "ep-000001.mcap", "ep-000002.mcap.partial"]
    );
    let cut = offworld_recorder::read::summarize(&files[2]).expect("partial");
    assert!(!cut.complete);
    assert_eq!(cut.last_step.map(|s| s.step), Some(0));
    let _ = std::fs::remove_dir_all(&runs);
}

/// Waits until the robot is moving, runs `act`, and returns how long until
/// the base was commanded zero (and stayed there for a second).
async fn stop_latency(cmd_vel: &CmdVelLog, act: impl FnOnce()) -> Duration {
    for _ in 0..100 {
        tokio::time::sleep(Duration::from_millis(20)).await;
        let moving = cmd_vel.snapshot().last().map(|(_, v, w)| (*v, *w));
        if moving.is_some_and(|(v, w)| v != 0.0 || w != 0.0) {
            break;
        }
    }
    tokio::time::sleep(Duration::from_millis(200)).await;
    let moving = cmd_vel.snapshot().last().map(|(_, v, w)| (*v, *w));
    assert!(
        moving.is_some_and(|(v, w)| v != 0.0 || w != 0.0),
        "mid-motion: {moving:?}"
    );
    act();
    let acted = Instant::now();
    tokio::time::sleep(Duration::from_millis(1000)).await;
    let after: Vec<_> = cmd_vel
        .snapshot()
        .into_iter()
        .filter(|(t, _, _)| *t >= acted)
        .collect();
    let first_zero = after
        .iter()
        .position(|(_, v, w)| *v == 0.0 && *w == 0.0)
        .expect("a zero velocity afterwards");
    assert!(
        after[first_zero..]
            .iter()
            .all(|(_, v, w)| *v == 0.0 && *w == 0.0),
        "the robot stays stopped"
    );
    after[first_zero].0.saturating_duration_since(acted)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tracker_silence_fails_the_step_with_a_typed_error_and_stops_the_robot() {
    let _one = ONE_ENCLOSURE.lock().await;
    let mut options = Options::new("MonolithDiscrete").expect("options");
    options.pausable_tracker = true;
    let deployment = EmulatedEnclosure::start(&options).expect("deployment");
    deployment
        .ready(Duration::from_secs(60))
        .await
        .expect("deployment ready");
    let (_session, mut gym) = open(&deployment, "tracker-silence").await;
    let robot_side = robot_side(&deployment).await;
    let (cmd_vel, _cmd_sub) = CmdVelLog::watch(&robot_side).await;
    reset(&mut gym, 5).await;
    let ok = gym
        .step(Action::Discrete(0))
        .await
        .expect("a step while tracked");
    assert_eq!(ok.info.step, 1);

    let proxy = deployment.tracker_proxy.as_ref().expect("proxy");
    proxy.pause(true);
    tokio::time::sleep(Duration::from_millis(600)).await;
    let silenced = Instant::now();
    let err = gym
        .step(Action::Discrete(2))
        .await
        .expect_err("no step is scored on a stale pose");
    assert_eq!(err.code, ErrorCode::Unavailable, "{err}");
    assert!(err.message.contains("tracking lost"), "{err}");
    tokio::time::sleep(Duration::from_millis(300)).await;
    let since: Vec<_> = cmd_vel
        .snapshot()
        .into_iter()
        .filter(|(t, _, _)| *t >= silenced)
        .collect();
    assert!(
        since.iter().all(|(_, v, w)| *v == 0.0 && *w == 0.0),
        "the robot was not moved while tracking was lost: {since:?}"
    );

    // The episode was aborted (recorded with the reason), not silently kept.
    let err = gym
        .step(Action::Discrete(0))
        .await
        .expect_err("aborted episode");
    assert_eq!(err.code, ErrorCode::InvalidState, "{err}");

    // Tracking back: a new episode starts and steps again.
    proxy.pause(false);
    reset(&mut gym, 6).await;
    let again = gym
        .step(Action::Discrete(2))
        .await
        .expect("step after recovery");
    assert_eq!(again.info.step, 1);
}

/// Issue 22, defence in depth beyond the router: a peer on the robot
/// computer's own network (no ACL in its way) floods motion commands and
/// tracker poses at the monolith. The base is never told to move (the
/// robot agent obeys only commands sealed with the site's command key) and
/// no step scores on the forged poses (the controller believes only poses
/// sealed with the tracker key); the researcher's steps run as usual.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_rogue_peer_on_the_robot_network_can_neither_drive_nor_score() {
    let _one = ONE_ENCLOSURE.lock().await;
    let options = Options::new("MonolithDiscrete").expect("options");
    let deployment = EmulatedEnclosure::start(&options).expect("deployment");
    deployment
        .ready(Duration::from_secs(60))
        .await
        .expect("deployment ready");
    let (_session, mut gym) = open(&deployment, "rogue-peer").await;
    reset(&mut gym, 5).await;
    let rogue = robot_side(&deployment).await;
    let (cmd_vel, _cmd_vel_sub) = CmdVelLog::watch(&rogue).await;
    let flooding = Arc::new(std::sync::atomic::AtomicBool::new(true));
    let (session, env, flag) = (rogue.clone(), deployment.env.clone(), flooding.clone());
    let flood = tokio::spawn(async move {
        let at_the_monolith = PoseStamped {
            header: Header::new(Time::now(), "world"),
            pose: Pose {
                position: Point {
                    x: MONOLITH.0,
                    y: MONOLITH.1,
                    z: 0.0,
                },
                orientation: Quaternion::from_yaw(0.0),
            },
        };
        // Bounded: 60 s at most, whatever the test does.
        for seq in 0..3_000u64 {
            if !flag.load(std::sync::atomic::Ordering::SeqCst) {
                break;
            }
            let forward = MotionCommand {
                seq: 9_000_000 + seq,
                linear_x: 0.2,
                angular_z: 0.0,
                duration_s: 1.0,
            };
            let _ = offworld_runtime::wire::put(&session, &env.key(Topic::Cmd), &forward).await;
            let _ = offworld_runtime::wire::put(&session, &env.key(Topic::Pose), &at_the_monolith)
                .await;
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    });
    let started = Instant::now();
    tokio::time::sleep(Duration::from_secs(2)).await;
    let told: Vec<_> = cmd_vel
        .snapshot()
        .into_iter()
        .filter(|(at, v, w)| *at >= started && (*v != 0.0 || *w != 0.0))
        .collect();
    assert!(
        told.is_empty(),
        "the base was told to move by forged commands: {told:?}"
    );
    // Steps while the forged poses keep coming: none scores on them.
    for _ in 0..3 {
        let step = gym.step(Action::Discrete(0)).await.expect("step");
        assert!(
            !step.terminated && step.reward == 0.0,
            "a step scored on forged poses: reward {}, terminated {}",
            step.reward,
            step.terminated
        );
    }
    flooding.store(false, std::sync::atomic::Ordering::SeqCst);
    flood.await.expect("flood");
    gym.close().await.expect("close");
}
