//! E-stop scopes with real processes (issue 21): the emulated enclosure's
//! robot agent and a sim twin, both served by one controller, walked
//! through every (latches, press) combination of the site and env e-stops,
//! with the agent, the twin and the controller each killed and restarted
//! in between. A model of the two latches says what must hold after every
//! step; checked against every component that answers for an env:
//!
//! - each press is acknowledged by exactly the robot agents and twins under
//!   its scope, each reporting the latches the model holds;
//! - every `estop_state` answer for an env (agent or twin, and controller)
//!   and the controller's status agree with the model;
//! - a restarted component comes back with the latches (the agent from its
//!   file and the network, the twin and the controller from the network);
//! - motion is refused by the real env and the sim env alike, with the same
//!   typed error naming every engaged latch, and allowed once both are
//!   released.

use std::collections::BTreeSet;
use std::time::Duration;

use offworld_client::operator::{press_estop, EStopScope, PressReport};
use offworld_client::{self as client, ClientTimeouts, EnvClient};
use offworld_runtime::codec;
use offworld_runtime::keys::{Component, EnvId, Realm, Topic};
use offworld_runtime::msg::{EStopState, Seed};
use offworld_runtime::{ErrorCode, SessionConfig};
use offworld_tests::emulated::{EmulatedEnclosure, Options, Part};
use offworld_tests::faults::open_request;
use zenoh::query::{ConsolidationMode, QueryTarget};
use zenoh::Session;

/// How long a press waits for its obeyers to be present, and for their
/// acknowledgements (generous: this host also runs every process).
const PRESENCE: Duration = Duration::from_secs(20);
const ACK: Duration = Duration::from_secs(5);

/// A press: engage or release one latch of every env (the env presses go
/// to both envs, so the site latch and each env's latch stay comparable).
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Press {
    EngageSite,
    ReleaseSite,
    EngageEnv,
    ReleaseEnv,
}

/// What the latches must be: engaged or not, and the reason of the last
/// press of each.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
struct Model {
    site: Option<String>,
    env: Option<String>,
    site_reason: String,
    env_reason: String,
}

impl Model {
    fn key(&self) -> (bool, bool) {
        (self.site.is_some(), self.env.is_some())
    }

    fn apply(&mut self, press: Press, reason: &str) {
        match press {
            Press::EngageSite => self.site = Some(reason.to_owned()),
            Press::ReleaseSite => self.site = None,
            Press::EngageEnv => self.env = Some(reason.to_owned()),
            Press::ReleaseEnv => self.env = None,
        }
        match press {
            Press::EngageSite | Press::ReleaseSite => self.site_reason = reason.to_owned(),
            Press::EngageEnv | Press::ReleaseEnv => self.env_reason = reason.to_owned(),
        }
    }

    /// Asserts a component's report of the latches.
    fn assert_state(&self, state: &EStopState, who: &str) {
        if let Err(e) = self.check_state(state, who) {
            panic!("{e}");
        }
    }

    /// Whether a component's report of the latches is the model's.
    fn check_state(&self, state: &EStopState, who: &str) -> Result<(), String> {
        let reported = (
            state.site.engaged,
            state.env.engaged,
            state.site.reason.as_str(),
            state.env.reason.as_str(),
        );
        let (site, env) = self.key();
        let expected = (
            site,
            env,
            self.site_reason.as_str(),
            self.env_reason.as_str(),
        );
        if reported == expected {
            Ok(())
        } else {
            Err(format!(
                "{who}: latches {} ({state:?}), the model {self:?}",
                state.summary()
            ))
        }
    }

    /// The refusal every env gives while a latch is engaged.
    fn refusal(&self) -> Option<String> {
        let mut engaged = Vec::new();
        if let Some(reason) = &self.site {
            engaged.push(format!("site ({reason})"));
        }
        if let Some(reason) = &self.env {
            engaged.push(format!("env ({reason})"));
        }
        (!engaged.is_empty()).then(|| format!("e-stop engaged: {}", engaged.join(", ")))
    }
}

/// Every (latches, press) pair of the two latches, each once, as one walk
/// from and back to "none" (an Euler circuit of the 4-state graph).
const WALK: [Press; 16] = [
    Press::ReleaseSite,
    Press::ReleaseEnv,
    Press::EngageSite,
    Press::EngageSite,
    Press::ReleaseEnv,
    Press::EngageEnv,
    Press::EngageEnv,
    Press::EngageSite,
    Press::ReleaseSite,
    Press::ReleaseSite,
    Press::EngageEnv,
    Press::EngageSite,
    Press::ReleaseEnv,
    Press::ReleaseSite,
    Press::EngageEnv,
    Press::ReleaseEnv,
];

/// After which press of [`WALK`] which part is killed and restarted: one
/// of each in a state where the latch it must recover is engaged.
fn restart_after(step: usize) -> Option<Part> {
    match step {
        3 => Some(Part::RobotAgent),  // site
        6 => Some(Part::Twin),        // site+env
        7 => Some(Part::Controller),  // site+env
        11 => Some(Part::Twin),       // env
        12 => Some(Part::RobotAgent), // site+env
        13 => Some(Part::Controller), // site
        _ => None,
    }
}

struct Rig {
    deployment: EmulatedEnclosure,
    operator: Session,
    real: EnvId,
    sim: EnvId,
    experiments: BTreeSet<String>,
}

impl Rig {
    fn envs(&self) -> [EnvId; 2] {
        [self.real.clone(), self.sim.clone()]
    }

    async fn press(&self, press: Press, reason: &str) -> Vec<PressReport> {
        let engaged = matches!(press, Press::EngageSite | Press::EngageEnv);
        let scopes = match press {
            Press::EngageSite | Press::ReleaseSite => vec![EStopScope::Site],
            Press::EngageEnv | Press::ReleaseEnv => {
                self.envs().into_iter().map(EStopScope::Env).collect()
            }
        };
        let mut reports = Vec::new();
        for scope in scopes {
            let report = press_estop(&self.operator, &scope, engaged, reason, PRESENCE, ACK)
                .await
                .unwrap_or_else(|e| panic!("{press:?} on {scope:?}: {e}"));
            reports.push(report);
        }
        reports
    }

    /// Every answer of `estop_state` for each env (the agent or twin, and
    /// the controller) and the controller's status agree with `model`.
    async fn assert_latches(&self, model: &Model, when: &str) {
        if let Err(e) = self.check_latches(model, when).await {
            panic!("{e}");
        }
    }

    /// [`Rig::assert_latches`], allowing a restarted component a few
    /// seconds to learn the latches from the network (it asks again, see
    /// `estop::RECALL_AGAIN`; its robot's agent holds its own meanwhile).
    async fn until_latches(&self, model: &Model, when: &str) {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
        loop {
            match self.check_latches(model, when).await {
                Ok(()) => return,
                Err(e) if tokio::time::Instant::now() >= deadline => panic!("{e}"),
                Err(_) => tokio::time::sleep(Duration::from_millis(200)).await,
            }
        }
    }

    async fn check_latches(&self, model: &Model, when: &str) -> Result<(), String> {
        for env in self.envs() {
            let replies = self
                .operator
                .get(env.key(Topic::EStopState))
                .target(QueryTarget::All)
                .consolidation(ConsolidationMode::None)
                .timeout(Duration::from_secs(3))
                .await
                .expect("estop_state query");
            let mut answers = 0;
            while let Ok(reply) = replies.recv_async().await {
                // A queryable that did not answer within the query's time
                // is an error reply (`Timeout`): right after a restart the
                // router may still route to the killed process's
                // declarations or the new one's session may be starting.
                let sample = reply.result().map_err(|e| {
                    format!(
                        "{when}: an estop_state query of {env} got an error reply: {}",
                        e.payload().try_to_string().unwrap_or_default()
                    )
                })?;
                let state: EStopState =
                    codec::decode_payload(sample.payload()).expect("an EStopState");
                model.check_state(&state, &format!("{when}: estop_state of {env}"))?;
                answers += 1;
            }
            if answers < 2 {
                return Err(format!(
                    "{when}: {env}'s obeyer and the controller answer ({answers})"
                ));
            }
            let status = client::status(&self.operator, &env, Duration::from_secs(5))
                .await
                .map_err(|e| format!("{when}: status of {env}: {e}"))?;
            model.check_state(&status.estop, &format!("{when}: status of {env}"))?;
        }
        Ok(())
    }

    /// Both envs refuse a reset with the model's refusal, or, with both
    /// latches released, start an episode.
    async fn assert_motion(&mut self, model: &Model, when: &str) {
        let session = SessionConfig::connecting(&self.deployment.endpoint)
            .open()
            .await
            .expect("client session");
        for env in self.envs() {
            let experiment = format!("estop-{}", env.name());
            let resume = !self.experiments.insert(experiment.clone());
            let mut gym = EnvClient::open_when_ready(
                &session,
                &env,
                open_request(&self.deployment.token, &experiment, resume),
                ClientTimeouts::default(),
                Duration::from_secs(60),
            )
            .await
            .unwrap_or_else(|e| panic!("{when}: open {env}: {e}"));
            // A robot that has not yet heard the controller's first
            // heartbeat answers `Unavailable` (transient, like any start
            // race); e-stop refusals are `InvalidState` and never retried.
            let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
            let reset = loop {
                match gym.reset(Seed::Fixed(7)).await {
                    Err(e)
                        if e.code == ErrorCode::Unavailable
                            && tokio::time::Instant::now() < deadline =>
                    {
                        tokio::time::sleep(Duration::from_millis(100)).await;
                    }
                    reset => break reset,
                }
            };
            match (model.refusal(), reset) {
                (Some(refusal), Err(e)) => {
                    assert_eq!(e.code, ErrorCode::InvalidState, "{when}: {env}: {e}");
                    assert_eq!(e.message, refusal, "{when}: {env}");
                }
                (Some(refusal), Ok(_)) => panic!("{when}: {env} moved under {refusal}"),
                (None, Ok(_)) => {}
                (None, Err(e)) => panic!("{when}: {env} refused with every latch released: {e}"),
            }
            gym.close().await.expect("close");
        }
    }

    /// Kills a part (like a crash) and starts it again; waits until it is
    /// back on the network.
    async fn restart(&mut self, part: Part) {
        self.deployment.kill(part);
        self.deployment.start_part(part).expect("restart");
        let token = match part {
            Part::RobotAgent => self.real.alive_key(Component::RobotAgent),
            Part::Twin => self.sim.alive_key(Component::SimTwin),
            _ => self.real.alive_key(Component::Controller),
        };
        let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
        loop {
            let seen = offworld_tests::token_seen(&self.operator, &token).await;
            if seen.expect("liveliness get") {
                break;
            }
            assert!(
                tokio::time::Instant::now() < deadline,
                "{part:?} did not come back"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        if part == Part::Controller {
            self.deployment
                .ready(Duration::from_secs(60))
                .await
                .expect("controller back");
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_estop_combination_holds_across_restarts_on_real_and_sim_alike() {
    let mut options = Options::new("MonolithDiscrete").expect("options");
    let sim = EnvId::sim("estop-0").expect("env");
    options.twin = Some(sim.clone());
    let deployment = EmulatedEnclosure::start(&options).expect("deployment");
    deployment
        .ready(Duration::from_secs(60))
        .await
        .expect("deployment ready");
    let operator = SessionConfig::connecting(&deployment.endpoint)
        .open()
        .await
        .expect("operator session");
    let mut rig = Rig {
        real: deployment.env.clone(),
        sim,
        deployment,
        operator,
        experiments: BTreeSet::new(),
    };
    let obeyers = |envs: &[EnvId]| -> BTreeSet<(String, String)> {
        envs.iter()
            .map(|env| {
                let component = if env.realm() == Realm::Real {
                    "robot_agent"
                } else {
                    "sim_twin"
                };
                (env.to_string(), component.to_owned())
            })
            .collect()
    };

    let mut model = Model::default();
    rig.assert_motion(&model, "at start").await;
    let mut covered = BTreeSet::new();
    let mut motion_checked = BTreeSet::new();
    for (step, press) in WALK.into_iter().enumerate() {
        let before = model.key();
        covered.insert((before, press));
        let reason = format!("press {step}");
        let when = format!("{press:?} from {before:?} (press {step})");
        let reports = rig.press(press, &reason).await;
        model.apply(press, &reason);

        // Acknowledged by exactly what the scope covers, each in the model's state.
        let acked: BTreeSet<(String, String)> = reports
            .iter()
            .flat_map(|r| &r.acknowledged)
            .map(|a| (a.env.clone(), a.component.clone()))
            .collect();
        assert_eq!(acked, obeyers(&rig.envs()), "{when}: who acknowledged");
        for ack in reports.iter().flat_map(|r| &r.acknowledged) {
            model.assert_state(
                &ack.state,
                &format!("{when}: {}'s acknowledgement", ack.env),
            );
        }
        rig.assert_latches(&model, &when).await;

        if let Some(part) = restart_after(step) {
            rig.restart(part).await;
            let when = format!("{when}, then {part:?} restarted");
            rig.until_latches(&model, &when).await;
            rig.assert_motion(&model, &when).await;
            motion_checked.insert(model.key());
        } else if motion_checked.insert(model.key()) {
            rig.assert_motion(&model, &when).await;
        }
    }
    assert_eq!(model.key(), (false, false), "the walk ends released");
    rig.assert_motion(&model, "at the end").await;
    let states = [(false, false), (true, false), (false, true), (true, true)];
    let presses = [
        Press::EngageSite,
        Press::ReleaseSite,
        Press::EngageEnv,
        Press::ReleaseEnv,
    ];
    for state in states {
        assert!(
            motion_checked.contains(&state),
            "motion checked in {state:?}"
        );
        for press in presses {
            assert!(
                covered.contains(&(state, press)),
                "{press:?} from {state:?}"
            );
        }
    }
}
