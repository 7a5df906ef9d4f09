//! Sessions and leases: who may drive the env (tokens, booked slots), the
//! lease an `open` takes and a `close` or a vanished client gives back.

use super::*;

impl EnvServer {
    pub(super) fn authenticate(&self, token: &str) -> Result<User, WireError> {
        if token.is_empty() && !self.options.allow_anonymous {
            return Err(WireError::unauthorized(format!(
                "{} needs an access token",
                self.env
            )));
        }
        let user = self.store(|s| s.authenticate(token))?;
        match user {
            Some(u) if u.name == ANONYMOUS && !self.options.allow_anonymous => Err(
                WireError::unauthorized("anonymous access is not allowed here"),
            ),
            Some(u) => Ok(u),
            None => Err(WireError::unauthorized("unknown access token")),
        }
    }

    /// Checks that `session_id` holds the lease and renews it.
    pub(super) fn holder<'a>(
        &self,
        state: &'a mut State,
        session_id: &str,
    ) -> Result<&'a mut Lease, WireError> {
        let now = Instant::now();
        match state.lease.as_mut() {
            Some(l) if l.session_id == session_id && l.expires > now && !l.disconnected => {
                l.expires = now + self.options.lease_idle;
                l.expires_unix_ms = unix_ms_in(self.options.lease_idle);
                let (expires, until) = (l.expires, l.expires_unix_ms);
                self.posted.send_modify(|p| {
                    if let Some(posted) = p.lease.as_mut() {
                        (posted.expires, posted.until_unix_ms) = (expires, until);
                    }
                });
                Ok(l)
            }
            Some(l) if l.session_id == session_id => Err(WireError::unauthorized(
                "your lease expired; open the env again to continue",
            )),
            _ => match &state.revoked {
                Some(revoked) if revoked.session_id == session_id => {
                    Err(WireError::unauthorized(revoked.reason.clone()))
                }
                _ => Err(WireError::unauthorized(
                    "this session does not hold the env's lease",
                )),
            },
        }
    }

    /// `open`: authenticate, take the lease, create or resume the experiment.
    pub async fn open(&self, req: OpenRequest) -> Result<OpenReply, WireError> {
        // Every input checked before any lock is taken.
        validate_options(&req.obs)?;
        validate_client_id(&self.env, &req.client_id)?;
        let name = if req.experiment_name.is_empty() {
            format!("run-{}", now_ms())
        } else {
            req.experiment_name.clone()
        };
        validate_experiment_name(&name)?;
        let user = self.authenticate(&req.token)?;
        // Before waiting for the state (a real reset holds it for seconds):
        // the request arrived, so its sender still waits.
        self.line().touch(&req.client_id, user.id, Instant::now());
        let mut state = self.state.lock().await;
        if let Some(maintenance) = &state.maintenance {
            return Err(maintenance.refusal(&self.env));
        }
        if !self.link.online() {
            return Err(WireError::unavailable(format!(
                "{} is offline: no robot or sim twin",
                self.env
            )));
        }
        let now = Instant::now();
        let env_id = self.env.to_string();
        let slot = self.slot_at(now_ms())?;
        let mut refusal = None;
        let booked_until_unix_ms = match &slot {
            Some((booking, holder)) if *holder != user.id => {
                refusal = Some(format!(
                    "{} is booked by {} until {}",
                    self.env,
                    booking.user,
                    format_unix_ms(booking.end_unix_ms)
                ));
                None
            }
            Some((booking, _)) => Some(booking.end_unix_ms),
            None => None,
        };
        let live = state.lease.as_ref().filter(|l| l.expires > now);
        // Not for anonymous users: they share one user, and a client id
        // is no secret (it names the client's liveliness token).
        let own_again = |l: &&Lease| {
            !l.disconnected
                && !req.client_id.is_empty()
                && l.client_id == req.client_id
                && l.user.id == user.id
                && user.name != ANONYMOUS
        };
        if let Some(lease) = live.filter(own_again).filter(|_| refusal.is_none()) {
            // This client's own open again (a wait's retry after its reply
            // was lost, e.g. a timeout behind a reset): the lease it holds.
            return Ok(OpenReply {
                session_id: lease.session_id.clone(),
                lease_until_unix_ms: lease.expires_unix_ms,
                spec: self.spec(),
                experiment: experiment_info(&lease.experiment),
            });
        }
        if let Some(lease) = live {
            if lease.user.id != user.id && booked_until_unix_ms.is_some() {
                tracing::info!(env = %self.env, user = %user.name, "booked slot: lease taken over");
            } else if lease.user.id != user.id {
                refusal.get_or_insert_with(|| {
                    format!(
                        "{} is leased by another user until {}",
                        self.env,
                        format_unix_ms(lease.expires_unix_ms)
                    )
                });
            } else if user.name == ANONYMOUS && !lease.disconnected {
                refusal.get_or_insert_with(|| {
                    format!(
                        "{} is in use by another anonymous session until {}",
                        self.env,
                        format_unix_ms(lease.expires_unix_ms)
                    )
                });
            }
        }
        // A free env goes to the first in line; a booked slot's holder, or
        // the lease holder's own user taking it over, does not queue.
        if refusal.is_none() && live.is_none() && booked_until_unix_ms.is_none() {
            let ahead = self.line().ahead_of(&req.client_id, user.id, now);
            if ahead > 0 {
                let waiting = if ahead == 1 { "client" } else { "clients" };
                refusal = Some(format!(
                    "{} is held for the {ahead} {waiting} waiting before you",
                    self.env
                ));
            }
        }
        if let Some(refusal) = refusal {
            let place = self.line().keep(&req.client_id, user.id, now);
            return Err(WireError::busy(format!("{refusal}{}", place.said())));
        }
        self.line().leave(&req.client_id, user.id);
        // The same user reconnecting takes the lease over; the old
        // session's unfinished episode is recorded as aborted.
        self.abort_episode(&mut state, "session replaced").await;
        let experiment = self.store(|s| {
            s.open_experiment(
                &user,
                &env_id,
                &self.task.name,
                &name,
                req.resume_experiment,
                req.learning_type,
                req.algorithm_mode,
            )
        })?;
        let session_id: String = {
            let mut rng = rand::rng();
            (0..24)
                .map(|_| format!("{:x}", rng.random_range(0..16u8)))
                .collect()
        };
        let lease_until_unix_ms = unix_ms_in(self.options.lease_idle);
        tracing::info!(env = %self.env, user = %user.name, experiment = %experiment.name, "lease granted");
        let info = experiment_info(&experiment);
        state.lease = Some(Lease {
            session_id: session_id.clone(),
            client_id: req.client_id.clone(),
            user,
            experiment,
            obs: req.obs,
            expires: now + self.options.lease_idle,
            expires_unix_ms: lease_until_unix_ms,
            disconnected: false,
            booked_until_unix_ms,
        });
        state.episode = None;
        self.publish_status(&mut state).await;
        Ok(OpenReply {
            session_id,
            lease_until_unix_ms,
            spec: self.spec(),
            experiment: info,
        })
    }

    /// `close`: record, release the lease.
    pub async fn close(&self, req: CloseRequest) -> Result<CloseReply, WireError> {
        let mut state = self.state.lock().await;
        self.holder(&mut state, &req.session_id)?;
        self.abort_episode(&mut state, "closed").await;
        if let Some(recorder) = &self.recorder {
            // A client that closed its env finds its episodes complete.
            recorder.caught_up().await;
        }
        let lease = state
            .lease
            .take()
            .ok_or_else(|| WireError::internal("lease vanished"))?;
        tracing::info!(env = %self.env, user = %lease.user.name, "lease released");
        self.publish_status(&mut state).await;
        Ok(CloseReply {
            experiment: experiment_info(&lease.experiment),
        })
    }

    /// The holder's client vanished: stop the robot, record the episode as
    /// aborted, keep the lease for the reconnect grace period.
    pub async fn client_disconnected(&self, client_id: &str) {
        let mut state = self.state.lock().await;
        let holder = state
            .lease
            .as_ref()
            .is_some_and(|l| l.client_id == client_id && !l.disconnected);
        if !holder {
            return;
        }
        tracing::warn!(env = %self.env, client_id, "lease holder disconnected; robot stopped");
        self.link.stop().await;
        self.abort_episode(&mut state, "client disconnected").await;
        if let Some(lease) = state.lease.as_mut() {
            lease.disconnected = true;
            lease.expires = Instant::now() + self.options.reconnect_grace;
            lease.expires_unix_ms = unix_ms_in(self.options.reconnect_grace);
        }
        self.publish_status(&mut state).await;
    }

    /// The holder's client is back (its liveliness token reappeared, e.g.
    /// after a network flap or a router restart) within the grace period:
    /// the lease is theirs again. The interrupted episode stays aborted; the
    /// client goes on with `reset()` without opening the env again.
    pub async fn client_reconnected(&self, client_id: &str) {
        let mut state = self.state.lock().await;
        let now = Instant::now();
        let Some(lease) = state
            .lease
            .as_mut()
            .filter(|l| l.client_id == client_id && l.disconnected && l.expires > now)
        else {
            return;
        };
        tracing::info!(env = %self.env, client_id, "lease holder reconnected; lease restored");
        lease.disconnected = false;
        lease.expires = now + self.options.lease_idle;
        lease.expires_unix_ms = unix_ms_in(self.options.lease_idle);
        self.publish_status(&mut state).await;
    }
}
