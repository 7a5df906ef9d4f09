//! The tasks as data (`env_controller/tasks.toml` + `runtime/worlds/`):
//! action tables, limits, reward geometry. Nothing task-specific is a
//! constant in code.

use offworld_runtime::msg::{Action, ActionSpace, MotionCommand};
use offworld_runtime::WireError;
use offworld_runtime::WorldSpec;
use serde::Deserialize;

use crate::error::ControllerError;

const TASKS: &str = include_str!("../tasks.toml");

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct TaskFile {
    discrete: DiscreteActions,
    continuous: ContinuousActions,
    episode: EpisodeLimits,
    task: Vec<TaskEntry>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
struct TaskEntry {
    name: String,
    world: String,
    action: ActionKind,
}

/// Discrete or continuous control.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ActionKind {
    /// `Discrete(4)` from the action table.
    Discrete,
    /// `Box([-1, 1]^2)` scaled to the physical range.
    Continuous,
}

/// The discrete action table.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiscreteActions {
    /// Names, index order.
    pub names: Vec<String>,
    /// `[linear, angular, duration]` per action.
    pub table: Vec<[f64; 3]>,
}

/// The continuous action mapping.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ContinuousActions {
    /// |linear| at action ±1, m/s.
    pub max_linear: f64,
    /// |angular| at action ±1, rad/s.
    pub max_angular: f64,
    /// How long each action is held, s.
    pub hold_s: f64,
}

/// Episode limits.
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EpisodeLimits {
    /// Truncation step count.
    pub max_steps: u32,
    /// Depth range of uint8 observations, m.
    pub depth_max_m: f32,
}

/// One task, fully resolved.
#[derive(Debug, Clone, PartialEq)]
pub struct Task {
    /// `MonolithDiscrete`, …
    pub name: String,
    /// The world it runs in.
    pub world: WorldSpec,
    /// Control type.
    pub action: ActionKind,
    /// Discrete table.
    pub discrete: DiscreteActions,
    /// Continuous mapping.
    pub continuous: ContinuousActions,
    /// Limits.
    pub episode: EpisodeLimits,
}

impl Task {
    /// Names of all tasks.
    pub fn names() -> Vec<String> {
        toml::from_str::<TaskFile>(TASKS)
            .map(|f| f.task.into_iter().map(|t| t.name).collect())
            .unwrap_or_default()
    }

    /// A task by name.
    pub fn by_name(name: &str) -> Result<Self, ControllerError> {
        let file: TaskFile = toml::from_str(TASKS)
            .map_err(|e| ControllerError::Config(format!("tasks.toml: {e}")))?;
        let entry = file.task.iter().find(|t| t.name == name).ok_or_else(|| {
            ControllerError::Config(format!("unknown task `{name}`; known: {:?}", Self::names()))
        })?;
        if file.discrete.names.len() != file.discrete.table.len() {
            return Err(ControllerError::Config(
                "discrete names and table differ in length".into(),
            ));
        }
        let world =
            WorldSpec::builtin(&entry.world).map_err(|e| ControllerError::Config(e.to_string()))?;
        Ok(Self {
            name: entry.name.clone(),
            world,
            action: entry.action,
            discrete: file.discrete,
            continuous: file.continuous,
            episode: file.episode,
        })
    }

    /// The gym action space.
    pub fn action_space(&self) -> ActionSpace {
        match self.action {
            ActionKind::Discrete => ActionSpace::Discrete {
                n: self.discrete.table.len() as u32,
                names: self.discrete.names.clone(),
            },
            ActionKind::Continuous => ActionSpace::Box {
                low: vec![-1.0, -1.0],
                high: vec![1.0, 1.0],
            },
        }
    }

    /// Validates an action and turns it into a motion. Out-of-range,
    /// non-finite and wrong-shape actions are errors, never clipped.
    pub fn motion(&self, action: &Action, seq: u64) -> Result<MotionCommand, WireError> {
        let (linear_x, angular_z, duration_s) = match (self.action, action) {
            (ActionKind::Discrete, Action::Discrete(i)) => {
                let row = usize::try_from(*i)
                    .ok()
                    .and_then(|i| self.discrete.table.get(i))
                    .ok_or_else(|| {
                        WireError::bad_request(format!(
                            "discrete action {i} out of range 0..{}",
                            self.discrete.table.len()
                        ))
                    })?;
                (row[0], row[1], row[2])
            }
            (ActionKind::Continuous, Action::Continuous(values)) => {
                let [linear, angular] = values[..] else {
                    return Err(WireError::bad_request(format!(
                        "continuous action must have shape (2,), got ({},)",
                        values.len()
                    )));
                };
                for (name, v) in [("linear", linear), ("angular", angular)] {
                    if !v.is_finite() {
                        return Err(WireError::bad_request(format!("{name} action is {v}")));
                    }
                    if !(-1.0..=1.0).contains(&v) {
                        return Err(WireError::bad_request(format!(
                            "{name} action {v} outside [-1, 1] (not clipped)"
                        )));
                    }
                }
                let c = &self.continuous;
                (
                    f64::from(linear) * c.max_linear,
                    f64::from(angular) * c.max_angular,
                    c.hold_s,
                )
            }
            (ActionKind::Discrete, Action::Continuous(_)) => {
                return Err(WireError::bad_request("this task takes a discrete action"))
            }
            (ActionKind::Continuous, Action::Discrete(_)) => {
                return Err(WireError::bad_request(
                    "this task takes a continuous action",
                ))
            }
        };
        Ok(MotionCommand {
            seq,
            linear_x,
            angular_z,
            duration_s,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use offworld_runtime::ErrorCode;

    #[test]
    fn all_four_tasks_resolve() {
        let names = Task::names();
        assert_eq!(names.len(), 4);
        for name in names {
            let task = Task::by_name(&name).expect("task");
            assert_eq!(task.episode.max_steps, 100);
        }
        assert!(
            Task::by_name("MonolithObstacleDiscrete")
                .expect("t")
                .world
                .boulders
                .len()
                == 14
        );
        assert!(Task::by_name("Mars").is_err());
    }

    #[test]
    fn discrete_actions_follow_the_reference_table() {
        let task = Task::by_name("MonolithDiscrete").expect("task");
        let m = |i| task.motion(&Action::Discrete(i), 1).expect("valid");
        assert_eq!(
            (m(0).linear_x, m(0).angular_z, m(0).duration_s),
            (0.07, 1.25, 1.2)
        );
        assert_eq!(
            (m(1).linear_x, m(1).angular_z, m(1).duration_s),
            (0.07, -1.25, 1.2)
        );
        assert_eq!(
            (m(2).linear_x, m(2).angular_z, m(2).duration_s),
            (0.10, 0.0, 0.6)
        );
        assert_eq!(
            (m(3).linear_x, m(3).angular_z, m(3).duration_s),
            (-0.10, 0.0, 0.6)
        );
        for bad in [-1, 4, i64::MAX] {
            let e = task
                .motion(&Action::Discrete(bad), 1)
                .expect_err("rejected");
            assert_eq!(e.code, ErrorCode::BadRequest);
        }
        let e = task
            .motion(&Action::Continuous(vec![0.0, 0.0]), 1)
            .expect_err("wrong kind");
        assert_eq!(e.code, ErrorCode::BadRequest);
    }

    #[test]
    fn continuous_actions_map_to_the_physical_range_and_are_never_clipped() {
        let task = Task::by_name("MonolithContinuous").expect("task");
        let m = task
            .motion(&Action::Continuous(vec![1.0, -0.5]), 3)
            .expect("valid");
        assert_eq!(
            (m.seq, m.linear_x, m.angular_z, m.duration_s),
            (3, 0.7, -1.25, 1.0)
        );
        let m = task
            .motion(&Action::Continuous(vec![-1.0, 1.0]), 3)
            .expect("valid");
        assert_eq!((m.linear_x, m.angular_z), (-0.7, 2.5));
        for bad in [
            vec![1.01, 0.0],
            vec![0.0, -1.5],
            vec![f32::NAN, 0.0],
            vec![0.0, f32::INFINITY],
            vec![0.0],
            vec![0.0, 0.0, 0.0],
            vec![],
        ] {
            let e = task
                .motion(&Action::Continuous(bad.clone()), 1)
                .expect_err("rejected");
            assert_eq!(e.code, ErrorCode::BadRequest, "{bad:?}");
        }
    }
}
