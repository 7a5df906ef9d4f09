//! The line of clients waiting for a free env: first come, first served.
//!
//! A client that waits (`EnvClient::open_waiting`, Python `wait=`) asks
//! `open` again about every second with the same client id. Its first
//! refused `open` takes a place; asking again makes it count (a client
//! refused once that never asks again holds nobody up). It leaves the line
//! when it gets the env, or [`STALE`] after its last request arrived. A
//! place is its user's: another user sending the same client id is someone
//! else. When the env is free (no live lease) it goes to the first in line:
//! anyone else is told how many wait before them. A booked slot's holder
//! does not queue. One user holds at most [`PER_USER`] places (anonymous
//! users count as one), the line at most [`CAPACITY`].
//!
//! Liveliness is not trusted to remove a waiter: anyone may declare and
//! drop a token under another client's id. Anonymous users share one user,
//! so among them a place is only as private as a client id (which names a
//! liveliness token operators can list, and anyone on a peer-to-peer
//! network): best effort, on sim envs only.

use std::time::{Duration, Instant};

/// A waiter no request arrived from for this long has given up: longer
/// than a request can be stuck behind a real reset (the client's 10 s
/// timeout) plus its next poll, short enough that a waiter that gave up
/// holds a free env only briefly.
pub const STALE: Duration = Duration::from_secs(15);

/// The most places one user holds in one env's line.
pub const PER_USER: usize = 4;

/// The most clients one env keeps in line (more are refused without a place).
pub const CAPACITY: usize = 256;

/// One env's line.
#[derive(Debug, Default)]
pub struct WaitingLine {
    /// In order of arrival.
    waiters: Vec<Waiter>,
}

#[derive(Debug)]
struct Waiter {
    client_id: String,
    /// Whose client it is (a user id of the store).
    user_id: i64,
    /// When a request of it last arrived.
    seen: Instant,
    /// It asked again after its first refusal: it is waiting.
    waiting: bool,
}

impl Waiter {
    fn is(&self, client_id: &str, user_id: i64) -> bool {
        self.client_id == client_id && self.user_id == user_id
    }
}

impl WaitingLine {
    /// Drops the waiters that stopped asking.
    fn prune(&mut self, now: Instant) {
        self.waiters
            .retain(|w| now.saturating_duration_since(w.seen) < STALE);
    }

    /// A request of `client_id` arrived (it may wait behind a reset for
    /// the env's state): it is still there.
    pub fn touch(&mut self, client_id: &str, user_id: i64, now: Instant) {
        if let Some(waiter) = self.waiters.iter_mut().find(|w| w.is(client_id, user_id)) {
            waiter.seen = now;
        }
    }

    /// How many clients wait before `client_id` of `user_id` (all of them
    /// if it is not in line).
    pub fn ahead_of(&mut self, client_id: &str, user_id: i64, now: Instant) -> usize {
        self.prune(now);
        self.waiters
            .iter()
            .take_while(|w| !w.is(client_id, user_id))
            .filter(|w| w.waiting)
            .count()
    }

    /// `client_id` of user `user_id` was refused: it keeps its place (and
    /// now counts), or takes the last one.
    pub fn keep(&mut self, client_id: &str, user_id: i64, now: Instant) -> Place {
        self.prune(now);
        if client_id.is_empty() {
            return Place::NoClientId;
        }
        let at = match self.waiters.iter().position(|w| w.is(client_id, user_id)) {
            Some(at) => {
                let waiter = &mut self.waiters[at];
                (waiter.seen, waiter.waiting) = (now, true);
                at
            }
            None => {
                let users = self.waiters.iter().filter(|w| w.user_id == user_id).count();
                if users >= PER_USER {
                    return Place::UsersShareTaken;
                }
                if self.waiters.len() >= CAPACITY {
                    return Place::LineFull;
                }
                self.waiters.push(Waiter {
                    client_id: client_id.to_owned(),
                    user_id,
                    seen: now,
                    waiting: false,
                });
                self.waiters.len() - 1
            }
        };
        let ahead = self.waiters[..at].iter().filter(|w| w.waiting).count();
        Place::InLine(ahead + 1)
    }

    /// `client_id` of `user_id` got the env: it is no longer in line.
    pub fn leave(&mut self, client_id: &str, user_id: i64) {
        self.waiters.retain(|w| !w.is(client_id, user_id));
    }
}

/// Where a refused client stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Place {
    /// 1-based position in the line.
    InLine(usize),
    /// A request without a client id (a raw one): it cannot wait.
    NoClientId,
    /// Its user holds [`PER_USER`] places already.
    UsersShareTaken,
    /// The line holds [`CAPACITY`] clients.
    LineFull,
}

impl Place {
    /// What a refusal says of it, e.g. `; 2nd in line`.
    pub fn said(self) -> String {
        match self {
            Place::InLine(n) => format!("; {} in line", ordinal(n)),
            Place::NoClientId => String::new(),
            Place::UsersShareTaken => {
                format!("; no place in line: your user holds {PER_USER} already")
            }
            Place::LineFull => format!("; no place in line: {CAPACITY} clients wait already"),
        }
    }
}

/// `1st`, `2nd`, `3rd`, `4th`, …, `11th`, `21st`.
fn ordinal(n: usize) -> String {
    let suffix = match (n % 10, n % 100) {
        (_, 11..=13) => "th",
        (1, _) => "st",
        (2, _) => "nd",
        (3, _) => "rd",
        _ => "th",
    };
    format!("{n}{suffix}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_come_first_served_among_those_who_ask_again() {
        let mut line = WaitingLine::default();
        let t0 = Instant::now();
        let t1 = t0 + Duration::from_secs(1);
        assert_eq!(line.keep("a", 1, t0), Place::InLine(1));
        assert_eq!(line.keep("b", 2, t0), Place::InLine(1));
        // Refused once: nobody is held up yet.
        assert_eq!(line.ahead_of("stranger", 9, t0), 0);
        // Asking again keeps the place and makes it count.
        assert_eq!(line.keep("a", 1, t1), Place::InLine(1));
        assert_eq!(line.keep("b", 2, t1), Place::InLine(2));
        assert_eq!(line.ahead_of("a", 1, t1), 0);
        assert_eq!(line.ahead_of("b", 2, t1), 1);
        assert_eq!(line.ahead_of("stranger", 9, t1), 2);
        line.leave("a", 1);
        assert_eq!(line.ahead_of("b", 2, t1), 0);
        assert_eq!(line.ahead_of("stranger", 9, t1), 1);
    }

    #[test]
    fn a_place_is_its_users_not_its_client_ids() {
        let mut line = WaitingLine::default();
        let t0 = Instant::now();
        line.keep("head", 1, t0);
        line.keep("head", 1, t0);
        // Another user sending the head's client id is behind it, and
        // cannot take it out of the line.
        assert_eq!(line.ahead_of("head", 2, t0), 1);
        line.leave("head", 2);
        assert_eq!(line.keep("head", 2, t0), Place::InLine(2));
        line.touch("head", 2, t0 + STALE);
        assert_eq!(
            line.ahead_of("someone", 3, t0 + STALE),
            0,
            "head 1 went stale"
        );
    }

    #[test]
    fn a_client_refused_once_holds_nobody_up() {
        let mut line = WaitingLine::default();
        let t0 = Instant::now();
        line.keep("one-shot", 1, t0);
        line.keep("waiter", 2, t0);
        line.keep("waiter", 2, t0 + Duration::from_secs(1));
        assert_eq!(line.ahead_of("waiter", 2, t0 + Duration::from_secs(1)), 0);
    }

    #[test]
    fn a_waiter_no_request_arrived_from_loses_its_place() {
        let mut line = WaitingLine::default();
        let t0 = Instant::now();
        line.keep("gone", 1, t0);
        line.keep("gone", 1, t0);
        line.keep("stuck", 2, t0);
        line.keep("stuck", 2, t0);
        // A request stuck behind a long reset still keeps its sender's place.
        line.touch("stuck", 2, t0 + STALE - Duration::from_secs(1));
        let later = t0 + STALE;
        assert_eq!(line.ahead_of("stuck", 2, later), 0);
        // Back after losing it: the last place.
        assert_eq!(line.keep("gone", 1, later), Place::InLine(2));
    }

    #[test]
    fn no_place_without_a_client_id_beyond_a_users_share_or_capacity() {
        let mut line = WaitingLine::default();
        let t0 = Instant::now();
        assert_eq!(line.keep("", 1, t0), Place::NoClientId);
        for i in 0..PER_USER {
            assert_eq!(line.keep(&format!("mine{i}"), 1, t0), Place::InLine(1));
        }
        assert_eq!(line.keep("one-more-of-mine", 1, t0), Place::UsersShareTaken);
        assert_eq!(
            Place::UsersShareTaken.said(),
            "; no place in line: your user holds 4 already"
        );
        let mut line = WaitingLine::default();
        for i in 0..CAPACITY {
            let user = i64::try_from(i).expect("small");
            line.keep(&format!("c{i}"), user, t0);
            assert_eq!(line.keep(&format!("c{i}"), user, t0), Place::InLine(i + 1));
        }
        assert_eq!(line.keep("one-too-many", -1, t0), Place::LineFull);
        assert_eq!(line.ahead_of("one-too-many", -1, t0), CAPACITY);
        assert_eq!(
            Place::LineFull.said(),
            "; no place in line: 256 clients wait already"
        );
    }

    #[test]
    fn ordinals_read_as_english() {
        let said: Vec<String> = [1, 2, 3, 4, 11, 12, 13, 21, 22, 101, 111]
            .into_iter()
            .map(ordinal)
            .collect();
        assert_eq!(
            said,
            [
                "1st", "2nd", "3rd", "4th", "11th", "12th", "13th", "21st", "22nd", "101st",
                "111th"
            ]
        );
    }
}
