//! Our own recorded message types (`offworld_msgs/msg/*`), field for field
//! as their `.msg` files in `recorder/msg/offworld_msgs/msg/` define them,
//! so the CDR the runtime's codec writes is what the schemas describe.

use offworld_runtime::msg::{Action, EpisodeEvent, Header, MotionCommand};
use serde::{Deserialize, Serialize};

/// `offworld_msgs/msg/Step`: one gym transition as the controller answered
/// it (step 0 is the reset).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Step {
    /// Stamp: when the step's camera frame was captured.
    pub header: Header,
    /// The episode's index in its experiment.
    pub episode_id: u64,
    /// 0 = the reset, then 1, 2, …
    pub step: u32,
    /// The motion command whose frame is this step's observation.
    pub command_seq: u64,
    /// Index into the task's discrete actions; −1 when continuous or the reset.
    pub action_discrete: i64,
    /// `[linear, angular]` in [−1, 1]; empty when discrete or the reset.
    pub action_continuous: Vec<f32>,
    /// Commanded linear velocity, m/s.
    pub linear_x: f64,
    /// Commanded angular velocity, rad/s.
    pub angular_z: f64,
    /// How long the velocity was held, s.
    pub duration_s: f64,
    /// The step's reward.
    pub reward: f64,
    /// Sum of the episode's rewards so far.
    pub episode_return: f64,
    /// The episode ended (success or out of bounds).
    pub terminated: bool,
    /// The episode was cut (step limit).
    pub truncated: bool,
    /// The monolith was reached.
    pub success: bool,
    /// Why the episode ended; empty while it runs.
    pub end_reason: String,
}

impl Step {
    /// The step an [`EpisodeEvent`] reports (the controller's and a
    /// subscriber's recordings build it alike): its counters and outcome,
    /// the `action` asked for (none: the reset, or unknown to a
    /// subscriber) and the `motion` commanded (none: the reset, or not
    /// received). The header is stamped from the frame when written.
    pub fn from_event(
        event: &EpisodeEvent,
        action: Option<&Action>,
        motion: Option<&MotionCommand>,
    ) -> Self {
        let (action_discrete, action_continuous) = match action {
            Some(Action::Discrete(i)) => (*i, Vec::new()),
            Some(Action::Continuous(values)) => (-1, values.clone()),
            None => (-1, Vec::new()),
        };
        Self {
            header: Header::default(),
            episode_id: event.episode_id,
            step: event.step,
            command_seq: event.command_seq,
            action_discrete,
            action_continuous,
            linear_x: motion.map_or(0.0, |m| m.linear_x),
            angular_z: motion.map_or(0.0, |m| m.angular_z),
            duration_s: motion.map_or(0.0, |m| m.duration_s),
            reward: event.reward,
            episode_return: event.episode_return,
            terminated: event.terminated,
            truncated: event.truncated,
            success: event.success,
            end_reason: event.end_reason.clone(),
        }
    }
}

/// `offworld_msgs/msg/EpisodeInfo`: what an episode file holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeInfo {
    /// Stamp: when the episode began.
    pub header: Header,
    /// `sim/monolith-0`, `real/enclosure-a`, …
    pub env_id: String,
    /// `MonolithDiscrete`, …
    pub task: String,
    /// `monolith`, `monolith_obstacle`.
    pub world: String,
    /// The experiment's row id.
    pub experiment_id: u64,
    /// The experiment's name.
    pub experiment: String,
    /// `end2end` | `sim2real` | `humandemos`.
    pub learning_type: String,
    /// `train` | `test`.
    pub algorithm_mode: String,
    /// The episode's index in its experiment.
    pub episode_id: u64,
    /// Whether the reset was seeded.
    pub seeded: bool,
    /// The reset's seed (0 when not seeded).
    pub seed: u64,
    /// `twin` | `robot`.
    pub embodiment: String,
    /// The recorder's version.
    pub software_version: String,
    /// The task's step limit.
    pub max_episode_steps: u32,
    /// `[x m, y m, yaw rad]` the reset asked for.
    pub requested_start: [f64; 3],
}

impl EpisodeInfo {
    /// The same values as strings, for the MCAP metadata record.
    pub fn metadata(&self) -> std::collections::BTreeMap<String, String> {
        let [x, y, yaw] = self.requested_start;
        [
            ("env_id", self.env_id.clone()),
            ("task", self.task.clone()),
            ("world", self.world.clone()),
            ("experiment_id", self.experiment_id.to_string()),
            ("experiment", self.experiment.clone()),
            ("learning_type", self.learning_type.clone()),
            ("algorithm_mode", self.algorithm_mode.clone()),
            ("episode_id", self.episode_id.to_string()),
            ("seeded", self.seeded.to_string()),
            ("seed", self.seed.to_string()),
            ("embodiment", self.embodiment.clone()),
            ("software_version", self.software_version.clone()),
            ("max_episode_steps", self.max_episode_steps.to_string()),
            ("requested_start", format!("{x} {y} {yaw}")),
            ("started", self.header.stamp.as_secs_f64().to_string()),
        ]
        .into_iter()
        .map(|(k, v)| (k.to_owned(), v))
        .collect()
    }
}

/// `offworld_msgs/msg/EpisodeEnd`: the last message of a file whose
/// episode ended while it was recorded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EpisodeEnd {
    /// Stamp: when the episode ended.
    pub header: Header,
    /// The episode's index in its experiment.
    pub episode_id: u64,
    /// Steps taken after the reset.
    pub steps: u32,
    /// Sum of the episode's rewards.
    pub episode_return: f64,
    /// The monolith was reached.
    pub success: bool,
    /// The episode terminated (success or out of bounds).
    pub terminated: bool,
    /// The episode was cut (step limit).
    pub truncated: bool,
    /// `success`, `out_of_bounds`, `step_limit`, `aborted: …`, `recorder_stopped: …`.
    pub end_reason: String,
}

impl EpisodeEnd {
    /// The end of episode `episode_id` for `end_reason`, now, with the
    /// counters of its `last` step (none: ended before any was recorded).
    pub fn after(episode_id: u64, last: Option<&Step>, end_reason: &str) -> Self {
        Self {
            header: Header::new(offworld_runtime::msg::Time::now(), "world"),
            episode_id,
            steps: last.map_or(0, |s| s.step),
            episode_return: last.map_or(0.0, |s| s.episode_return),
            success: last.is_some_and(|s| s.success),
            terminated: last.is_some_and(|s| s.terminated),
            truncated: last.is_some_and(|s| s.truncated),
            end_reason: end_reason.to_owned(),
        }
    }
}
