//! What the web service shows, as data: the JSON of `/api/envs` and the
//! input of the HTML pages. Field names are part of the public API
//! (documented in `docs/web.md`): add fields, never rename one.

use offworld_runtime::keys::EnvId;
use offworld_runtime::msg::{
    Booking, EStopState, EnvState, EnvStatus, LatchState, Leaderboard, LeaderboardEntry,
    ResetAccuracy, Time,
};
use serde::Serialize;

/// Every env and the deployment's health at one moment.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct Snapshot {
    /// When this snapshot was made, Unix ms.
    pub generated_unix_ms: i64,
    /// Whether the deployment answers.
    pub deployment: DeploymentView,
    /// Every env ever seen through this service, sorted by id.
    pub envs: Vec<EnvView>,
}

impl Snapshot {
    /// The env `id`, if known.
    pub fn env(&self, id: &EnvId) -> Option<&EnvView> {
        let id = id.to_string();
        self.envs.iter().find(|e| e.id == id)
    }
}

/// Whether the web service reaches the deployment.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct DeploymentView {
    /// The last sweep reached the deployment (false before the first).
    pub reachable: bool,
    /// Why not, when not reachable after a sweep.
    pub message: Option<String>,
    /// When envs were last listed, Unix ms (null before the first sweep).
    pub last_sweep_unix_ms: Option<i64>,
}

/// The one-word state of an env, most urgent first: an offline env's
/// other fields are stale, and an e-stop stops a leased env too.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, strum::IntoStaticStr)]
#[serde(rename_all = "snake_case")]
#[strum(serialize_all = "snake_case")]
pub enum StateKind {
    /// No controller answers for it, or its robot or twin is missing.
    Offline,
    /// The site's or the env's e-stop is engaged: motion is refused.
    Estopped,
    /// An operator took it out of service.
    Maintenance,
    /// Someone holds its lease.
    Leased,
    /// Anyone may open a session.
    Free,
}

impl StateKind {
    /// The JSON and CSS name.
    pub fn as_str(self) -> &'static str {
        self.into()
    }
}

/// One env.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EnvView {
    /// `sim/monolith-0`.
    pub id: String,
    /// `sim` or `real`.
    pub realm: String,
    /// `monolith-0`.
    pub name: String,
    /// `MonolithDiscrete`; null until its controller answered.
    pub task: Option<String>,
    /// See [`StateKind`].
    pub state: StateKind,
    /// While leased.
    pub lease: Option<LeaseView>,
    /// While in maintenance.
    pub maintenance: Option<MaintenanceView>,
    /// While offline.
    pub offline: Option<OfflineView>,
    /// The e-stop latches that apply to it.
    pub estop: EStopView,
    /// The booked slot in progress or next, if any.
    pub next_booking: Option<BookingView>,
    /// Components alive under it (`controller`, `sim_twin`, …), sorted.
    pub components: Vec<String>,
    /// When anything was last heard from it, Unix ms.
    pub last_seen_unix_ms: Option<i64>,
    /// How well its last reset put the robot at its spawn pose.
    pub last_reset: Option<ResetView>,
    /// The last command its robot or twin refused or could not answer.
    pub last_fault: Option<FaultView>,
    /// The tracker's last word on localisation (real envs; null until it
    /// publishes one).
    pub tracking: Option<TrackingView>,
}

/// A lease.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LeaseView {
    /// Who holds it (the user's name); null until the controller's
    /// status says.
    pub holder: Option<String>,
    /// When it lapses if left idle, Unix ms (each request renews it).
    pub until_unix_ms: i64,
}

/// Maintenance.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MaintenanceView {
    /// The operator's message.
    pub message: String,
    /// The operator's user name.
    pub by: String,
    /// When the operator expects the env back, Unix ms (null: not said).
    pub back_unix_ms: Option<i64>,
}

/// Why an env is offline.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OfflineView {
    /// What is missing.
    pub reason: String,
}

/// The e-stop latches of one env.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct EStopView {
    /// Either latch is engaged.
    pub engaged: bool,
    /// `none`, `site`, `env` or `site+env`.
    pub scope: String,
    /// The site-wide latch.
    pub site: LatchView,
    /// The env's own latch.
    pub env: LatchView,
}

/// One e-stop latch.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct LatchView {
    /// Motion refused while true.
    pub engaged: bool,
    /// The operator's reason of the last change.
    pub reason: String,
    /// When it last changed, Unix ms (null: never).
    pub changed_unix_ms: Option<i64>,
}

/// A booked slot.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BookingView {
    /// Holder's user name.
    pub user: String,
    /// Slot start, Unix ms.
    pub start_unix_ms: i64,
    /// Slot end (exclusive), Unix ms.
    pub end_unix_ms: i64,
}

/// A reset's accuracy.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ResetView {
    /// Planar distance between the requested and the achieved pose, m.
    pub position_error_m: f64,
    /// Heading difference, rad.
    pub yaw_error_rad: f64,
    /// From the request to the first observation, s.
    pub duration_s: f64,
    /// When the reset ended, Unix ms.
    pub unix_ms: i64,
}

/// A fault.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FaultView {
    /// Why the command was not answered.
    pub reason: String,
    /// When this service received it, Unix ms.
    pub unix_ms: i64,
}

/// Whether the robot is localised (a change of the tracker's status).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TrackingView {
    /// Poses arrive and are accepted: episodes can be scored.
    pub ok: bool,
    /// Age of the last accepted pose when it was said, s.
    pub last_pose_age_s: f64,
    /// The tracker's reason (empty when ok).
    pub reason: String,
    /// When this service received it, Unix ms.
    pub unix_ms: i64,
}

/// One env's leaderboard, best first.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LeaderboardView {
    /// `sim/monolith-0`.
    pub env: String,
    /// Ranked entries.
    pub entries: Vec<LeaderboardRow>,
}

/// One experiment on a leaderboard.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LeaderboardRow {
    /// 1 for the best.
    pub rank: usize,
    /// The controller's entry, its fields side by side with `rank` in JSON.
    #[serde(flatten)]
    pub entry: LeaderboardEntry,
}

impl From<Leaderboard> for LeaderboardView {
    fn from(board: Leaderboard) -> Self {
        Self {
            env: board.env_id,
            entries: board
                .entries
                .into_iter()
                .enumerate()
                .map(|(i, entry)| LeaderboardRow { rank: i + 1, entry })
                .collect(),
        }
    }
}

fn unix_ms(time: &Time) -> Option<i64> {
    let ms = i64::from(time.sec) * 1000 + i64::from(time.nanosec / 1_000_000);
    (ms != 0).then_some(ms)
}

impl From<&LatchState> for LatchView {
    fn from(latch: &LatchState) -> Self {
        Self {
            engaged: latch.engaged,
            reason: latch.reason.clone(),
            changed_unix_ms: unix_ms(&latch.changed),
        }
    }
}

impl From<&EStopState> for EStopView {
    fn from(estop: &EStopState) -> Self {
        Self {
            engaged: estop.site.engaged || estop.env.engaged,
            scope: estop.summary().to_owned(),
            site: (&estop.site).into(),
            env: (&estop.env).into(),
        }
    }
}

impl From<&Booking> for BookingView {
    fn from(b: &Booking) -> Self {
        Self {
            user: b.user.clone(),
            start_unix_ms: b.start_unix_ms,
            end_unix_ms: b.end_unix_ms,
        }
    }
}

fn reset_view(reset: &ResetAccuracy) -> Option<ResetView> {
    reset.measured.then_some(ResetView {
        position_error_m: reset.position_error_m,
        yaw_error_rad: reset.yaw_error_rad,
        duration_s: reset.duration_s,
        unix_ms: reset.unix_ms,
    })
}

impl EnvView {
    /// An env known by id only (nothing heard yet): offline until its
    /// controller answers.
    pub fn new(env: &EnvId) -> Self {
        let mut view = Self {
            id: env.to_string(),
            realm: env.realm().as_str().to_owned(),
            name: env.name().to_owned(),
            task: None,
            state: StateKind::Offline,
            lease: None,
            maintenance: None,
            offline: None,
            estop: EStopView::from(&EStopState::default()),
            next_booking: None,
            components: Vec::new(),
            last_seen_unix_ms: None,
            last_reset: None,
            last_fault: None,
            tracking: None,
        };
        view.set_offline("not heard from yet");
        view
    }

    /// Applies a status its controller published or answered.
    pub fn apply_status(&mut self, status: &EnvStatus) {
        self.estop = (&status.estop).into();
        if let Some(reset) = reset_view(&status.last_reset) {
            self.last_reset = Some(reset);
        }
        self.apply_state(&status.state);
    }

    /// Applies the controller's availability (or discovery's verdict).
    pub fn apply_state(&mut self, state: &EnvState) {
        self.lease = None;
        self.maintenance = None;
        self.offline = None;
        match state {
            EnvState::Free => {}
            EnvState::Leased {
                until_unix_ms,
                holder,
            } => {
                self.lease = Some(LeaseView {
                    holder: Some(holder.clone()),
                    until_unix_ms: *until_unix_ms,
                })
            }
            EnvState::Maintenance {
                message,
                by,
                back_unix_ms,
            } => {
                self.maintenance = Some(MaintenanceView {
                    message: message.clone(),
                    by: by.clone(),
                    back_unix_ms: (*back_unix_ms > 0).then_some(*back_unix_ms),
                })
            }
            EnvState::Offline { reason } => {
                self.offline = Some(OfflineView {
                    reason: reason.clone(),
                })
            }
        }
        self.state = self.derived_state();
    }

    /// Marks the env offline for `reason` (its controller's state unknown).
    pub fn set_offline(&mut self, reason: &str) {
        self.apply_state(&EnvState::Offline {
            reason: reason.to_owned(),
        });
    }

    fn derived_state(&self) -> StateKind {
        if self.offline.is_some() {
            StateKind::Offline
        } else if self.estop.engaged {
            StateKind::Estopped
        } else if self.maintenance.is_some() {
            StateKind::Maintenance
        } else if self.lease.is_some() {
            StateKind::Leased
        } else {
            StateKind::Free
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use offworld_runtime::msg::Pose2D;

    fn env() -> EnvId {
        EnvId::sim("m-0").expect("env id")
    }

    fn status(state: EnvState) -> EnvStatus {
        EnvStatus {
            env_id: "sim/m-0".into(),
            state,
            estop: EStopState::default(),
            last_reset: ResetAccuracy::default(),
        }
    }

    #[test]
    fn a_new_env_is_offline_until_heard() {
        let view = EnvView::new(&env());
        assert_eq!(view.state, StateKind::Offline);
        assert_eq!((view.realm.as_str(), view.name.as_str()), ("sim", "m-0"));
    }

    #[test]
    fn e_stops_outrank_leases_and_offline_outranks_e_stops() {
        let mut view = EnvView::new(&env());
        let mut leased = status(EnvState::Leased {
            until_unix_ms: 42,
            holder: "alice".into(),
        });
        view.apply_status(&leased);
        assert_eq!(view.state, StateKind::Leased);
        assert_eq!(
            view.lease,
            Some(LeaseView {
                holder: Some("alice".into()),
                until_unix_ms: 42
            })
        );
        leased.estop.site.engaged = true;
        leased.estop.site.changed = Time {
            sec: 2,
            nanosec: 5_000_000,
        };
        view.apply_status(&leased);
        assert_eq!(view.state, StateKind::Estopped);
        assert_eq!(view.estop.scope, "site");
        assert_eq!(view.estop.site.changed_unix_ms, Some(2005));
        assert!(view.lease.is_some(), "the lease is still shown");
        view.set_offline("gone");
        assert_eq!(view.state, StateKind::Offline);
        assert_eq!(view.lease, None);
    }

    #[test]
    fn a_reset_is_kept_until_a_newer_one_is_measured() {
        let mut view = EnvView::new(&env());
        let mut free = status(EnvState::Free);
        free.last_reset = ResetAccuracy::measure(
            Pose2D::default(),
            Pose2D {
                x: 3.0,
                y: 4.0,
                yaw: 0.0,
            },
            1.5,
            7,
        );
        view.apply_status(&free);
        let reset = view.last_reset.clone().expect("measured");
        assert_eq!((reset.position_error_m, reset.unix_ms), (5.0, 7));
        view.apply_status(&status(EnvState::Free));
        assert_eq!(view.last_reset, Some(reset));
    }
}
