//! The operator's requests: maintenance and lease revocation.

use super::*;

/// Longest operator message (maintenance, revocation reason), characters.
pub const MAX_OPERATOR_TEXT: usize = 500;

impl EnvServer {
    /// `admin`: who a token is (anyone's); operators put the env into or
    /// out of maintenance and revoke its lease.
    pub async fn admin(&self, req: AdminRequest) -> Result<AdminReply, WireError> {
        let user = self
            .store(|s| s.authenticate(req.token()))?
            .filter(|u| u.name != ANONYMOUS)
            .ok_or_else(|| WireError::unauthorized("unknown access token"))?;
        let reply = |status| AdminReply {
            user: user.name.clone(),
            operator: user.is_operator(),
            status,
        };
        if let AdminRequest::Identify { .. } = req {
            return Ok(reply(self.status()));
        }
        if !user.is_operator() {
            return Err(WireError::unauthorized(format!(
                "{} is not an operator: only operators change an env's service",
                user.name
            )));
        }
        let mut state = self.state.lock().await;
        match req {
            AdminRequest::SetMaintenance {
                message,
                back_unix_ms,
                ..
            } => {
                validate_operator_text("maintenance message", &message)?;
                if back_unix_ms > LATEST_BOOKABLE_MS {
                    return Err(WireError::bad_request(format!(
                        "the expected return {back_unix_ms} is not a date (Unix ms up to year 9999)"
                    )));
                }
                tracing::warn!(env = %self.env, %message, by = %user.name, "maintenance on");
                self.link.stop().await;
                self.abort_episode(&mut state, "maintenance").await;
                // The lease ends with it: its holder is told why at their
                // next request, and nobody holds the env through it.
                state.episode = None;
                if let Some(lease) = state.lease.take() {
                    state.revoked = Some(Revoked {
                        session_id: lease.session_id,
                        reason: format!(
                            "{} went into maintenance ({message}); your lease ended with it",
                            self.env
                        ),
                    });
                }
                state.maintenance = Some(Maintenance {
                    message,
                    by: user.name.clone(),
                    back_unix_ms: back_unix_ms.max(0),
                });
            }
            AdminRequest::ClearMaintenance { .. } => {
                tracing::warn!(env = %self.env, by = %user.name, "maintenance off");
                state.maintenance = None;
            }
            AdminRequest::RevokeLease { reason, .. } => {
                validate_operator_text("reason", &reason)?;
                if state.lease.is_none() {
                    return Err(WireError::not_found(format!(
                        "{} has no lease to revoke",
                        self.env
                    )));
                }
                self.link.stop().await;
                // Recorded while the lease (its experiment) is still known.
                self.abort_episode(&mut state, "lease revoked").await;
                state.episode = None;
                let Some(lease) = state.lease.take() else {
                    return Err(WireError::internal("lease vanished"));
                };
                tracing::warn!(env = %self.env, holder = %lease.user.name, by = %user.name, %reason, "lease revoked");
                state.revoked = Some(Revoked {
                    session_id: lease.session_id,
                    reason: format!(
                        "your lease on {} was revoked by the operator {}: {reason}",
                        self.env, user.name
                    ),
                });
            }
            AdminRequest::Identify { .. } => {}
        }
        self.publish_status(&mut state).await;
        Ok(reply(self.status_of(&state)))
    }
}

/// An operator's `what`: 1 to [`MAX_OPERATOR_TEXT`] characters, no control
/// characters (it is shown on pages and in logs).
pub(super) fn validate_operator_text(what: &str, text: &str) -> Result<(), WireError> {
    let bad = |why: String| Err(WireError::bad_request(why));
    if text.trim().is_empty() {
        return bad(format!("the {what} must say something"));
    }
    if text.chars().take(MAX_OPERATOR_TEXT + 1).count() > MAX_OPERATOR_TEXT {
        return bad(format!("the {what} is over {MAX_OPERATOR_TEXT} characters"));
    }
    if text.chars().any(char::is_control) {
        return bad(format!("the {what} holds a control character"));
    }
    Ok(())
}
