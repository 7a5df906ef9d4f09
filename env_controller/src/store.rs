//! The experiment store (SQLite via rusqlite, WAL): users with hashed
//! tokens, experiments with their counters, and one row per finished
//! episode, written in one transaction as each episode ends — a crash
//! loses at most the episode in progress.

use std::path::Path;

use offworld_runtime::msg::{AlgorithmMode, Booking, LeaderboardEntry, LearningType};
use rand::Rng;
use rusqlite::{params, Connection, OptionalExtension};
use sha2::{Digest, Sha256};

use crate::error::ControllerError;

/// A registered user.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct User {
    /// Row id.
    pub id: i64,
    /// Display name.
    pub name: String,
    /// `user` or `operator`.
    pub role: String,
}

impl User {
    /// Operators may put envs into maintenance.
    pub fn is_operator(&self) -> bool {
        self.role == "operator"
    }
}

/// An experiment row.
#[derive(Debug, Clone, PartialEq)]
pub struct Experiment {
    /// Row id.
    pub id: i64,
    /// Owner.
    pub user: String,
    /// Env it runs on.
    pub env_id: String,
    /// Task name.
    pub task: String,
    /// Experiment name.
    pub name: String,
    /// `end2end`, `sim2real`, `humandemos`.
    pub learning_type: String,
    /// `train` or `test`.
    pub algorithm_mode: String,
    /// Finished episodes.
    pub episodes: u64,
    /// Steps in finished episodes.
    pub steps: u64,
}

/// One recorded episode, as listed.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeSummary {
    /// Episode index within the experiment.
    pub index: u64,
    /// Steps taken.
    pub steps: u32,
    /// Sum of rewards.
    pub episode_return: f64,
    /// Reached the monolith.
    pub success: bool,
    /// Why it ended.
    pub end_reason: String,
}

/// A finished (or aborted) episode.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeRecord {
    /// Experiment row id.
    pub experiment_id: i64,
    /// Episode index within the experiment.
    pub episode_index: u64,
    /// Seed passed to reset, if any.
    pub seed: Option<u64>,
    /// Steps taken.
    pub steps: u32,
    /// Sum of rewards.
    pub episode_return: f64,
    /// Reached the monolith.
    pub success: bool,
    /// Why it ended.
    pub end_reason: String,
    /// Spawn pose asked for (x, y, yaw).
    pub requested_start: [f64; 3],
    /// Spawn pose reached (x, y, yaw): the reset-accuracy record.
    pub achieved_start: [f64; 3],
    /// Unix ms.
    pub started_ms: i64,
    /// Unix ms.
    pub ended_ms: i64,
}

const SCHEMA: &str = "
PRAGMA journal_mode = WAL;
PRAGMA synchronous = NORMAL;
PRAGMA foreign_keys = ON;
CREATE TABLE IF NOT EXISTS users (
    id INTEGER PRIMARY KEY,
    name TEXT NOT NULL UNIQUE,
    token_sha256 TEXT NOT NULL UNIQUE,
    role TEXT NOT NULL DEFAULT 'user',
    created_ms INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS experiments (
    id INTEGER PRIMARY KEY,
    user_id INTEGER NOT NULL REFERENCES users(id),
    env_id TEXT NOT NULL,
    task TEXT NOT NULL,
    name TEXT NOT NULL,
    learning_type TEXT NOT NULL,
    algorithm_mode TEXT NOT NULL,
    episodes INTEGER NOT NULL DEFAULT 0,
    steps INTEGER NOT NULL DEFAULT 0,
    created_ms INTEGER NOT NULL,
    updated_ms INTEGER NOT NULL,
    UNIQUE (user_id, env_id, name)
);
CREATE TABLE IF NOT EXISTS episodes (
    id INTEGER PRIMARY KEY,
    experiment_id INTEGER NOT NULL REFERENCES experiments(id),
    episode_index INTEGER NOT NULL,
    seed INTEGER,
    steps INTEGER NOT NULL,
    episode_return REAL NOT NULL,
    success INTEGER NOT NULL,
    end_reason TEXT NOT NULL,
    requested_x REAL NOT NULL, requested_y REAL NOT NULL, requested_yaw REAL NOT NULL,
    achieved_x REAL NOT NULL, achieved_y REAL NOT NULL, achieved_yaw REAL NOT NULL,
    started_ms INTEGER NOT NULL,
    ended_ms INTEGER NOT NULL,
    UNIQUE (experiment_id, episode_index)
);
CREATE TABLE IF NOT EXISTS bookings (
    id INTEGER PRIMARY KEY,
    env_id TEXT NOT NULL,
    user_id INTEGER NOT NULL REFERENCES users(id),
    start_ms INTEGER NOT NULL,
    end_ms INTEGER NOT NULL,
    created_ms INTEGER NOT NULL,
    CHECK (end_ms > start_ms)
);
CREATE INDEX IF NOT EXISTS bookings_by_env ON bookings (env_id, end_ms);
";

/// Name of the user sim envs admit without a token.
pub const ANONYMOUS: &str = "anonymous";

/// The store.
pub struct Store {
    conn: Connection,
}

fn db(e: rusqlite::Error) -> ControllerError {
    ControllerError::Store(e.to_string())
}

/// Wall clock, Unix ms.
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// SHA-256 of a token, hex. Tokens are random 128-bit strings, so a plain
/// hash suffices (no dictionary to attack).
pub fn hash_token(token: &str) -> String {
    Sha256::digest(token.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

impl Store {
    /// Opens (creating if needed) a database file.
    pub fn open(path: &Path) -> Result<Self, ControllerError> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir)
                .map_err(|e| ControllerError::Store(format!("{}: {e}", dir.display())))?;
        }
        Self::init(Connection::open(path).map_err(db)?)
    }

    /// A private in-memory database (embedded sims that keep no records).
    pub fn in_memory() -> Result<Self, ControllerError> {
        Self::init(Connection::open_in_memory().map_err(db)?)
    }

    fn init(conn: Connection) -> Result<Self, ControllerError> {
        conn.execute_batch(SCHEMA).map_err(db)?;
        conn.execute(
            "INSERT OR IGNORE INTO users (name, token_sha256, role, created_ms) VALUES (?1, ?2, 'user', ?3)",
            params![ANONYMOUS, hash_token(""), now_ms()],
        )
        .map_err(db)?;
        Ok(Self { conn })
    }

    /// Registers a user and returns their token (shown once, stored hashed).
    pub fn add_user(&self, name: &str, operator: bool) -> Result<String, ControllerError> {
        let token: String = {
            let mut rng = rand::rng();
            (0..32)
                .map(|_| format!("{:x}", rng.random_range(0..16u8)))
                .collect()
        };
        self.add_user_with_token(name, &token, operator)?;
        Ok(token)
    }

    /// Registers a user with a given token (deployment scripts, tests).
    pub fn add_user_with_token(
        &self,
        name: &str,
        token: &str,
        operator: bool,
    ) -> Result<(), ControllerError> {
        if token.len() < 8 {
            return Err(ControllerError::Config(
                "tokens must have at least 8 characters".into(),
            ));
        }
        let role = if operator { "operator" } else { "user" };
        self.conn
            .execute(
                "INSERT INTO users (name, token_sha256, role, created_ms) VALUES (?1, ?2, ?3, ?4)",
                params![name, hash_token(token), role, now_ms()],
            )
            .map_err(db)?;
        Ok(())
    }

    /// The user holding `token`, if any.
    pub fn authenticate(&self, token: &str) -> Result<Option<User>, ControllerError> {
        self.conn
            .query_row(
                "SELECT id, name, role FROM users WHERE token_sha256 = ?1",
                params![hash_token(token)],
                |r| {
                    Ok(User {
                        id: r.get(0)?,
                        name: r.get(1)?,
                        role: r.get(2)?,
                    })
                },
            )
            .optional()
            .map_err(db)
    }

    /// Creates or resumes an experiment. Resuming an unknown experiment, or
    /// creating one that exists, is an error.
    #[allow(clippy::too_many_arguments)]
    pub fn open_experiment(
        &self,
        user: &User,
        env_id: &str,
        task: &str,
        name: &str,
        resume: bool,
        learning_type: LearningType,
        mode: AlgorithmMode,
    ) -> Result<Experiment, ControllerError> {
        let existing = self.experiment(user.id, env_id, name)?;
        match (existing, resume) {
            (Some(e), true) => Ok(e),
            (Some(_), false) => Err(ControllerError::Conflict(format!(
                "experiment `{name}` exists on {env_id}; pass resume_experiment=True to continue it"
            ))),
            (None, true) => Err(ControllerError::NotFound(format!(
                "no experiment `{name}` on {env_id} to resume"
            ))),
            (None, false) => {
                let now = now_ms();
                self.conn
                    .execute(
                        "INSERT INTO experiments (user_id, env_id, task, name, learning_type, algorithm_mode, created_ms, updated_ms)
                         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?7)",
                        params![user.id, env_id, task, name, learning_type.as_str(), mode.as_str(), now],
                    )
                    .map_err(db)?;
                self.experiment(user.id, env_id, name)?.ok_or_else(|| {
                    ControllerError::Store("experiment vanished after insert".into())
                })
            }
        }
    }

    fn experiment(
        &self,
        user_id: i64,
        env_id: &str,
        name: &str,
    ) -> Result<Option<Experiment>, ControllerError> {
        self.conn
            .query_row(
                "SELECT e.id, u.name, e.env_id, e.task, e.name, e.learning_type, e.algorithm_mode, e.episodes, e.steps
                 FROM experiments e JOIN users u ON u.id = e.user_id
                 WHERE e.user_id = ?1 AND e.env_id = ?2 AND e.name = ?3",
                params![user_id, env_id, name],
                experiment_row,
            )
            .optional()
            .map_err(db)
    }

    /// Records a finished episode and advances its experiment's counters,
    /// atomically.
    pub fn record_episode(&mut self, ep: &EpisodeRecord) -> Result<(), ControllerError> {
        let tx = self.conn.transaction().map_err(db)?;
        tx.execute(
            "INSERT INTO episodes (experiment_id, episode_index, seed, steps, episode_return, success, end_reason,
                requested_x, requested_y, requested_yaw, achieved_x, achieved_y, achieved_yaw, started_ms, ended_ms)
             VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15)",
            params![
                ep.experiment_id,
                ep.episode_index as i64,
                ep.seed.map(|s| s as i64),
                ep.steps,
                ep.episode_return,
                ep.success,
                ep.end_reason,
                ep.requested_start[0],
                ep.requested_start[1],
                ep.requested_start[2],
                ep.achieved_start[0],
                ep.achieved_start[1],
                ep.achieved_start[2],
                ep.started_ms,
                ep.ended_ms
            ],
        )
        .map_err(db)?;
        tx.execute(
            "UPDATE experiments SET episodes = episodes + 1, steps = steps + ?2, updated_ms = ?3 WHERE id = ?1",
            params![ep.experiment_id, ep.steps, ep.ended_ms],
        )
        .map_err(db)?;
        tx.commit().map_err(db)
    }

    /// All experiments, newest first.
    pub fn experiments(&self) -> Result<Vec<Experiment>, ControllerError> {
        let mut stmt = self
            .conn
            .prepare(
                "SELECT e.id, u.name, e.env_id, e.task, e.name, e.learning_type, e.algorithm_mode, e.episodes, e.steps
                 FROM experiments e JOIN users u ON u.id = e.user_id ORDER BY e.updated_ms DESC, e.id DESC",
            )
            .map_err(db)?;
        let rows = stmt.query_map([], experiment_row).map_err(db)?;
        rows.collect::<Result<_, _>>().map_err(db)
    }

    /// Episodes of one experiment, in order.
    pub fn episodes(&self, experiment_id: i64) -> Result<Vec<EpisodeSummary>, ControllerError> {
        let mut stmt = self
            .conn
            .prepare(
                "SELECT episode_index, steps, episode_return, success, end_reason FROM episodes
                 WHERE experiment_id = ?1 ORDER BY episode_index",
            )
            .map_err(db)?;
        let rows = stmt
            .query_map(params![experiment_id], |r| {
                Ok(EpisodeSummary {
                    index: r.get::<_, i64>(0)? as u64,
                    steps: r.get(1)?,
                    episode_return: r.get(2)?,
                    success: r.get(3)?,
                    end_reason: r.get(4)?,
                })
            })
            .map_err(db)?;
        rows.collect::<Result<_, _>>().map_err(db)
    }

    /// Test-mode experiments on `env_id`, ranked by success rate then mean
    /// return. Aborted episodes do not count.
    pub fn leaderboard(&self, env_id: &str) -> Result<Vec<LeaderboardEntry>, ControllerError> {
        let mut stmt = self
            .conn
            .prepare(
                "SELECT e.name, u.name, e.learning_type, COUNT(p.id), AVG(p.success), AVG(p.episode_return)
                 FROM experiments e JOIN users u ON u.id = e.user_id JOIN episodes p ON p.experiment_id = e.id
                 WHERE e.env_id = ?1 AND e.algorithm_mode = 'test'
                   AND p.end_reason IN ('success', 'out_of_bounds', 'step_limit')
                 GROUP BY e.id
                 ORDER BY AVG(p.success) DESC, AVG(p.episode_return) DESC, e.name",
            )
            .map_err(db)?;
        let rows = stmt
            .query_map(params![env_id], |r| {
                Ok(LeaderboardEntry {
                    experiment: r.get(0)?,
                    user: r.get(1)?,
                    learning_type: r.get(2)?,
                    episodes: r.get::<_, i64>(3)? as u64,
                    success_rate: r.get(4)?,
                    mean_return: r.get(5)?,
                })
            })
            .map_err(db)?;
        rows.collect::<Result<_, _>>().map_err(db)
    }
}

fn experiment_row(r: &rusqlite::Row<'_>) -> rusqlite::Result<Experiment> {
    Ok(Experiment {
        id: r.get(0)?,
        user: r.get(1)?,
        env_id: r.get(2)?,
        task: r.get(3)?,
        name: r.get(4)?,
        learning_type: r.get(5)?,
        algorithm_mode: r.get(6)?,
        episodes: r.get::<_, i64>(7)? as u64,
        steps: r.get::<_, i64>(8)? as u64,
    })
}

/// Limits on bookings.
#[derive(Debug, Clone, Copy)]
pub struct BookingRules {
    /// Longest slot.
    pub max_slot_ms: i64,
    /// How far ahead a slot may start.
    pub horizon_ms: i64,
}

impl Default for BookingRules {
    fn default() -> Self {
        Self {
            max_slot_ms: 4 * 3600 * 1000,
            horizon_ms: 30 * 24 * 3600 * 1000,
        }
    }
}

fn format_ms(ms: i64) -> String {
    let t = std::time::UNIX_EPOCH + std::time::Duration::from_millis(ms.max(0) as u64);
    humantime::format_rfc3339_seconds(t).to_string()
}

/// The booking situation of an env at a time (see [`Store::slot_at`]).
#[derive(Debug, Clone, PartialEq)]
pub struct SlotAt {
    /// The slot in progress and its holder's user id.
    pub slot: Option<(Booking, i64)>,
    /// Unix ms until which `slot` stays the answer, barring new bookings.
    pub until_ms: i64,
}

const BOOKING_COLUMNS: &str =
    "b.id, b.env_id, u.name, b.start_ms, b.end_ms, b.user_id FROM bookings b JOIN users u ON u.id = b.user_id";

fn booking_row(r: &rusqlite::Row<'_>) -> rusqlite::Result<(Booking, i64)> {
    Ok((
        Booking {
            id: r.get(0)?,
            env_id: r.get(1)?,
            user: r.get(2)?,
            start_unix_ms: r.get(3)?,
            end_unix_ms: r.get(4)?,
        },
        r.get(5)?,
    ))
}

impl Store {
    /// Reserves `[start_ms, end_ms)` on `env_id` for `user`, atomically
    /// against overlapping slots.
    pub fn book(
        &mut self,
        user: &User,
        env_id: &str,
        start_ms: i64,
        end_ms: i64,
        now_ms: i64,
        rules: BookingRules,
    ) -> Result<Booking, ControllerError> {
        if user.name == ANONYMOUS {
            return Err(ControllerError::Unauthorized(
                "bookings need a registered user's token".into(),
            ));
        }
        if end_ms <= start_ms {
            return Err(ControllerError::Config(format!(
                "a slot must end after it starts ({} .. {})",
                format_ms(start_ms),
                format_ms(end_ms)
            )));
        }
        if end_ms <= now_ms {
            return Err(ControllerError::Config(format!(
                "the slot ended already at {}",
                format_ms(end_ms)
            )));
        }
        if end_ms - start_ms > rules.max_slot_ms {
            return Err(ControllerError::Config(format!(
                "slots are at most {} min long",
                rules.max_slot_ms / 60_000
            )));
        }
        if start_ms > now_ms + rules.horizon_ms {
            return Err(ControllerError::Config(format!(
                "slots may start at most {} days ahead",
                rules.horizon_ms / 86_400_000
            )));
        }
        // A slot that started already begins now.
        let start_ms = start_ms.max(now_ms);
        let tx = self.conn.transaction().map_err(db)?;
        let clash = tx
            .query_row(
                &format!(
                    "SELECT {BOOKING_COLUMNS} WHERE b.env_id = ?1 AND b.start_ms < ?3 AND b.end_ms > ?2 ORDER BY b.start_ms LIMIT 1"
                ),
                params![env_id, start_ms, end_ms],
                booking_row,
            )
            .optional()
            .map_err(db)?;
        if let Some((b, _)) = clash {
            return Err(ControllerError::Busy(format!(
                "{env_id} is booked by {} from {} to {}",
                b.user,
                format_ms(b.start_unix_ms),
                format_ms(b.end_unix_ms)
            )));
        }
        tx.execute(
            "INSERT INTO bookings (env_id, user_id, start_ms, end_ms, created_ms) VALUES (?1, ?2, ?3, ?4, ?5)",
            params![env_id, user.id, start_ms, end_ms, now_ms],
        )
        .map_err(db)?;
        let id = tx.last_insert_rowid();
        tx.commit().map_err(db)?;
        Ok(Booking {
            id,
            env_id: env_id.to_owned(),
            user: user.name.clone(),
            start_unix_ms: start_ms,
            end_unix_ms: end_ms,
        })
    }

    /// Slots of `env_id` ending after `from_ms`, earliest first.
    pub fn bookings(&self, env_id: &str, from_ms: i64) -> Result<Vec<Booking>, ControllerError> {
        let mut stmt = self
            .conn
            .prepare(&format!(
                "SELECT {BOOKING_COLUMNS} WHERE b.env_id = ?1 AND b.end_ms > ?2 ORDER BY b.start_ms"
            ))
            .map_err(db)?;
        let rows = stmt
            .query_map(params![env_id, from_ms], booking_row)
            .map_err(db)?;
        rows.map(|r| r.map(|(b, _)| b).map_err(db)).collect()
    }

    /// The slot of `env_id` covering `at_ms`, with its holder's user id.
    pub fn booking_at(
        &self,
        env_id: &str,
        at_ms: i64,
    ) -> Result<Option<(Booking, i64)>, ControllerError> {
        self.conn
            .query_row(
                &format!(
                    "SELECT {BOOKING_COLUMNS} WHERE b.env_id = ?1 AND b.start_ms <= ?2 AND b.end_ms > ?2 LIMIT 1"
                ),
                params![env_id, at_ms],
                booking_row,
            )
            .optional()
            .map_err(db)
    }

    /// The slot of `env_id` covering `at_ms` and until when that answer
    /// holds (the slot's end, or the next slot's start), so callers can
    /// skip the database until then.
    pub fn slot_at(&self, env_id: &str, at_ms: i64) -> Result<SlotAt, ControllerError> {
        let slot = self.booking_at(env_id, at_ms)?;
        let until_ms = match &slot {
            Some((booking, _)) => booking.end_unix_ms,
            None => self
                .conn
                .query_row(
                    "SELECT MIN(start_ms) FROM bookings WHERE env_id = ?1 AND start_ms > ?2",
                    params![env_id, at_ms],
                    |r| r.get::<_, Option<i64>>(0),
                )
                .map_err(db)?
                .unwrap_or(i64::MAX),
        };
        Ok(SlotAt { slot, until_ms })
    }

    /// Cancels a slot: its holder's, or any for an operator.
    pub fn cancel_booking(
        &self,
        user: &User,
        env_id: &str,
        id: i64,
    ) -> Result<(), ControllerError> {
        let holder: Option<i64> = self
            .conn
            .query_row(
                "SELECT user_id FROM bookings WHERE id = ?1 AND env_id = ?2",
                params![id, env_id],
                |r| r.get(0),
            )
            .optional()
            .map_err(db)?;
        match holder {
            None => Err(ControllerError::NotFound(format!(
                "no booking {id} on {env_id}"
            ))),
            Some(h) if h != user.id && !user.is_operator() => Err(ControllerError::Unauthorized(
                format!("booking {id} is someone else's"),
            )),
            Some(_) => {
                self.conn
                    .execute("DELETE FROM bookings WHERE id = ?1", params![id])
                    .map_err(db)?;
                Ok(())
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slot_at_says_until_when_the_answer_holds() {
        let mut store = Store::in_memory().expect("store");
        let token = store.add_user("ada", false).expect("user");
        let ada = store
            .authenticate(&token)
            .expect("db")
            .expect("ada is known");
        let (env, now) = ("sim/a", 1_000_000);
        let free = store.slot_at(env, now).expect("query");
        assert_eq!(
            free,
            SlotAt {
                slot: None,
                until_ms: i64::MAX
            }
        );
        let rules = BookingRules::default();
        let first = store
            .book(&ada, env, now + 10_000, now + 20_000, now, rules)
            .expect("first slot");
        store
            .book(&ada, env, now + 20_000, now + 30_000, now, rules)
            .expect("adjacent slot");
        // Before the first slot: free until it starts.
        let before = store.slot_at(env, now).expect("query");
        assert_eq!((before.slot, before.until_ms), (None, now + 10_000));
        // In it: held until its end, where the adjacent one takes over.
        let during = store.slot_at(env, now + 10_000).expect("query");
        assert_eq!(during.until_ms, now + 20_000);
        assert_eq!(
            during.slot.map(|(b, holder)| (b.id, holder)),
            Some((first.id, ada.id))
        );
        let next = store.slot_at(env, now + 20_000).expect("query");
        assert_eq!(next.until_ms, now + 30_000);
        // Another env's bookings never count.
        assert_eq!(
            store.slot_at("sim/b", now + 15_000).expect("query").slot,
            None
        );
    }
}
