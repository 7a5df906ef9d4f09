//! The twin node over real Zenoh sessions on loopback: commands in, frames
//! and poses out with matching sequence numbers; goto; e-stop; bad input.

use offworld_runtime::Resolution;
use std::time::Duration;

use offworld_runtime::codec;
use offworld_runtime::keys::global_estop_key;
use offworld_runtime::msg::*;
use offworld_runtime::preview::ViewerCopy;
use offworld_runtime::session::loopback_pair;
use offworld_runtime::wire::{self, RequestError};
use offworld_runtime::{Component, EnvId, ErrorCode, Topic};
use offworld_sim_twin::overhead::OverheadStream;
use offworld_sim_twin::{Clock, NodeOptions, PlanarPose, SimTwin, Stepping, TwinConfig, TwinNode};
use zenoh::handlers::FifoChannelHandler;
use zenoh::pubsub::Subscriber;
use zenoh::sample::Sample;
use zenoh::{Session, Wait};

struct Client {
    session: Session,
    env: EnvId,
    obs: Subscriber<FifoChannelHandler<Sample>>,
    pose: Subscriber<FifoChannelHandler<Sample>>,
    odom: Subscriber<FifoChannelHandler<Sample>>,
}

impl Client {
    async fn new(session: Session, env: EnvId) -> Self {
        let sub = |topic| {
            let key = env.key(topic);
            let session = session.clone();
            async move { session.declare_subscriber(key).await.expect("subscriber") }
        };
        Self {
            obs: sub(Topic::Obs).await,
            pose: sub(Topic::Pose).await,
            odom: sub(Topic::Odom).await,
            session,
            env,
        }
    }

    async fn command(&self, seq: u64, linear_x: f64, angular_z: f64, duration_s: f64) {
        let cmd = MotionCommand {
            seq,
            linear_x,
            angular_z,
            duration_s,
        };
        wire::put(&self.session, &self.env.key(Topic::Cmd), &cmd)
            .await
            .expect("put");
    }

    /// Waits for the obs answering `seq`; returns (frame, pose, odom).
    async fn answer(&self, seq: u64) -> Option<(CameraFrame, PoseStamped, Odometry)> {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(5);
        let frame = loop {
            let sample = tokio::time::timeout_at(deadline, self.obs.recv_async())
                .await
                .ok()?
                .ok()?;
            let frame: CameraFrame = codec::decode_payload(sample.payload()).expect("frame");
            if frame.seq == seq {
                break frame;
            }
        };
        // Pose and odometry carry the same seq; odometry may follow the frame.
        let pose = tagged(&self.pose, seq, deadline).await?;
        let odom = tagged(&self.odom, seq, deadline).await?;
        let pose = codec::decode_payload(pose.payload()).expect("pose");
        let odom = codec::decode_payload(odom.payload()).expect("odom");
        Some((frame, pose, odom))
    }

    /// First contact: repeats an observe-only command until answered.
    async fn connect(&self) -> (CameraFrame, PoseStamped, Odometry) {
        for attempt in 0..50u64 {
            self.command(1_000_000 + attempt, 0.0, 0.0, 0.0).await;
            if let Ok(Some(a)) =
                tokio::time::timeout(Duration::from_millis(200), self.answer(1_000_000 + attempt))
                    .await
            {
                return a;
            }
        }
        panic!("twin never answered");
    }
}

/// The next sample on `sub` tagged with `seq`, by `deadline`.
async fn tagged(
    sub: &Subscriber<FifoChannelHandler<Sample>>,
    seq: u64,
    deadline: tokio::time::Instant,
) -> Option<Sample> {
    loop {
        let s = tokio::time::timeout_at(deadline, sub.recv_async())
            .await
            .ok()?
            .ok()?;
        if wire::decode_attachment::<SeqTag>(&s) == Some(SeqTag { seq }) {
            return Some(s);
        }
    }
}

async fn setup(world: &str, res: Resolution) -> (TwinNode, Client, Session) {
    setup_with_clock(world, res, Clock::Lockstep).await
}

async fn setup_with_clock(
    world: &str,
    res: Resolution,
    clock: Clock,
) -> (TwinNode, Client, Session) {
    let options = NodeOptions {
        clock,
        ..NodeOptions::default()
    };
    setup_with(world, res, options).await
}

async fn setup_with(
    world: &str,
    res: Resolution,
    options: NodeOptions,
) -> (TwinNode, Client, Session) {
    let (server, client) = loopback_pair().await.expect("loopback sessions");
    let env = EnvId::sim("node-test").expect("env");
    let mut config = TwinConfig::builtin(world).expect("world");
    config.resolution = Some(res);
    config.start = PlanarPose {
        x: -1.0,
        y: 0.5,
        yaw: 0.0,
    };
    let node = TwinNode::spawn_with(
        &server,
        env.clone(),
        SimTwin::new(config).expect("twin"),
        options,
    )
    .expect("node");
    (node, Client::new(client, env).await, server)
}

fn planar(p: &PoseStamped) -> (f64, f64, f64) {
    (
        p.pose.position.x,
        p.pose.position.y,
        p.pose.orientation.yaw(),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn commands_in_frames_and_poses_out_with_matching_seq() {
    let (node, client, _server) = setup("monolith", Resolution::new(64, 48)).await;
    let (frame, pose0, _) = client.connect().await;
    let connected = node.stats();
    assert_eq!((frame.color.width, frame.color.height), (64, 48));
    assert_eq!(frame.color.validate(), Ok(PixelEncoding::Rgb8));
    assert_eq!(frame.depth.validate(), Ok(PixelEncoding::Depth32FC1));
    let (x0, y0, yaw0) = planar(&pose0);
    // The chassis settles on its springs: base_link shifts by millimetres.
    assert!(
        (x0 + 1.0).abs() < 0.01 && (y0 - 0.5).abs() < 0.01 && yaw0.abs() < 0.02,
        "{x0} {y0} {yaw0}"
    );

    client.command(7, 0.10, 0.0, 0.6).await; // FORWARD
    let (frame, pose, odom) = client.answer(7).await.expect("answer to seq 7");
    assert_eq!(frame.seq, 7);
    let (x, y, _) = planar(&pose);
    let moved = ((x - x0).powi(2) + (y - y0).powi(2)).sqrt();
    assert!((moved - 0.06).abs() < 0.01, "moved {moved}");
    assert_eq!(pose.header.frame_id, "world");
    assert_eq!(odom.child_frame_id, "base_link");
    assert!(
        odom.pose.pose.position.x > 0.05,
        "wheel odometry counted the motion"
    );

    client.command(8, 0.07, 1.25, 1.2).await; // LEFT
    let (_, pose, _) = client.answer(8).await.expect("answer to seq 8");
    let turned = pose.pose.orientation.yaw() - yaw0;
    assert!((turned - 1.5).abs() < 0.1, "turned {turned}");
    // Both answers were counted before they were published, with the time
    // spent simulating and rendering them.
    let stats = node.stats();
    assert_eq!(stats.answered, connected.answered + 2);
    assert!(stats.compute > connected.compute);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_overhead_view_is_streamed_for_spectators() {
    let (_node, client, _server) = setup("monolith", Resolution::new(64, 48)).await;
    let key = client
        .env
        .overhead_key(offworld_sim_twin::node::OVERHEAD_CAMERA)
        .expect("key");
    let overhead = client
        .session
        .declare_subscriber(key)
        .await
        .expect("subscriber");
    client.connect().await;
    // The twin renders the view only once it knows of a spectator (Zenoh's
    // matching status, a moment after subscribing): step until one comes.
    let mut sample = None;
    for seq in 9..59 {
        client.command(seq, 0.10, 0.0, 0.1).await;
        client.answer(seq).await.expect("answer");
        if let Ok(Ok(s)) =
            tokio::time::timeout(Duration::from_millis(100), overhead.recv_async()).await
        {
            sample = Some(s);
            break;
        }
    }
    let sample = sample.expect("an overhead frame within 50 steps");
    let image: Image = codec::decode_payload(sample.payload()).expect("image");
    assert_eq!(image.validate(), Ok(PixelEncoding::Rgb8));
    assert_eq!(image.width, 320);
    assert_eq!(image.header.frame_id, "overhead");
}

/// Nobody watching, the overhead view costs nothing: no frame is rendered
/// or encoded. A spectator's subscription starts it; its end stops it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_overhead_view_is_rendered_only_while_watched() {
    let (server, client) = loopback_pair().await.expect("loopback sessions");
    let key = EnvId::sim("overhead-test")
        .expect("env")
        .overhead_key("top")
        .expect("key");
    let copy = ViewerCopy::declare_on(&server, key.clone()).expect("viewers' stream");
    let twin = SimTwin::new(TwinConfig::builtin("monolith").expect("world")).expect("twin");
    // A high rate: the period never holds a frame back here.
    let mut stream = OverheadStream::new(twin.scene(), copy.watch(), 60.0);
    let robot = twin.ground_truth();
    let watched_becomes = |want: bool| {
        let watch = copy.watch();
        async move {
            for _ in 0..500 {
                if watch.watched() == want {
                    return;
                }
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
            panic!("watched never became {want}");
        }
    };

    assert!(!copy.watched());
    assert_eq!(stream.maybe_encode(twin.scene(), &robot), None, "unwatched");

    let spectator = client.declare_subscriber(&key).await.expect("subscriber");
    watched_becomes(true).await;
    let bytes = stream
        .maybe_encode(twin.scene(), &robot)
        .expect("a frame while watched");
    assert!(copy.put(bytes.clone().into(), None));
    let sample = tokio::time::timeout(Duration::from_secs(5), spectator.recv_async())
        .await
        .expect("the frame within 5 s")
        .expect("sample");
    assert_eq!(sample.payload().to_bytes().as_ref(), bytes.as_slice());
    let image: Image = codec::decode_payload(sample.payload()).expect("image");
    assert_eq!(
        (image.width, image.header.frame_id.as_str()),
        (320, "overhead")
    );

    spectator.undeclare().await.expect("undeclare");
    watched_becomes(false).await;
    tokio::time::sleep(Duration::from_millis(20)).await; // a period later
    assert_eq!(
        stream.maybe_encode(twin.scene(), &robot),
        None,
        "unwatched again"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn goto_teleports_and_bad_input_is_rejected_without_stopping_the_node() {
    let (node, client, _server) = setup("monolith_obstacle", Resolution::new(32, 24)).await;
    client.connect().await;
    let connected = node.stats();
    let goto_key = client.env.key(Topic::Goto);
    let request = GotoRequest {
        seq: 3,
        target: Pose2D {
            x: 0.5,
            y: -0.6,
            yaw: 2.0,
        },
        timeout_s: 5.0,
    };
    let reply: GotoReply =
        wire::request(&client.session, &goto_key, &request, Duration::from_secs(5))
            .await
            .expect("goto");
    assert_eq!(reply.seq, 3);
    assert!((reply.achieved.x - 0.5).abs() < 0.01 && (reply.achieved.y + 0.6).abs() < 0.01);
    assert!((reply.achieved.yaw - 2.0).abs() < 0.05);

    // Outside the enclosure: a typed error.
    let outside = GotoRequest {
        target: Pose2D {
            x: 5.0,
            y: 0.0,
            yaw: 0.0,
        },
        ..request
    };
    match wire::request::<_, GotoReply>(
        &client.session,
        &goto_key,
        &outside,
        Duration::from_secs(5),
    )
    .await
    {
        Err(RequestError::Remote(e)) => assert_eq!(e.code, ErrorCode::BadRequest),
        other => panic!("expected BadRequest, got {other:?}"),
    }
    // Garbage goto payload: a typed error.
    match wire::request_raw::<GotoReply>(
        &client.session,
        &goto_key,
        vec![1, 2, 3],
        Duration::from_secs(5),
    )
    .await
    {
        Err(RequestError::Remote(e)) => assert_eq!(e.code, ErrorCode::BadRequest),
        other => panic!("expected BadRequest, got {other:?}"),
    }
    // Garbage and impossible commands are dropped; the node keeps serving.
    client
        .session
        .put(client.env.key(Topic::Cmd), vec![0u8, 1, 0, 0, 42])
        .await
        .expect("put");
    client.command(9, f64::NAN, 0.0, 1.0).await;
    client.command(10, 0.1, 0.0, 1e9).await;
    client.command(11, 0.0, 0.0, 0.0).await;
    let (_, pose, _) = client.answer(11).await.expect("still serving");
    let (x, y, _) = planar(&pose);
    assert!(
        (x - 0.5).abs() < 0.01 && (y + 0.6).abs() < 0.01,
        "nothing moved the robot"
    );
    // Only seq 11 was answered: gotos and rejected commands are not counted.
    assert_eq!(node.stats().answered, connected.answered + 1);
}

/// Under an e-stop a command that would move is refused on `fault`
/// (naming the latch) and a reset `goto` is refused `InvalidState`, as the
/// robot agent does; an observation request is still answered; every
/// e-stop is acknowledged; site and env latches are independent.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn estop_refuses_motion_and_liveliness_is_declared() {
    let (_node, client, _server) = setup("monolith", Resolution::new(32, 24)).await;
    let (_, before, _) = client.connect().await;
    let alive = client
        .session
        .liveliness()
        .get(client.env.alive_key(Component::SimTwin))
        .await
        .expect("liveliness get");
    assert!(alive.recv_async().await.is_ok(), "sim twin token visible");
    let faults = client
        .session
        .declare_subscriber(client.env.key(Topic::Fault))
        .await
        .expect("fault subscriber");
    let acks = client
        .session
        .declare_subscriber(client.env.key(Topic::EStopAck))
        .await
        .expect("ack subscriber");
    // As an operator presses: a new press id (the clock) each time.
    let press = |key: String, engaged: bool, reason: &'static str| {
        let session = client.session.clone();
        let acks = &acks;
        let press_id = offworld_runtime::estop::new_press_id();
        async move {
            let stop = EStop {
                engaged,
                reason: reason.into(),
                press_id,
            };
            wire::put(&session, &key, &stop).await.expect("estop");
            loop {
                let sample = tokio::time::timeout(Duration::from_secs(5), acks.recv_async())
                    .await
                    .expect("acknowledged")
                    .expect("subscriber");
                let ack: EStopAck = codec::decode_payload(sample.payload()).expect("ack");
                if ack.press_id == press_id {
                    assert_eq!(
                        (ack.component.as_str(), ack.env.as_str()),
                        ("sim_twin", "sim/node-test")
                    );
                    return ack.state;
                }
            }
        }
    };
    let (env_key, site_key) = (client.env.key(Topic::EStop), global_estop_key());
    assert_eq!(
        press(site_key.clone(), true, "fire alarm").await.summary(),
        "site"
    );
    assert_eq!(
        press(env_key.clone(), true, "test").await.summary(),
        "site+env"
    );
    assert_eq!(
        press(env_key.clone(), false, "clear").await.summary(),
        "site"
    );

    client.command(20, 0.5, 0.0, 1.0).await;
    let sample = tokio::time::timeout(Duration::from_secs(5), faults.recv_async())
        .await
        .expect("refused on fault")
        .expect("subscriber");
    let fault: MotionFault = codec::decode_payload(sample.payload()).expect("fault");
    assert_eq!(
        fault,
        MotionFault {
            seq: 20,
            reason: "motion refused: e-stop engaged: site (fire alarm)".into()
        }
    );
    let request = GotoRequest {
        seq: 3,
        target: Pose2D {
            x: 0.5,
            y: 0.5,
            yaw: 0.0,
        },
        timeout_s: 5.0,
    };
    let refused: Result<GotoReply, _> = wire::request(
        &client.session,
        &client.env.key(Topic::Goto),
        &request,
        Duration::from_secs(5),
    )
    .await;
    match refused {
        Err(RequestError::Remote(e)) => assert_eq!(e.code, ErrorCode::InvalidState, "{e}"),
        other => panic!("goto under e-stop: {other:?}"),
    }
    // An observation request still answers, from where the robot stands.
    client.command(21, 0.0, 0.0, 0.0).await;
    let (_, pose, _) = client.answer(21).await.expect("observation answered");
    assert!(
        (planar(&pose).0 - planar(&before).0).abs() < 1e-3,
        "robot moved under e-stop"
    );

    assert_eq!(press(site_key, false, "all clear").await.summary(), "none");
    client.command(22, 0.5, 0.0, 1.0).await;
    let (_, pose, _) = client.answer(22).await.expect("answer");
    assert!(
        planar(&pose).0 - planar(&before).0 > 0.3,
        "robot moves after release"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn real_time_clock_streams_tracker_poses_and_answers_commands() {
    let (_node, client, _server) =
        setup_with_clock("monolith", Resolution::new(32, 24), Clock::RealTime).await;
    // Like a tracker, the real-time twin streams untagged poses unasked.
    let mut untagged = 0;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while untagged < 5 {
        let sample = tokio::time::timeout_at(deadline, client.pose.recv_async())
            .await
            .expect("poses keep coming")
            .expect("subscriber open");
        if wire::decode_attachment::<SeqTag>(&sample).is_none() {
            untagged += 1;
        }
    }
    let (_, before, _) = client.connect().await;
    client.command(30, 0.10, 0.0, 0.6).await;
    let (frame, pose, _) = client.answer(30).await.expect("answered after the motion");
    assert_eq!(frame.seq, 30);
    let moved = ((pose.pose.position.x - before.pose.position.x).powi(2)
        + (pose.pose.position.y - before.pose.position.y).powi(2))
    .sqrt();
    assert!((moved - 0.06).abs() < 0.01, "moved {moved}");
}

/// Whether `env`'s sim twin token is visible from `session`.
async fn twin_alive(session: &Session, env: &EnvId) -> bool {
    let replies = session
        .liveliness()
        .get(env.alive_key(Component::SimTwin))
        .timeout(Duration::from_millis(500))
        .await
        .expect("liveliness get");
    replies.recv_async().await.is_ok()
}

/// A simulation thread stuck on one event (here: a 2048×2048 frame through
/// the per-pixel renderer, seconds of work, against a 300 ms limit) is
/// reported, its twin withdrawn (the controller then shows the env
/// offline rather than timing out every step), and dropping the node does
/// not wait for it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stuck_simulation_thread_withdraws_its_twin() {
    let (server, client) = loopback_pair().await.expect("loopback sessions");
    let env = EnvId::sim("stuck-test").expect("env");
    let mut config = TwinConfig::builtin("monolith").expect("world");
    config.resolution = Some(Resolution::new(2048, 2048));
    config.profile.camera.pitch_deg = 2.0;
    let options = NodeOptions {
        stuck_after: Duration::from_millis(300),
        ..NodeOptions::default()
    };
    let node = TwinNode::spawn_with(
        &server,
        env.clone(),
        SimTwin::new(config).expect("twin"),
        options,
    )
    .expect("node");
    let client = Client::new(client, env.clone()).await;
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    while !twin_alive(&client.session, &env).await {
        assert!(tokio::time::Instant::now() < deadline, "never alive");
    }
    assert!(!node.stuck());
    client.command(1, 0.0, 0.0, 0.0).await;
    while !node.stuck() {
        assert!(tokio::time::Instant::now() < deadline, "never called stuck");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    while twin_alive(&client.session, &env).await {
        assert!(
            tokio::time::Instant::now() < deadline,
            "token never withdrawn"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let dropped = std::thread::spawn(move || drop(node));
    let deadline = std::time::Instant::now() + Duration::from_secs(5);
    while !dropped.is_finished() {
        assert!(
            std::time::Instant::now() < deadline,
            "drop waited for the stuck thread"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    drop(server);
}

/// Every way a lockstep twin can step.
const STEPPINGS: [Stepping; 2] = [Stepping::OwnThread, Stepping::OnArrival];

fn stepping(stepping: Stepping) -> NodeOptions {
    NodeOptions {
        stepping,
        ..NodeOptions::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_watched_twins_preview_ends_on_its_newest_frame() {
    for s in STEPPINGS {
        let res = Resolution::new(32, 24);
        let (_node, client, _server) = setup_with("monolith", res, stepping(s)).await;
        preview_ends_on_the_newest_frame(&client).await;
    }
}

async fn preview_ends_on_the_newest_frame(client: &Client) {
    client.connect().await;
    let preview = client
        .session
        .declare_subscriber(client.env.key(Topic::Preview))
        .await
        .expect("subscriber");
    let mut seq = 1;
    // Until the subscription has reached the twin (bounded).
    for _attempt in 0..50 {
        // A burst of steps far faster than the preview's period.
        let mut newest_answer = None;
        for _ in 0..5 {
            seq += 1;
            client.command(seq, 0.0, 0.5, 0.1).await;
            newest_answer = client.answer(seq).await.map(|(frame, _, _)| frame);
        }
        let newest_answer = newest_answer.expect("the twin answers");
        // The last preview after the burst is the burst's last frame: held
        // for being early, then put when its period ended.
        let mut newest_preview = None;
        while let Ok(Ok(sample)) =
            tokio::time::timeout(Duration::from_millis(300), preview.recv_async()).await
        {
            let frame: CameraFrame = codec::decode_payload(sample.payload()).expect("frame");
            newest_preview = Some(frame);
        }
        if let Some(frame) = newest_preview {
            assert_eq!(frame, newest_answer);
            return;
        }
    }
    panic!("no preview while watched");
}

/// Where a command is simulated: on the node's thread, or on the thread
/// that delivers it — there before the put that delivers it returns, unless
/// the node's thread holds the simulation then (a recall of the e-stop
/// latches, now and then), which then simulates it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_twin_stepping_on_arrival_answers_on_the_delivering_thread() {
    const COMMANDS: u64 = 20;
    for s in STEPPINGS {
        let res = Resolution::new(32, 24);
        let (_node, client, server) = setup_with("monolith", res, stepping(s)).await;
        client.connect().await;
        // The frame's thread, as its subscriber on the twin's own session
        // sees it (a local subscriber runs on the publisher's thread).
        let (tx, rx) = std::sync::mpsc::channel();
        let _frames = server
            .declare_subscriber(client.env.key(Topic::Obs))
            .callback(move |_| {
                let _ = tx.send(std::thread::current().name().map(str::to_owned));
            })
            .await
            .expect("subscriber");
        let (session, key) = (server.clone(), client.env.key(Topic::Cmd));
        let answers = std::thread::Builder::new()
            .name("delivers-commands".into())
            .spawn(move || {
                (0..COMMANDS)
                    .map(|seq| {
                        let cmd = MotionCommand {
                            seq,
                            linear_x: 0.2,
                            angular_z: 0.0,
                            duration_s: 0.05,
                        };
                        session
                            .put(key.clone(), codec::encode(&cmd).expect("encode"))
                            .wait()
                            .expect("put");
                        let before = rx.try_recv().ok();
                        let frame_thread = before
                            .clone()
                            .or_else(|| rx.recv_timeout(Duration::from_secs(5)).ok())
                            .expect("answered")
                            .expect("a named thread");
                        // Time for a node thread that took this one to let
                        // the simulation go: else it may take the next too.
                        std::thread::sleep(Duration::from_millis(5));
                        (before.is_some(), frame_thread)
                    })
                    .collect::<Vec<_>>()
            })
            .expect("thread")
            .join()
            .expect("joined");
        let node_thread = "sim_twin/sim/node-test";
        let here = answers
            .iter()
            .filter(|(_, t)| t == "delivers-commands")
            .count();
        match s {
            Stepping::OnArrival => {
                for (before_the_put_returned, thread) in &answers {
                    assert!(thread == "delivers-commands" || thread == node_thread);
                    if thread == "delivers-commands" {
                        assert!(before_the_put_returned);
                    }
                }
                assert!(here * 2 >= answers.len(), "{answers:?}");
            }
            Stepping::OwnThread => {
                assert!(answers.iter().all(|(_, t)| t == node_thread), "{answers:?}");
            }
        }
        client
            .answer(COMMANDS - 1)
            .await
            .expect("answered remotely too");
    }
}

/// An e-stop delivered just before a command is applied before it, however
/// the twin steps: the command is refused, never simulated.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_estop_delivered_before_a_command_is_applied_first() {
    for s in STEPPINGS {
        let res = Resolution::new(32, 24);
        let (_node, client, _server) = setup_with("monolith", res, stepping(s)).await;
        client.connect().await;
        let faults = client
            .session
            .declare_subscriber(client.env.key(Topic::Fault))
            .await
            .expect("fault subscriber");
        // Both on one link, in this order, without waiting in between.
        for round in 0..20u64 {
            let press_id = offworld_runtime::estop::new_press_id();
            let stop = |engaged| EStop {
                engaged,
                reason: "ordering".into(),
                press_id,
            };
            let key = client.env.key(Topic::EStop);
            wire::put(&client.session, &key, &stop(true))
                .await
                .expect("press");
            let seq = 100 + round;
            client.command(seq, 0.5, 0.0, 0.5).await;
            let sample = tokio::time::timeout(Duration::from_secs(5), faults.recv_async())
                .await
                .expect("refused on fault")
                .expect("subscriber");
            let fault: MotionFault = codec::decode_payload(sample.payload()).expect("fault");
            assert_eq!(fault.seq, seq, "{s:?}");
            let release = EStop {
                press_id: offworld_runtime::estop::new_press_id(),
                ..stop(false)
            };
            wire::put(&client.session, &key, &release)
                .await
                .expect("release");
        }
        // Released: the next command moves and is answered.
        client.command(1_000, 0.5, 0.0, 0.5).await;
        client
            .answer(1_000)
            .await
            .expect("answered after the release");
    }
}
