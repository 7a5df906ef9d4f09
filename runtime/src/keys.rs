//! The key space: the only place that formats or parses Zenoh key expressions.
//!
//! Every key lives under `offworld/@v1/<realm>/<name>/…`. `@v1` is a verbatim
//! chunk: wildcards never match it, so a peer speaking another protocol
//! version can never receive (or answer) our messages by accident. `<realm>`
//! (`sim` or `real`) plus `<name>` form the [`EnvId`]; pointing a controller or
//! client at a twin or at the real robot is a matter of namespace alone.

use std::fmt;
use std::str::FromStr;

use crate::error::ContractError;

/// Root chunk of every key.
pub const ROOT: &str = "offworld";
/// Protocol version chunk (verbatim: only matched literally).
pub const VERSION: &str = "@v1";

/// Whether an environment is a simulated twin or a physical enclosure.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Hash,
    PartialOrd,
    Ord,
    strum::IntoStaticStr,
    strum::EnumIter,
    strum::VariantNames,
)]
#[strum(serialize_all = "snake_case")]
pub enum Realm {
    /// A simulated twin (sim_twin).
    Sim,
    /// A physical enclosure (robot_agent + tracker_agent).
    Real,
}

impl Realm {
    /// The key chunk for this realm.
    pub fn as_str(self) -> &'static str {
        self.into()
    }
}

impl FromStr for Realm {
    type Err = ContractError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        crate::named::parse("realm", s).map_err(ContractError::InvalidEnvId)
    }
}

/// One enclosure instance, e.g. `sim/monolith-0` or `real/enclosure-a`.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct EnvId {
    realm: Realm,
    name: String,
}

impl EnvId {
    /// Builds an env id; `name` must be one non-empty key chunk of
    /// `[A-Za-z0-9_-]` (no `/`, no wildcards, no `@`).
    pub fn new(realm: Realm, name: &str) -> Result<Self, ContractError> {
        let valid = !name.is_empty()
            && name.len() <= 64
            && name
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
        if !valid {
            return Err(ContractError::InvalidEnvId(format!(
                "env name must be 1-64 chars of [A-Za-z0-9_-], got `{name}`"
            )));
        }
        Ok(Self {
            realm,
            name: name.to_owned(),
        })
    }

    /// A simulated env; panics never — returns an error on a bad name.
    pub fn sim(name: &str) -> Result<Self, ContractError> {
        Self::new(Realm::Sim, name)
    }

    /// A physical env.
    pub fn real(name: &str) -> Result<Self, ContractError> {
        Self::new(Realm::Real, name)
    }

    /// The realm (sim or real).
    pub fn realm(&self) -> Realm {
        self.realm
    }

    /// The instance name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The key prefix `offworld/@v1/<realm>/<name>`.
    pub fn prefix(&self) -> String {
        format!("{ROOT}/{VERSION}/{}/{}", self.realm.as_str(), self.name)
    }

    /// The full key of one topic of this env.
    pub fn key(&self, topic: Topic) -> String {
        format!("{}/{}", self.prefix(), topic.as_str())
    }

    /// Liveliness token key for one component serving this env.
    pub fn alive_key(&self, component: Component) -> String {
        format!("{}/alive/{}", self.prefix(), component.as_str())
    }

    /// Selector of this env's components' liveliness tokens (not clients').
    pub fn components_alive_selector(&self) -> String {
        format!("{}/alive/*", self.prefix())
    }

    /// Selector of this env's clients' liveliness tokens.
    pub fn clients_alive_selector(&self) -> String {
        format!("{}/alive/client/*", self.prefix())
    }

    /// Liveliness token key of one client session (lease holder) on this env.
    pub fn client_alive_key(&self, session_id: &str) -> Result<String, ContractError> {
        // Reuse the env-name rule: one safe chunk.
        EnvId::new(self.realm, session_id)?;
        Ok(format!("{}/alive/client/{session_id}", self.prefix()))
    }

    /// Key of one overhead camera stream of this env.
    pub fn overhead_key(&self, camera: &str) -> Result<String, ContractError> {
        EnvId::new(self.realm, camera)?;
        Ok(format!("{}/overhead/{camera}", self.prefix()))
    }

    /// Selector matching every overhead camera stream of this env.
    pub fn overhead_selector(&self) -> String {
        format!("{}/overhead/*", self.prefix())
    }

    /// Parses an env id back out of any key under it.
    pub fn from_key(key: &str) -> Result<Self, ContractError> {
        let mut chunks = key.split('/');
        let (Some(ROOT), Some(VERSION), Some(realm), Some(name)) =
            (chunks.next(), chunks.next(), chunks.next(), chunks.next())
        else {
            return Err(ContractError::InvalidEnvId(format!(
                "`{key}` is not under `{ROOT}/{VERSION}/<realm>/<name>`"
            )));
        };
        Self::new(realm.parse()?, name)
    }
}

impl fmt::Display for EnvId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}", self.realm.as_str(), self.name)
    }
}

impl FromStr for EnvId {
    type Err = ContractError;
    /// Parses `sim/monolith-0` or `real/enclosure-a`.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.split_once('/') {
            Some((realm, name)) => Self::new(realm.parse()?, name),
            None => Err(ContractError::InvalidEnvId(format!(
                "env id must look like `sim/<name>` or `real/<name>`, got `{s}`"
            ))),
        }
    }
}

/// The per-env topics. Payloads are CDR (see [`crate::msg`]). Each one's
/// key chunk is its name in snake case (`HeartbeatEcho` → `heartbeat_echo`),
/// `estop` spelt as one word.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, strum::IntoStaticStr, strum::EnumIter)]
#[strum(serialize_all = "snake_case")]
pub enum Topic {
    /// Controller → twin/robot: [`crate::msg::MotionCommand`] (pub/sub).
    Cmd,
    /// Twin/robot → controller and recorders: [`crate::msg::CameraFrame`]
    /// answering a command, every one delivered (pub/sub).
    Obs,
    /// Twin/robot → viewers (live monitors, the web page's thumbnails): the
    /// same frames, at most one every [`crate::preview::PREVIEW_PERIOD`],
    /// dropped rather than waited for, published only while someone
    /// subscribes ([`crate::preview::PreviewPublisher`]).
    Preview,
    /// Controller → viewers: each `cmd`, dropped rather than waited for,
    /// published only while someone subscribes
    /// ([`crate::preview::WatchedPublisher`]).
    PreviewCmd,
    /// Twin/tracker → viewers: each `pose`, as [`Topic::PreviewCmd`].
    PreviewPose,
    /// Twin/robot → viewers: each `odom`, as [`Topic::PreviewCmd`].
    PreviewOdom,
    /// Twin/robot → all: `nav_msgs/Odometry` (pub/sub).
    Odom,
    /// Robot → controller: [`crate::msg::MotionFault`], a command that
    /// will not be answered and why (pub/sub), so the step fails at once
    /// instead of after its answer timeout.
    Fault,
    /// Twin/tracker → all: `geometry_msgs/PoseStamped` of base_link in the world frame.
    Pose,
    /// Tracker → all: [`crate::msg::TrackingStatus`] on change.
    Tracking,
    /// Controller → all: [`crate::msg::EpisodeEvent`] after every step.
    Reward,
    /// Controller → all: [`crate::msg::EnvStatus`] on change; also a queryable.
    Status,
    /// Controller → robot: [`crate::msg::Heartbeat`] keeping the watchdog armed.
    Heartbeat,
    /// Robot agent / twin → controller: each [`crate::msg::Heartbeat`]
    /// echoed as received, so the controller knows within a fraction of a
    /// second when it stops hearing the robot (a cut or frozen link).
    HeartbeatEcho,
    /// Operator/controller → robot: [`crate::msg::EStop`] (acts immediately).
    #[strum(serialize = "estop")]
    EStop,
    /// Robot agent / twin → operators: [`crate::msg::EStopAck`], one per
    /// e-stop received and applied.
    #[strum(serialize = "estop_ack")]
    EStopAck,
    /// Queryable on robot agents, twins and the controller: () →
    /// [`crate::msg::EStopState`], the latches in force for the env (how a
    /// restarted component learns them from the network).
    #[strum(serialize = "estop_state")]
    EStopState,
    /// Queryable on the twin/robot: [`crate::msg::GotoRequest`] → [`crate::msg::GotoReply`]
    /// (sim teleports, real navigates).
    Goto,
    /// Queryable on the controller: [`crate::msg::OpenRequest`] → [`crate::msg::OpenReply`].
    Open,
    /// Queryable on the controller: () → [`crate::msg::EnvSpec`].
    Spec,
    /// Queryable on the controller: [`crate::msg::ResetRequest`] → [`crate::msg::ResetReply`].
    Reset,
    /// Queryable on the controller: [`crate::msg::StepRequest`] → [`crate::msg::StepReply`].
    Step,
    /// Queryable on the controller: [`crate::msg::CloseRequest`] → [`crate::msg::CloseReply`].
    Close,
    /// Queryable on the controller: [`crate::msg::AdminRequest`] → [`crate::msg::AdminReply`].
    Admin,
    /// Queryable on the controller: () → [`crate::msg::Leaderboard`].
    Leaderboard,
    /// Queryable on the controller: [`crate::msg::BookingRequest`] →
    /// [`crate::msg::Bookings`].
    Book,
    /// Queryable on the controller: [`crate::msg::ExperimentsRequest`] →
    /// [`crate::msg::Experiments`].
    Experiments,
}

impl Topic {
    /// The key chunk of this topic.
    pub fn as_str(self) -> &'static str {
        self.into()
    }

    /// Where viewers read this topic: its copy, delivered [`Latest`] and
    /// put only while watched, for the topics the controller and recorders
    /// must receive whole (delivered [`Every`]); `None` for the others,
    /// which viewers read as they are. A viewer reading the originals
    /// would hold up their publishers when it stalls.
    ///
    /// [`Latest`]: crate::wire::Delivery::Latest
    /// [`Every`]: crate::wire::Delivery::Every
    pub fn viewers_copy(self) -> Option<Topic> {
        match self {
            Topic::Obs => Some(Topic::Preview),
            Topic::Cmd => Some(Topic::PreviewCmd),
            Topic::Pose => Some(Topic::PreviewPose),
            Topic::Odom => Some(Topic::PreviewOdom),
            _ => None,
        }
    }
}

/// Components that declare liveliness tokens.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, strum::IntoStaticStr)]
#[strum(serialize_all = "snake_case")]
pub enum Component {
    /// The gym server.
    Controller,
    /// The simulated robot + tracker.
    SimTwin,
    /// The robot-side agent.
    RobotAgent,
    /// The tracker-side agent.
    TrackerAgent,
    /// The rerun monitor.
    Monitor,
    /// The robot's independent safety process: zeroes the base when the
    /// robot agent dies, hangs or goes silent mid-motion.
    BaseGuard,
}

impl Component {
    /// The key chunk of this component.
    pub fn as_str(self) -> &'static str {
        self.into()
    }
}

/// A random id usable as a key chunk (16 hex digits), e.g. a client's id.
pub fn random_id() -> String {
    use rand::Rng;
    let mut rng = rand::rng();
    (0..16)
        .map(|_| format!("{:x}", rng.random_range(0..16u8)))
        .collect()
}

/// Key of the site-wide e-stop that stops every robot at once.
pub fn global_estop_key() -> String {
    format!("{ROOT}/{VERSION}/estop")
}

/// Selector matching every key of every env (an operator's spy: it takes
/// every `obs` frame, and makes every twin and robot send its `preview`).
pub fn all_envs_selector() -> String {
    format!("{ROOT}/{VERSION}/**")
}

/// Selector matching one topic on every env, e.g. all `spec` queryables.
pub fn topic_on_all_envs(topic: Topic) -> String {
    format!("{ROOT}/{VERSION}/*/*/{}", topic.as_str())
}

/// Selector matching every overhead camera of every env.
pub fn overhead_on_all_envs() -> String {
    format!("{ROOT}/{VERSION}/*/*/overhead/*")
}

/// Selector matching the components' liveliness tokens of every env
/// (`alive/controller`, `alive/sim_twin`, …), not clients': discovery
/// needs no more, and a trainer may declare client tokens by the thousand.
pub fn components_alive_selector() -> String {
    format!("{ROOT}/{VERSION}/*/*/alive/*")
}

/// Selector matching the clients' liveliness tokens of every env
/// (`alive/client/<id>`): through a site's router only operators (and
/// controllers) may hear them.
pub fn clients_alive_selector() -> String {
    format!("{ROOT}/{VERSION}/*/*/alive/client/*")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_have_the_documented_shape() {
        let env = EnvId::sim("monolith-0").expect("valid");
        assert_eq!(env.key(Topic::Cmd), "offworld/@v1/sim/monolith-0/cmd");
        assert_eq!(
            env.key(Topic::Preview),
            "offworld/@v1/sim/monolith-0/preview"
        );
        assert_eq!(
            env.key(Topic::PreviewOdom),
            "offworld/@v1/sim/monolith-0/preview_odom"
        );
        assert_eq!(
            env.alive_key(Component::Controller),
            "offworld/@v1/sim/monolith-0/alive/controller"
        );
        let real = EnvId::real("enclosure-a").expect("valid");
        assert_eq!(real.key(Topic::Step), "offworld/@v1/real/enclosure-a/step");
        assert_eq!(
            real.overhead_key("cam1").expect("valid"),
            "offworld/@v1/real/enclosure-a/overhead/cam1"
        );
        assert_eq!(
            real.overhead_selector(),
            "offworld/@v1/real/enclosure-a/overhead/*"
        );
        assert_eq!(overhead_on_all_envs(), "offworld/@v1/*/*/overhead/*");
    }

    #[test]
    fn env_ids_round_trip_and_reject_bad_names() {
        let env: EnvId = "real/enclosure-a".parse().expect("valid");
        assert_eq!(env.realm(), Realm::Real);
        assert_eq!(EnvId::from_key(&env.key(Topic::Obs)).expect("parse"), env);
        for bad in ["", "a/b", "*", "**", "x$", "@v1", "a b"] {
            assert!(EnvId::sim(bad).is_err(), "{bad:?} accepted");
        }
        assert!("lab/x".parse::<EnvId>().is_err());
        assert!("monolith".parse::<EnvId>().is_err());
        assert!(EnvId::from_key("offworld/v1/sim/x/cmd").is_err());
    }

    #[test]
    fn every_topic_key_is_a_valid_zenoh_key() {
        let env = EnvId::sim("m").expect("valid");
        for topic in <Topic as strum::IntoEnumIterator>::iter() {
            let key = env.key(topic);
            zenoh::key_expr::KeyExpr::try_from(key.clone()).expect(&key);
        }
        zenoh::key_expr::KeyExpr::try_from(all_envs_selector()).expect("selector");
        zenoh::key_expr::KeyExpr::try_from(topic_on_all_envs(Topic::Spec)).expect("sel");
    }

    /// Viewers read a copy of exactly the streams delivered `Every`.
    #[test]
    fn viewers_read_copies_of_the_every_streams() {
        use strum::IntoEnumIterator;
        let copied: Vec<(Topic, Topic)> = Topic::iter()
            .filter_map(|t| t.viewers_copy().map(|copy| (t, copy)))
            .collect();
        assert_eq!(
            copied,
            vec![
                (Topic::Cmd, Topic::PreviewCmd),
                (Topic::Obs, Topic::Preview),
                (Topic::Odom, Topic::PreviewOdom),
                (Topic::Pose, Topic::PreviewPose),
            ]
        );
        assert_eq!(Topic::Reward.viewers_copy(), None);
        assert_eq!(Topic::Preview.viewers_copy(), None, "no copy of a copy");
    }
}
