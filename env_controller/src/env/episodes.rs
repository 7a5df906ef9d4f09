//! Episodes: `reset` and `step`, each run by [`crate::step`] (judged once,
//! replied once), then recorded and accounted for here.

use super::*;

impl EnvServer {
    /// `reset`: spawn (seeded), move the robot there, observe.
    pub async fn reset(&self, req: ResetRequest) -> Result<Encoded<ResetReply>, WireError> {
        let began = Instant::now();
        let mut state = self.state.lock().await;
        self.enforce_slots(&mut state, &req.session_id).await?;
        self.holder(&mut state, &req.session_id)?;
        if let Some(maintenance) = &state.maintenance {
            return Err(maintenance.refusal(&self.env));
        }
        if let Err(refused) = self.estops.refuse_motion() {
            self.abort_episode(&mut state, &refused.message).await;
            return Err(refused);
        }
        self.abort_episode(&mut state, "reset before the episode ended")
            .await;
        let seed = match req.seed {
            Seed::Fixed(s) => {
                state.sampler.reseed(s);
                Some(s)
            }
            Seed::Continue => None,
        };
        let target = state
            .sampler
            .sample(&self.task)
            .ok_or_else(|| WireError::internal("no valid spawn pose in this world"))?;
        state.seq += 1;
        let arrived = self.link.goto(state.seq, target).await?;
        state.seq += 1;
        let observe = MotionCommand {
            seq: state.seq,
            linear_x: 0.0,
            angular_z: 0.0,
            duration_s: 0.0,
        };
        let obs = self.holder(&mut state, &req.session_id)?.obs;
        let answered = Plan::observe(observe, self.observation_request(obs))
            .run(&self.link)
            .await?;
        let lease = self.holder(&mut state, &req.session_id)?;
        let index = lease.experiment.episodes;
        let experiment = (lease.experiment.name.clone(), lease.experiment.id);
        let recorded = self.recorder.is_some().then(|| RecordedEpisode {
            header: Header::new(Time::now(), "world"),
            env_id: self.env.to_string(),
            task: self.task.name.clone(),
            world: self.task.world.name.clone(),
            experiment_id: u64::try_from(lease.experiment.id).unwrap_or_default(),
            experiment: lease.experiment.name.clone(),
            learning_type: lease.experiment.learning_type.clone(),
            algorithm_mode: lease.experiment.algorithm_mode.clone(),
            episode_id: index,
            seeded: seed.is_some(),
            seed: seed.unwrap_or_default(),
            embodiment: match self.env.realm() {
                offworld_runtime::Realm::Sim => "twin",
                offworld_runtime::Realm::Real => "robot",
            }
            .to_owned(),
            software_version: env!("CARGO_PKG_VERSION").to_owned(),
            max_episode_steps: self.task.episode.max_steps,
            requested_start: [target.x, target.y, target.yaw],
        });
        let achieved = answered.pose.planar();
        let accuracy =
            ResetAccuracy::measure(target, achieved, began.elapsed().as_secs_f64(), now_ms());
        tracing::debug!(env = %self.env, ?target, reached = ?arrived.achieved, ?accuracy, "reset");
        let episode = Episode {
            index,
            seed,
            steps: 0,
            episode_return: 0.0,
            over: false,
            reset: accuracy,
            started_ms: accuracy.unix_ms,
            saved: Instant::now(),
        };
        // On record from its first moment: a controller killed mid-episode
        // leaves it, closed as aborted at the next start.
        let started = episode.record(lease.experiment.id, None, episode.started_ms);
        lock_store(&self.store)
            .begin_episode(&started)
            .map_err(WireError::from)?;
        lease.experiment.episodes += 1;
        state.episode = Some(episode);
        state.last_reset = accuracy;
        self.publish_status(&mut state).await;
        let event = episode_event(&experiment, index, 0, observe.seq, None, 0.0);
        if let (Some(recorder), Some(info)) = (&self.recorder, recorded) {
            // How well the reset placed the robot, with the episode
            // (`parity replay` reports it).
            // (The achieved pose is the reset step's recorded pose.)
            let notes = std::collections::BTreeMap::from([(
                offworld_recorder::episode_file::RESET_DURATION_NOTE.to_owned(),
                format!("{:.6}", accuracy.duration_s),
            )]);
            recorder.begin_annotated(info, notes).await;
            let step = Step::from_event(&event, None, None);
            self.record_step(&answered, step, None).await;
        }
        let reply = ResetReply {
            info: step_info(&self.task, index, 0, &achieved, None, self.shares_pose()),
            observation: obs.shape(),
        };
        let reply = answered
            .reply_with(&reply)?
            .ok_or_else(|| WireError::internal("a reset was replied where its frame arrived"))?;
        self.publish_event(&event).await;
        Ok(reply)
    }

    /// Whether `info` carries the robot's ground truth (see
    /// [`EnvOptions::share_real_pose`]).
    pub(super) fn shares_pose(&self) -> bool {
        self.env.realm() == offworld_runtime::Realm::Sim || self.options.share_real_pose
    }

    /// What to build from the frames answering the lease holder's commands.
    pub(super) fn observation_request(&self, options: ObsOptions) -> ObservationRequest {
        ObservationRequest {
            options,
            depth_max_m: self.task.episode.depth_max_m,
        }
    }

    /// `step`: act, observe, judge. The reply to `query` is sent from
    /// where the robot's answer is received when it can be (not for an
    /// episode's last step, which is recorded first), and this returns
    /// `None`; otherwise the reply to send.
    pub async fn step(
        &self,
        req: StepRequest,
        query: Query,
    ) -> Result<Option<Encoded<StepReply>>, WireError> {
        let mut state = self.state.lock().await;
        self.enforce_slots(&mut state, &req.session_id).await?;
        let lease = self.holder(&mut state, &req.session_id)?;
        let obs = lease.obs;
        let experiment = (lease.experiment.name.clone(), lease.experiment.id);
        if let Some(maintenance) = &state.maintenance {
            return Err(maintenance.refusal(&self.env));
        }
        if let Err(refused) = self.estops.refuse_motion() {
            // Whatever stopped the robot may have moved it: the episode
            // cannot go on from here.
            self.abort_episode(&mut state, &refused.message).await;
            return Err(refused);
        }
        let (index, step) = match &state.episode {
            None => return Err(WireError::invalid_state("call reset() before step()")),
            Some(e) if e.over => {
                return Err(WireError::invalid_state(
                    "the episode has ended; call reset()",
                ))
            }
            Some(e) => (e.index, e.steps + 1),
        };
        let motion = self.task.motion(&req.action, state.seq + 1)?;
        state.seq += 1;
        let request = self.observation_request(obs);
        let judge = StepJudge {
            task: self.task.clone(),
            share_pose: self.shares_pose(),
            seq: req.seq,
            episode_id: index,
            step,
            obs,
        };
        let commanded_at = Time::now();
        let answered = match Plan::judged(motion, request, judge, Some(query))
            .run(&self.link)
            .await
        {
            Ok(a) => a,
            Err(e) => {
                // The step cannot be scored, so neither can the episode (a
                // robot that did not answer has been stopped by the link).
                self.abort_episode(&mut state, &format!("aborted: {}", e.message))
                    .await;
                // An e-stop that cut the motion short is the reason to
                // report, whichever message arrived first.
                return Err(self.estops.refuse_motion().err().unwrap_or(e));
            }
        };
        let outcome = &answered.verdict.outcome;
        let Some(episode) = state.episode.as_mut() else {
            return Err(WireError::internal("episode vanished"));
        };
        episode.steps = step;
        episode.episode_return += outcome.reward;
        let (steps, ret) = (episode.steps, episode.episode_return);
        let event = episode_event(&experiment, index, steps, motion.seq, Some(outcome), ret);
        if self.recorder.is_some() {
            let recorded = Step::from_event(&event, Some(&req.action), Some(&motion));
            let command = Twist::planar(motion.linear_x, motion.angular_z);
            self.record_step(&answered, recorded, Some((command, commanded_at)))
                .await;
        }
        let reply = answered.reply_with(&answered.verdict.reply)?;
        self.publish_event(&event).await;
        match &outcome.end {
            Some(end) => self.finish_episode(&mut state, end).await?,
            None => self.save_progress(&mut state).await,
        }
        Ok(reply)
    }

    /// Stops the robot and records the episode in progress as aborted
    /// (the controller is stopping).
    pub async fn stop_and_record(&self, reason: &str) {
        self.link.close();
        self.link.stop().await;
        let mut state = self.state.lock().await;
        self.abort_episode(&mut state, reason).await;
    }

    /// Records an unfinished episode as ended for `reason`.
    pub(super) async fn abort_episode(&self, state: &mut State, reason: &str) {
        let running = state.episode.as_ref().is_some_and(|e| !e.over);
        if running {
            let end = EndReason::Aborted(reason.to_owned());
            if let Err(e) = self.finish_episode(state, &end).await {
                tracing::error!(env = %self.env, "could not record the aborted episode: {}", e.message);
            }
        }
    }

    /// Saves the running episode's progress when [`PROGRESS_EVERY`] has
    /// passed since the last save (a failure is logged: the step stands).
    pub(super) async fn save_progress(&self, state: &mut State) {
        let (Some(episode), Some(lease)) = (state.episode.as_mut(), state.lease.as_ref()) else {
            return;
        };
        if episode.over || episode.saved.elapsed() < PROGRESS_EVERY {
            return;
        }
        episode.saved = Instant::now();
        // Writes to SQLite: not on the thread a step started on (a twin
        // stepping where its command arrives answers within that start).
        crate::start::hand_off().await;
        let record = episode.record(lease.experiment.id, None, now_ms());
        if let Err(e) = lock_store(&self.store).progress_episode(&record) {
            tracing::error!(env = %self.env, "could not save the episode's progress: {e}");
        }
    }

    pub(super) async fn finish_episode(
        &self,
        state: &mut State,
        end: &EndReason,
    ) -> Result<(), WireError> {
        let (Some(episode), Some(lease)) = (state.episode.as_mut(), state.lease.as_mut()) else {
            return Ok(());
        };
        // Writes to SQLite: not on the thread a step started on.
        crate::start::hand_off().await;
        episode.over = true;
        let record = episode.record(lease.experiment.id, Some(end), now_ms());
        // The recording ends whether or not the database takes the record.
        if let Some(recorder) = &self.recorder {
            recorder
                .end(RecordedEnd {
                    header: Header::new(Time::now(), "world"),
                    episode_id: episode.index,
                    steps: episode.steps,
                    episode_return: episode.episode_return,
                    success: record.success,
                    terminated: matches!(end, EndReason::Success | EndReason::OutOfBounds),
                    truncated: *end == EndReason::StepLimit,
                    end_reason: end.as_str().to_owned(),
                })
                .await;
        }
        lock_store(&self.store)
            .record_episode(&record)
            .map_err(WireError::from)?;
        lease.experiment.steps += u64::from(episode.steps);
        Ok(())
    }

    /// Hands a step to the recorder (which stamps it with its frame's
    /// capture time), when recording.
    pub(super) async fn record_step<V>(
        &self,
        answered: &Answered<V>,
        step: Step,
        command: Option<(Twist, Time)>,
    ) {
        let Some(recorder) = &self.recorder else {
            return;
        };
        recorder
            .step(StepRecord {
                step,
                frame: answered.frame.payload().clone(),
                pose: answered.pose.pose.clone(),
                command,
            })
            .await;
    }

    /// Publishes a step's (or a reset's) event for spectators, monitors
    /// and subscriber-side recorders.
    pub(super) async fn publish_event(&self, event: &EpisodeEvent) {
        if let Err(e) = wire::publish(&self.events, event) {
            tracing::warn!("reward publish failed: {e}");
        }
    }
}

/// The event of step `step` of episode `episode_id` in `experiment` (name,
/// id), answered by the frame of command `command_seq`: the reset when
/// `outcome` is `None`. The recorded `Step` is built from it
/// ([`Step::from_event`]), so both say the same.
pub(super) fn episode_event(
    experiment: &(String, i64),
    episode_id: u64,
    step: u32,
    command_seq: u64,
    outcome: Option<&Outcome>,
    episode_return: f64,
) -> EpisodeEvent {
    let end = outcome.and_then(|o| o.end.as_ref());
    EpisodeEvent {
        experiment: experiment.0.clone(),
        episode_id,
        step,
        reward: outcome.map_or(0.0, |o| o.reward),
        episode_return,
        terminated: outcome.is_some_and(|o| o.terminated),
        truncated: outcome.is_some_and(|o| o.truncated),
        success: end == Some(&EndReason::Success),
        end_reason: end.map(|e| e.as_str().to_owned()).unwrap_or_default(),
        experiment_id: experiment.1,
        command_seq,
    }
}
