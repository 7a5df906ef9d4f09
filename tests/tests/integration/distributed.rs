//! Beyond one machine: a sim site behind the real `zenohd` router with the
//! repository's deployment files (QUIC with TLS 1.3, mutual TLS for site
//! components, user/password for every connection, access control). Every
//! component is a separate process on its own loopback address pair, and in
//! the last test the router and the site live in network namespaces of
//! their own; see `offworld_deploy::site`.
//!
//! Every "denied" claim has a positive control: the same observer sees the
//! allowed role do the same thing.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use offworld_client::operator::{press_estop, EStopScope, PressError};

use offworld_client::{ClientTimeouts, EnvClient};
use offworld_deploy::farm::SimFarm;
use offworld_deploy::process::Process;
use offworld_deploy::site::{generate_certificates, Link, Role, RouterSite};
use offworld_runtime::codec;
use offworld_runtime::keys::{global_estop_key, Component, EnvId, Topic};
use offworld_runtime::msg::*;
use offworld_runtime::wire;
use offworld_runtime::{ContractError, ErrorCode, WireError};
use offworld_tests::netns::Namespaces;
use zenoh::sample::Sample;
use zenoh::Session;

/// One site at a time: each runs a router and two component processes.
static ONE_SITE: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

const FORWARD: i64 = 2;

/// A router, a sim twin (agent role) and a controller (controller role).
struct SimSite {
    farm: SimFarm,
    env: EnvId,
}

impl SimSite {
    fn start(name: &str) -> anyhow::Result<Self> {
        Self::on(RouterSite::start(name)?, name)
    }

    /// The twin and controller behind an already started router.
    fn on(router: RouterSite, name: &str) -> anyhow::Result<Self> {
        let farm = SimFarm::start_on(router, name, 1, "MonolithDiscrete", Link::LocalSocket)?;
        let env = farm.envs[0].clone();
        Ok(Self { farm, env })
    }

    async fn session(&self, role: Role) -> Session {
        self.farm
            .site
            .session(role)
            .open()
            .await
            .unwrap_or_else(|e| panic!("{} session: {e}", role.name()))
    }
}

fn request(experiment: &str, resume: bool) -> OpenRequest {
    OpenRequest {
        experiment_name: experiment.to_owned(),
        resume_experiment: resume,
        ..OpenRequest::anonymous(ObsOptions {
            channels: Channels::DepthOnly,
            height: 84,
            width: 84,
            depth_format: DepthFormat::Uint8,
        })
    }
}

/// Opens the env once the controller and twin are up (bounded wait).
async fn open(session: &Session, env: &EnvId, experiment: &str, resume: bool) -> EnvClient {
    EnvClient::open_when_ready(
        session,
        env,
        request(experiment, resume),
        ClientTimeouts::default(),
        Duration::from_secs(30),
    )
    .await
    .unwrap_or_else(|e| panic!("the site did not come up within 30 s: {e}"))
}

/// One received sample: key, seq attachment if any, payload.
type Received = (String, Option<u64>, Vec<u8>);

/// Everything a subscriber saw.
#[derive(Clone, Default)]
struct Seen(Arc<Mutex<Vec<Received>>>);

impl Seen {
    async fn watch(session: &Session, key: &str) -> (Self, zenoh::pubsub::Subscriber<()>) {
        let seen = Seen::default();
        let log = seen.clone();
        let sub = session
            .declare_subscriber(key)
            .callback(move |sample: Sample| {
                let seq = wire::decode_attachment::<SeqTag>(&sample).map(|t| t.seq);
                if let Ok(mut v) = log.0.lock() {
                    v.push((
                        sample.key_expr().as_str().to_owned(),
                        seq,
                        sample.payload().to_bytes().to_vec(),
                    ));
                }
            })
            .await
            .expect("subscriber");
        (seen, sub)
    }

    fn count(&self, topic: &str, seq: Option<u64>) -> usize {
        self.0
            .lock()
            .map(|v| {
                v.iter()
                    .filter(|(k, s, _)| {
                        k.ends_with(&format!("/{topic}")) && (seq.is_none() || *s == seq)
                    })
                    .count()
            })
            .unwrap_or(0)
    }

    /// The pose answering command `seq`, waiting up to 3 s for it (the
    /// spy is a separate session: it may hear it after the step's reply).
    async fn wait_pose(&self, seq: u64) -> Option<PoseStamped> {
        for _ in 0..60 {
            if let Some(p) = self.pose(seq) {
                return Some(p);
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        None
    }

    /// The pose answering command `seq`.
    fn pose(&self, seq: u64) -> Option<PoseStamped> {
        let v = self.0.lock().ok()?;
        v.iter()
            .find(|(k, s, _)| k.ends_with("/pose") && *s == Some(seq))
            .and_then(|(_, _, p)| codec::decode::<PoseStamped>(p).ok())
    }

    fn cmds(&self) -> Vec<MotionCommand> {
        self.0
            .lock()
            .map(|v| {
                v.iter()
                    .filter(|(k, _, _)| k.ends_with("/cmd"))
                    .filter_map(|(_, _, p)| codec::decode::<MotionCommand>(p).ok())
                    .collect()
            })
            .unwrap_or_default()
    }
}

fn planar_distance(a: &PoseStamped, b: &PoseStamped) -> f64 {
    let (pa, pb) = (&a.pose.position, &b.pose.position);
    ((pa.x - pb.x).powi(2) + (pa.y - pb.y).powi(2)).sqrt()
}

/// Lets denied and allowed messages cross the router (or not).
/// `config` without credentials: no user and no password at all (a role
/// file names a user; dropping the overrides would leave it).
fn anonymous(mut config: offworld_runtime::SessionConfig) -> offworld_runtime::SessionConfig {
    config
        .overrides
        .retain(|o| !o.starts_with("transport/auth"));
    config
        .overrides
        .push("transport/auth/usrpwd/user:null".into());
    config
        .overrides
        .push("transport/auth/usrpwd/password:null".into());
    config
}

/// (role, key, allowed) rows over the network, then over the local socket,
/// each with its link.
fn over_links<const N: usize, const S: usize>(
    network: [(Role, String, bool); N],
    socket: [(Role, String, bool); S],
) -> Vec<(Role, Link, String, bool)> {
    let on = |link: Link| move |(role, key, allowed)| (role, link, key, allowed);
    network
        .into_iter()
        .map(on(Link::Network))
        .chain(socket.into_iter().map(on(Link::LocalSocket)))
        .collect()
}

async fn settle() {
    tokio::time::sleep(Duration::from_millis(700)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_episode_runs_through_the_router_over_tls_with_passwords() -> anyhow::Result<()> {
    // Over QUIC (TLS 1.3, the deployment's default); the TLS-over-TCP
    // fallback is checked at the end.
    let _one = ONE_SITE.lock().await;
    let site = SimSite::start("episode")?;
    let trainer = site.session(Role::Trainer).await;
    let mut gym = open(&trainer, &site.env, "through-router", false).await;
    // Discovery through the router: the env, its task, its components, leased.
    let listed = offworld_client::discover(&trainer, Duration::from_secs(3))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    assert_eq!(listed.len(), 1, "{listed:?}");
    assert_eq!(listed[0].env, site.env);
    assert_eq!(listed[0].task, "MonolithDiscrete");
    assert_eq!(listed[0].components, ["controller", "sim_twin"]);
    assert_eq!(listed[0].bookings, [], "nothing booked");
    assert!(
        matches!(listed[0].state, EnvState::Leased { .. }),
        "{listed:?}"
    );
    let reset = gym
        .reset(Seed::Fixed(7))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    assert_eq!(reset.info.step, 0);
    let o = &reset.observation;
    assert_eq!((o.height, o.width, o.channels), (84, 84, 1));
    let mut steps = 0u32;
    let mut last = None;
    for i in 0..100 {
        let r = gym
            .step(Action::Discrete([FORWARD, 0, FORWARD, 1][i % 4]))
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
        steps += 1;
        assert_eq!(r.info.step, steps);
        assert_eq!(r.observation.data.len(), 84 * 84);
        let done = r.terminated || r.truncated;
        last = Some(r);
        if done {
            break;
        }
    }
    let last = last.expect("stepped");
    assert!(
        last.terminated || last.truncated,
        "an episode ends by step 100"
    );
    let closed = gym.close().await.map_err(|e| anyhow::anyhow!(e))?;
    assert_eq!(closed.experiment.episodes, 1);
    assert_eq!(closed.experiment.steps, u64::from(steps));
    // The TLS-over-TCP fallback port reaches the same env.
    let mut over_tcp = site.farm.site.session(Role::Trainer);
    over_tcp.connect = vec![RouterSite::over_tcp(&site.farm.site.trainer_endpoint)];
    let fallback = over_tcp.open().await?;
    let mut gym = open(&fallback, &site.env, "over-tcp", false).await;
    let reset = gym
        .reset(Seed::Fixed(7))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    assert_eq!(
        reset.info.episode_id, 0,
        "a new experiment starts at episode 0"
    );
    gym.close().await.map_err(|e| anyhow::anyhow!(e))?;
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connections_without_valid_credentials_are_refused() -> anyhow::Result<()> {
    let _one = ONE_SITE.lock().await;
    let site = RouterSite::start("auth")?;
    let refused = |config: offworld_runtime::SessionConfig| async move {
        match config.open().await {
            Err(ContractError::Zenoh(_)) => Ok(()),
            Err(e) => Err(anyhow::anyhow!("refused with an unexpected error: {e}")),
            Ok(_) => Err(anyhow::anyhow!("the router accepted the connection")),
        }
    };
    // Positive control: the trainer's own credentials work.
    site.session(Role::Trainer).open().await?;
    // No user/password.
    refused(anonymous(site.session(Role::Trainer))).await?;
    // A wrong password.
    let mut wrong = site.session(Role::Trainer);
    wrong
        .overrides
        .push(r#"transport/auth/usrpwd/password:"guess""#.into());
    refused(wrong).await?;
    // Plain TCP to the TLS port.
    let mut plain = site.session(Role::Trainer);
    plain.connect = vec![site.trainer_endpoint.replace("quic/", "tcp/")];
    refused(plain).await?;
    // The site port needs a client certificate: a trainer's password is not
    // enough, over QUIC or over TCP.
    for endpoint in [
        site.site_endpoint.clone(),
        RouterSite::over_tcp(&site.site_endpoint),
    ] {
        let mut no_cert = site.session(Role::Trainer);
        no_cert.connect = vec![endpoint];
        refused(no_cert).await?;
    }
    // No credentials over the TCP fallback either.
    let mut anonymous_tcp = anonymous(site.session(Role::Trainer));
    anonymous_tcp.connect = vec![RouterSite::over_tcp(&site.trainer_endpoint)];
    refused(anonymous_tcp).await?;
    // The local socket asks for a password too (positive control: the sim
    // twin's own).
    site.session_over(Role::SimTwin, Link::LocalSocket)
        .open()
        .await?;
    refused(anonymous(
        site.session_over(Role::SimTwin, Link::LocalSocket),
    ))
    .await?;
    let mut wrong_local = site.session_over(Role::SimTwin, Link::LocalSocket);
    wrong_local
        .overrides
        .push(r#"transport/auth/usrpwd/password:"guess""#.into());
    refused(wrong_local).await?;
    // A certificate signed by another CA.
    let other_ca = site.dir.join("other-ca");
    generate_certificates(&other_ca, None)?;
    let mut forged = site.session(Role::SimTwin);
    forged.overrides.push(format!(
        "transport/link/tls/connect_certificate:{:?}",
        other_ca.join("sim_twin.pem")
    ));
    forged.overrides.push(format!(
        "transport/link/tls/connect_private_key:{:?}",
        other_ca.join("sim_twin.key")
    ));
    refused(forged).await?;
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn access_control_denies_each_role_what_it_may_not_do() -> anyhow::Result<()> {
    let _one = ONE_SITE.lock().await;
    let site = SimSite::start("acl")?;
    let env = site.env.clone();
    let operator = site.session(Role::Operator).await;
    let (spy, _spy_sub) = Seen::watch(&operator, &format!("{}/**", env.prefix())).await;
    let (spy_global, _spy_global_sub) = Seen::watch(&operator, &global_estop_key()).await;
    let trainer = site.session(Role::Trainer).await;
    let mut gym = open(&trainer, &env, "acl", false).await;
    gym.reset(Seed::Fixed(3))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;

    // A trainer cannot read localisation or sensor data.
    let mallory = site.session(Role::Trainer).await;
    let (stolen, _stolen_sub) = Seen::watch(&mallory, &env.key(Topic::Pose)).await;
    let (stolen_obs, _stolen_obs_sub) = Seen::watch(&mallory, &env.key(Topic::Obs)).await;
    let (stolen_preview, _stolen_preview_sub) =
        Seen::watch(&mallory, &env.key(Topic::Preview)).await;
    let (stolen_copies, _stolen_copies_sub) =
        Seen::watch(&mallory, &format!("{}/preview_$*", env.prefix())).await;
    // …but may watch episode events.
    let (events, _events_sub) = Seen::watch(&mallory, &env.key(Topic::Reward)).await;
    settle().await;
    for _ in 0..3 {
        step(&mut gym, &spy).await;
    }
    settle().await;
    assert!(spy.count("pose", None) >= 3, "control: poses flow");
    assert_eq!(stolen.count("pose", None), 0, "a trainer read poses");
    assert_eq!(stolen_obs.count("obs", None), 0, "a trainer read frames");
    // The operator watching the env is what has the twin send its preview.
    assert!(spy.count("preview", None) >= 1, "control: previews flow");
    assert_eq!(
        stolen_preview.count("preview", None),
        0,
        "a trainer read the camera's preview"
    );
    // …nor the viewers' copies of commands, poses and odometry, which the
    // operator (watching every key) has the controller and twin send.
    for copy in ["preview_cmd", "preview_pose", "preview_odom"] {
        assert!(spy.count(copy, None) >= 3, "control: {copy} flows");
        assert_eq!(stolen_copies.count(copy, None), 0, "a trainer read {copy}");
    }
    assert!(
        events.count("reward", None) >= 3,
        "spectator keys are readable"
    );

    // Only the controller commands the robot: a trainer's and an agent's
    // commands never arrive, and the twin never moves for them.
    let cmds_before = spy.cmds().len();
    assert!(
        cmds_before >= 4,
        "control: the controller's commands arrive"
    );
    let rogue = MotionCommand {
        seq: 900_001,
        linear_x: 0.3,
        angular_z: 0.0,
        duration_s: 1.0,
    };
    wire::put(&mallory, &env.key(Topic::Cmd), &rogue).await?;
    let agent = site.session(Role::SimTwin).await;
    let agent_cmd = MotionCommand {
        seq: 900_002,
        ..rogue
    };
    wire::put(&agent, &env.key(Topic::Cmd), &agent_cmd).await?;
    settle().await;
    let seqs: Vec<u64> = spy.cmds().iter().map(|c| c.seq).collect();
    assert!(
        !seqs.contains(&900_001) && !seqs.contains(&900_002),
        "{seqs:?}"
    );
    for seq in [900_001, 900_002] {
        assert_eq!(spy.count("pose", Some(seq)), 0, "the twin answered {seq}");
        assert_eq!(spy.count("obs", Some(seq)), 0, "the twin answered {seq}");
    }

    // Only agents publish sensor data: a trainer's and the controller's
    // fake poses never arrive.
    let fake = PoseStamped {
        header: Header::new(Time::default(), "forged"),
        pose: Pose::default(),
    };
    wire::put(&mallory, &env.key(Topic::Pose), &fake).await?;
    let controller_session = site.session(Role::Controller).await;
    wire::put(&controller_session, &env.key(Topic::Pose), &fake).await?;
    settle().await;
    let forged = spy
        .0
        .lock()
        .map(|v| {
            v.iter()
                .filter(|(k, _, p)| {
                    k.ends_with("/pose")
                        && codec::decode::<PoseStamped>(p)
                            .map(|p| p.header.frame_id == "forged")
                            .unwrap_or(false)
                })
                .count()
        })
        .unwrap_or(0);
    assert_eq!(forged, 0, "a forged pose arrived");

    // E-stops are for operators: a trainer's and the controller's e-stops
    // do not stop the robot…
    let engage = EStop::new(true, "test");
    wire::put(&mallory, &env.key(Topic::EStop), &engage).await?;
    wire::put(&mallory, &global_estop_key(), &engage).await?;
    // Pressed like the CLI presses, with a credential the router's ACL
    // denies e-stops: nobody acknowledges, and the press says so.
    match press_estop(
        &controller_session,
        &EStopScope::Env(env.clone()),
        true,
        "not an operator",
        Duration::from_secs(10),
        Duration::from_secs(2),
    )
    .await
    {
        Err(PressError::Unacknowledged { report, .. }) => {
            assert_eq!(report.silent, [(env.to_string(), "sim_twin".to_owned())]);
        }
        other => panic!("an ACL-dropped press must fail, got {other:?}"),
    }
    settle().await;
    assert_eq!(spy.count("estop", None), 0);
    assert_eq!(spy_global.count("estop", None), 0);
    let moved_seq = step(&mut gym, &spy).await;
    let before = spy.wait_pose(moved_seq - 1).await.expect("pose before");
    let after = spy.wait_pose(moved_seq).await.expect("pose after");
    assert!(
        planar_distance(&before, &after) > 0.03,
        "the robot moved: {before:?} -> {after:?}"
    );
    // …an operator's does (pressed as `env_controller estop` presses it:
    // once the robot's subscription is seen through the router).
    // The twin's acknowledgement comes back through the router.
    let report = press_estop(
        &operator,
        &EStopScope::Env(env.clone()),
        true,
        "test",
        Duration::from_secs(10),
        Duration::from_secs(5),
    )
    .await?;
    assert_eq!(report.acknowledged.len(), 1, "{report:?}");
    assert_eq!(report.acknowledged[0].component, "sim_twin");
    assert_eq!(report.acknowledged[0].state.summary(), "env");
    settle().await;
    // Once, or again while the acknowledgement was on its way (a press
    // repeats itself while someone is silent).
    assert!(spy.count("estop", None) >= 1);
    // The controller refuses motion under the e-stop (as for a real env),
    // and no command reaches the robot.
    let commands = spy.cmds().len();
    let refused = gym
        .step(Action::Discrete(FORWARD))
        .await
        .expect_err("no step under an e-stop");
    assert_eq!(refused.code, ErrorCode::InvalidState, "{refused}");
    assert!(
        refused.message.contains("e-stop engaged: env (test)"),
        "{refused}"
    );
    settle().await;
    assert_eq!(spy.cmds().len(), commands, "no command was sent");
    gym.close().await.map_err(|e| anyhow::anyhow!(e))?;
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_lab_web_role_reads_the_site_and_presses_estops_but_never_drives() -> anyhow::Result<()>
{
    let _one = ONE_SITE.lock().await;
    let site = SimSite::start("web")?;
    let env = site.env.clone();
    let trainer = site.session(Role::Trainer).await;
    let mut gym = open(&trainer, &env, "watched", false).await;
    let web = site.session(Role::LabWeb).await;
    let (status, _status_sub) = Seen::watch(&web, &env.key(Topic::Status)).await;
    let (stolen, _stolen_sub) = Seen::watch(&web, &format!("{}/pose", env.prefix())).await;
    let (frames, _frames_sub) = Seen::watch(&web, &env.key(Topic::Preview)).await;
    let (every_frame, _every_frame_sub) = Seen::watch(&web, &env.key(Topic::Obs)).await;
    settle().await;

    // What its pages read: the listing with the lease's holder, a
    // leaderboard, the bookings, and `admin` (a user's token, checked by
    // the controller: a stranger's is refused there, not at the router).
    let listed = offworld_client::discover(&web, Duration::from_secs(5))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    let listing = listed
        .iter()
        .find(|l| l.env == env)
        .unwrap_or_else(|| panic!("{env} listed: {listed:?}"));
    assert_eq!(listing.task, "MonolithDiscrete");
    assert!(
        matches!(&listing.state, EnvState::Leased { holder, .. } if holder == "anonymous"),
        "{listing:?}"
    );
    let timeout = Duration::from_secs(5);
    offworld_client::leaderboard(&web, &env, timeout)
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    offworld_client::book(
        &web,
        &env,
        &BookingRequest::List { from_unix_ms: 0 },
        timeout,
    )
    .await
    .map_err(|e| anyhow::anyhow!(e))?;
    let stranger = AdminRequest::Identify {
        token: "not-a-user".into(),
    };
    let refused = offworld_client::admin(&web, &env, &stranger, timeout)
        .await
        .expect_err("a stranger's token");
    assert_eq!(refused.code, ErrorCode::Unauthorized, "{refused}");

    // Its console presses an e-stop: the twin acknowledges through the
    // router, and the controller's status (which the page shows) says so.
    let report = press_as(&web, &env, true, "from the web console").await?;
    assert_eq!(report.acknowledged.len(), 1, "{report:?}");
    assert_eq!(report.acknowledged[0].component, "sim_twin");
    let refused = gym
        .step(Action::Discrete(FORWARD))
        .await
        .expect_err("no step under an e-stop");
    assert_eq!(refused.code, ErrorCode::InvalidState, "{refused}");
    press_as(&web, &env, false, "clear").await?;
    gym.reset(Seed::Fixed(4))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    gym.step(Action::Discrete(FORWARD))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    settle().await;
    assert!(status.count("status", None) >= 2, "status reaches the page");
    assert!(
        frames.count("preview", None) >= 1,
        "the camera's preview reaches its thumbnails"
    );
    assert_eq!(
        every_frame.count("obs", None),
        0,
        "the web page received every frame"
    );
    // It never reads localisation…
    assert_eq!(stolen.count("pose", None), 0, "the web page read poses");
    // …never publishes what it only hears (an operator watches: a forged
    // acknowledgement or fault never arrives)…
    let operator = site.session(Role::Operator).await;
    let (forged, _forged_sub) = Seen::watch(&operator, &format!("{}/**", env.prefix())).await;
    settle().await;
    let ack = EStopAck {
        press_id: 7,
        component: "robot_agent".into(),
        env: env.to_string(),
        state: EStopState::default(),
    };
    wire::put(&web, &env.key(Topic::EStopAck), &ack).await?;
    let fault = MotionFault {
        seq: 1,
        reason: "forged".into(),
    };
    wire::put(&web, &env.key(Topic::Fault), &fault).await?;
    let frame = CameraFrame {
        seq: 1,
        color: Image::default(),
        depth: Image::default(),
    };
    wire::put(&web, &env.key(Topic::Preview), &frame).await?;
    settle().await;
    assert_eq!(
        forged.count("estop_ack", None),
        0,
        "a forged acknowledgement arrived"
    );
    assert_eq!(forged.count("fault", None), 0, "a forged fault arrived");
    assert_eq!(forged.count("preview", None), 0, "a forged preview arrived");
    // Control: the twin's own acknowledgement reaches the same observer
    // (one per press it hears: a press late to be acknowledged on a loaded
    // host is repeated, and a full run under two spin loops saw two).
    press_as(&web, &env, false, "control").await?;
    settle().await;
    assert!(
        forged.count("estop_ack", None) >= 1,
        "the twin's acknowledgement did not arrive"
    );
    // …and never drives: the router drops its `open` (the trainer's
    // opened the same env above).
    gym.close().await.map_err(|e| anyhow::anyhow!(e))?;
    let driving = EnvClient::open(
        &web,
        &env,
        request("from-the-web", false),
        ClientTimeouts {
            control: Duration::from_secs(3),
            ..ClientTimeouts::default()
        },
    )
    .await;
    let refused = driving.err().expect("the web page opened a gym session");
    // To this identity the gym's driving queries do not exist.
    assert_eq!(refused.code, ErrorCode::NotFound, "{refused}");
    Ok(())
}

/// Presses (`engaged`) or releases `env`'s e-stop through `session` as the
/// CLI does; an error names the press by its `reason`.
async fn press_as(
    session: &Session,
    env: &EnvId,
    engaged: bool,
    reason: &str,
) -> anyhow::Result<offworld_client::operator::PressReport> {
    press_estop(
        session,
        &EStopScope::Env(env.clone()),
        engaged,
        reason,
        Duration::from_secs(10),
        // Generous: the press repeats itself while the twin is silent, and
        // this suite runs routers and twins of parallel tests on 2 cores
        // (CI saw a release unacknowledged after 5 s).
        Duration::from_secs(15),
    )
    .await
    .map_err(|e| anyhow::anyhow!("press {reason}: {e}"))
}

/// Steps FORWARD and returns the command's seq as the spy saw it; on
/// failure, says what the spy saw of that command.
async fn step(gym: &mut EnvClient, spy: &Seen) -> u64 {
    let before = spy.cmds().len();
    if let Err(e) = gym.step(Action::Discrete(FORWARD)).await {
        let seq = last_cmd_seq(spy);
        let seqs: Vec<u64> = spy.cmds().iter().map(|c| c.seq).collect();
        panic!(
            "step failed: {e}; commands seen {seqs:?}; answers to {seq}: pose {} obs {} odom {}",
            spy.count("pose", Some(seq)),
            spy.count("obs", Some(seq)),
            spy.count("odom", Some(seq))
        );
    }
    for _ in 0..60 {
        if spy.cmds().len() > before {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    last_cmd_seq(spy)
}

/// Resets with `seed`, then steps (forward, left, right, …) until the
/// episode ends, checking the step counter; returns the episode's length.
async fn play_episode(gym: &mut EnvClient, seed: u64) -> anyhow::Result<u64> {
    gym.reset(Seed::Fixed(seed))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    let mut steps = 0u64;
    loop {
        let r = gym
            .step(Action::Discrete([FORWARD, 0, 1][steps as usize % 3]))
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
        steps += 1;
        assert_eq!(u64::from(r.info.step), steps);
        if r.terminated || r.truncated {
            return Ok(steps);
        }
    }
}

/// The seq of the newest command the spy saw.
fn last_cmd_seq(spy: &Seen) -> u64 {
    spy.cmds().last().map(|c| c.seq).expect("a command")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_router_restart_mid_training_is_a_typed_error_then_training_resumes() -> anyhow::Result<()>
{
    let _one = ONE_SITE.lock().await;
    let mut site = SimSite::start("restart")?;
    let trainer = site.session(Role::Trainer).await;
    let mut gym = open(&trainer, &site.env, "survives-restart", false).await;
    // One whole episode, then two steps into the next.
    let first = play_episode(&mut gym, 11).await?;
    gym.reset(Seed::Fixed(12))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    for _ in 0..2 {
        gym.step(Action::Discrete(FORWARD))
            .await
            .map_err(|e| anyhow::anyhow!(e))?;
    }

    // The router dies: the next step fails with a typed, transient error
    // (never `NotFound`: the env was there a moment ago), no hang.
    site.farm.site.stop_router();
    let lost = gym
        .step(Action::Discrete(FORWARD))
        .await
        .expect_err("no router");
    assert!(
        matches!(lost.code, ErrorCode::Timeout | ErrorCode::Unavailable),
        "{lost}"
    );

    // It comes back on the same endpoints; every client reconnects by
    // itself. The trainer's session is back within the grace period, so its
    // lease is restored: it goes on with reset() without opening again
    // (until its liveliness token is back, the lease is "disconnected").
    site.farm.site.start_router()?;
    let deadline = std::time::Instant::now() + Duration::from_secs(30);
    loop {
        match gym.reset(Seed::Fixed(13)).await {
            Ok(_) => break,
            Err(e) if std::time::Instant::now() < deadline => {
                assert!(
                    matches!(
                        e.code,
                        ErrorCode::Timeout | ErrorCode::Unavailable | ErrorCode::Unauthorized
                    ),
                    "{e}"
                );
                tokio::time::sleep(Duration::from_millis(200)).await;
            }
            Err(e) => anyhow::bail!("the lease was not restored within 30 s: {e}"),
        }
    }
    let r = gym
        .step(Action::Discrete(FORWARD))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    assert_eq!(r.info.step, 1);
    assert_eq!(r.info.episode_id, 2, "episode numbering continues");
    // Nothing recorded is lost: the finished episode, the interrupted one
    // (recorded as aborted) with all their steps, and the new one.
    let closed = gym.close().await.map_err(|e| anyhow::anyhow!(e))?;
    assert_eq!(closed.experiment.episodes, 3, "{:?}", closed.experiment);
    assert_eq!(
        closed.experiment.steps,
        first + 3,
        "{:?}",
        closed.experiment
    );
    // A new session resumes the experiment where it stopped.
    let resumed = open(&trainer, &site.env, "survives-restart", true).await;
    let info = &resumed.opened().experiment;
    assert_eq!((info.episodes, info.steps), (3, first + 3), "{info:?}");
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn in_network_namespaces_trainers_reach_the_site_only_through_the_router(
) -> anyhow::Result<()> {
    let _one = ONE_SITE.lock().await;
    let ns = match Namespaces::create() {
        Ok(ns) => ns,
        Err(e) => {
            // The same rules are proven on loopback addresses above.
            eprintln!("SKIPPED: network namespaces are unavailable here: {e}");
            return Ok(());
        }
    };
    // Declared after `ns`: the site stops before its namespaces go.
    let site = RouterSite::start_namespaced("netns", ns.placement())?;
    // The site has no route to the host: only the router's session links
    // them (the router's namespace has a route to both).
    assert!(!Namespaces::routes(&ns.site, &ns.host_ip));
    assert!(Namespaces::routes(&ns.site, &ns.router_site_ip));
    assert!(Namespaces::routes(&ns.router, &ns.host_ip));
    // The farm on the site's network (its own namespace), not the socket.
    let farm = SimFarm::start_on(site, "netns", 1, "MonolithDiscrete", Link::Network)?;
    let env = farm.envs[0].clone();
    let session = |role: Role| {
        let config = farm.site.session(role);
        async move { config.open().await }
    };

    // A client without credentials is refused.
    assert!(matches!(
        anonymous(farm.site.session(Role::Trainer)).open().await,
        Err(ContractError::Zenoh(_))
    ));

    // A full episode through the router.
    let trainer = session(Role::Trainer).await?;
    let mut gym = open(&trainer, &env, "netns", false).await;
    play_episode(&mut gym, 5).await?;

    // A trainer's `cmd` never reaches the robot: an operator (on the host,
    // mutual TLS) sees neither the command nor an answer to it, while it
    // does see the controller's commands and their answers.
    let operator = session(Role::Operator).await?;
    let (spy, _spy_sub) = Seen::watch(&operator, &format!("{}/**", env.prefix())).await;
    settle().await;
    gym.reset(Seed::Fixed(6))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    let allowed = step(&mut gym, &spy).await;
    assert!(
        spy.wait_pose(allowed).await.is_some(),
        "control: the controller's command is answered"
    );
    let forged = MotionCommand {
        seq: 9_000_000,
        linear_x: 0.2,
        angular_z: 0.0,
        duration_s: 1.0,
    };
    for _ in 0..5 {
        wire::put(&trainer, &env.key(Topic::Cmd), &forged).await?;
    }
    settle().await;
    assert!(
        spy.cmds().iter().all(|c| c.seq != forged.seq),
        "a trainer's command crossed the router"
    );
    assert_eq!(
        spy.count("pose", Some(forged.seq)),
        0,
        "the robot answered a trainer"
    );
    assert_eq!(spy.count("obs", Some(forged.seq)), 0);
    gym.close().await.map_err(|e| anyhow::anyhow!(e))?;
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn agents_never_command_even_past_an_open_router() -> anyhow::Result<()> {
    let _one = ONE_SITE.lock().await;
    let mut site = RouterSite::start("agent-acl")?;
    // The router's ACL switched off: only the agents' own (role file) is left.
    site.restart_router_with(&["access_control/enabled:false"])?;
    let env = EnvId::sim("agent-acl")?;
    let operator = site.session(Role::Operator).open().await?;
    let (spy, _spy_sub) = Seen::watch(&operator, "offworld/@v1/**").await;
    let motion = MotionCommand {
        seq: 5,
        linear_x: 0.2,
        angular_z: 0.0,
        duration_s: 1.0,
    };
    let engage = EStop::new(true, "test");
    let pose = PoseStamped {
        header: Header::new(Time::default(), "world"),
        pose: Pose::default(),
    };
    let trainer = site.session(Role::Trainer).open().await?;
    for role in [Role::SimTwin, Role::TrackerAgent] {
        let agent = site.session(role).open().await?;
        settle().await;
        let before = (spy.count("pose", None), spy.count("cmd", None));
        // Control: its sensor keys go out.
        wire::put(&agent, &env.key(Topic::Pose), &pose).await?;
        // Denied at the source: commands and e-stops.
        wire::put(&agent, &env.key(Topic::Cmd), &motion).await?;
        wire::put(&agent, &env.key(Topic::EStop), &engage).await?;
        wire::put(&agent, &global_estop_key(), &engage).await?;
        settle().await;
        let name = role.name();
        assert_eq!(spy.count("pose", None), before.0 + 1, "{name}'s pose");
        assert_eq!(spy.count("cmd", None), before.1, "{name} sent a command");
        assert_eq!(spy.count("estop", None), 0, "{name} pressed an e-stop");
        agent.close().await.map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    // Control: this open router does pass a trainer's command and e-stop.
    wire::put(&trainer, &env.key(Topic::Cmd), &motion).await?;
    wire::put(&trainer, &env.key(Topic::EStop), &engage).await?;
    settle().await;
    assert_eq!(spy.count("cmd", None), 1, "the open router passes commands");
    assert_eq!(
        spy.count("estop", None),
        1,
        "the open router passes e-stops"
    );
    Ok(())
}

/// Realms: no credential reaches beyond its own. Each role tries what the
/// router's ACL must drop — a sim credential commanding or posing as the
/// real robot, an agent publishing another's data or commands, a controller
/// declaring an agent's presence — beside what the same role may do (the
/// positive controls); an operator watching everything sees exactly the
/// allowed ones.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_credential_crosses_its_realm() -> anyhow::Result<()> {
    let _one = ONE_SITE.lock().await;
    let mut site = RouterSite::start("realms")?;
    site.audit_router()?;
    let site = site;
    let open = |role: Role, link: Link| {
        let config = site.session_over(role, link);
        async move {
            config
                .open()
                .await
                .unwrap_or_else(|e| panic!("{} session over {link:?}: {e}", role.name()))
        }
    };
    let operator = open(Role::Operator, Link::Network).await;
    let (spy, _spy_sub) = Seen::watch(&operator, "offworld/@v1/**").await;
    let (real, sim) = (EnvId::real("enclosure")?, EnvId::sim("farm-0")?);
    // A sim farm on the router's host, on its local socket.
    let local = EnvId::sim("farm-1")?;
    // (role, key, allowed): a put of the action's name on the key.
    let network_puts = [
        (Role::Controller, real.key(Topic::Cmd), true),
        (Role::Controller, real.key(Topic::Pose), false),
        (Role::SimController, sim.key(Topic::Cmd), true),
        (Role::SimController, real.key(Topic::Cmd), false),
        (Role::SimController, real.key(Topic::Heartbeat), false),
        (Role::SimTwin, sim.key(Topic::Pose), true),
        (Role::SimTwin, real.key(Topic::Pose), false),
        (Role::SimTwin, real.key(Topic::Obs), false),
        (Role::SimTwin, sim.key(Topic::Preview), true),
        (Role::SimTwin, real.key(Topic::Preview), false),
        (Role::SimTwin, sim.key(Topic::Cmd), false),
        (Role::RobotAgent, real.key(Topic::Obs), true),
        (Role::RobotAgent, real.key(Topic::Pose), false),
        (Role::RobotAgent, real.key(Topic::Cmd), false),
        (Role::RobotAgent, sim.key(Topic::Obs), false),
        (Role::RobotAgent, real.key(Topic::Preview), true),
        (Role::RobotAgent, sim.key(Topic::Preview), false),
        (Role::Controller, real.key(Topic::Preview), false),
        (Role::SimController, sim.key(Topic::Preview), false),
        (Role::TrackerAgent, real.key(Topic::Preview), false),
        (Role::TrackerAgent, real.key(Topic::Pose), true),
        // The viewers' copies: each from whoever publishes the original.
        (Role::Controller, real.key(Topic::PreviewCmd), true),
        (Role::SimController, sim.key(Topic::PreviewCmd), true),
        (Role::SimController, real.key(Topic::PreviewCmd), false),
        (Role::Controller, real.key(Topic::PreviewPose), false),
        (Role::SimTwin, sim.key(Topic::PreviewPose), true),
        (Role::SimTwin, sim.key(Topic::PreviewOdom), true),
        (Role::SimTwin, real.key(Topic::PreviewPose), false),
        (Role::SimTwin, sim.key(Topic::PreviewCmd), false),
        (Role::RobotAgent, real.key(Topic::PreviewOdom), true),
        (Role::RobotAgent, real.key(Topic::PreviewPose), false),
        (Role::TrackerAgent, real.key(Topic::PreviewPose), true),
        (Role::TrackerAgent, real.key(Topic::PreviewCmd), false),
        (Role::Trainer, real.key(Topic::PreviewPose), false),
        (Role::Controller, real.key(Topic::PreviewOdom), false),
        (Role::SimController, sim.key(Topic::PreviewPose), false),
        (Role::RobotAgent, real.key(Topic::PreviewCmd), false),
        (Role::TrackerAgent, real.key(Topic::PreviewOdom), false),
        (Role::TrackerAgent, real.key(Topic::Cmd), false),
        (Role::TrackerAgent, real.key(Topic::Obs), false),
        (Role::TrackerAgent, sim.key(Topic::Pose), false),
        (Role::Trainer, real.key(Topic::Cmd), false),
    ];
    // Over the local socket the sim roles keep their rights (in `sim/`
    // only); the real site's roles, without their certificate there, have
    // none.
    let socket_puts = [
        (Role::SimTwin, local.key(Topic::Pose), true),
        (Role::SimTwin, local.key(Topic::Obs), true),
        (Role::SimTwin, real.key(Topic::Pose), false),
        (Role::SimTwin, local.key(Topic::Cmd), false),
        (Role::SimController, local.key(Topic::Cmd), true),
        (Role::SimController, real.key(Topic::Cmd), false),
        (Role::SimController, real.key(Topic::Heartbeat), false),
        (Role::Controller, real.key(Topic::Cmd), false),
        (Role::Controller, real.key(Topic::Heartbeat), false),
        (Role::RobotAgent, real.key(Topic::Obs), false),
        (Role::TrackerAgent, real.key(Topic::Pose), false),
        (Role::Operator, global_estop_key(), false),
        (Role::Trainer, local.key(Topic::Cmd), false),
    ];
    let puts = over_links(network_puts, socket_puts);
    // (role, token key, allowed).
    let network_tokens = [
        (
            Role::RobotAgent,
            real.alive_key(Component::RobotAgent),
            true,
        ),
        (Role::SimTwin, sim.alive_key(Component::SimTwin), true),
        (Role::SimTwin, real.alive_key(Component::RobotAgent), false),
        (
            Role::SimController,
            real.alive_key(Component::RobotAgent),
            false,
        ),
        (
            Role::Controller,
            real.alive_key(Component::TrackerAgent),
            false,
        ),
        (
            Role::TrackerAgent,
            real.alive_key(Component::RobotAgent),
            false,
        ),
        (Role::Operator, real.alive_key(Component::Monitor), true),
        (Role::Operator, real.alive_key(Component::RobotAgent), false),
        (Role::Trainer, sim.alive_key(Component::Monitor), false),
    ];
    let socket_tokens = [
        (Role::SimTwin, local.alive_key(Component::SimTwin), true),
        (
            Role::SimController,
            local.alive_key(Component::Controller),
            true,
        ),
        (Role::SimTwin, real.alive_key(Component::RobotAgent), false),
        (
            Role::Controller,
            real.alive_key(Component::Controller),
            false,
        ),
        (
            Role::RobotAgent,
            real.alive_key(Component::RobotAgent),
            false,
        ),
    ];
    let tokens = over_links(network_tokens, socket_tokens);
    let mut sessions = Vec::new();
    let mut put_by = Vec::new();
    let mut held = Vec::new();
    for (role, link, key, _) in &tokens {
        let session = open(*role, *link).await;
        held.push(session.liveliness().declare_token(key.as_str()).await);
        sessions.push(session);
    }
    settle().await;
    for (role, link, key, _) in &puts {
        let session = open(*role, *link).await;
        // Clients send only where a subscriber is known: let the spy's
        // subscription reach the new session first.
        settle().await;
        session
            .put(key.as_str(), role.name())
            .await
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        put_by.push(session.zid().to_string());
        sessions.push(session);
    }
    settle().await;

    let heard: Vec<(String, String)> = spy
        .0
        .lock()
        .map(|v| {
            v.iter()
                .map(|(k, _, p)| (String::from_utf8_lossy(p).into_owned(), k.clone()))
                .collect()
        })
        .unwrap_or_default();
    let expected: Vec<(String, String)> = puts
        .iter()
        .filter(|(_, _, _, allowed)| *allowed)
        .map(|(role, _, key, _)| (role.name().to_owned(), key.clone()))
        .collect();
    assert_eq!(
        heard, expected,
        "exactly the allowed puts crossed the router"
    );

    let alive: Vec<String> = operator
        .liveliness()
        .get("offworld/@v1/*/*/alive/**")
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?
        .into_iter()
        .filter_map(|reply| reply.into_result().ok())
        .map(|sample| sample.key_expr().as_str().to_owned())
        .collect();
    let mut alive = alive;
    alive.sort();
    let mut expected: Vec<String> = tokens
        .iter()
        .filter(|(_, _, _, allowed)| *allowed)
        .map(|(_, _, key, _)| key.clone())
        .collect();
    expected.sort();
    assert_eq!(alive, expected, "exactly the allowed tokens are seen");

    // Logged: the router names each session it refused or let through,
    // the action and the key (zenohd's access-control decisions, see
    // `audit_router`). An agent whose role file carries its own ACL may
    // drop a forbidden put at the source: then the router never sees it.
    let log = site.router_log();
    for ((role, link, key, allowed), zid) in puts.iter().zip(&put_by) {
        let decided = |verdict: &str| {
            log.lines().any(|line| {
                line.contains(zid.as_str())
                    && line.contains(&format!("{verdict} to Put (ingress) on {key}"))
            })
        };
        let (passed, refused) = (decided("is authorized"), decided("is unauthorized"));
        let own_acl = role.config().contains("access_control");
        let name = role.name();
        // The real site's roles over the socket match no subject at all.
        let sim_or_trainer = matches!(role, Role::SimTwin | Role::SimController | Role::Trainer);
        if *link == Link::LocalSocket && !sim_or_trainer {
            let unmatched = log.lines().any(|line| {
                line.contains(zid.as_str())
                    && line.contains("did not match any configured ACL subject")
            });
            assert!(
                unmatched && !passed,
                "{name} over the socket: logged as matching no subject"
            );
            continue;
        }
        if *allowed {
            assert!(
                passed && !refused,
                "{name}'s put on {key} over {link:?}: logged as let through"
            );
            // zenohd names the subject it matched: the user and the link
            // the session really came over.
            let came_over = match link {
                Link::Network => "Transport(Quic)",
                Link::LocalSocket => "Transport(UnixsockStream)",
            };
            let user = format!("Username({name})");
            let verdict = format!("is authorized to Put (ingress) on {key}");
            assert!(
                log.lines()
                    .any(|line| [zid.as_str(), &user, came_over, &verdict]
                        .iter()
                        .all(|part| line.contains(part))),
                "{name}'s put on {key}: not logged as {user} over {came_over}"
            );
        } else if own_acl {
            assert!(
                !passed,
                "{name}'s put on {key} over {link:?}: the router let it through"
            );
        } else {
            assert!(
                refused && !passed,
                "{name}'s put on {key} over {link:?}: logged as refused"
            );
        }
    }
    drop(held);
    Ok(())
}

/// Issue 22: the robot agent joins the site's router over mutual TLS with
/// nothing but its role file and password (`-c deploy/roles/robot_agent.json5`,
/// as every binary takes its Zenoh configuration): an operator sees it
/// alive through the router, and it obeys and acknowledges an e-stop.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_robot_agent_joins_the_mtls_router_with_its_role_file() -> anyhow::Result<()> {
    let _one = ONE_SITE.lock().await;
    let site = RouterSite::start("agent-mtls")?;
    let env = EnvId::real("mtls-0")?;
    let latch = site.dir.join("robot_agent.estop");
    let _agent = site.spawn(
        Role::RobotAgent,
        &[
            "robot",
            "--env",
            &env.to_string(),
            "--estop-latch",
            &latch.to_string_lossy(),
        ],
    )?;
    let operator = site.session(Role::Operator).open().await?;
    let wait = Duration::from_secs(20);
    for (engaged, summary) in [(true, "env"), (false, "none")] {
        let scope = EStopScope::Env(env.clone());
        let report = press_estop(&operator, &scope, engaged, "mTLS check", wait, wait).await?;
        let acks: Vec<_> = report
            .acknowledged
            .iter()
            .map(|a| (a.env.as_str(), a.component.as_str(), a.state.summary()))
            .collect();
        assert_eq!(acks, [("real/mtls-0", "robot_agent", summary)]);
    }
    Ok(())
}

/// Steps for `span` (at most 20,000 steps), starting a new episode at each
/// end; the number of steps, or the first step's error.
async fn step_for(gym: &mut EnvClient, span: Duration) -> Result<u32, WireError> {
    let started = std::time::Instant::now();
    let mut steps = 0;
    while started.elapsed() < span && steps < 20_000 {
        let reply = gym.step(Action::Discrete(i64::from(steps % 3))).await?;
        steps += 1;
        if reply.terminated || reply.truncated {
            gym.reset(Seed::Continue).await?;
        }
    }
    Ok(steps)
}

/// `env` opened (once the site is up) and reset, each step given 2 s and
/// each reset 4 s: a twin answers within milliseconds, so one held up
/// fails.
async fn impatient_gym(
    session: &Session,
    env: &EnvId,
    experiment: &str,
) -> anyhow::Result<EnvClient> {
    // A reset between steps (an episode's end) may be the request a stall
    // catches: it must time out before the router's 5 s wait ends too.
    let timeouts = ClientTimeouts {
        step: Duration::from_secs(2),
        reset: Duration::from_secs(4),
        ..ClientTimeouts::default()
    };
    let mut gym = EnvClient::open_when_ready(
        session,
        env,
        request(experiment, false),
        timeouts,
        Duration::from_secs(30),
    )
    .await
    .map_err(|e| anyhow::anyhow!(e))?;
    gym.reset(Seed::Fixed(1))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    Ok(gym)
}

/// An operator's monitor on the env, a process of its own, subscribed.
async fn watching(site: &SimSite, env: &EnvId, extra: &[&str]) -> anyhow::Result<Process> {
    // Nobody connects to its viewer port: the kernel picks one.
    let env_arg = env.to_string();
    let mut command = vec!["monitor", "--env", &env_arg, "--serve", "127.0.0.1:0"];
    command.extend(["--serve-memory-mib", "16", "--no-blueprint"]);
    command.extend(extra);
    let (onlooker, token) = (
        site.session(Role::Trainer).await,
        env.alive_key(Component::Monitor),
    );
    let watched = || offworld_tests::token_seen(&onlooker, &token);
    let deadline = |s| std::time::Instant::now() + Duration::from_secs(s);
    // A previous monitor's token is gone once the router dropped its link.
    let gone_by = deadline(30);
    while watched().await != Some(false) {
        anyhow::ensure!(
            std::time::Instant::now() < gone_by,
            "a previous monitor still watches {env} after 30 s"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let mut monitor = site.farm.site.spawn(Role::Operator, &command)?;
    // Its `alive/monitor` token follows its subscriptions on the same link:
    // once the router passes it on, the router sends this monitor the env's
    // messages.
    let watching_by = deadline(30);
    while std::time::Instant::now() < watching_by {
        if let Some(status) = monitor.0.try_wait()? {
            anyhow::bail!("the monitor exited: {status}");
        }
        if watched().await == Some(true) {
            return Ok(monitor);
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    anyhow::bail!("the monitor did not watch {env} within 30 s")
}

/// A live monitor that freezes (an operator's laptop asleep mid-view, a
/// process stopped) holds up no step: it reads only the viewers' copies,
/// which the router drops for it. Control: a frozen monitor that takes
/// every message (`--every-frame`, as the controller reads them) does hold
/// its env's steps up, for the 5 s the router waits before closing its link.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frozen_live_monitor_holds_up_no_step() -> anyhow::Result<()> {
    let _one = ONE_SITE.lock().await;
    let site = SimSite::start("frozen")?;
    let trainer = site.session(Role::Trainer).await;
    let mut gym = impatient_gym(&trainer, &site.env, "frozen").await?;
    let freeze = Duration::from_secs(8);

    // Control. Now and then under load (session 41: 1 of 17 runs, the
    // monitor alive and stopped, its token seen), the frozen reader of
    // every message held up no step at all: 684 steps in 8 s, none over
    // 30 ms, as if the router had no route to its fresh subscription (in
    // the others, its socket's buffer was full and steps were held within
    // ~25). Not explained yet (docs/performance.md, session 41); the
    // control needs one freeze that holds steps up, so it gets three.
    let mut not_held = Vec::new();
    loop {
        let control = watching(&site, &site.env, &["--every-frame"]).await?;
        step_for(&mut gym, Duration::from_secs(1)).await?;
        control.signal("STOP");
        let held_up = step_for(&mut gym, freeze).await;
        drop(control); // killed
        match held_up {
            Err(error) => {
                assert_eq!(error.code, ErrorCode::Timeout, "{error}");
                break;
            }
            Ok(steps) if not_held.len() < 2 => not_held.push(steps),
            Ok(steps) => panic!(
                "control: a frozen reader of every message holds steps up; three did not \
                 ({not_held:?} and {steps} steps while frozen)"
            ),
        }
    }
    // The router closed the frozen monitor's link: steps go on.
    tokio::time::sleep(Duration::from_secs(6)).await;
    gym.reset(Seed::Fixed(2))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;

    let live = watching(&site, &site.env, &[]).await?;
    step_for(&mut gym, Duration::from_secs(1)).await?;
    live.signal("STOP");
    let steps = step_for(&mut gym, freeze).await?;
    live.signal("CONT");
    assert!(steps > 100, "{steps} steps while the monitor was frozen");
    gym.close().await.map_err(|e| anyhow::anyhow!(e))?;

    // A monitor watches an env; it is no part of one: discovery lists
    // neither it among the env's components nor an env it alone watches.
    let nobody = EnvId::sim("nobody-0")?;
    let _typo = watching(&site, &nobody, &[]).await?;
    let listed = offworld_client::discover(&trainer, Duration::from_secs(3))
        .await
        .map_err(|e| anyhow::anyhow!(e))?;
    let listed: Vec<_> = listed.iter().map(|l| (&l.env, &l.components)).collect();
    assert_eq!(
        listed,
        [(
            &site.env,
            &vec!["controller".to_owned(), "sim_twin".to_owned()]
        )]
    );
    Ok(())
}

/// A client that sends a burst of questions and stops reading before the
/// answers arrive (a laptop asleep mid-burst, or a flood on purpose) holds
/// up nobody else's steps: the router forwards the gym's questions "drop"
/// (`deploy/router/zenohd.json5`, `gym_answers_never_wait`), so it never
/// waits on that client's full link with the controller's messages to
/// everyone else behind them. Control: the same burst through a router
/// without that rule holds the other trainer's next step past its timeout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_stops_reading_holds_up_no_one_else() -> anyhow::Result<()> {
    let _one = ONE_SITE.lock().await;
    let mut router = RouterSite::start("unread-control")?;
    router.restart_router_with(&["qos/network:[]"])?;
    let control = SimSite::on(router, "unread-control")?;
    let held_up = burst_then_sleep(&control).await?;
    let error = held_up.expect_err("control: a stopped reader of answers holds the others up");
    assert_eq!(error.code, ErrorCode::Timeout, "{error}");
    drop(control);

    let site = SimSite::start("unread")?;
    let steps = burst_then_sleep(&site).await?;
    let steps = steps.map_err(|e| anyhow::anyhow!("a step while the reader slept: {e}"))?;
    assert!(steps > 0);
    Ok(())
}

/// A trainer may declare its presence (liveliness tokens under
/// `alive/client/*`); one that declares and drops them by the ten
/// thousand, distinct ones, must not hold up another trainer's steps:
/// the controller hears only its lease holder's token, and discovery only
/// components'.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_trainer_flooding_presence_tokens_holds_up_no_one_else() -> anyhow::Result<()> {
    let _one = ONE_SITE.lock().await;
    let site = SimSite::start("flood")?;
    let trainer = site.session(Role::Trainer).await;
    let mut gym = impatient_gym(&trainer, &site.env, "flood").await?;
    step_for(&mut gym, Duration::from_secs(1)).await?;

    let helper = offworld_deploy::process::binary_dir().join("test_helper");
    let mut args = vec!["floods-tokens".to_owned()];
    args.extend(site.farm.site.role_args(Role::Trainer));
    args.extend(["--env".into(), site.env.to_string()]);
    args.extend([
        "--count".into(),
        "30000".into(),
        "--seconds".into(),
        "60".into(),
    ]);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let mut flooder = Process::start(None, &helper, &args, "warn", std::process::Stdio::piped())?;
    let said = first_line(&mut flooder).await?;
    assert_eq!(said.trim(), "flooding", "test_helper floods-tokens");
    let steps = step_for(&mut gym, Duration::from_secs(5))
        .await
        .map_err(|e| anyhow::anyhow!("a step during the flood: {e}"))?;
    eprintln!("{steps} steps in 5 s during the flood");
    assert!(steps > 0);

    // The flood is real (an operator sees it), and a trainer sees none of
    // it: clients' tokens are not discovery's.
    let clients = site.env.clients_alive_selector();
    let operator = site.session(Role::Operator).await;
    let flooded = |keys: &[String]| keys.iter().filter(|k| k.contains("/client/flood")).count();
    let seen = flooded(&client_tokens(&operator, &clients).await?);
    assert!(
        seen > 1_000,
        "the operator saw {seen} of the flood's tokens"
    );
    // Its own token (a session lists its own without asking the router).
    let seen = client_tokens(&trainer, &clients).await?;
    assert_eq!(
        flooded(&seen),
        0,
        "a trainer listed others' tokens: {seen:?}"
    );
    assert_eq!(seen.len(), 1, "{seen:?}");
    drop(flooder); // killed
    Ok(())
}

/// The liveliness tokens `session` may list under `selector` (2 s).
async fn client_tokens(session: &Session, selector: &str) -> anyhow::Result<Vec<String>> {
    let replies = session
        .liveliness()
        .get(selector)
        .timeout(Duration::from_secs(2))
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut seen = Vec::new();
    while let Ok(reply) = replies.recv_async().await {
        if let Ok(sample) = reply.result() {
            seen.push(sample.key_expr().as_str().to_owned());
        }
    }
    Ok(seen)
}

/// The first line `process` prints (within 60 s).
async fn first_line(process: &mut Process) -> anyhow::Result<String> {
    let stdout = process.0.stdout.take().expect("piped");
    let said = tokio::task::spawn_blocking(move || {
        use std::io::BufRead;
        let mut line = String::new();
        let _ = std::io::BufReader::new(stdout).read_line(&mut line);
        line
    });
    Ok(tokio::time::timeout(Duration::from_secs(60), said).await??)
}

/// A trainer steps `site`'s env; then a client of its own process
/// (`test_helper stops-reading`) asks the controller 20,000 times and stops before
/// reading the answers: the trainer's steps for the next 3 s (each within
/// 2 s, else a `Timeout`).
async fn burst_then_sleep(site: &SimSite) -> anyhow::Result<Result<u32, WireError>> {
    let trainer = site.session(Role::Trainer).await;
    let mut gym = impatient_gym(&trainer, &site.env, "unread").await?;
    step_for(&mut gym, Duration::from_secs(1)).await?;

    let helper = offworld_deploy::process::binary_dir().join("test_helper");
    let mut args = vec!["stops-reading".to_owned()];
    args.extend(site.farm.site.role_args(Role::Trainer));
    args.extend(["--key".into(), site.env.key(Topic::Spec)]);
    args.extend(["--count".into(), "20000".into()]);
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let mut asker = Process::start(None, &helper, &args, "warn", std::process::Stdio::piped())?;
    let said = first_line(&mut asker).await?;
    assert_eq!(said.trim(), "sent 20000", "test_helper stops-reading");
    let steps = step_for(&mut gym, Duration::from_secs(3)).await;
    drop(asker); // killed
    Ok(steps)
}
