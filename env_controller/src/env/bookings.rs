//! Booked slots: the cached answer a step checks without the database,
//! and the `book` queryable.

use super::*;

impl EnvServer {
    /// The slot in progress at `now` (Unix ms) and its holder's user id.
    pub(super) fn slot_at(&self, now: i64) -> Result<Option<(Booking, i64)>, WireError> {
        // Only ever replaced whole: a panic cannot leave it half written.
        let mut cache = self.slots.lock().unwrap_or_else(PoisonError::into_inner);
        match cache.as_ref() {
            Some(known) if now < known.until_ms => Ok(known.slot.clone()),
            _ => {
                let env_id = self.env.to_string();
                let fresh = self.store(|s| s.slot_at(&env_id, now))?;
                let slot = fresh.slot.clone();
                *cache = Some(fresh);
                Ok(slot)
            }
        }
    }

    /// Whether [`EnvServer::slot_at`] answers `now` from its cache.
    fn slots_known_at(&self, now: i64) -> bool {
        let cache = self.slots.lock().unwrap_or_else(PoisonError::into_inner);
        cache.as_ref().is_some_and(|known| now < known.until_ms)
    }

    pub(super) fn forget_slots(&self) {
        *self.slots.lock().unwrap_or_else(PoisonError::into_inner) = None;
    }

    /// Ends the lease of `session_id` when its booked slot is over or
    /// someone else's slot began: the robot stops, the episode is recorded
    /// as aborted, and the caller learns why (401).
    pub(super) async fn enforce_slots(
        &self,
        state: &mut State,
        session_id: &str,
    ) -> Result<(), WireError> {
        let now = now_ms();
        if !self.slots_known_at(now) {
            // Reads the database: not on the thread a step started on.
            crate::start::hand_off().await;
        }
        let Some(lease) = state.lease.as_ref().filter(|l| l.session_id == session_id) else {
            return Ok(());
        };
        let reason = match lease.booked_until_unix_ms {
            Some(end) if now >= end => Some(format!(
                "your booked slot on {} ended at {}; the lease ended with it",
                self.env,
                format_unix_ms(end)
            )),
            _ => match self.slot_at(now)? {
                Some((booking, holder)) if holder != lease.user.id => Some(format!(
                    "{} is booked by {} from {} to {}; your lease ended",
                    self.env,
                    booking.user,
                    format_unix_ms(booking.start_unix_ms),
                    format_unix_ms(booking.end_unix_ms)
                )),
                _ => None,
            },
        };
        let Some(reason) = reason else {
            return Ok(());
        };
        tracing::info!(env = %self.env, %reason, "lease ended by a booking");
        crate::start::hand_off().await;
        self.link.stop().await;
        self.abort_episode(state, "booked slot ended").await;
        state.lease = None;
        state.episode = None;
        self.publish_status(state).await;
        Err(WireError::unauthorized(reason))
    }

    /// `book`: make, list or cancel slots.
    pub fn book(&self, req: BookingRequest) -> Result<Bookings, WireError> {
        let env_id = self.env.to_string();
        match req {
            BookingRequest::Make {
                token,
                start_unix_ms,
                end_unix_ms,
            } => {
                let user = self.authenticate(&token)?;
                let rules = self.options.booking_rules;
                // Checked here, before the store is locked (and again by
                // the store, which clamps the start to its own `now`).
                let now = now_ms();
                rules
                    .validate(start_unix_ms, end_unix_ms, now)
                    .map_err(|e| WireError::from(crate::ControllerError::from(e)))?;
                let booking =
                    self.store(|s| s.book(&user, &env_id, start_unix_ms, end_unix_ms, now, rules))?;
                self.forget_slots();
                tracing::info!(env = %self.env, user = %user.name, id = booking.id, "slot booked");
                Ok(Bookings {
                    bookings: vec![booking],
                })
            }
            BookingRequest::List { from_unix_ms } => Ok(Bookings {
                bookings: self.store(|s| s.bookings(&env_id, from_unix_ms))?,
            }),
            BookingRequest::Cancel { token, id } => {
                let user = self.authenticate(&token)?;
                self.store(|s| s.cancel_booking(&user, &env_id, id))?;
                self.forget_slots();
                Ok(Bookings {
                    bookings: self.store(|s| s.bookings(&env_id, now_ms()))?,
                })
            }
        }
    }
}
