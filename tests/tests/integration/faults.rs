//! Fault injection with real processes on the emulated enclosure, against
//! the worst-case base (it holds the last velocity forever): the robot
//! agent killed, terminated and frozen, the camera hardware killed, the
//! tracker agent killed, the robot's router killed — each while a step
//! turns the robot. Asserted for each: the base stopped and stayed stopped
//! (it turned far less than the 1.5 rad/s it was told would give over the
//! window), the client's step failed with a typed transient error, and at
//! the end no episode record was lost and the experiment resumes.
//!
//! The full matrix with its figures is the `fault_matrix` program.

use std::time::Duration;

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_env_controller::Store;
use offworld_runtime::{ErrorCode, SessionConfig};
use offworld_tests::emulated::{EmulatedEnclosure, Options, Part};
use offworld_tests::faults::{
    inject, open_request, recover, reset_when_ready, BaseObserver, Fault,
};
use offworld_tests::link::Impairment;
use zenoh::Session;

/// How long the base is watched after each fault. A base that held its
/// velocity would turn 1.5 rad/s × 3 s = 4.5 rad in it.
const WINDOW: Duration = Duration::from_secs(3);
/// What the base may still turn after a fault: 200 ms at the robot's
/// top 2.5 rad/s is 0.5 rad; the rest is slack for a loaded machine.
const TURN_BOUND_RAD: f64 = 1.2;

/// Starts the deployment and opens a training session on `experiment`.
async fn deploy(
    options: &Options,
    experiment: &str,
) -> (EmulatedEnclosure, BaseObserver, Session, EnvClient) {
    let deployment = EmulatedEnclosure::start(options).expect("deployment");
    deployment
        .ready(Duration::from_secs(60))
        .await
        .expect("deployment ready");
    let base = BaseObserver::connect(&deployment).await.expect("observer");
    let session = SessionConfig::connecting(&deployment.endpoint)
        .open()
        .await
        .expect("client session");
    let gym = EnvClient::open_when_ready(
        &session,
        &deployment.env,
        open_request(&deployment.token, experiment, false),
        ClientTimeouts::default(),
        Duration::from_secs(30),
    )
    .await
    .expect("open");
    (deployment, base, session, gym)
}

/// Every episode started on `experiment` was recorded (each ended aborted
/// by its fault), and the experiment resumes with all of them.
async fn assert_every_episode_recorded(
    deployment: &EmulatedEnclosure,
    session: &Session,
    experiment: &str,
    started: u64,
) {
    let store = Store::open(&deployment.dir.join("gym.db")).expect("store");
    let recorded = store
        .experiments()
        .expect("experiments")
        .into_iter()
        .find(|e| e.name == experiment)
        .expect("the experiment");
    assert_eq!(recorded.episodes, started, "no episode record lost");
    let resumed = EnvClient::open(
        session,
        &deployment.env,
        open_request(&deployment.token, experiment, true),
        ClientTimeouts::default(),
    )
    .await
    .expect("resume");
    assert_eq!(resumed.opened().experiment.episodes, started);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_base_stops_and_the_client_gets_a_typed_error_on_every_fault() {
    let options = Options::new("MonolithContinuous").expect("options");
    assert_eq!(options.base_cmd_timeout_ms, None, "the worst-case base");
    let (mut deployment, base, session, mut gym) = deploy(&options, "faults").await;

    let scenarios = [
        (Part::RobotAgent, Fault::Kill),
        (Part::RobotAgent, Fault::Terminate),
        (Part::RobotAgent, Fault::Freeze(Duration::from_secs(5))),
        (Part::TrackerAgent, Fault::Kill),
        (Part::Router, Fault::Kill),
        (Part::Hardware, Fault::Kill),
    ];
    let mut resets = 0u64;
    for (seed, (part, fault)) in (10u64..).zip(scenarios) {
        reset_when_ready(&mut gym, seed, Duration::from_secs(90))
            .await
            .unwrap_or_else(|e| panic!("{part:?} {fault}: no reset: {e}"));
        resets += 1;
        let (back, outcome) = inject(&mut deployment, gym, &base, part, fault, WINDOW).await;
        gym = back;
        eprintln!(
            "{:<14} {:<10} moved for {:?}, turned {:.2} rad, client {:?} after {:?}",
            part.name(),
            fault.to_string(),
            outcome.moved_for,
            outcome.turned_rad,
            outcome.client_error.as_ref().map(|e| e.to_string()),
            outcome.result_after
        );
        if part != Part::Hardware {
            // (A killed emulator takes its odometry with it: nothing to see.)
            assert!(
                outcome.observed,
                "{part:?} {fault}: odometry heard after the fault"
            );
            assert!(
                outcome.stopped_within(Duration::from_secs(1)),
                "{part:?} {fault}: the base kept moving ({:?})",
                outcome.moved_for
            );
            assert!(
                outcome.turned_rad < TURN_BOUND_RAD,
                "{part:?} {fault}: turned {:.2} rad after the fault",
                outcome.turned_rad
            );
        }
        let error = outcome
            .client_error
            .unwrap_or_else(|| panic!("{part:?} {fault}: the interrupted step succeeded"));
        assert_eq!(
            error.code,
            ErrorCode::Unavailable,
            "{part:?} {fault}: a transient, typed error: {error}"
        );
        recover(&mut deployment, part, fault)
            .await
            .unwrap_or_else(|e| panic!("{part:?} {fault}: no recovery: {e}"));
    }

    gym.close().await.expect("close");
    assert_every_episode_recorded(&deployment, &session, "faults", resets).await;
}

/// The control: without the base guard, a killed robot agent leaves the
/// worst-case base turning for as long as it is watched — what the guard
/// exists for, and proof that the measurement above can see motion.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_the_guard_a_killed_agent_leaves_the_worst_case_base_moving() {
    let mut options = Options::new("MonolithContinuous").expect("options");
    options.base_guard = false;
    let (mut deployment, base, _session, mut gym) = deploy(&options, "unguarded").await;
    reset_when_ready(&mut gym, 3, Duration::from_secs(90))
        .await
        .expect("reset");
    let (_gym, outcome) = inject(
        &mut deployment,
        gym,
        &base,
        Part::RobotAgent,
        Fault::Kill,
        WINDOW,
    )
    .await;
    assert!(outcome.observed, "odometry heard after the fault");
    assert_eq!(
        outcome.moved_for, None,
        "still moving at the end of the window"
    );
    assert!(
        outcome.turned_rad > 3.0,
        "kept turning at 1.5 rad/s: {:.2} rad in {WINDOW:?}",
        outcome.turned_rad
    );
}

/// The robot's network link, between the site (controller) and the robot
/// computer: cut, lossy (30 %), slow (500 ms each way). Whatever the link
/// does, the worst-case base stops and the client gets an answer it can
/// act on; once the link is clear again, training resumes with every
/// episode recorded.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_base_stops_and_the_client_gets_an_answer_on_robot_link_faults() {
    let mut options = Options::new("MonolithContinuous").expect("options");
    options.isolated_robot = true;
    let (mut deployment, base, session, mut gym) = deploy(&options, "link-faults").await;
    let held = Duration::from_secs(4);
    let faults = [
        Fault::Link(Impairment::Cut, held),
        Fault::Link(Impairment::Loss { percent: 30 }, held),
        Fault::Link(Impairment::Delay(Duration::from_millis(500)), held),
    ];
    let mut resets = 0u64;
    for (seed, fault) in (20u64..).zip(faults) {
        reset_when_ready(&mut gym, seed, Duration::from_secs(90))
            .await
            .unwrap_or_else(|e| panic!("{fault}: no reset: {e}"));
        resets += 1;
        let (back, outcome) = inject(
            &mut deployment,
            gym,
            &base,
            Part::RobotLink,
            fault,
            WINDOW + held,
        )
        .await;
        gym = back;
        eprintln!(
            "robot_link {:<22} moved for {:?}, turned {:.2} rad, client {:?} after {:?}",
            fault.to_string(),
            outcome.moved_for,
            outcome.turned_rad,
            outcome.client_error.as_ref().map(|e| e.to_string()),
            outcome.result_after
        );
        assert!(outcome.observed, "{fault}: odometry heard after the fault");
        assert!(
            outcome.moved_for.is_some(),
            "{fault}: the base still moves at the end of the window"
        );
        if matches!(fault, Fault::Link(Impairment::Cut, _)) {
            // The controller stops hearing the robot's heartbeat echoes: the
            // step fails while the link is still cut, not when it returns.
            let error = outcome.client_error.as_ref().expect("the cut step failed");
            assert_eq!(error.code, ErrorCode::Unavailable, "{error}");
            assert!(error.message.contains("no word from the robot"), "{error}");
            assert!(
                outcome.result_after < held,
                "{fault}: failed during the cut, after {:?}",
                outcome.result_after
            );
            // Nothing reaches the robot: its watchdog stops it.
            assert!(
                outcome.stopped_within(Duration::from_secs(1)),
                "{fault}: the base kept moving ({:?})",
                outcome.moved_for
            );
            assert!(
                outcome.turned_rad < TURN_BOUND_RAD,
                "{fault}: turned {:.2} rad after the fault",
                outcome.turned_rad
            );
        }
        if let Some(error) = &outcome.client_error {
            assert!(
                matches!(error.code, ErrorCode::Unavailable | ErrorCode::Timeout),
                "{fault}: a transient, typed error: {error}"
            );
        }
        recover(&mut deployment, Part::RobotLink, fault)
            .await
            .unwrap_or_else(|e| panic!("{fault}: no recovery: {e}"));
    }
    gym.close().await.expect("close");
    assert_every_episode_recorded(&deployment, &session, "link-faults", resets).await;
}
