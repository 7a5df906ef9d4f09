//! Commands, tracker poses and odometry: the robot's transform, its
//! trajectory and the odometry anchored to the tracker.

use super::*;

impl Worker {
    pub(super) fn on_cmd(
        &mut self,
        env: &EnvId,
        sample: &Sample,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let cmd: MotionCommand = codec::decode_payload(sample.payload())?;
        // u64::MAX is the controller's halt: not a step of its own.
        let seq = (cmd.seq != u64::MAX).then_some(cmd.seq);
        self.log_command(env, seq, cmd.linear_x, cmd.angular_z, wall);
        Ok(())
    }

    /// Makes `seq` the env's current step: data without a seq of its own
    /// is logged at it.
    pub fn set_seq(&mut self, env: &EnvId, seq: u64) {
        self.view(env).seq = Some(seq);
    }

    /// A motion command (`cmd`, or a recording's `/cmd_vel`); `seq` (the
    /// command's) becomes the env's current step.
    pub fn log_command(
        &mut self,
        env: &EnvId,
        seq: Option<u64>,
        linear_x: f64,
        angular_z: f64,
        wall: SystemTime,
    ) {
        let view = self.view(env);
        if seq.is_some() {
            view.seq = seq;
        }
        let stamp = Self::stamp(view.seq, None, wall);
        self.columns
            .push(env_path(env, paths::LINEAR_X), stamp, Row::Scalar(linear_x));
        self.columns.push(
            env_path(env, paths::ANGULAR_Z),
            stamp,
            Row::Scalar(angular_z),
        );
        self.count(&self.shared.counters.commands);
    }

    pub(super) fn on_pose(
        &mut self,
        env: &EnvId,
        sample: &Sample,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let pose: PoseStamped = codec::decode_payload(sample.payload())?;
        let tag = wire::decode_attachment::<SeqTag>(sample).map(|t| t.seq);
        self.log_pose(env, &pose, tag, wall)
    }

    /// A tracker pose (`pose`, or a recording's `/tracker/pose`): the robot
    /// and its trajectory. At `tag`, else the env's current step.
    pub fn log_pose(
        &mut self,
        env: &EnvId,
        pose: &PoseStamped,
        tag: Option<u64>,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let p = &pose.pose.position;
        let q = &pose.pose.orientation;
        finite(&[p.x, p.y, p.z, q.x, q.y, q.z, q.w])?;
        let here = [p.x as f32, p.y as f32, p.z as f32];
        let planar = Planar {
            x: p.x,
            y: p.y,
            z: p.z,
            yaw: yaw_of(q),
        };
        let view = self.view(env);
        let step = tag.or(view.seq);
        view.last_pose = Some(planar);
        let extend = view.trajectory.last().is_none_or(|last| {
            let d = [here[0] - last[0], here[1] - last[1], here[2] - last[2]];
            (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() >= TRAJECTORY_STEP_M
        });
        if extend {
            if view.trajectory.len() >= MAX_TRAJECTORY {
                view.trajectory.remove(0);
            }
            view.trajectory.push(here);
            view.trajectory_dirty = true;
        }
        let due = view.trajectory_logged.is_none_or(|at| {
            wall.duration_since(at)
                .map_or(true, |since| since >= TRAJECTORY_PERIOD)
        });
        let strip = (view.trajectory_dirty && due).then(|| {
            view.trajectory_dirty = false;
            view.trajectory_logged = Some(wall);
            view.trajectory.clone()
        });
        let stamp = Self::stamp(step, Some(&pose.header.stamp), wall);
        self.row(env, paths::ROBOT, stamp, Row::Transform(here, unit_quat(q)));
        if let Some(strip) = strip {
            self.row(env, paths::TRAJECTORY, stamp, Row::Trajectory(strip));
        }
        self.count(&self.shared.counters.poses);
        Ok(())
    }

    pub(super) fn on_odom(
        &mut self,
        env: &EnvId,
        sample: &Sample,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let odom: Odometry = codec::decode_payload(sample.payload())?;
        let tag = wire::decode_attachment::<SeqTag>(sample).map(|t| t.seq);
        self.log_odom(env, &odom, tag, wall)
    }

    /// Odometry (`odom`, or a recording's `/odom`). At `tag`, else the env's
    /// current step.
    pub fn log_odom(
        &mut self,
        env: &EnvId,
        odom: &Odometry,
        tag: Option<u64>,
        wall: SystemTime,
    ) -> Result<(), Skip> {
        let p = &odom.pose.pose.position;
        let q = &odom.pose.pose.orientation;
        finite(&[p.x, p.y, p.z, q.x, q.y, q.z, q.w])?;
        let view = self.view(env);
        let step = tag.or(view.seq);
        let first = view.last_odom.is_none();
        view.last_odom = Some(Planar {
            x: p.x,
            y: p.y,
            z: p.z,
            yaw: yaw_of(q),
        });
        let stamp = Self::stamp(step, Some(&odom.header.stamp), wall);
        if first {
            // Until the first reset anchors it, draw odom as if it were the world.
            self.anchor_odom(env, stamp);
        }
        let here = [p.x as f32, p.y as f32, p.z as f32];
        self.row(
            env,
            paths::ODOM_ROBOT,
            stamp,
            Row::Transform(here, unit_quat(q)),
        );
        self.count(&self.shared.counters.odometry);
        Ok(())
    }

    /// Places the odom frame in the world so that the odometry pose
    /// coincides with the tracker pose now (planar), from `stamp` on.
    /// Identity without both.
    pub(super) fn anchor_odom(&mut self, env: &EnvId, stamp: Stamp) {
        let view = self.view(env);
        let (translation, yaw) = match (view.last_pose, view.last_odom) {
            (Some(w), Some(o)) => {
                let yaw = w.yaw - o.yaw;
                let (s, c) = yaw.sin_cos();
                (
                    [
                        (w.x - (c * o.x - s * o.y)) as f32,
                        (w.y - (s * o.x + c * o.y)) as f32,
                        (w.z - o.z) as f32,
                    ],
                    yaw,
                )
            }
            _ => ([0.0; 3], 0.0),
        };
        let half = (yaw * 0.5) as f32;
        let rotation = [0.0, 0.0, half.sin(), half.cos()];
        self.row(
            env,
            paths::ODOM,
            stamp,
            Row::Transform(translation, rotation),
        );
    }
}

pub(super) fn yaw_of(q: &offworld_runtime::msg::Quaternion) -> f64 {
    q.yaw()
}

/// Normalised (x, y, z, w) or identity when degenerate.
pub(super) fn unit_quat(q: &offworld_runtime::msg::Quaternion) -> [f32; 4] {
    let n = (q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w).sqrt();
    if !(n.is_finite() && n > 1e-9) {
        return [0.0, 0.0, 0.0, 1.0];
    }
    [
        (q.x / n) as f32,
        (q.y / n) as f32,
        (q.z / n) as f32,
        (q.w / n) as f32,
    ]
}
