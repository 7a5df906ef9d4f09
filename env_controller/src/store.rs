//! The experiment store (SQLite via rusqlite, WAL): users with hashed
//! tokens, experiments with their counters, and one row per finished
//! episode, written in one transaction as each episode ends — a crash
//! loses at most the episode in progress.

use std::cell::RefCell;
use std::collections::HashSet;
use std::fmt::Write as _;
use std::path::Path;
use std::sync::{Mutex, MutexGuard, PoisonError};

use offworld_runtime::msg::{
    AlgorithmMode, Booking, EpisodeRecordEntry, ExperimentRecord, LeaderboardEntry, LearningType,
    Pose2D, ResetAccuracy,
};
use rand::Rng;
use rusqlite::{params, Connection, OptionalExtension};
use rusqlite_migration::{Migrations, M};
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

/// A registered user as `users list` shows them (never their token).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UserRecord {
    /// Name.
    pub name: String,
    /// `user` or `operator`.
    pub role: String,
    /// When registered, Unix ms.
    pub created_ms: i64,
    /// When the current token was issued, Unix ms.
    pub token_issued_ms: i64,
    /// When the token was revoked (it no longer works), Unix ms.
    pub revoked_ms: Option<i64>,
    /// Experiments they own.
    pub experiments: i64,
}

impl User {
    /// Operators may put envs into maintenance.
    pub fn is_operator(&self) -> bool {
        self.role == "operator"
    }
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
    /// Spawn pose asked for and reached, and how long the reset took.
    pub reset: ResetAccuracy,
    /// Unix ms.
    pub started_ms: i64,
    /// Unix ms.
    pub ended_ms: i64,
}

/// The end reason of an episode that has not ended (yet).
pub const IN_PROGRESS: &str = "in_progress";

fn insert_episode(
    tx: &rusqlite::Transaction<'_>,
    ep: &EpisodeRecord,
) -> Result<(), ControllerError> {
    tx.execute(
        "INSERT INTO episodes (experiment_id, episode_index, seed, steps, episode_return, success, end_reason,
            requested_x, requested_y, requested_yaw, achieved_x, achieved_y, achieved_yaw, started_ms, ended_ms,
            reset_us)
         VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8, ?9, ?10, ?11, ?12, ?13, ?14, ?15, ?16)",
        params![
            ep.experiment_id,
            ep.episode_index as i64,
            ep.seed.map(|s| s as i64),
            ep.steps,
            ep.episode_return,
            ep.success,
            ep.end_reason,
            ep.reset.requested.x,
            ep.reset.requested.y,
            ep.reset.requested.yaw,
            ep.reset.achieved.x,
            ep.reset.achieved.y,
            ep.reset.achieved.yaw,
            ep.started_ms,
            ep.ended_ms,
            ep.reset
                .measured
                .then(|| (ep.reset.duration_s * 1e6).round() as i64)
        ],
    )
    .map_err(db)?;
    Ok(())
}

/// WAL with `synchronous = FULL`: a committed transaction (an episode's
/// record, a booking) is on disk before the call returns, so it survives a
/// killed process and a power cut alike; one fsync per episode start and
/// end is nothing beside a robot's step. (Outside the migrations: a
/// journal mode cannot change inside their transaction.)
const PRAGMAS: &str = "
PRAGMA journal_mode = WAL;
PRAGMA synchronous = FULL;
PRAGMA foreign_keys = ON;
";

/// The schema's versions, oldest first: SQLite's `user_version` says how
/// many a database has applied, and opening it applies the rest in one
/// transaction. Append a migration for every change; never edit one that
/// has shipped (site databases have applied it).
const MIGRATIONS: &[M<'static>] = &[
    // 1: the schema as it was before versions were recorded. `IF NOT
    // EXISTS`, so a database made then (user_version 0, tables present)
    // takes it as a no-op.
    M::up(SCHEMA_1),
    // 2: how long each reset took, µs (a twin's takes well under a ms;
    // NULL for the episodes before).
    M::up("ALTER TABLE episodes ADD COLUMN reset_us INTEGER;"),
    // 3: revoked tokens (NULL: the token works) and when a user's token was
    // last issued (rotation).
    M::up(
        "ALTER TABLE users ADD COLUMN revoked_ms INTEGER;
         ALTER TABLE users ADD COLUMN token_issued_ms INTEGER;",
    ),
];

/// The schema version this build writes.
pub const SCHEMA_VERSION: usize = MIGRATIONS.len();

const SCHEMA_1: &str = "
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
    /// Booking rows read back that break the invariants (see
    /// [`booking_violation`]): ignored, and warned about once each.
    quarantine: Quarantine,
}

/// Locks the shared store. A panic while it was held (a bug) does not make
/// it unusable: SQLite rolled back the transaction the panic interrupted
/// (a [`rusqlite::Transaction`] dropped unfinished rolls back), so the
/// store is as consistent as after any failed request.
pub fn lock_store(store: &Mutex<Store>) -> MutexGuard<'_, Store> {
    store.lock().unwrap_or_else(PoisonError::into_inner)
}

fn db(e: rusqlite::Error) -> ControllerError {
    ControllerError::Store(e.to_string())
}

/// A new access token: 128 random bits as 32 hex digits.
fn new_token() -> String {
    let mut rng = rand::rng();
    (0..32)
        .map(|_| format!("{:x}", rng.random_range(0..16u8)))
        .collect()
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

    /// Opens a database file that exists (the record-keeping commands: a
    /// mistyped `--db` must not look like an empty site).
    pub fn open_existing(path: &Path) -> Result<Self, ControllerError> {
        if !path.is_file() {
            return Err(ControllerError::NotFound(format!(
                "no database at {} (name it with --db PATH or OFFWORLD_DB; `serve` and \
                 `users add` create one)",
                path.display()
            )));
        }
        Self::open(path)
    }

    /// A private in-memory database (embedded sims that keep no records).
    pub fn in_memory() -> Result<Self, ControllerError> {
        Self::init(Connection::open_in_memory().map_err(db)?)
    }

    fn init(mut conn: Connection) -> Result<Self, ControllerError> {
        let migrations = Migrations::from_slice(MIGRATIONS);
        // Refuse a database a newer build made before touching it: its
        // data may depend on columns this build would not write.
        let version: usize = conn
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .map_err(db)?;
        if version > SCHEMA_VERSION {
            return Err(ControllerError::Store(format!(
                "the database has schema version {version}, newer than this env_controller's \
                 {SCHEMA_VERSION}: run the env_controller that wrote it, or a newer one"
            )));
        }
        conn.execute_batch(PRAGMAS).map_err(db)?;
        migrations
            .to_latest(&mut conn)
            .map_err(|e| ControllerError::Store(format!("migrating the schema: {e}")))?;
        conn.execute(
            "INSERT OR IGNORE INTO users (name, token_sha256, role, created_ms) VALUES (?1, ?2, 'user', ?3)",
            params![ANONYMOUS, hash_token(""), now_ms()],
        )
        .map_err(db)?;
        Ok(Self {
            conn,
            quarantine: Quarantine::default(),
        })
    }

    /// Registers a user and returns their token (shown once, stored hashed).
    pub fn add_user(&self, name: &str, operator: bool) -> Result<String, ControllerError> {
        let token = new_token();
        self.add_user_with_token(name, &token, operator)?;
        Ok(token)
    }

    /// Every registered user (not the anonymous one), by name.
    pub fn users(&self) -> Result<Vec<UserRecord>, ControllerError> {
        let mut statement = self
            .conn
            .prepare(
                "SELECT u.name, u.role, u.created_ms, COALESCE(u.token_issued_ms, u.created_ms),
                        u.revoked_ms, (SELECT COUNT(*) FROM experiments e WHERE e.user_id = u.id)
                 FROM users u WHERE u.name != ?1 ORDER BY u.name",
            )
            .map_err(db)?;
        let rows = statement
            .query_map(params![ANONYMOUS], |r| {
                Ok(UserRecord {
                    name: r.get(0)?,
                    role: r.get(1)?,
                    created_ms: r.get(2)?,
                    token_issued_ms: r.get(3)?,
                    revoked_ms: r.get(4)?,
                    experiments: r.get(5)?,
                })
            })
            .map_err(db)?;
        rows.collect::<Result<_, _>>().map_err(db)
    }

    /// Revokes `name`'s token: it no longer opens a session, books or
    /// administers (their records stay). A lease taken before runs until it
    /// ends; an operator revokes it from the web console.
    pub fn revoke_user(&self, name: &str) -> Result<(), ControllerError> {
        self.user_named(name)?;
        self.conn
            .execute(
                "UPDATE users SET revoked_ms = COALESCE(revoked_ms, ?2) WHERE name = ?1",
                params![name, now_ms()],
            )
            .map_err(db)?;
        Ok(())
    }

    /// Issues `name` a new token (returned, shown once) in place of the old
    /// one, which stops working; a revoked user is reinstated with it.
    pub fn rotate_token(&self, name: &str) -> Result<String, ControllerError> {
        self.user_named(name)?;
        let token = new_token();
        self.conn
            .execute(
                "UPDATE users SET token_sha256 = ?2, token_issued_ms = ?3, revoked_ms = NULL
                 WHERE name = ?1",
                params![name, hash_token(&token), now_ms()],
            )
            .map_err(db)?;
        Ok(token)
    }

    /// Checks that a registered user `name` exists.
    fn user_named(&self, name: &str) -> Result<(), ControllerError> {
        validate_user_name(name)?;
        let known: bool = self
            .conn
            .query_row(
                "SELECT EXISTS (SELECT 1 FROM users WHERE name = ?1 AND name != ?2)",
                params![name, ANONYMOUS],
                |r| r.get(0),
            )
            .map_err(db)?;
        if known {
            Ok(())
        } else {
            Err(ControllerError::NotFound(format!(
                "no user named {name} (env_controller users list shows them)"
            )))
        }
    }

    /// Registers a user with a given token (deployment scripts, tests).
    pub fn add_user_with_token(
        &self,
        name: &str,
        token: &str,
        operator: bool,
    ) -> Result<(), ControllerError> {
        validate_user_name(name)?;
        if token.len() < 8 || token.len() > MAX_TOKEN_LEN {
            return Err(ControllerError::Config(format!(
                "tokens must have 8 to {MAX_TOKEN_LEN} characters"
            )));
        }
        let role = if operator { "operator" } else { "user" };
        let now = now_ms();
        let inserted = self.conn.execute(
            "INSERT INTO users (name, token_sha256, role, created_ms, token_issued_ms)
             VALUES (?1, ?2, ?3, ?4, ?4)",
            params![name, hash_token(token), role, now],
        );
        match inserted {
            Ok(_) => Ok(()),
            Err(rusqlite::Error::SqliteFailure(e, _))
                if e.code == rusqlite::ErrorCode::ConstraintViolation =>
            {
                let taken: bool = self
                    .conn
                    .query_row(
                        "SELECT EXISTS (SELECT 1 FROM users WHERE name = ?1)",
                        params![name],
                        |r| r.get(0),
                    )
                    .map_err(db)?;
                Err(ControllerError::Conflict(if taken {
                    format!(
                        "a user named {name} exists already (env_controller users list; users rotate {name} \
                         issues a new token)"
                    )
                } else {
                    "that token is another user's: choose another".into()
                }))
            }
            Err(e) => Err(db(e)),
        }
    }

    /// The user holding `token`, if any. A token longer than any issued
    /// is unknown without being hashed.
    pub fn authenticate(&self, token: &str) -> Result<Option<User>, ControllerError> {
        if token.len() > MAX_TOKEN_LEN {
            return Ok(None);
        }
        self.conn
            .query_row(
                "SELECT id, name, role FROM users WHERE token_sha256 = ?1 AND revoked_ms IS NULL",
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
    ) -> Result<ExperimentRecord, ControllerError> {
        validate_experiment_name(name)?;
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
    ) -> Result<Option<ExperimentRecord>, ControllerError> {
        Ok(self
            .experiments_where(
                "e.user_id = ?1 AND e.env_id = ?2 AND e.name = ?3",
                params![user_id, env_id, name],
            )?
            .pop())
    }

    /// Records an episode that starts now (end reason [`IN_PROGRESS`]) and
    /// counts it in its experiment, so a controller killed before the end
    /// still leaves its record: [`Store::abandon_in_progress`] closes it
    /// at the next start.
    pub fn begin_episode(&mut self, ep: &EpisodeRecord) -> Result<(), ControllerError> {
        let started = EpisodeRecord {
            steps: 0,
            episode_return: 0.0,
            success: false,
            end_reason: IN_PROGRESS.to_owned(),
            ended_ms: ep.started_ms,
            ..ep.clone()
        };
        let tx = self.conn.transaction().map_err(db)?;
        insert_episode(&tx, &started)?;
        tx.execute(
            "UPDATE experiments SET episodes = episodes + 1, updated_ms = ?2 WHERE id = ?1",
            params![ep.experiment_id, ep.started_ms],
        )
        .map_err(db)?;
        tx.commit().map_err(db)
    }

    /// Records a finished episode and advances its experiment's counters,
    /// atomically: completes the row [`Store::begin_episode`] wrote, or
    /// adds one.
    pub fn record_episode(&mut self, ep: &EpisodeRecord) -> Result<(), ControllerError> {
        let tx = self.conn.transaction().map_err(db)?;
        let completed = tx
            .execute(
                "UPDATE episodes SET steps = ?3, episode_return = ?4, success = ?5, end_reason = ?6, ended_ms = ?7
                 WHERE experiment_id = ?1 AND episode_index = ?2 AND end_reason = ?8",
                params![
                    ep.experiment_id,
                    ep.episode_index as i64,
                    ep.steps,
                    ep.episode_return,
                    ep.success,
                    ep.end_reason,
                    ep.ended_ms,
                    IN_PROGRESS
                ],
            )
            .map_err(db)?;
        if completed == 0 {
            insert_episode(&tx, ep)?;
        }
        tx.execute(
            "UPDATE experiments SET episodes = episodes + ?4, steps = steps + ?2, updated_ms = ?3 WHERE id = ?1",
            params![ep.experiment_id, ep.steps, ep.ended_ms, i64::from(completed == 0)],
        )
        .map_err(db)?;
        tx.commit().map_err(db)
    }

    /// Saves how far the episode in progress `ep` got (steps, return, when),
    /// so that a controller killed mid-episode loses at most what came
    /// after the last save; the row stays in progress.
    pub fn progress_episode(&mut self, ep: &EpisodeRecord) -> Result<(), ControllerError> {
        self.conn
            .execute(
                "UPDATE episodes SET steps = ?3, episode_return = ?4, ended_ms = ?5
                 WHERE experiment_id = ?1 AND episode_index = ?2 AND end_reason = ?6",
                params![
                    ep.experiment_id,
                    ep.episode_index as i64,
                    ep.steps,
                    ep.episode_return,
                    ep.ended_ms,
                    IN_PROGRESS
                ],
            )
            .map(|_| ())
            .map_err(db)
    }

    /// Closes the episodes of `env_id` still in progress (their controller
    /// stopped without ending them: killed, power cut) as aborted with
    /// `reason`; returns how many.
    pub fn abandon_in_progress(
        &mut self,
        env_id: &str,
        reason: &str,
    ) -> Result<usize, ControllerError> {
        let tx = self.conn.transaction().map_err(db)?;
        // Their saved steps count for the experiment, as an ended episode's do.
        tx.execute(
            "UPDATE experiments SET steps = steps + (
                 SELECT COALESCE(SUM(steps), 0) FROM episodes
                 WHERE experiment_id = experiments.id AND end_reason = ?2)
             WHERE env_id = ?1",
            params![env_id, IN_PROGRESS],
        )
        .map_err(db)?;
        let closed = tx
            .execute(
                "UPDATE episodes SET end_reason = ?2
                 WHERE end_reason = ?3
                   AND experiment_id IN (SELECT id FROM experiments WHERE env_id = ?1)",
                params![env_id, reason, IN_PROGRESS],
            )
            .map_err(db)?;
        tx.commit().map_err(db)?;
        Ok(closed)
    }

    /// All experiments, most recently used first.
    pub fn experiments(&self) -> Result<Vec<ExperimentRecord>, ControllerError> {
        self.experiments_where("1", params![])
    }

    /// The experiments on `env_id`, most recently used first: `owner`'s
    /// only, or everyone's with `None`.
    pub fn experiments_on(
        &self,
        env_id: &str,
        owner: Option<&User>,
    ) -> Result<Vec<ExperimentRecord>, ControllerError> {
        match owner {
            Some(user) => {
                self.experiments_where("e.env_id = ?1 AND e.user_id = ?2", params![env_id, user.id])
            }
            None => self.experiments_where("e.env_id = ?1", params![env_id]),
        }
    }

    /// Experiment `id`, if it exists.
    pub fn experiment_by_id(&self, id: i64) -> Result<Option<ExperimentRecord>, ControllerError> {
        Ok(self.experiments_where("e.id = ?1", params![id])?.pop())
    }

    /// `condition` is one of this module's literals, never user text.
    fn experiments_where(
        &self,
        condition: &str,
        values: &[&dyn rusqlite::ToSql],
    ) -> Result<Vec<ExperimentRecord>, ControllerError> {
        let mut stmt = self
            .conn
            .prepare(&format!(
                "SELECT {EXPERIMENT_COLUMNS} FROM experiments e JOIN users u ON u.id = e.user_id
                 WHERE {condition} ORDER BY e.updated_ms DESC, e.id DESC"
            ))
            .map_err(db)?;
        let rows = stmt.query_map(values, experiment_row).map_err(db)?;
        rows.collect::<Result<_, _>>().map_err(db)
    }

    /// Episodes of one experiment, in order (without recordings: the store
    /// does not know the files).
    pub fn episodes(&self, experiment_id: i64) -> Result<Vec<EpisodeRecordEntry>, ControllerError> {
        self.episodes_from(experiment_id, 0, u32::MAX)
    }

    /// At most `limit` episodes of one experiment from index `from` on, in order.
    pub fn episodes_from(
        &self,
        experiment_id: i64,
        from: u64,
        limit: u32,
    ) -> Result<Vec<EpisodeRecordEntry>, ControllerError> {
        let from = i64::try_from(from).unwrap_or(i64::MAX);
        let mut stmt = self
            .conn
            .prepare(
                "SELECT episode_index, seed, steps, episode_return, success, end_reason, started_ms, ended_ms,
                        requested_x, requested_y, requested_yaw, achieved_x, achieved_y, achieved_yaw, reset_us
                 FROM episodes WHERE experiment_id = ?1 AND episode_index >= ?2
                 ORDER BY episode_index LIMIT ?3",
            )
            .map_err(db)?;
        let rows = stmt
            .query_map(params![experiment_id, from, limit], |r| {
                let seed = r.get::<_, Option<i64>>(1)?;
                let pose = |i| -> rusqlite::Result<Pose2D> {
                    Ok(Pose2D {
                        x: r.get(i)?,
                        y: r.get(i + 1)?,
                        yaw: r.get(i + 2)?,
                    })
                };
                let (requested, achieved) = (pose(8)?, pose(11)?);
                let started_unix_ms = r.get(6)?;
                // The reset ended where the episode started.
                let reset = match r.get::<_, Option<i64>>(14)? {
                    Some(us) => ResetAccuracy::measure(
                        requested,
                        achieved,
                        us as f64 / 1e6,
                        started_unix_ms,
                    ),
                    None => ResetAccuracy {
                        measured: false,
                        ..ResetAccuracy::measure(requested, achieved, 0.0, 0)
                    },
                };
                Ok(EpisodeRecordEntry {
                    index: r.get::<_, i64>(0)? as u64,
                    seeded: seed.is_some(),
                    seed: seed.unwrap_or_default() as u64,
                    steps: r.get(2)?,
                    episode_return: r.get(3)?,
                    success: r.get(4)?,
                    end_reason: r.get(5)?,
                    started_unix_ms,
                    ended_unix_ms: r.get(7)?,
                    reset,
                    recordings: Vec::new(),
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

/// The columns [`experiment_row`] reads, in its order.
const EXPERIMENT_COLUMNS: &str = "e.id, u.name, e.env_id, e.task, e.name, e.learning_type, \
     e.algorithm_mode, e.episodes, e.steps, e.created_ms, e.updated_ms";

fn experiment_row(r: &rusqlite::Row<'_>) -> rusqlite::Result<ExperimentRecord> {
    Ok(ExperimentRecord {
        id: r.get(0)?,
        user: r.get(1)?,
        env_id: r.get(2)?,
        task: r.get(3)?,
        name: r.get(4)?,
        learning_type: r.get(5)?,
        algorithm_mode: r.get(6)?,
        episodes: r.get::<_, i64>(7)? as u64,
        steps: r.get::<_, i64>(8)? as u64,
        created_unix_ms: r.get(9)?,
        updated_unix_ms: r.get(10)?,
    })
}

/// Longest user name, characters.
pub const MAX_USER_NAME: usize = 64;
/// Longest experiment name, characters.
pub const MAX_EXPERIMENT_NAME: usize = 128;
/// Longest token looked up (issued tokens have 32 characters): a longer one
/// is unknown, and is not even hashed.
pub const MAX_TOKEN_LEN: usize = 256;
/// What an experiment name may hold besides letters and digits.
pub const EXPERIMENT_NAME_PUNCTUATION: &str = "-_.:+=@#/,()[] ";

/// `text` for an error message: at most 40 characters of it, quoted and
/// escaped (a hostile name is neither echoed whole nor able to carry
/// control characters into a terminal).
fn quoted(text: &str) -> String {
    let mut head: String = text.chars().take(40).collect();
    if head.len() < text.len() {
        head.push('…');
    }
    format!("{head:?}")
}

/// Checks a user name: 1 to [`MAX_USER_NAME`] of `[A-Za-z0-9._@-]`.
pub fn validate_user_name(name: &str) -> Result<(), ControllerError> {
    let valid = !name.is_empty()
        && name.len() <= MAX_USER_NAME
        && name
            .bytes()
            .all(|b| b.is_ascii_alphanumeric() || matches!(b, b'.' | b'_' | b'@' | b'-'));
    if valid {
        Ok(())
    } else {
        Err(ControllerError::InvalidArgument(format!(
            "user names are 1 to {MAX_USER_NAME} characters of A-Z a-z 0-9 . _ @ -, got {}",
            quoted(name)
        )))
    }
}

/// Checks an experiment name: 1 to [`MAX_EXPERIMENT_NAME`] letters, digits,
/// spaces (not at either end) and [`EXPERIMENT_NAME_PUNCTUATION`].
pub fn validate_experiment_name(name: &str) -> Result<(), ControllerError> {
    let invalid = |why: String| Err(ControllerError::InvalidArgument(why));
    if name.is_empty() {
        return invalid("an experiment name must not be empty".into());
    }
    // Bounded count: a megabyte of name is refused without walking it all.
    let chars = name.chars().take(MAX_EXPERIMENT_NAME + 1).count();
    if chars > MAX_EXPERIMENT_NAME {
        return invalid(format!(
            "experiment names are at most {MAX_EXPERIMENT_NAME} characters; {} is longer",
            quoted(name)
        ));
    }
    if let Some(bad) = name
        .chars()
        .find(|c| !c.is_alphanumeric() && !EXPERIMENT_NAME_PUNCTUATION.contains(*c))
    {
        return invalid(format!(
            "experiment names hold letters, digits, spaces and {:?}; {bad:?} in {} is not allowed",
            EXPERIMENT_NAME_PUNCTUATION.trim_end(),
            quoted(name)
        ));
    }
    if name.starts_with(' ') || name.ends_with(' ') {
        return invalid(format!(
            "experiment names do not begin or end with a space: {}",
            quoted(name)
        ));
    }
    Ok(())
}

/// The last bookable instant, Unix ms: 9999-12-31T23:59:59.999Z (a later
/// date has no RFC 3339 form). No stored booking lies outside
/// `0..=LATEST_BOOKABLE_MS`.
pub const LATEST_BOOKABLE_MS: i64 = 253_402_300_799_999;

/// A Unix time in ms as RFC 3339 (seconds), for messages. Total: a time
/// outside years 1970-9999 is written as a number instead of panicking.
pub fn format_unix_ms(ms: i64) -> String {
    if (0..=LATEST_BOOKABLE_MS).contains(&ms) {
        let t = std::time::UNIX_EPOCH + std::time::Duration::from_millis(ms.unsigned_abs());
        let mut text = String::new();
        if write!(text, "{}", humantime::format_rfc3339_seconds(t)).is_ok() {
            return text;
        }
    }
    format!("{ms} ms after the Unix epoch (outside years 1970-9999)")
}

/// A span in ms, for messages (`4h`, `30days`); total.
fn format_span(ms: i64) -> String {
    humantime::format_duration(std::time::Duration::from_millis(ms.max(0).unsigned_abs()))
        .to_string()
}

/// Limits on bookings: a site's policy (see [`crate::EnvOptions`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BookingRules {
    /// Longest slot, ms.
    pub max_slot_ms: i64,
    /// How far ahead a slot may start, ms.
    pub horizon_ms: i64,
    /// How far in the past a slot may start (clock skew, a request in
    /// flight), ms; such a slot begins when it is made.
    pub past_grace_ms: i64,
}

impl Default for BookingRules {
    fn default() -> Self {
        Self {
            max_slot_ms: 4 * 3600 * 1000,
            horizon_ms: 30 * 24 * 3600 * 1000,
            past_grace_ms: 60 * 1000,
        }
    }
}

/// Why a requested slot is refused (400: [`ControllerError::InvalidArgument`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SlotError {
    /// A time lies outside years 1970-9999.
    #[error(
        "slot times lie between 1970-01-01T00:00:00Z and 9999-12-31T23:59:59Z (Unix ms 0..={LATEST_BOOKABLE_MS}); got {start_ms} .. {end_ms}"
    )]
    OutOfRange {
        /// Requested start, Unix ms.
        start_ms: i64,
        /// Requested end, Unix ms.
        end_ms: i64,
    },
    /// Empty or reversed.
    #[error("a slot must end after it starts; got {} .. {}", format_unix_ms(*start_ms), format_unix_ms(*end_ms))]
    EndNotAfterStart {
        /// Requested start, Unix ms.
        start_ms: i64,
        /// Requested end, Unix ms.
        end_ms: i64,
    },
    /// Longer than the site allows.
    #[error("slots are at most {} long; this one is {}", format_span(*max_ms), format_span(*length_ms))]
    TooLong {
        /// Requested length, ms.
        length_ms: i64,
        /// The site's maximum, ms.
        max_ms: i64,
    },
    /// Starts further in the past than the grace allows.
    #[error("the slot starts at {}, in the past (now {}); book from now on", format_unix_ms(*start_ms), format_unix_ms(*now_ms))]
    StartsInPast {
        /// Requested start, Unix ms.
        start_ms: i64,
        /// The server's clock, Unix ms.
        now_ms: i64,
    },
    /// Over before it is made.
    #[error("the slot ended already at {}", format_unix_ms(*end_ms))]
    AlreadyEnded {
        /// Requested end, Unix ms.
        end_ms: i64,
    },
    /// Starts beyond the site's horizon.
    #[error("slots may start at most {} ahead, by {}; this one starts at {}", format_span(*horizon_ms), format_unix_ms(*latest_start_ms), format_unix_ms(*start_ms))]
    TooFarAhead {
        /// Requested start, Unix ms.
        start_ms: i64,
        /// The latest start allowed now, Unix ms.
        latest_start_ms: i64,
        /// The site's horizon, ms.
        horizon_ms: i64,
    },
}

impl From<SlotError> for ControllerError {
    fn from(e: SlotError) -> Self {
        ControllerError::InvalidArgument(e.to_string())
    }
}

impl BookingRules {
    /// Checks the rules themselves (a site's configuration).
    pub fn check(&self) -> Result<(), ControllerError> {
        if self.max_slot_ms <= 0 {
            return Err(ControllerError::Config(format!(
                "the longest booking slot must be positive, got {} ms",
                self.max_slot_ms
            )));
        }
        if self.horizon_ms < 0 || self.past_grace_ms < 0 {
            return Err(ControllerError::Config(format!(
                "the booking horizon ({} ms) and past grace ({} ms) must not be negative",
                self.horizon_ms, self.past_grace_ms
            )));
        }
        Ok(())
    }

    /// Validates a requested slot `[start_ms, end_ms)` at `now_ms` and
    /// returns the slot to store (one starting within the grace in the
    /// past begins at `now_ms`). Total: checked arithmetic, no panic for
    /// any input, and every slot returned lies in `0..=LATEST_BOOKABLE_MS`.
    pub fn validate(
        &self,
        start_ms: i64,
        end_ms: i64,
        now_ms: i64,
    ) -> Result<(i64, i64), SlotError> {
        let bookable = 0..=LATEST_BOOKABLE_MS;
        if !bookable.contains(&start_ms) || !bookable.contains(&end_ms) {
            return Err(SlotError::OutOfRange { start_ms, end_ms });
        }
        if end_ms <= start_ms {
            return Err(SlotError::EndNotAfterStart { start_ms, end_ms });
        }
        let length_ms = end_ms.checked_sub(start_ms).unwrap_or(i64::MAX);
        if length_ms > self.max_slot_ms {
            return Err(SlotError::TooLong {
                length_ms,
                max_ms: self.max_slot_ms,
            });
        }
        if start_ms < now_ms.saturating_sub(self.past_grace_ms.max(0)) {
            return Err(SlotError::StartsInPast { start_ms, now_ms });
        }
        if end_ms <= now_ms {
            return Err(SlotError::AlreadyEnded { end_ms });
        }
        let latest_start_ms = now_ms.saturating_add(self.horizon_ms.max(0));
        if start_ms > latest_start_ms {
            return Err(SlotError::TooFarAhead {
                start_ms,
                latest_start_ms,
                horizon_ms: self.horizon_ms,
            });
        }
        Ok((start_ms.max(now_ms), end_ms))
    }
}

/// Why a booking row read back from the database cannot be a booking, if
/// it cannot. Every slot [`BookingRules::validate`] returns passes; a row
/// written by an older version (or by hand) may not.
pub fn booking_violation(b: &Booking) -> Option<&'static str> {
    if b.end_unix_ms <= b.start_unix_ms {
        Some("it does not end after it starts")
    } else if b.start_unix_ms < 0 || b.end_unix_ms > LATEST_BOOKABLE_MS {
        Some("its times lie outside years 1970-9999")
    } else {
        None
    }
}

/// Booking rows that break the invariants: skipped by every reader, and
/// reported once each.
#[derive(Default)]
struct Quarantine(RefCell<HashSet<String>>);

impl Quarantine {
    /// `row` if it is a valid booking; otherwise `None`, warned about the
    /// first time.
    fn admit(&self, row: rusqlite::Result<(Booking, i64)>) -> Option<(Booking, i64)> {
        let (key, why) = match &row {
            Err(e) => (e.to_string(), format!("unreadable: {e}")),
            Ok((b, _)) => match booking_violation(b) {
                None => return row.ok(),
                Some(why) => (format!("booking {}", b.id), why.to_owned()),
            },
        };
        // Never re-entered; should it be, warning twice beats panicking.
        let first = self
            .0
            .try_borrow_mut()
            .map_or(true, |mut seen| seen.insert(key));
        if first {
            match &row {
                Ok((b, _)) => tracing::warn!(
                    id = b.id,
                    env = %b.env_id,
                    user = %b.user,
                    start_ms = b.start_unix_ms,
                    end_ms = b.end_unix_ms,
                    "booking quarantined: {why}; it is ignored (an operator may cancel it by its id)"
                ),
                Err(_) => tracing::warn!("booking row quarantined: {why}; it is ignored"),
            }
        }
        None
    }
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
    /// against overlapping slots. The slot is validated by `rules` first
    /// (see [`BookingRules::validate`]).
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
        // A slot that started already (within the grace) begins now.
        let (start_ms, end_ms) = rules.validate(start_ms, end_ms, now_ms)?;
        let quarantine = &self.quarantine;
        let tx = self.conn.transaction().map_err(db)?;
        let clash = {
            let mut stmt = tx
                .prepare(&format!(
                    "SELECT {BOOKING_COLUMNS} WHERE b.env_id = ?1 AND b.start_ms < ?3 AND b.end_ms > ?2 ORDER BY b.start_ms"
                ))
                .map_err(db)?;
            let mut rows = stmt
                .query_map(params![env_id, start_ms, end_ms], booking_row)
                .map_err(db)?;
            rows.find_map(|row| quarantine.admit(row))
        };
        if let Some((b, _)) = clash {
            return Err(ControllerError::Busy(format!(
                "{env_id} is booked by {} from {} to {}",
                b.user,
                format_unix_ms(b.start_unix_ms),
                format_unix_ms(b.end_unix_ms)
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

    /// The valid bookings of `env_id` matching `filter` (SQL over `b.`,
    /// `?1` the env, `?2` the time), earliest first; invalid rows are
    /// quarantined.
    fn valid_bookings<T>(
        &self,
        env_id: &str,
        at_ms: i64,
        filter: &str,
        take: impl FnOnce(&mut dyn Iterator<Item = (Booking, i64)>) -> T,
    ) -> Result<T, ControllerError> {
        let mut stmt = self
            .conn
            .prepare(&format!(
                "SELECT {BOOKING_COLUMNS} WHERE b.env_id = ?1 AND {filter} ORDER BY b.start_ms, b.id"
            ))
            .map_err(db)?;
        let rows = stmt
            .query_map(params![env_id, at_ms], booking_row)
            .map_err(db)?;
        let mut valid = rows.filter_map(|row| self.quarantine.admit(row));
        Ok(take(&mut valid))
    }

    /// Slots of `env_id` ending after `from_ms`, earliest first.
    pub fn bookings(&self, env_id: &str, from_ms: i64) -> Result<Vec<Booking>, ControllerError> {
        self.valid_bookings(env_id, from_ms, "b.end_ms > ?2", |rows| {
            rows.map(|(b, _)| b).collect()
        })
    }

    /// The slot of `env_id` covering `at_ms`, with its holder's user id.
    pub fn booking_at(
        &self,
        env_id: &str,
        at_ms: i64,
    ) -> Result<Option<(Booking, i64)>, ControllerError> {
        self.valid_bookings(
            env_id,
            at_ms,
            "b.start_ms <= ?2 AND b.end_ms > ?2",
            |rows| rows.next(),
        )
    }

    /// The slot of `env_id` covering `at_ms` and until when that answer
    /// holds (the slot's end, or the next slot's start), so callers can
    /// skip the database until then.
    pub fn slot_at(&self, env_id: &str, at_ms: i64) -> Result<SlotAt, ControllerError> {
        let slot = self.booking_at(env_id, at_ms)?;
        let until_ms = match &slot {
            Some((booking, _)) => booking.end_unix_ms,
            None => self
                .valid_bookings(env_id, at_ms, "b.start_ms > ?2", |rows| {
                    rows.next().map(|(b, _)| b.start_unix_ms)
                })?
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

    use offworld_test_support::ScratchDir;

    fn user_version(path: &Path) -> usize {
        Connection::open(path)
            .expect("open")
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .expect("user_version")
    }

    #[test]
    fn the_migrations_are_valid() {
        Migrations::from_slice(MIGRATIONS)
            .validate()
            .expect("valid migrations");
    }

    #[test]
    fn a_database_from_before_schema_versions_is_migrated_with_its_records() {
        let dir = ScratchDir::new("store-test");
        let path = dir.0.join("site.db");
        {
            // What every controller before schema versions made.
            let old = Connection::open(&path).expect("open");
            old.execute_batch(PRAGMAS).expect("pragmas");
            old.execute_batch(SCHEMA_1).expect("schema");
            old.execute_batch(
                "INSERT INTO users (name, token_sha256, role, created_ms) VALUES ('ada', 'x', 'user', 1);
                 INSERT INTO experiments (user_id, env_id, task, name, learning_type, algorithm_mode, created_ms, updated_ms)
                     VALUES (1, 'real/a', 'MonolithDiscrete', 'old', 'end2end', 'train', 1, 1);
                 INSERT INTO episodes (experiment_id, episode_index, seed, steps, episode_return, success, end_reason,
                     requested_x, requested_y, requested_yaw, achieved_x, achieved_y, achieved_yaw, started_ms, ended_ms)
                     VALUES (1, 0, 7, 12, 1.0, 1, 'success', 1.0, 2.0, 0.5, 1.0, 2.03, 0.25, 1000, 2000);",
            )
            .expect("old rows");
        }
        assert_eq!(user_version(&path), 0);
        let store = Store::open(&path).expect("migrated");
        assert_eq!(user_version(&path), SCHEMA_VERSION);
        let episodes = store.episodes(1).expect("episodes");
        assert_eq!(episodes.len(), 1);
        let reset = episodes[0].reset;
        assert!(!reset.measured, "an old row has no reset duration");
        assert_eq!(
            (reset.requested, reset.achieved),
            (
                Pose2D {
                    x: 1.0,
                    y: 2.0,
                    yaw: 0.5
                },
                Pose2D {
                    x: 1.0,
                    y: 2.03,
                    yaw: 0.25
                }
            )
        );
        assert_eq!((episodes[0].steps, episodes[0].success), (12, true));
        drop(store);
        // Opening it again changes nothing.
        Store::open(&path).expect("reopened");
        assert_eq!(user_version(&path), SCHEMA_VERSION);
    }

    #[test]
    fn a_database_from_a_newer_build_is_refused_and_left_untouched() {
        let dir = ScratchDir::new("store-test");
        let path = dir.0.join("site.db");
        let store = Store::open(&path).expect("store");
        store.add_user("ada", false).expect("user");
        drop(store);
        let future = SCHEMA_VERSION + 1;
        Connection::open(&path)
            .expect("open")
            .pragma_update(None, "user_version", future)
            .expect("set version");
        let before = std::fs::read(&path).expect("read");
        let Err(ControllerError::Store(message)) = Store::open(&path) else {
            panic!("a newer schema must be refused");
        };
        assert!(
            message.contains(&format!("schema version {future}")) && message.contains("newer"),
            "{message}"
        );
        assert_eq!(
            std::fs::read(&path).expect("read"),
            before,
            "file unchanged"
        );
        assert_eq!(user_version(&path), future);
    }

    #[test]
    fn an_episode_keeps_its_reset_accuracy() {
        let mut store = Store::in_memory().expect("store");
        let token = store.add_user("ada", false).expect("user");
        let ada = store.authenticate(&token).expect("db").expect("ada");
        let experiment = store
            .open_experiment(
                &ada,
                "real/a",
                "MonolithDiscrete",
                "reset",
                false,
                LearningType::EndToEnd,
                AlgorithmMode::Train,
            )
            .expect("experiment");
        let reset = ResetAccuracy::measure(
            Pose2D {
                x: 1.0,
                y: 2.0,
                yaw: 3.1,
            },
            Pose2D {
                x: 1.03,
                y: 2.04,
                yaw: -3.1,
            },
            41.5,
            5_000,
        );
        store
            .begin_episode(&EpisodeRecord {
                experiment_id: experiment.id,
                episode_index: 0,
                seed: None,
                steps: 0,
                episode_return: 0.0,
                success: false,
                end_reason: IN_PROGRESS.into(),
                reset,
                started_ms: 5_000,
                ended_ms: 5_000,
            })
            .expect("begin");
        let stored = store.episodes(experiment.id).expect("episodes")[0].reset;
        assert_eq!(stored, reset);
        assert!(stored.measured);
        assert!((stored.position_error_m - 0.05).abs() < 1e-12);
        // Across ±π: 0.083 rad, not 6.2.
        assert!((stored.yaw_error_rad - (std::f64::consts::TAU - 6.2)).abs() < 1e-9);
        assert_eq!((stored.duration_s, stored.unix_ms), (41.5, 5_000));
    }

    #[test]
    fn an_episode_is_on_record_from_its_start_and_closed_after_a_crash() {
        let mut store = Store::in_memory().expect("store");
        let token = store.add_user("ada", false).expect("user");
        let ada = store.authenticate(&token).expect("db").expect("ada");
        let open = |store: &Store| {
            store
                .open_experiment(
                    &ada,
                    "real/a",
                    "MonolithDiscrete",
                    "crash",
                    true,
                    LearningType::EndToEnd,
                    AlgorithmMode::Train,
                )
                .expect("experiment")
        };
        let experiment = store
            .open_experiment(
                &ada,
                "real/a",
                "MonolithDiscrete",
                "crash",
                false,
                LearningType::EndToEnd,
                AlgorithmMode::Train,
            )
            .expect("experiment");
        let episode = |index, steps, end_reason: &str| EpisodeRecord {
            experiment_id: experiment.id,
            episode_index: index,
            seed: Some(7),
            steps,
            episode_return: 1.0,
            success: end_reason == "success",
            end_reason: end_reason.into(),
            reset: ResetAccuracy::measure(
                Pose2D {
                    x: 1.0,
                    y: 2.0,
                    yaw: 0.5,
                },
                Pose2D {
                    x: 1.01,
                    y: 2.0,
                    yaw: 0.5,
                },
                41.5,
                1_000,
            ),
            started_ms: 1_000,
            ended_ms: 2_000,
        };
        // Episode 0 ends normally: one row, counted once, its steps added.
        store
            .begin_episode(&episode(0, 0, IN_PROGRESS))
            .expect("begin");
        assert_eq!(open(&store).episodes, 1, "counted from its start");
        store
            .record_episode(&episode(0, 12, "success"))
            .expect("end");
        // Episode 1 is cut by a crash, after 4 of its steps were saved.
        store
            .begin_episode(&episode(1, 0, IN_PROGRESS))
            .expect("begin");
        store
            .progress_episode(&episode(1, 4, IN_PROGRESS))
            .expect("progress");
        let in_progress = store.episodes(experiment.id).expect("episodes");
        assert_eq!(in_progress[1].end_reason, IN_PROGRESS);
        // Another env's controller starting leaves it alone; its own closes it.
        assert_eq!(store.abandon_in_progress("real/b", "x").expect("sweep"), 0);
        let why = "aborted: the controller stopped";
        assert_eq!(store.abandon_in_progress("real/a", why).expect("sweep"), 1);
        assert_eq!(store.abandon_in_progress("real/a", why).expect("sweep"), 0);
        let episodes = store.episodes(experiment.id).expect("episodes");
        let summary: Vec<_> = episodes
            .iter()
            .map(|e| (e.index, e.steps, e.success, e.end_reason.as_str()))
            .collect();
        assert_eq!(summary, vec![(0, 12, true, "success"), (1, 4, false, why)]);
        let resumed = open(&store);
        assert_eq!((resumed.episodes, resumed.steps), (2, 16));
        // A record without a begun row (an older caller) is added whole.
        store
            .record_episode(&episode(2, 5, "step_limit"))
            .expect("record");
        let resumed = open(&store);
        assert_eq!((resumed.episodes, resumed.steps), (3, 21));
    }

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

    /// A registered user of `store` (a booking needs one).
    fn user(store: &Store, name: &str) -> User {
        let token = store.add_user(name, false).expect("user");
        store
            .authenticate(&token)
            .expect("db")
            .expect("the user is known")
    }

    /// Writes a booking row as an older version (or a hand edit) could
    /// have: around the validation and the table's CHECK.
    fn plant(store: &Store, env: &str, user: &User, start_ms: i64, end_ms: i64) -> i64 {
        store
            .conn
            .execute_batch("PRAGMA ignore_check_constraints = ON")
            .expect("pragma");
        store
            .conn
            .execute(
                "INSERT INTO bookings (env_id, user_id, start_ms, end_ms, created_ms) VALUES (?1, ?2, ?3, ?4, 0)",
                params![env, user.id, start_ms, end_ms],
            )
            .expect("planted");
        store
            .conn
            .execute_batch("PRAGMA ignore_check_constraints = OFF")
            .expect("pragma");
        store.conn.last_insert_rowid()
    }

    #[test]
    fn invalid_booking_rows_are_quarantined_by_every_reader() {
        let mut store = Store::in_memory().expect("store");
        let (mallory, ada) = (user(&store, "mallory"), user(&store, "ada"));
        let (env, now) = ("sim/a", 1_700_000_000_000);
        // What the [i64::MIN, i64::MAX) booking of old versions stored, a
        // reversed slot, an empty one and one before 1970.
        let hostile = [
            (now - 1_000, i64::MAX),
            (now + 60_000, now - 60_000),
            (now, now),
            (-5_000, now + 5_000),
        ];
        for (start, end) in hostile {
            plant(&store, env, &mallory, start, end);
        }
        // None of them is listed, holds the env now, or ends the free time.
        assert_eq!(store.bookings(env, i64::MIN).expect("list"), vec![]);
        assert_eq!(store.booking_at(env, now).expect("at"), None);
        assert_eq!(
            store.slot_at(env, now).expect("slot"),
            SlotAt {
                slot: None,
                until_ms: i64::MAX
            }
        );
        // Nor does any block a valid booking over the same time.
        let rules = BookingRules::default();
        let made = store
            .book(&ada, env, now, now + 60_000, now, rules)
            .expect("booked over quarantined rows");
        assert_eq!(store.bookings(env, 0).expect("list"), vec![made.clone()]);
        let at = store.slot_at(env, now + 1).expect("slot");
        assert_eq!(at.slot, Some((made, ada.id)));
        assert_eq!(at.until_ms, now + 60_000);
    }

    #[test]
    fn a_hostile_booking_is_refused_and_never_stored() {
        let mut store = Store::in_memory().expect("store");
        let mallory = user(&store, "mallory");
        let (env, now) = ("sim/a", 1_700_000_000_000);
        let rules = BookingRules::default();
        let after_9999 = LATEST_BOOKABLE_MS + 1_000_000;
        for (start, end) in [
            (i64::MIN, i64::MAX),
            (after_9999, after_9999 - 1),
            (after_9999, after_9999 + 1),
            (now, i64::MAX),
            (now + 10_000, now),
            (now, now + rules.max_slot_ms + 1),
            (now + rules.horizon_ms + 1, now + rules.horizon_ms + 60_000),
            (now - 3_600_000, now + 60_000),
        ] {
            let refused = store
                .book(&mallory, env, start, end, now, rules)
                .expect_err("refused");
            assert!(
                matches!(refused, ControllerError::InvalidArgument(_)),
                "{start} .. {end}: {refused}"
            );
            assert_eq!(
                offworld_runtime::WireError::from(refused).code,
                offworld_runtime::ErrorCode::BadRequest
            );
        }
        assert_eq!(store.bookings(env, i64::MIN).expect("list"), vec![]);
    }

    #[test]
    fn dates_outside_years_1970_to_9999_format_without_panicking() {
        assert_eq!(format_unix_ms(0), "1970-01-01T00:00:00Z");
        assert_eq!(format_unix_ms(LATEST_BOOKABLE_MS), "9999-12-31T23:59:59Z");
        for ms in [LATEST_BOOKABLE_MS + 1, i64::MAX, -1, i64::MIN] {
            assert!(
                format_unix_ms(ms).contains("outside years 1970-9999"),
                "{ms}"
            );
        }
    }

    #[test]
    fn names_and_tokens() {
        for good in ["alice", "ops.team", "a_b-c@site"] {
            validate_user_name(good).expect(good);
        }
        for bad in ["", "a b", "x\n", &"a".repeat(MAX_USER_NAME + 1), "ünï"] {
            assert!(validate_user_name(bad).is_err(), "{bad:?}");
        }
        for good in [
            "dqn-depth",
            "Demo",
            "run-1712345678901",
            "ppo (v2) seed=3",
            "実験-1",
        ] {
            validate_experiment_name(good).expect(good);
        }
        let long = "x".repeat(MAX_EXPERIMENT_NAME + 1);
        for bad in [
            "",
            " lead",
            "trail ",
            "bell\u{7}",
            "rtl\u{202e}txt",
            &long,
            "semi;colon",
        ] {
            let e = validate_experiment_name(bad).expect_err(bad);
            assert!(matches!(e, ControllerError::InvalidArgument(_)), "{e}");
            // The message quotes at most 40 characters of the name.
            assert!(e.to_string().len() < 300, "{e}");
        }
        // A token longer than any issued is unknown, unhashed.
        let store = Store::in_memory().expect("store");
        let huge = "t".repeat(MAX_TOKEN_LEN + 1);
        assert_eq!(store.authenticate(&huge).expect("db"), None);
        assert!(store.add_user_with_token("eve", &huge, false).is_err());
        assert!(store
            .add_user_with_token("bad name", "long-enough-token", false)
            .is_err());
    }

    mod properties {
        use super::super::*;
        use crate::test_strategies::{any_text, text, ALNUM};
        use proptest::prelude::*;

        const NAME_CHARS: &[char] = &[
            'a', 'Z', '7', 'é', '実', '-', '_', '.', ':', '+', '=', '@', '#', '/', ',', '(', ')',
            '[', ']', ' ',
        ];
        const USER_CHARS: &[char] = &['a', 'Z', '0', '9', '.', '_', '@', '-'];

        fn rules() -> impl Strategy<Value = BookingRules> {
            (any::<i64>(), any::<i64>(), any::<i64>()).prop_map(
                |(max_slot_ms, horizon_ms, past_grace_ms)| BookingRules {
                    max_slot_ms,
                    horizon_ms,
                    past_grace_ms,
                },
            )
        }

        /// Times where the edges are: around now, 0, year 9999 and i64's ends.
        fn time() -> impl Strategy<Value = i64> {
            prop_oneof![
                any::<i64>(),
                (-10_000_000i64..10_000_000).prop_map(|d| 1_700_000_000_000 + d),
                (-10_000i64..10_000).prop_map(|d| LATEST_BOOKABLE_MS.saturating_add(d)),
                (-10_000i64..10_000),
                Just(i64::MIN),
                Just(i64::MAX),
            ]
        }

        proptest! {
            #![proptest_config(ProptestConfig::with_cases(4096))]

            /// Any input: an answer, never a panic, and a slot accepted only
            /// if it meets every rule (checked with i128, no overflow).
            #[test]
            fn validate_is_total_and_sound(
                rules in prop_oneof![Just(BookingRules::default()), rules()],
                start in time(),
                end in time(),
                now in time(),
            ) {
                match rules.validate(start, end, now) {
                    Ok((s, e)) => {
                        let (start, end, now) = (i128::from(start), i128::from(end), i128::from(now));
                        let bookable = 0..=i128::from(LATEST_BOOKABLE_MS);
                        prop_assert!(bookable.contains(&start) && bookable.contains(&end));
                        prop_assert!(end > start);
                        prop_assert!(end - start <= i128::from(rules.max_slot_ms));
                        prop_assert!(start >= now - i128::from(rules.past_grace_ms.max(0)));
                        prop_assert!(start <= now + i128::from(rules.horizon_ms.max(0)));
                        prop_assert!(end > now);
                        // Stored: begins no earlier than now, same end.
                        prop_assert_eq!(i128::from(s), start.max(now));
                        prop_assert_eq!(i128::from(e), end);
                        let stored = Booking {
                            id: 1,
                            env_id: String::new(),
                            user: String::new(),
                            start_unix_ms: s,
                            end_unix_ms: e,
                        };
                        prop_assert_eq!(booking_violation(&stored), None);
                    }
                    Err(refused) => {
                        // The message is total too, and maps to 400.
                        prop_assert!(!refused.to_string().is_empty());
                        let wire = offworld_runtime::WireError::from(ControllerError::from(refused));
                        prop_assert_eq!(wire.code, offworld_runtime::ErrorCode::BadRequest);
                    }
                }
            }

            /// Every slot that meets the default rules is accepted.
            #[test]
            fn validate_accepts_every_valid_slot(
                now in 0i64..LATEST_BOOKABLE_MS - 40 * 86_400_000,
                offset in -60_000i64..=30 * 86_400_000,
                length in 1i64..=4 * 3_600_000,
            ) {
                let (start, end) = (now + offset, now + offset + length);
                prop_assume!(start >= 0 && end > now);
                let rules = BookingRules::default();
                prop_assert_eq!(rules.validate(start, end, now), Ok((start.max(now), end)));
            }

            #[test]
            fn format_unix_ms_is_total(ms in time()) {
                let text = format_unix_ms(ms);
                if (0..=LATEST_BOOKABLE_MS).contains(&ms) {
                    prop_assert_eq!(text.len(), 20, "{}", text);
                    prop_assert!(text.ends_with('Z'));
                } else {
                    prop_assert!(text.contains("outside years 1970-9999"));
                }
            }

            /// Names made of the allowed characters pass; any string gets
            /// an answer, and an accepted one keeps to the rules.
            #[test]
            fn experiment_names(
                (first, middle, last) in (text(ALNUM, 1..=1), text(NAME_CHARS, 0..=126), text(ALNUM, 1..=1)),
                any_name in any_text(),
            ) {
                let good = format!("{first}{middle}{last}");
                prop_assert!(validate_experiment_name(&good).is_ok(), "{:?}", good);
                if validate_experiment_name(&any_name).is_ok() {
                    prop_assert!(!any_name.is_empty());
                    prop_assert!(any_name.chars().count() <= MAX_EXPERIMENT_NAME);
                    prop_assert!(any_name.chars().all(|c| !c.is_control()));
                    prop_assert!(!any_name.starts_with(' ') && !any_name.ends_with(' '));
                }
            }

            #[test]
            fn user_names(
                good in text(USER_CHARS, 1..=64),
                any_name in any_text(),
            ) {
                prop_assert!(validate_user_name(&good).is_ok(), "{:?}", good);
                if validate_user_name(&any_name).is_ok() {
                    prop_assert!(!any_name.is_empty() && any_name.len() <= MAX_USER_NAME);
                    prop_assert!(any_name.is_ascii());
                }
            }
        }
    }
}
