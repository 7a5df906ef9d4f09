//! The gym protocol between clients and the controller: request/reply types
//! for the `open`, `spec`, `reset`, `step`, `close` and `admin` queryables,
//! and the `reward` / `status` publications. Errors travel as
//! [`crate::WireError`] replies.

use serde::{Deserialize, Serialize};

/// Which camera channels an observation carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Channels {
    /// One depth channel.
    DepthOnly,
    /// Red, green, blue.
    RgbOnly,
    /// Red, green, blue, depth.
    Rgbd,
}

impl Channels {
    /// Channels per pixel.
    pub fn count(self) -> u32 {
        match self {
            Channels::DepthOnly => 1,
            Channels::RgbOnly => 3,
            Channels::Rgbd => 4,
        }
    }
}

/// How depth (and then every channel) is represented.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum DepthFormat {
    /// u8: depth scaled 0–255 over the spec's depth range; RGB 0–255.
    Uint8,
    /// f32: depth in metres; RGB as 0–255 floats.
    Meters,
}

/// Element type of an observation array.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum DType {
    /// u8.
    #[default]
    U8,
    /// little-endian f32.
    F32,
}

impl DType {
    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::U8 => 1,
            DType::F32 => 4,
        }
    }
}

/// What the client wants its observations to look like.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ObsOptions {
    /// Which channels.
    pub channels: Channels,
    /// Rows (resized server-side).
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// u8 or metric.
    pub depth_format: DepthFormat,
}

impl ObsOptions {
    /// The observation these options ask for, without its data: shape and
    /// element type (metric depth makes every channel `f32`).
    pub fn shape(&self) -> ObsArray {
        ObsArray {
            height: self.height,
            width: self.width,
            channels: self.channels.count(),
            dtype: match self.depth_format {
                DepthFormat::Uint8 => DType::U8,
                DepthFormat::Meters => DType::F32,
            },
            data: Vec::new(),
        }
    }
}

impl Default for ObsOptions {
    fn default() -> Self {
        Self {
            channels: Channels::DepthOnly,
            height: 240,
            width: 320,
            depth_format: DepthFormat::Uint8,
        }
    }
}

/// An observation tensor, shape (height, width, channels), row-major, interleaved.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ObsArray {
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Channels per pixel.
    pub channels: u32,
    /// Element type.
    pub dtype: DType,
    /// Little-endian elements.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

impl ObsArray {
    /// Bytes of data the shape and element type call for.
    pub fn shape_len(&self) -> u64 {
        u64::from(self.height)
            * u64::from(self.width)
            * u64::from(self.channels)
            * self.dtype.size() as u64
    }

    /// Checks that the data length matches the shape.
    pub fn is_consistent(&self) -> bool {
        self.shape_len() == self.data.len() as u64
    }
}

/// What kind of learning an experiment does (the original's `learning_type`).
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Hash,
    Serialize,
    Deserialize,
    strum::IntoStaticStr,
    strum::EnumIter,
    strum::VariantNames,
)]
pub enum LearningType {
    /// Trained on the real robot from scratch.
    #[strum(serialize = "end2end")]
    EndToEnd,
    /// Trained in sim, evaluated on the real robot.
    #[strum(serialize = "sim2real")]
    SimToReal,
    /// From human demonstrations.
    #[strum(serialize = "humandemos")]
    HumanDemos,
}

impl LearningType {
    /// The original's string.
    pub fn as_str(self) -> &'static str {
        self.into()
    }
}

/// Train or test; test runs count for the leaderboard.
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    Hash,
    Serialize,
    Deserialize,
    strum::IntoStaticStr,
    strum::EnumIter,
    strum::VariantNames,
)]
#[strum(serialize_all = "snake_case")]
pub enum AlgorithmMode {
    /// Training.
    Train,
    /// Evaluation.
    Test,
}

impl AlgorithmMode {
    /// The original's string.
    pub fn as_str(self) -> &'static str {
        self.into()
    }
}

/// Opens a session (takes the env's lease).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OpenRequest {
    /// The user's access token (never logged; stored hashed).
    pub token: String,
    /// A per-process client id; its liveliness token marks the client alive.
    pub client_id: String,
    /// Experiment to create or resume.
    pub experiment_name: String,
    /// Continue counters of an existing experiment.
    pub resume_experiment: bool,
    /// Learning type of the experiment.
    pub learning_type: LearningType,
    /// Train or test.
    pub algorithm_mode: AlgorithmMode,
    /// Observation layout for this session.
    pub obs: ObsOptions,
}

impl OpenRequest {
    /// An anonymous training session with `obs` observations (sim envs that
    /// allow anonymous access); set the other fields as needed.
    pub fn anonymous(obs: ObsOptions) -> Self {
        Self {
            token: String::new(),
            client_id: String::new(),
            experiment_name: String::new(),
            resume_experiment: false,
            learning_type: LearningType::EndToEnd,
            algorithm_mode: AlgorithmMode::Train,
            obs,
        }
    }
}

/// Counters of an experiment.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ExperimentInfo {
    /// Store id.
    pub id: i64,
    /// Name given by the user.
    pub name: String,
    /// Episodes completed so far.
    pub episodes: u64,
    /// Steps taken so far.
    pub steps: u64,
}

/// The session is open; the caller holds the lease.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OpenReply {
    /// Pass in every later request.
    pub session_id: String,
    /// Lease expiry if idle, Unix ms.
    pub lease_until_unix_ms: i64,
    /// The env's spec.
    pub spec: EnvSpec,
    /// The experiment's counters.
    pub experiment: ExperimentInfo,
}

/// An action, checked by the server (never silently clipped).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Action {
    /// Index into the discrete action table.
    Discrete(i64),
    /// [linear, angular] in [−1, 1], mapped to the physical range.
    Continuous(Vec<f32>),
}

/// Take one step.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StepRequest {
    /// From [`OpenReply`].
    pub session_id: String,
    /// Client's step counter, echoed.
    pub seq: u64,
    /// What to do.
    pub action: Action,
}

/// Episode bookkeeping returned with every reset and step. The robot's
/// ground truth is in it only where the env's rules share it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StepInfo {
    /// Episode id within the experiment.
    pub episode_id: u64,
    /// Steps taken in this episode.
    pub step: u32,
    /// This step reached the monolith.
    pub is_success: bool,
    /// Why the episode ended with this step (`success`, `out_of_bounds`,
    /// `step_limit`); empty while it runs.
    pub end_reason: String,
    /// Whether `x`, `y`, `yaw` and `distance_to_goal` hold the robot's
    /// ground truth: always on sim envs; on real envs only where the site's
    /// operator allows it (privileged information: an agent meant to learn
    /// from the camera must not lean on it). Zero when not shared.
    pub pose_shared: bool,
    /// Robot position in the world frame, m.
    pub x: f64,
    /// Robot position in the world frame, m.
    pub y: f64,
    /// Robot heading in the world frame, rad.
    pub yaw: f64,
    /// Distance from the robot to the monolith's centre, m.
    pub distance_to_goal: f64,
}

/// The outcome of a step.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StepReply {
    /// Echo of the request's `seq`.
    pub seq: u64,
    /// Reward for this step.
    pub reward: f64,
    /// Episode ended by the task (success or out of bounds).
    pub terminated: bool,
    /// Episode cut at the step limit.
    pub truncated: bool,
    /// Counters.
    pub info: StepInfo,
    /// Observation after the action. Last on the wire, its pixels last of
    /// all, so a server writes them straight into the payload
    /// ([`crate::codec::encode_with_tail`]).
    pub observation: ObsArray,
}

/// How to seed a reset (CDR has no `Option`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Seed {
    /// Continue the env's RNG stream.
    Continue,
    /// Reseed: the episode becomes reproducible (in sim).
    Fixed(u64),
}

/// Start a new episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ResetRequest {
    /// From [`OpenReply`].
    pub session_id: String,
    /// Seed for the spawn sampler.
    pub seed: Seed,
}

/// The first observation of the new episode.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ResetReply {
    /// Counters (step = 0).
    pub info: StepInfo,
    /// Observation after arrival at the spawn pose (last, as in [`StepReply`]).
    pub observation: ObsArray,
}

/// Release the lease.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CloseRequest {
    /// From [`OpenReply`].
    pub session_id: String,
}

/// The lease is released.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct CloseReply {
    /// The experiment's final counters.
    pub experiment: ExperimentInfo,
}

/// An action space.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum ActionSpace {
    /// `Discrete(n)`.
    Discrete {
        /// Number of actions.
        n: u32,
        /// Their names, index order.
        names: Vec<String>,
    },
    /// `Box(low, high)` of float32.
    Box {
        /// Lower bounds.
        low: Vec<f32>,
        /// Upper bounds.
        high: Vec<f32>,
    },
}

/// An env's description.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EnvSpec {
    /// `sim/monolith-0` etc.
    pub env_id: String,
    /// Task name, e.g. `MonolithDiscrete`.
    pub task: String,
    /// World name, e.g. `monolith` or `monolith_obstacle`.
    pub world: String,
    /// Action space.
    pub action_space: ActionSpace,
    /// Native camera rows.
    pub native_height: u32,
    /// Native camera columns.
    pub native_width: u32,
    /// Depth range mapped onto 0–255 for `DepthFormat::Uint8`, m.
    pub depth_max_m: f32,
    /// Steps before truncation.
    pub max_episode_steps: u32,
}

/// One step's result as published for spectators and monitors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeEvent {
    /// Experiment name.
    pub experiment: String,
    /// Episode id.
    pub episode_id: u64,
    /// Step within the episode (0 = reset).
    pub step: u32,
    /// Reward of this step.
    pub reward: f64,
    /// Return so far.
    pub episode_return: f64,
    /// Terminated flag.
    pub terminated: bool,
    /// Truncated flag.
    pub truncated: bool,
    /// Reached the monolith.
    pub success: bool,
    /// Why the episode ended ("" while running).
    pub end_reason: String,
    /// The experiment's store id (the `exp-NNNNNN` of its recordings).
    pub experiment_id: i64,
    /// The `seq` of the [`crate::msg::MotionCommand`] whose `CameraFrame`
    /// is this step's observation (the reset's observing command for step
    /// 0): pairs the event with its frame, pose and command.
    pub command_seq: u64,
}

/// Availability of an env.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum EnvState {
    /// Anyone may open a session.
    Free,
    /// Someone holds the lease.
    Leased {
        /// Lease expiry if idle, Unix ms.
        until_unix_ms: i64,
        /// Who holds it: the user's name (`anonymous` where anonymous
        /// sessions are allowed).
        holder: String,
    },
    /// An operator took the env out of service.
    Maintenance {
        /// Operator's message.
        message: String,
        /// The operator's user name.
        by: String,
        /// When the operator expects it back, Unix ms; 0: not said.
        back_unix_ms: i64,
    },
    /// The robot, tracker or twin is not answering.
    Offline {
        /// What is missing.
        reason: String,
    },
}

/// Status of one env, published on change and served on `status`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EnvStatus {
    /// `sim/monolith-0` etc.
    pub env_id: String,
    /// Current state.
    pub state: EnvState,
    /// The e-stop latches that apply (site and env): motion is refused
    /// while either is engaged, whatever `state` says.
    pub estop: super::EStopState,
    /// How well the env's last reset put the robot where it was asked.
    pub last_reset: ResetAccuracy,
}

/// How well a reset put the robot at its spawn pose: on a real robot the
/// reset is a drive, and where it ends is part of the episode's truth.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct ResetAccuracy {
    /// The other fields hold a measurement: false before an env's first
    /// reset, and for episodes stored before resets were timed (their
    /// poses are still filled in, their duration is 0).
    pub measured: bool,
    /// The spawn pose the reset asked for (world frame).
    pub requested: super::Pose2D,
    /// The pose the episode started from (the first observation's).
    pub achieved: super::Pose2D,
    /// Planar distance between the two, m.
    pub position_error_m: f64,
    /// Absolute heading difference, wrapped to [0, π], rad.
    pub yaw_error_rad: f64,
    /// From the reset request to its first observation, s.
    pub duration_s: f64,
    /// When the reset ended, Unix ms.
    pub unix_ms: i64,
}

impl ResetAccuracy {
    /// A reset that asked for `requested`, started from `achieved` and
    /// took `duration_s`, ending at `unix_ms`.
    pub fn measure(
        requested: super::Pose2D,
        achieved: super::Pose2D,
        duration_s: f64,
        unix_ms: i64,
    ) -> Self {
        let turn = (achieved.yaw - requested.yaw).rem_euclid(std::f64::consts::TAU);
        Self {
            measured: true,
            requested,
            achieved,
            position_error_m: (achieved.x - requested.x).hypot(achieved.y - requested.y),
            yaw_error_rad: turn.min(std::f64::consts::TAU - turn),
            duration_s,
            unix_ms,
        }
    }
}

/// Operator commands, and who a token is (answered with an
/// [`AdminReply`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum AdminRequest {
    /// Take the env out of service (its lease and episode end).
    SetMaintenance {
        /// Operator token.
        token: String,
        /// Shown to users.
        message: String,
        /// When the env is expected back, Unix ms; 0: not said.
        back_unix_ms: i64,
    },
    /// Put it back in service.
    ClearMaintenance {
        /// Operator token.
        token: String,
    },
    /// End the current lease: the robot stops, the episode is recorded as
    /// aborted, and the holder's next request learns why.
    RevokeLease {
        /// Operator token.
        token: String,
        /// Told to the holder.
        reason: String,
    },
    /// Who `token` is (any user's token; changes nothing): how a service
    /// acting for users (the lab's web page) learns a user's name and role.
    Identify {
        /// The user's token.
        token: String,
    },
}

impl AdminRequest {
    /// The token the request carries.
    pub fn token(&self) -> &str {
        match self {
            Self::SetMaintenance { token, .. }
            | Self::ClearMaintenance { token }
            | Self::RevokeLease { token, .. }
            | Self::Identify { token } => token,
        }
    }
}

/// The answer to an [`AdminRequest`]: who asked, and the env's status
/// after the request.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AdminReply {
    /// The token's user name.
    pub user: String,
    /// Whether that user is an operator.
    pub operator: bool,
    /// The env's status after the request.
    pub status: EnvStatus,
}

/// One ranked experiment (test mode only).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LeaderboardEntry {
    /// Experiment name.
    pub experiment: String,
    /// Owner's user name.
    pub user: String,
    /// Learning type string (`end2end`, …).
    pub learning_type: String,
    /// Episodes evaluated.
    pub episodes: u64,
    /// Fraction of episodes that reached the monolith.
    pub success_rate: f64,
    /// Mean episode return.
    pub mean_return: f64,
}

/// Test-mode experiments of one env, best first (success rate, then mean return).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Leaderboard {
    /// `sim/monolith-0` etc.
    pub env_id: String,
    /// Ranked entries.
    pub entries: Vec<LeaderboardEntry>,
}

/// A reserved time slot on an env: during it only its holder may take the
/// lease.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Booking {
    /// Store id (cancel by it).
    pub id: i64,
    /// `real/enclosure-a` etc.
    pub env_id: String,
    /// Holder's user name.
    pub user: String,
    /// Slot start, Unix ms.
    pub start_unix_ms: i64,
    /// Slot end (exclusive), Unix ms.
    pub end_unix_ms: i64,
}

/// Bookings of one env: make, list, cancel.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum BookingRequest {
    /// Reserve `[start, end)`; refused (409) if it overlaps another slot.
    Make {
        /// The user's access token.
        token: String,
        /// Unix ms.
        start_unix_ms: i64,
        /// Unix ms.
        end_unix_ms: i64,
    },
    /// Slots that end after `from_unix_ms`, earliest first.
    List {
        /// Unix ms.
        from_unix_ms: i64,
    },
    /// Cancel one of your slots (operators: any slot).
    Cancel {
        /// The user's access token.
        token: String,
        /// [`Booking::id`].
        id: i64,
    },
}

/// Answer to a [`BookingRequest`]: the slot made, or the slots listed or
/// remaining after a cancel.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Bookings {
    /// Earliest first.
    pub bookings: Vec<Booking>,
}

/// An env's experiments, asked by their owner (operators: anyone's). The
/// same records `env_controller experiments` prints on the controller host.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum ExperimentsRequest {
    /// The caller's experiments on the env (operators: everyone's), most
    /// recently used first; no episodes.
    List {
        /// The user's access token (empty: anonymous, where allowed).
        token: String,
    },
    /// One experiment with its episodes from index `from_episode` on, at
    /// most [`EXPERIMENT_EPISODES_PER_REPLY`] of them, and their recordings.
    Show {
        /// The user's access token (empty: anonymous, where allowed).
        token: String,
        /// [`ExperimentRecord::id`].
        experiment_id: i64,
        /// The first episode index wanted (0: from the start).
        from_episode: u64,
    },
}

/// Most episodes in one [`Experiments`] answer; ask again from the next
/// index for more.
pub const EXPERIMENT_EPISODES_PER_REPLY: u32 = 1000;

/// Most experiments in one `List` answer (most recently used first).
pub const EXPERIMENTS_PER_REPLY: u32 = 1000;

/// One experiment as listed.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ExperimentRecord {
    /// Store id.
    pub id: i64,
    /// Owner's user name.
    pub user: String,
    /// `sim/monolith-0` etc.
    pub env_id: String,
    /// Task name (`MonolithDiscrete`, …).
    pub task: String,
    /// Name given by the user.
    pub name: String,
    /// Learning type string (`end2end`, `sim2real`, `humandemos`).
    pub learning_type: String,
    /// `train` or `test`.
    pub algorithm_mode: String,
    /// Episodes finished.
    pub episodes: u64,
    /// Steps in finished episodes.
    pub steps: u64,
    /// Created, Unix ms.
    pub created_unix_ms: i64,
    /// Last used, Unix ms.
    pub updated_unix_ms: i64,
}

/// One recorded episode file of an experiment.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct RecordingFile {
    /// Relative to the controller's recording directory (`serve --record`),
    /// `/`-separated: `sim/monolith-0/exp-000001/ep-000000.mcap`.
    pub path: String,
    /// Size, bytes.
    pub bytes: u64,
    /// False for a `.partial` file: its episode was cut short by a crash
    /// (`recorder recover` makes it a finished file).
    pub complete: bool,
}

/// One episode of an experiment.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeRecordEntry {
    /// Episode index within the experiment.
    pub index: u64,
    /// Whether reset was given a seed, and which.
    pub seeded: bool,
    /// The seed (0 when not seeded).
    pub seed: u64,
    /// Steps taken.
    pub steps: u32,
    /// Sum of rewards.
    pub episode_return: f64,
    /// Reached the monolith.
    pub success: bool,
    /// Why it ended (`success`, `out_of_bounds`, `step_limit`, `aborted: …`,
    /// `in_progress`).
    pub end_reason: String,
    /// Unix ms.
    pub started_unix_ms: i64,
    /// Unix ms (the start while in progress).
    pub ended_unix_ms: i64,
    /// How well its reset put the robot at its spawn pose.
    pub reset: ResetAccuracy,
    /// Its recordings (none when the env does not record).
    pub recordings: Vec<RecordingFile>,
}

/// Answer to an [`ExperimentsRequest`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Experiments {
    /// `List`: the experiments; `Show`: the one asked for.
    pub experiments: Vec<ExperimentRecord>,
    /// `Show`: its episodes in order, from the index asked for; `List`: empty.
    pub episodes: Vec<EpisodeRecordEntry>,
    /// `Show`: more episodes follow the last one here.
    pub more: bool,
}

/// Who asks: attached (as the Zenoh attachment) to every gym request that
/// [`crate::client`] sends, so the controller can hold each client to its
/// share (requests queued per env, requests per second). A request without
/// it counts as the shared `anonymous` client. Not a credential: the token
/// in the request is.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClientTag {
    /// 1 to 64 characters of `A-Z a-z 0-9 _ -` (the rule of a key chunk).
    pub client_id: String,
}

impl crate::codec::ByteTail for StepReply {
    fn tail_mut(&mut self) -> &mut Vec<u8> {
        &mut self.observation.data
    }
}

impl crate::codec::ByteTail for ResetReply {
    fn tail_mut(&mut self) -> &mut Vec<u8> {
        &mut self.observation.data
    }
}
