//! The controller's link to the robot over real Zenoh, with the test
//! playing the robot: a command the robot reports it cannot answer fails
//! with the robot's reason (Unavailable), not with the answer timeout;
//! faults of other commands and malformed faults are ignored; the
//! observation is built from the command's own frame, never a stale one;
//! a step is judged once and replied once, from where its frame arrives
//! when it can be.

use std::sync::Arc;
use std::time::Duration;

use offworld_env_controller::link::{LinkTimeouts, ObservationRequest, RobotLink};
use offworld_env_controller::step::{Answered, Plan, Reply, StepJudge};
use offworld_env_controller::Task;
use offworld_runtime::keys::{Component, EnvId, Topic};
use offworld_runtime::msg::{
    CameraFrame, Channels, DepthFormat, Header, Image, MotionCommand, MotionFault, ObsOptions,
    PixelEncoding, PoseStamped, SeqTag, StepReply,
};
use offworld_runtime::session::loopback_pair;
use offworld_runtime::wire::{self, Delivery};
use offworld_runtime::{codec, ErrorCode, WireError};
use zenoh::liveliness::LivelinessToken;
use zenoh::sample::Sample;
use zenoh::{Session, Wait};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reported_fault_fails_the_command_with_its_reason() {
    let (link, robot, env, _alive) = connect("fault-link").await;

    // The robot: every command gets a malformed fault, a fault of another
    // command, then its own.
    let (fault_session, fault_key) = (robot.clone(), env.key(Topic::Fault));
    let _robot_cmd = robot
        .declare_subscriber(env.key(Topic::Cmd))
        .callback(move |sample: Sample| {
            let Ok(cmd) = codec::decode_payload::<MotionCommand>(sample.payload()) else {
                return;
            };
            let put = |bytes: Vec<u8>| fault_session.put(&fault_key, bytes).wait();
            let fault = |seq| {
                codec::encode(&MotionFault {
                    seq,
                    reason: format!("fault of {seq}"),
                })
                .expect("encode")
            };
            let _ = put(vec![0xde, 0xad]);
            let _ = put(fault(cmd.seq + 1000));
            let _ = put(fault(cmd.seq));
        })
        .await
        .expect("robot's cmd subscriber");

    let (seq, result) = first_heard(&link, 1, 0.1, 0.5).await;
    let Err(err) = result else {
        panic!("command {seq} was answered")
    };
    assert_eq!(err.code, ErrorCode::Unavailable, "{err}");
    assert_eq!(
        err.message,
        format!("the robot cannot answer command {seq}: fault of {seq}")
    );

    // The link keeps serving: the next command fails with its own fault.
    let Err(err) = look(&link, command(50, 0.1, 0.5), rgbd(2, 2)).await else {
        panic!("command 50 was answered")
    };
    assert_eq!(err.code, ErrorCode::Unavailable);
    assert_eq!(
        err.message,
        "the robot cannot answer command 50: fault of 50"
    );
}

/// A 2×2 frame answering `seq`: every colour byte is `seq`, depth 1 m
/// except one pixel with no return (NaN).
fn frame(seq: u64) -> CameraFrame {
    let depth = [1.0f32, 1.0, f32::NAN, 1.0]
        .iter()
        .flat_map(|d| d.to_le_bytes())
        .collect();
    CameraFrame {
        seq,
        color: Image::packed(
            Header::default(),
            2,
            2,
            PixelEncoding::Rgb8,
            vec![seq as u8; 12],
        ),
        depth: Image::packed(Header::default(), 2, 2, PixelEncoding::Depth32FC1, depth),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_observation_is_built_from_the_commands_own_frame() {
    let (link, robot, env, _alive) = connect("obs-link").await;

    // The robot: every command gets a malformed frame, a stale frame (of
    // the command before), then its pose and its own frame.
    let obs = wire::publisher(&robot, env.key(Topic::Obs), Delivery::Every)
        .await
        .expect("obs publisher");
    let pose = wire::publisher(&robot, env.key(Topic::Pose), Delivery::Every)
        .await
        .expect("pose publisher");
    let _robot_cmd = robot
        .declare_subscriber(env.key(Topic::Cmd))
        .callback(move |sample: Sample| {
            let Ok(cmd) = codec::decode_payload::<MotionCommand>(sample.payload()) else {
                return;
            };
            let _ = obs.put(vec![0xde, 0xad]).wait();
            let _ = wire::publish(&obs, &frame(cmd.seq - 1));
            let tag = SeqTag { seq: cmd.seq };
            let _ = wire::publish_tagged(&pose, &PoseStamped::default(), tag);
            let _ = wire::publish(&obs, &frame(cmd.seq));
        })
        .await
        .expect("robot's cmd subscriber");

    let (seq, answer) = first_heard(&link, 10, 0.0, 0.0).await;
    let (pose, data) = observation(answer.expect("answered"));
    assert_eq!(pose, Some(seq));
    let c = seq as u8;
    // 1 m of 0–5 m is level 51; no return is 0.
    assert_eq!(
        data,
        [c, c, c, 51, c, c, c, 51, c, c, c, 0, c, c, c, 51].as_slice()
    );

    // The next command, with other options, gets its own.
    let mut depth_only = rgbd(1, 1);
    depth_only.options.channels = Channels::DepthOnly;
    let answer = look(&link, command(seq + 1, 0.0, 0.0), depth_only)
        .await
        .expect("answered");
    // Sampled at the source pixel nearest the centre: (1, 1).
    assert_eq!(observation(answer), (Some(seq + 1), vec![51]));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_reply_is_sent_where_the_frame_arrives_only_with_a_tagged_pose() {
    let (link, controller, robot, env, _alive) = connect_with_session("reply-link").await;

    // The robot: commands below 100 get a pose tagged with them, then their
    // frame (a twin); the others their frame, then untagged poses at 50 Hz
    // (a robot and its tracker). Its pose is inside the enclosure, 1.3 m
    // from the monolith: a step there goes on.
    let mut inside = PoseStamped::default();
    (inside.pose.position.x, inside.pose.position.y) = (1.0, 0.5);
    let obs = wire::publisher(&robot, env.key(Topic::Obs), Delivery::Every)
        .await
        .expect("obs publisher");
    let pose = Arc::new(
        wire::publisher(&robot, env.key(Topic::Pose), Delivery::Every)
            .await
            .expect("pose publisher"),
    );
    let _robot_cmd = robot
        .declare_subscriber(env.key(Topic::Cmd))
        .callback(move |sample: Sample| {
            let Ok(cmd) = codec::decode_payload::<MotionCommand>(sample.payload()) else {
                return;
            };
            if cmd.seq < 100 {
                let tag = SeqTag { seq: cmd.seq };
                let _ = wire::publish_tagged(&pose, &inside, tag);
                let _ = wire::publish(&obs, &frame(cmd.seq));
            } else {
                let _ = wire::publish(&obs, &frame(cmd.seq));
                let (tracker, inside) = (pose.clone(), inside.clone());
                std::thread::spawn(move || {
                    for _ in 0..10 {
                        std::thread::sleep(Duration::from_millis(20));
                        let _ = wire::publish(&tracker, &inside);
                    }
                });
            }
        })
        .await
        .expect("robot's cmd subscriber");
    let (seq, answer) = first_heard(&link, 20, 0.0, 0.0).await;
    answer.expect("answered");

    // A client's request, answered from the thread that gets the frame: the
    // client receives the judged reply and the observation, the caller
    // learns the pose used and the verdict.
    let step_key = env.key(Topic::Step);
    let queries = controller
        .declare_queryable(&step_key)
        .await
        .expect("queryable");
    let task = Arc::new(Task::by_name("MonolithDiscrete").expect("task"));
    let judge = |step| StepJudge {
        task: task.clone(),
        seq: 77,
        episode_id: 3,
        step,
        obs: rgbd(2, 2).options,
        share_pose: true,
    };
    let (replies, query) = step_query(&robot, &queries, &step_key).await;
    let answer = Plan::judged(
        command(seq + 1, 0.0, 0.0),
        rgbd(2, 2),
        judge(1),
        Some(query),
    )
    .run(&link)
    .await
    .expect("answered");
    assert!(
        matches!(answer.reply, Reply::Sent),
        "not replied where the frame arrived"
    );
    assert_eq!(answer.pose.seq, Some(seq + 1));
    assert_eq!(
        (answer.verdict.reply.seq, answer.verdict.reply.info.step),
        (77, 1)
    );
    let received = tokio::time::timeout(Duration::from_secs(5), replies.recv_async())
        .await
        .expect("reply in time")
        .expect("reply");
    let payload = received.result().expect("ok").payload().clone();
    let reply: StepReply = codec::decode_payload_tail(&payload).expect("a step reply");
    let c = (seq + 1) as u8;
    assert_eq!(
        reply.observation.data,
        [c, c, c, 51, c, c, c, 51, c, c, c, 0, c, c, c, 51].as_slice()
    );
    assert_eq!(
        reply,
        StepReply {
            observation: reply.observation.clone(),
            ..answer.verdict.reply
        }
    );

    // A step that ends its episode (here at the step limit) leaves the
    // reply to the caller, who records the episode first.
    let last = task.episode.max_steps;
    let (_replies, query) = step_query(&robot, &queries, &step_key).await;
    let answer = Plan::judged(
        command(seq + 2, 0.0, 0.0),
        rgbd(1, 1),
        judge(last),
        Some(query),
    )
    .run(&link)
    .await
    .expect("answered");
    assert!(answer.verdict.outcome.truncated);
    assert_eq!(
        observation(answer),
        (Some(seq + 2), vec![c + 1, c + 1, c + 1, 51])
    );

    // Without a pose tagged with the command, the reply is never attempted
    // there: the caller's task judges (once) and replies.
    let (_replies, query) = step_query(&robot, &queries, &step_key).await;
    let answer = Plan::judged(command(100, 0.0, 0.0), rgbd(1, 1), judge(1), Some(query))
        .run(&link)
        .await
        .expect("answered");
    assert_eq!(
        (answer.verdict.reply.seq, answer.verdict.reply.info.step),
        (77, 1)
    );
    assert_eq!(observation(answer), (None, vec![100, 100, 100, 51]));
}

/// A step request from the robot's session to `queries` on `key`: the
/// replies' receiver and the query. Until the queryable is known to the
/// robot's session, a get matches nothing: bounded attempts.
async fn step_query(
    robot: &Session,
    queries: &zenoh::query::Queryable<zenoh::handlers::FifoChannelHandler<zenoh::query::Query>>,
    key: &str,
) -> (
    zenoh::handlers::FifoChannelHandler<zenoh::query::Reply>,
    zenoh::query::Query,
) {
    for _ in 0..50 {
        let replies = robot.get(key).await.expect("get");
        let arrived = tokio::time::timeout(Duration::from_millis(100), queries.recv_async());
        if let Ok(Ok(query)) = arrived.await {
            return (replies, query);
        }
    }
    panic!("the query never arrived");
}

/// Sends `motion` and waits for its observation, judged by no one.
async fn look(
    link: &RobotLink,
    motion: MotionCommand,
    request: ObservationRequest,
) -> Result<Answered<()>, WireError> {
    Plan::observe(motion, request).run(link).await
}

/// The pose's tag and the observation's bytes of an answer not replied yet.
fn observation<V>(answer: Answered<V>) -> (Option<u64>, Vec<u8>) {
    match answer.reply {
        Reply::Due(data) => (answer.pose.seq, data.to_bytes().into_owned()),
        Reply::Sent => panic!("replied without being asked to"),
    }
}

/// A link to env `name` and the session that plays its robot. The answer
/// margin is far beyond the tests: a timeout would be its own error code.
/// A link to a robot played by the test on its own session; the robot
/// declares itself as a robot agent does (its token: the link fails
/// commands at once while no robot is there).
async fn connect(name: &str) -> (RobotLink, Session, EnvId, LivelinessToken) {
    let (link, _controller, robot, env, alive) = connect_with_session(name).await;
    (link, robot, env, alive)
}

/// [`connect`], with the link's own session.
async fn connect_with_session(name: &str) -> (RobotLink, Session, Session, EnvId, LivelinessToken) {
    let (controller, robot) = loopback_pair().await.expect("loopback sessions");
    let env = EnvId::real(name).expect("env id");
    let timeouts = LinkTimeouts {
        answer_margin: Duration::from_secs(60),
        ..LinkTimeouts::default()
    };
    let link = RobotLink::connect(&controller, &env, timeouts, &Default::default())
        .await
        .expect("link");
    let alive = robot
        .liveliness()
        .declare_token(env.alive_key(Component::RobotAgent))
        .await
        .expect("robot token");
    assert!(
        link.wait_online(Duration::from_secs(10)).await,
        "the link sees the robot's token"
    );
    (link, controller, robot, env, alive)
}

/// Command `seq`: straight ahead at `linear_x` for `duration_s`.
fn command(seq: u64, linear_x: f64, duration_s: f64) -> MotionCommand {
    MotionCommand {
        seq,
        linear_x,
        angular_z: 0.0,
        duration_s,
    }
}

/// Drives at `linear_x` for `duration_s` as command `first`, `first + 1`,
/// … until the robot hears one: the subscriptions may still be
/// propagating, and a command sent before that goes unanswered, so each
/// attempt is bounded.
async fn first_heard(
    link: &RobotLink,
    first: u64,
    linear_x: f64,
    duration_s: f64,
) -> (u64, Result<Answered<()>, WireError>) {
    for seq in first..first + 5 {
        let cmd = command(seq, linear_x, duration_s);
        let attempt = look(link, cmd, rgbd(2, 2));
        if let Ok(result) = tokio::time::timeout(Duration::from_secs(3), attempt).await {
            return (seq, result);
        }
    }
    panic!("no command reached the robot");
}

/// RGBD uint8 observations of `width × height`, depth 0–5 m.
fn rgbd(width: u32, height: u32) -> ObservationRequest {
    ObservationRequest {
        options: ObsOptions {
            channels: Channels::Rgbd,
            height,
            width,
            depth_format: DepthFormat::Uint8,
        },
        depth_max_m: 5.0,
    }
}

/// What the controller knows is gone fails the command in flight at once,
/// not after its answer timeout (60 s here): the base guard's fault for
/// whatever command is in flight, or the robot's token vanishing.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_vanished_robot_or_a_guard_stop_fails_the_command_in_flight_at_once() {
    let (link, robot, env, alive) = connect("gone-link").await;
    // The base guard stops the base: a fault for any command in flight
    // (repeated: the link's subscription may still be propagating).
    let seventh = command(7, 0.1, 30.0);
    let guard = async {
        loop {
            tokio::time::sleep(Duration::from_millis(200)).await;
            let fault = MotionFault {
                seq: MotionFault::ANY_COMMAND,
                reason: "the base guard stopped the base: test".into(),
            };
            wire::put(&robot, &env.key(Topic::Fault), &fault)
                .await
                .expect("fault");
        }
    };
    let result = tokio::time::timeout(Duration::from_secs(10), async {
        tokio::select! {
            result = look(&link, seventh, rgbd(2, 2)) => result,
            () = guard => unreachable!(),
        }
    })
    .await
    .expect("failed at once, not after the answer timeout");
    let Err(err) = result else { panic!("answered") };
    assert_eq!(err.code, ErrorCode::Unavailable);
    assert_eq!(
        err.message,
        "the robot cannot answer command 7: the base guard stopped the base: test"
    );

    // The robot's token vanishes mid-command.
    let eighth = command(8, 0.1, 30.0);
    let vanish = async {
        tokio::time::sleep(Duration::from_millis(300)).await;
        alive.undeclare().await.expect("undeclare");
        std::future::pending::<()>().await;
    };
    let result = tokio::time::timeout(Duration::from_secs(10), async {
        tokio::select! {
            result = look(&link, eighth, rgbd(2, 2)) => result,
            () = vanish => unreachable!(),
        }
    })
    .await
    .expect("failed at once, not after the answer timeout");
    let Err(err) = result else { panic!("answered") };
    assert_eq!(err.code, ErrorCode::Unavailable);
    assert!(err.message.contains("is gone"), "{err}");
    // And a new command fails before it is sent.
    let ninth = command(9, 0.1, 1.0);
    let Err(err) = look(&link, ninth, rgbd(2, 2)).await else {
        panic!("answered without a robot")
    };
    assert!(err.message.contains("is gone"), "{err}");
}
