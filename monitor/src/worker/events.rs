//! Episode events, tracking, status, e-stops, liveliness and the
//! monitor's own health, as scalars and text logs.

use super::*;
use rerun::TextLogLevel;

const DEBUG: &str = TextLogLevel::DEBUG;
const INFO: &str = TextLogLevel::INFO;
const WARN: &str = TextLogLevel::WARN;
const ERROR: &str = TextLogLevel::ERROR;

impl Worker {
    pub(super) fn on_reward(
        &mut self,
        env: &EnvId,
        sample: &Sample,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let event: EpisodeEvent = codec::decode_payload(sample.payload())?;
        self.maybe_retry_world(env);
        self.log_episode_event(env, &event, None, wall)
    }

    /// An episode's reset or step (`reward`, or a recording's
    /// `/offworld/step`): reward and return, episode start and end, the
    /// trajectory restarted at a reset. At the env's current step; on
    /// `sim_time` too when `stamp` is given (the step's frame).
    pub fn log_episode_event(
        &mut self,
        env: &EnvId,
        event: &EpisodeEvent,
        stamp: Option<&Time>,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let view = self.view(env);
        let step = view.seq;
        let new_episode = event.step == 0 || view.episode != Some(event.episode_id);
        view.episode = Some(event.episode_id);
        if event.step == 0 {
            // The reset's pose is this episode's first point.
            view.trajectory.clear();
            if let Some(p) = view.last_pose {
                view.trajectory.push([p.x as f32, p.y as f32, p.z as f32]);
            }
        }
        let ended = event.terminated || event.truncated;
        let strip = (event.step == 0 || (ended && view.trajectory_dirty)).then(|| {
            view.trajectory_dirty = false;
            view.trajectory_logged = Some(wall);
            view.trajectory.clone()
        });
        let stamp = Self::stamp(step, stamp, wall);
        if event.step == 0 {
            self.anchor_odom(env, stamp);
        }
        if let Some(strip) = strip {
            self.row(env, paths::TRAJECTORY, stamp, Row::Trajectory(strip));
        }
        self.row(env, paths::REWARD, stamp, Row::Scalar(event.reward));
        self.row(env, paths::RETURN, stamp, Row::Scalar(event.episode_return));
        if new_episode {
            let experiment = if event.experiment.is_empty() {
                String::new()
            } else {
                format!(" ({})", event.experiment)
            };
            let text = format!("episode {} started{experiment}", event.episode_id);
            self.row(env, paths::EVENTS, stamp, Row::Text(text, INFO));
        }
        if ended {
            let success = if event.success { 1.0 } else { 0.0 };
            self.row(env, paths::SUCCESS, stamp, Row::Scalar(success));
            let length = f64::from(event.step);
            self.row(env, paths::EPISODE_LENGTH, stamp, Row::Scalar(length));
            let how = if event.end_reason.is_empty() {
                if event.truncated {
                    "truncated"
                } else {
                    "terminated"
                }
            } else {
                event.end_reason.as_str()
            };
            self.log_end_text(env, event, how, stamp);
        }
        self.count(&self.shared.counters.rewards);
        Ok(())
    }

    /// An episode that ended without a terminal step (a reset or a close
    /// came first, or its recording stopped), as a recording's
    /// `/offworld/episode_end` tells: the event log only (success and
    /// length are for episodes that terminated or were truncated). `last`
    /// is its last step, `how` why it ended.
    pub fn log_episode_stopped(
        &mut self,
        env: &EnvId,
        last: &EpisodeEvent,
        how: &str,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let step = self.view(env).seq;
        self.log_end_text(env, last, how, Self::stamp(step, None, wall));
        Ok(())
    }

    /// "episode … ended after … steps" in the env's event log.
    pub(super) fn log_end_text(
        &mut self,
        env: &EnvId,
        last: &EpisodeEvent,
        how: &str,
        stamp: Stamp,
    ) {
        let text = format!(
            "episode {} ended after {} steps: {how} (return {:.3}{})",
            last.episode_id,
            last.step,
            last.episode_return,
            if last.success { ", success" } else { "" }
        );
        let level = if last.success { INFO } else { WARN };
        self.row(env, paths::EVENTS, stamp, Row::Text(text, level));
    }

    pub(super) fn on_tracking(
        &mut self,
        env: &EnvId,
        sample: &Sample,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let status: TrackingStatus = codec::decode_payload(sample.payload())?;
        let view = self.view(env);
        let step = view.seq;
        if view.tracking == Some(status.tracking) {
            return Ok(());
        }
        view.tracking = Some(status.tracking);
        let text = if status.tracking {
            Row::Text("tracking ok".to_owned(), INFO)
        } else {
            Row::Text(format!("tracking lost: {}", status.reason), WARN)
        };
        self.row(env, paths::EVENTS, Self::stamp(step, None, wall), text);
        Ok(())
    }

    pub(super) fn on_status(
        &mut self,
        env: &EnvId,
        sample: &Sample,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let status: EnvStatus = codec::decode_payload(sample.payload())?;
        self.count(&self.shared.counters.statuses);
        self.maybe_retry_world(env);
        let view = self.view(env);
        let step = view.seq;
        let reset = status.last_reset;
        let stamp = Self::stamp(step, None, wall);
        if reset.measured && view.last_reset_ms != Some(reset.unix_ms) {
            view.last_reset_ms = Some(reset.unix_ms);
            for (path, value) in [
                (paths::RESET_POSITION_ERROR, reset.position_error_m),
                (paths::RESET_YAW_ERROR, reset.yaw_error_rad),
                (paths::RESET_DURATION, reset.duration_s),
            ] {
                self.row(env, path, stamp, Row::Scalar(value));
            }
        }
        let view = self.view(env);
        if view
            .status
            .as_ref()
            .is_some_and(|s| same_status_kind(s, &status.state))
        {
            return Ok(());
        }
        let level = match status.state {
            EnvState::Free | EnvState::Leased { .. } => INFO,
            EnvState::Maintenance { .. } | EnvState::Offline { .. } => WARN,
        };
        let text = status_text(&status.state);
        view.status = Some(status.state);
        self.row(env, paths::EVENTS, stamp, Row::Text(text, level));
        Ok(())
    }

    /// An e-stop's press or release, as a line of the event log at `path`,
    /// sent at once with every row pending (an operator watches for it; it
    /// is rare).
    pub(super) fn estop_log(&mut self, path: String, stamp: Stamp, stop: &EStop) {
        let row = if stop.engaged {
            Row::Text(format!("e-stop engaged: {}", stop.reason), ERROR)
        } else {
            Row::Text(format!("e-stop released: {}", stop.reason), INFO)
        };
        self.columns.push(path, stamp, row);
        self.flush_columns();
    }

    pub(super) fn on_env_estop(
        &mut self,
        env: &EnvId,
        sample: &Sample,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let stop: EStop = codec::decode_payload(sample.payload())?;
        let view = self.view(env);
        let step = view.seq;
        if !view.env_latch.applies(Latch::Env, &stop, wall) || view.estop == Some(stop.engaged) {
            return Ok(());
        }
        view.estop = Some(stop.engaged);
        let stamp = Self::stamp(step, None, wall);
        self.estop_log(env_path(env, paths::EVENTS), stamp, &stop);
        Ok(())
    }

    pub(super) fn on_site_estop(&mut self, sample: &Sample, wall: SystemTime) -> Result<(), Skip> {
        let stop: EStop = codec::decode_payload(sample.payload())?;
        if !self.site_latch.applies(Latch::Site, &stop, wall)
            || self.site_estop == Some(stop.engaged)
        {
            return Ok(());
        }
        self.site_estop = Some(stop.engaged);
        let stamp = Self::stamp(None, None, wall);
        self.estop_log(paths::SITE_EVENTS.to_owned(), stamp, &stop);
        Ok(())
    }

    pub(super) fn on_alive(
        &mut self,
        key: &str,
        online: bool,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let Ok(env) = EnvId::from_key(key) else {
            return Err(Skip::Decode(format!("`{key}` is not an env key")));
        };
        let component = key.splitn(6, '/').nth(5).unwrap_or(key).to_owned();
        if online && component == "controller" {
            self.maybe_retry_world(&env);
        }
        let step = self.view(&env).seq;
        let text = format!("{component} {}", if online { "online" } else { "offline" });
        let level = if online { DEBUG } else { WARN };
        let stamp = Self::stamp(step, None, wall);
        self.row(&env, paths::EVENTS, stamp, Row::Text(text, level));
        Ok(())
    }

    /// The monitor's own counters, as rows (flushed with the others).
    pub(super) fn log_health(&mut self) {
        self.last_health = Some(Instant::now());
        let stats = self.shared.stats();
        let stamp = Self::stamp(None, None, SystemTime::now());
        for (path, value) in [
            (paths::MONITOR_DROPPED_FRAMES, stats.dropped_frames),
            (paths::MONITOR_DROPPED_MESSAGES, stats.dropped_messages),
            (paths::MONITOR_DECODE_ERRORS, stats.decode_errors),
        ] {
            self.columns
                .push(path.to_owned(), stamp, Row::Scalar(value as f64));
        }
    }
}

pub(super) fn status_text(state: &EnvState) -> String {
    match state {
        EnvState::Free => "status: free".into(),
        EnvState::Leased { .. } => "status: leased".into(),
        EnvState::Maintenance { message, by, .. } => {
            format!("status: maintenance by {by} ({message})")
        }
        EnvState::Offline { reason } => format!("status: offline ({reason})"),
    }
}

pub(super) fn same_status_kind(a: &EnvState, b: &EnvState) -> bool {
    match (a, b) {
        // A lease renewal is not news.
        (EnvState::Leased { .. }, EnvState::Leased { .. }) => true,
        _ => a == b,
    }
}
