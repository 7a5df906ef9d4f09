//! The line of clients waiting for a busy env: first come, first served.
//!
//! A client that waits (`EnvClient::open_waiting`, Python `wait=`) asks
//! `open` again about every second with the same client id, its liveliness
//! token declared all along. Its first refused `open` takes a place;
//! asking again makes it count (a client refused once that never asks
//! again holds nobody up). It leaves the line when it gets the env, when
//! its liveliness token goes (it gave up, or died), or after [`STALE`]
//! without a request arriving (the token's departure unseen). When the env
//! is free it goes to the first in line: anyone else is told how many wait
//! before them. A booked slot's holder, and the lease holder's own user
//! taking their lease over, do not queue. One user holds at most
//! [`PER_USER`] places (anonymous users count as one), the line at most
//! [`CAPACITY`].

use std::time::{Duration, Instant};

/// A waiter no request arrived from for this long has given up (a safety
/// net: a departed client's liveliness token normally removes it at once;
/// longer than a request stuck behind a real reset for its whole timeout).
pub const STALE: Duration = Duration::from_secs(30);

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

impl WaitingLine {
    /// Drops the waiters that stopped asking.
    fn prune(&mut self, now: Instant) {
        self.waiters
            .retain(|w| now.saturating_duration_since(w.seen) < STALE);
    }

    /// A request of `client_id` arrived (it may wait behind a reset for
    /// the env's state): it is still there.
    pub fn touch(&mut self, client_id: &str, now: Instant) {
        if let Some(waiter) = self.waiters.iter_mut().find(|w| w.client_id == client_id) {
            waiter.seen = now;
        }
    }

    /// How many clients wait before `client_id` (all of them if it is not
    /// in line).
    pub fn ahead_of(&mut self, client_id: &str, now: Instant) -> usize {
        self.prune(now);
        self.waiters
            .iter()
            .take_while(|w| w.client_id != client_id)
            .filter(|w| w.waiting)
            .count()
    }

    /// `client_id` of user `user_id` was refused: it keeps its place (and
    /// now counts), or takes the last one.
    pub fn keep(&mut self, client_id: &str, user_id: i64, now: Instant) -> Place {
        self.prune(now);
        if client_id.is_empty() {
            return Place::NotKept;
        }
        let at = match self.waiters.iter().position(|w| w.client_id == client_id) {
            Some(at) => {
                let waiter = &mut self.waiters[at];
                (waiter.seen, waiter.waiting) = (now, true);
                at
            }
            None => {
                let users = self.waiters.iter().filter(|w| w.user_id == user_id).count();
                if users >= PER_USER || self.waiters.len() >= CAPACITY {
                    return Place::NotKept;
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

    /// `client_id` got the env, or is gone: it is no longer in line.
    pub fn leave(&mut self, client_id: &str) {
        self.waiters.retain(|w| w.client_id != client_id);
    }
}

/// Where a refused client stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Place {
    /// 1-based position in the line.
    InLine(usize),
    /// Without a client id, beyond its user's share or with the line
    /// full: no place kept.
    NotKept,
}

impl Place {
    /// What a refusal says of it, e.g. `; 2nd in line`.
    pub fn said(self) -> String {
        match self {
            Place::InLine(n) => format!("; {} in line", ordinal(n)),
            Place::NotKept => String::new(),
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
        assert_eq!(line.ahead_of("stranger", t0), 0);
        // Asking again keeps the place and makes it count.
        assert_eq!(line.keep("a", 1, t1), Place::InLine(1));
        assert_eq!(line.keep("b", 2, t1), Place::InLine(2));
        assert_eq!(line.ahead_of("a", t1), 0);
        assert_eq!(line.ahead_of("b", t1), 1);
        assert_eq!(line.ahead_of("stranger", t1), 2);
        line.leave("a");
        assert_eq!(line.ahead_of("b", t1), 0);
        assert_eq!(line.ahead_of("stranger", t1), 1);
    }

    #[test]
    fn a_client_refused_once_holds_nobody_up() {
        let mut line = WaitingLine::default();
        let t0 = Instant::now();
        line.keep("one-shot", 1, t0);
        line.keep("waiter", 2, t0);
        line.keep("waiter", 2, t0 + Duration::from_secs(1));
        assert_eq!(line.ahead_of("waiter", t0 + Duration::from_secs(1)), 0);
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
        line.touch("stuck", t0 + STALE - Duration::from_secs(1));
        let later = t0 + STALE;
        assert_eq!(line.ahead_of("stuck", later), 0);
        // Back after losing it: the last place.
        assert_eq!(line.keep("gone", 1, later), Place::InLine(2));
    }

    #[test]
    fn no_place_without_a_client_id_beyond_a_users_share_or_capacity() {
        let mut line = WaitingLine::default();
        let t0 = Instant::now();
        assert_eq!(line.keep("", 1, t0), Place::NotKept);
        for i in 0..PER_USER {
            assert_eq!(line.keep(&format!("mine{i}"), 1, t0), Place::InLine(1));
        }
        assert_eq!(line.keep("one-more-of-mine", 1, t0), Place::NotKept);
        let mut line = WaitingLine::default();
        for i in 0..CAPACITY {
            let user = i64::try_from(i).expect("small");
            line.keep(&format!("c{i}"), user, t0);
            assert_eq!(line.keep(&format!("c{i}"), user, t0), Place::InLine(i + 1));
        }
        assert_eq!(line.keep("one-too-many", -1, t0), Place::NotKept);
        assert_eq!(line.ahead_of("one-too-many", t0), CAPACITY);
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
