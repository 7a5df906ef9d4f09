//! Experiments, their episodes (with recordings) and the leaderboard.

use super::*;

impl EnvServer {
    /// `experiments`: the caller's experiments on this env (operators:
    /// everyone's), or one of them with its episodes and recordings. Another
    /// user's experiment is answered as not found, like one that does not exist.
    pub async fn experiments(&self, req: ExperimentsRequest) -> Result<Experiments, WireError> {
        let env_id = self.env.to_string();
        match req {
            ExperimentsRequest::List { token } => {
                let user = self.authenticate(&token)?;
                let owner = (!user.is_operator()).then_some(&user);
                let mut experiments = self.store(|s| s.experiments_on(&env_id, owner))?;
                experiments.truncate(EXPERIMENTS_PER_REPLY as usize);
                Ok(Experiments {
                    experiments,
                    episodes: Vec::new(),
                    more: false,
                })
            }
            ExperimentsRequest::Show {
                token,
                experiment_id,
                from_episode,
            } => {
                let user = self.authenticate(&token)?;
                let not_found = || {
                    WireError::not_found(format!(
                        "no experiment {experiment_id} of yours on {env_id}"
                    ))
                };
                let experiment = self
                    .store(|s| s.experiment_by_id(experiment_id))?
                    .filter(|e| e.env_id == env_id && (user.is_operator() || e.user == user.name))
                    .ok_or_else(not_found)?;
                // One more than a page tells whether another follows.
                let mut episodes = self.store(|s| {
                    s.episodes_from(
                        experiment_id,
                        from_episode,
                        EXPERIMENT_EPISODES_PER_REPLY + 1,
                    )
                })?;
                let more = episodes.len() > EXPERIMENT_EPISODES_PER_REPLY as usize;
                episodes.truncate(EXPERIMENT_EPISODES_PER_REPLY as usize);
                self.attach_recordings(experiment_id, &mut episodes).await;
                Ok(Experiments {
                    experiments: vec![experiment],
                    episodes,
                    more,
                })
            }
        }
    }

    /// Lists each episode's files, when this env records. A directory that
    /// cannot be read leaves the episodes without files (and says so in the
    /// log): the store's record is still worth answering.
    pub(super) async fn attach_recordings(
        &self,
        experiment_id: i64,
        episodes: &mut [EpisodeRecordEntry],
    ) {
        let Some(recorder) = &self.recorder else {
            return;
        };
        // The files match what the client did: the episodes it ended are
        // finished, the one it began exists.
        recorder.caught_up().await;
        let files = match recorder
            .destination()
            .experiment_files(&self.env, u64::try_from(experiment_id).unwrap_or_default())
        {
            Ok(files) => files,
            Err(e) => {
                tracing::warn!(env = %self.env, experiment_id, "cannot list recordings: {e}");
                return;
            }
        };
        for file in files {
            let Ok(at) = episodes.binary_search_by_key(&file.episode_id, |e| e.index) else {
                continue;
            };
            let path = file
                .relative_path
                .iter()
                .map(|part| part.to_string_lossy())
                .collect::<Vec<_>>()
                .join("/");
            episodes[at].recordings.push(RecordingFile {
                path,
                bytes: file.bytes,
                complete: file.complete,
            });
        }
    }

    /// `leaderboard`: test-mode experiments ranked.
    pub fn leaderboard(&self) -> Result<Leaderboard, WireError> {
        let env_id = self.env.to_string();
        let entries = self.store(|s| s.leaderboard(&env_id))?;
        Ok(Leaderboard { env_id, entries })
    }
}

pub(super) fn experiment_info(e: &ExperimentRecord) -> ExperimentInfo {
    ExperimentInfo {
        id: e.id,
        name: e.name.clone(),
        episodes: e.episodes,
        steps: e.steps,
    }
}
