//! Sealed control messages: defence in depth beyond the router's access
//! control. The real-site controller seals what moves the robot (commands,
//! heartbeats, reset drives) with the site's *command key*, and the tracker
//! agent seals its poses and tracking status with the *tracker key*; a
//! robot agent given the command key obeys nothing unsealed, and a
//! controller or robot agent given the tracker key believes no pose that is
//! not sealed. A peer that reaches the robot around the router (a
//! misconfigured network, a stolen sim credential) can then neither drive
//! it nor fake a success.
//!
//! The seal is an HMAC-SHA256 (RustCrypto `hmac`) over the key expression,
//! the payload, any inner attachment (e.g. a `SeqTag`) and a header:
//! the sealer's *epoch* (random per process), a *counter* and the wall
//! clock. It travels as a trailer appended to the attachment:
//!
//! ```text
//! inner attachment … | epoch u64 | counter u64 | sent_at_ms i64 | tag [32] | "OWS1"
//! ```
//!
//! An [`Opener`] refuses a message that is unsealed, tampered with, older
//! (or newer) than its clock window, or replayed: a counter seen already
//! within the epoch's 64-message window (reordering within it is fine), or
//! an epoch older than the newest one heard (a restarted controller's
//! stream supersedes the old one's). E-stops are never sealed: anyone the
//! router lets press one may stop the robot.

use std::fmt;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use hmac::digest::KeyInit;
use hmac::{Hmac, Mac};
use sha2::Sha256;

/// Bytes of a seal trailer.
pub const TRAILER_LEN: usize = 8 + 8 + 8 + TAG_LEN + MAGIC.len();
const TAG_LEN: usize = 32;
const MAGIC: &[u8; 4] = b"OWS1";
/// Separates this use of a key from any other.
const DOMAIN: &[u8] = b"offworld/@v1 seal\0";
/// Bytes of a key.
pub const KEY_LEN: usize = 32;
/// How far out of order a sealed stream may arrive.
const REPLAY_WINDOW: u64 = 64;

/// The default clock window of an [`Opener`]: a site's hosts keep their
/// clocks within a few milliseconds (NTP); a captured message is refused
/// once this old.
pub const DEFAULT_MAX_AGE: Duration = Duration::from_secs(2);

/// Why a key could not be used, or a message was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SealError {
    /// The key file is unreadable, malformed or readable by others.
    #[error("key file {path}: {reason}")]
    KeyFile {
        /// The file.
        path: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The message carries no seal.
    #[error("unsealed")]
    Unsealed,
    /// The seal does not match the message (another key, or tampered with).
    #[error("bad seal (another key, or the message was altered)")]
    BadTag,
    /// The seal's clock is outside the window.
    #[error("stale seal: sent {age_ms} ms from now, window ±{max_ms} ms")]
    Stale {
        /// Signed distance from the receiver's clock (negative: future).
        age_ms: i64,
        /// The window.
        max_ms: u64,
    },
    /// Seen already, or from a superseded sealer.
    #[error("replayed seal (epoch {epoch:016x}, counter {counter})")]
    Replayed {
        /// The sealer's epoch.
        epoch: u64,
        /// The message's counter.
        counter: u64,
    },
}

/// A 32-byte secret shared by the sealer and the openers of one stream
/// family. Never printed.
#[derive(Clone)]
pub struct SealKey(Arc<[u8; KEY_LEN]>);

impl fmt::Debug for SealKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("SealKey(…)")
    }
}

impl PartialEq for SealKey {
    fn eq(&self, other: &Self) -> bool {
        self.0 == other.0
    }
}

impl SealKey {
    /// A new random key.
    pub fn generate() -> Self {
        Self(Arc::new(rand::random()))
    }

    /// The key as 64 hex digits (what a key file holds).
    pub fn to_hex(&self) -> String {
        self.0.iter().map(|b| format!("{b:02x}")).collect()
    }

    /// Parses 64 hex digits (surrounding whitespace ignored).
    pub fn from_hex(text: &str) -> Result<Self, String> {
        let text = text.trim();
        if text.len() != 2 * KEY_LEN || !text.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(format!(
                "expected {} hex digits (`openssl rand -hex {KEY_LEN}`), found {} characters",
                2 * KEY_LEN,
                text.len()
            ));
        }
        let mut key = [0u8; KEY_LEN];
        for (i, byte) in key.iter_mut().enumerate() {
            *byte = u8::from_str_radix(&text[2 * i..2 * i + 2], 16)
                .map_err(|e| format!("not hex: {e}"))?;
        }
        Ok(Self(Arc::new(key)))
    }

    /// Reads a key file (64 hex digits). Refuses a file that group or
    /// others may read, as ssh does: a key anyone on the host can read
    /// authenticates nothing.
    pub fn load(path: &Path) -> Result<Self, SealError> {
        let fail = |reason: String| SealError::KeyFile {
            path: path.display().to_string(),
            reason,
        };
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(path)
                .map_err(|e| fail(e.to_string()))?
                .permissions()
                .mode();
            if mode & 0o077 != 0 {
                return Err(fail(format!(
                    "readable by others (mode {:o}): chmod 600 it",
                    mode & 0o777
                )));
            }
        }
        let text = std::fs::read_to_string(path).map_err(|e| fail(e.to_string()))?;
        Self::from_hex(&text).map_err(fail)
    }

    /// Writes the key to a new file only its owner may read.
    pub fn save(&self, path: &Path) -> std::io::Result<()> {
        use std::io::Write;
        let mut options = std::fs::OpenOptions::new();
        options.write(true).create_new(true);
        #[cfg(unix)]
        {
            use std::os::unix::fs::OpenOptionsExt;
            options.mode(0o600);
        }
        let mut file = options.open(path)?;
        writeln!(file, "{}", self.to_hex())?;
        file.sync_all()
    }

    fn mac(&self, key_expr: &str, payload: &[u8], inner: &[u8], header: &[u8; 24]) -> Hmac<Sha256> {
        let mut mac = <Hmac<Sha256> as KeyInit>::new_from_slice(self.0.as_slice())
            .expect("HMAC takes keys of any length");
        for part in [DOMAIN, key_expr.as_bytes(), payload, inner] {
            mac.update(&(part.len() as u64).to_le_bytes());
            mac.update(part);
        }
        mac.update(header);
        mac
    }
}

/// Checks the seal of a received sample or query against an [`Opener`].
pub trait Sealed {
    /// The key expression, payload and attachment the seal covers.
    fn open_with(&self, opener: &Opener) -> Result<(), SealError>;
}

impl Sealed for zenoh::sample::Sample {
    fn open_with(&self, opener: &Opener) -> Result<(), SealError> {
        let attachment = self.attachment().map(|a| a.to_bytes());
        opener
            .open(
                self.key_expr().as_str(),
                &self.payload().to_bytes(),
                attachment.as_deref(),
            )
            .map(|_| ())
    }
}

impl Sealed for zenoh::query::Query {
    fn open_with(&self, opener: &Opener) -> Result<(), SealError> {
        let payload = self.payload().map(|p| p.to_bytes()).unwrap_or_default();
        let attachment = self.attachment().map(|a| a.to_bytes());
        opener
            .open(self.key_expr().as_str(), &payload, attachment.as_deref())
            .map(|_| ())
    }
}

/// An [`Opener`] in front of one stream: admits what is sealed and logs
/// what is refused (the 1st, 10th, 100th… refusal: a flood of forgeries
/// must not flood the log too).
#[derive(Debug)]
pub struct Gate {
    opener: Opener,
    what: &'static str,
    refused: AtomicU64,
}

impl Gate {
    /// A gate for `what` (`"motion command"`, `"tracker pose"`, …).
    pub fn new(key: SealKey, what: &'static str) -> Self {
        Self {
            opener: Opener::new(key, DEFAULT_MAX_AGE),
            what,
            refused: AtomicU64::new(0),
        }
    }

    /// Whether `message`'s seal holds; a refusal is logged.
    pub fn admit(&self, message: &impl Sealed) -> bool {
        match message.open_with(&self.opener) {
            Ok(()) => true,
            Err(e) => {
                let n = self.refused.fetch_add(1, Ordering::Relaxed) + 1;
                if n.is_power_of_two() || n.is_multiple_of(1000) {
                    tracing::warn!(
                        refused = n,
                        "ignored a {} that is not sealed by the site's key: {e} \
                         (a peer without the key publishes on its key: check the router's \
                         access control and who reaches this network)",
                        self.what
                    );
                }
                false
            }
        }
    }

    /// How many messages were refused so far.
    pub fn refused(&self) -> u64 {
        self.refused.load(Ordering::Relaxed)
    }
}

fn now_ms() -> i64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| d.as_millis() as i64)
        .unwrap_or(0)
}

/// Seals messages: one per process and key (its epoch tells a restarted
/// sender's stream from a replay of the old one).
#[derive(Debug)]
pub struct Sealer {
    key: SealKey,
    epoch: u64,
    counter: AtomicU64,
}

impl Sealer {
    /// A sealer with a fresh random epoch.
    pub fn new(key: SealKey) -> Self {
        Self {
            key,
            epoch: rand::random(),
            counter: AtomicU64::new(0),
        }
    }

    /// The attachment that carries `inner` (possibly empty) and the seal of
    /// a message of `payload` on `key_expr`.
    pub fn seal(&self, key_expr: &str, payload: &[u8], inner: &[u8]) -> Vec<u8> {
        let counter = self.counter.fetch_add(1, Ordering::Relaxed) + 1;
        let mut header = [0u8; 24];
        header[..8].copy_from_slice(&self.epoch.to_le_bytes());
        header[8..16].copy_from_slice(&counter.to_le_bytes());
        header[16..].copy_from_slice(&now_ms().to_le_bytes());
        let tag = self
            .key
            .mac(key_expr, payload, inner, &header)
            .finalize()
            .into_bytes();
        let mut out = Vec::with_capacity(inner.len() + TRAILER_LEN);
        out.extend_from_slice(inner);
        out.extend_from_slice(&header);
        out.extend_from_slice(&tag);
        out.extend_from_slice(MAGIC);
        out
    }
}

/// An attachment without its seal trailer, if it has one: what the
/// message's own attachment (e.g. a `SeqTag`) decodes from.
pub fn inner(attachment: &[u8]) -> &[u8] {
    split(attachment).map_or(attachment, |(inner, _)| inner)
}

fn split(attachment: &[u8]) -> Option<(&[u8], &[u8])> {
    let at = attachment.len().checked_sub(TRAILER_LEN)?;
    let (inner, trailer) = attachment.split_at(at);
    trailer.ends_with(MAGIC).then_some((inner, trailer))
}

/// Which counters of the current epoch were seen.
#[derive(Debug, Clone, Copy)]
struct Seen {
    epoch: u64,
    /// Newest sent_at of the epoch.
    sent_at_ms: i64,
    /// Highest counter.
    top: u64,
    /// Bit `i`: counter `top - i` seen.
    window: u64,
}

/// Checks the seals of one stream (one key expression's messages, from one
/// sealer at a time).
#[derive(Debug)]
pub struct Opener {
    key: SealKey,
    max_age: Duration,
    seen: Mutex<Option<Seen>>,
}

impl Opener {
    /// An opener accepting seals of `key` at most `max_age` off its clock.
    pub fn new(key: SealKey, max_age: Duration) -> Self {
        Self {
            key,
            max_age,
            seen: Mutex::new(None),
        }
    }

    /// Checks the seal of a message of `payload` on `key_expr`; returns the
    /// inner attachment.
    pub fn open<'a>(
        &self,
        key_expr: &str,
        payload: &[u8],
        attachment: Option<&'a [u8]>,
    ) -> Result<&'a [u8], SealError> {
        let (inner, trailer) = attachment.and_then(split).ok_or(SealError::Unsealed)?;
        let header: [u8; 24] = trailer[..24].try_into().expect("24 bytes");
        let tag = &trailer[24..24 + TAG_LEN];
        // In constant time (`verify_slice`).
        self.key
            .mac(key_expr, payload, inner, &header)
            .verify_slice(tag)
            .map_err(|_| SealError::BadTag)?;
        let word = |i: usize| u64::from_le_bytes(header[i..i + 8].try_into().expect("8 bytes"));
        let (epoch, counter, sent_at_ms) = (word(0), word(8), word(16) as i64);
        let age_ms = now_ms().saturating_sub(sent_at_ms);
        let max_ms = self.max_age.as_millis() as u64;
        if age_ms.unsigned_abs() > max_ms {
            return Err(SealError::Stale { age_ms, max_ms });
        }
        let mut seen = self.seen.lock().unwrap_or_else(|p| p.into_inner());
        let replayed = SealError::Replayed { epoch, counter };
        match seen.as_mut() {
            Some(s) if s.epoch == epoch => {
                if counter > s.top {
                    let shift = counter - s.top;
                    s.window = if shift >= 64 { 0 } else { s.window << shift };
                    s.window |= 1;
                    s.top = counter;
                } else {
                    let back = s.top - counter;
                    if back >= REPLAY_WINDOW || s.window & (1 << back) != 0 {
                        return Err(replayed);
                    }
                    s.window |= 1 << back;
                }
                s.sent_at_ms = s.sent_at_ms.max(sent_at_ms);
            }
            // Another epoch: a restarted sealer (newer than all we heard),
            // or a replay of a superseded one.
            Some(s) if sent_at_ms < s.sent_at_ms => return Err(replayed),
            _ => {
                *seen = Some(Seen {
                    epoch,
                    sent_at_ms,
                    top: counter,
                    window: 1,
                })
            }
        }
        Ok(inner)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn key() -> SealKey {
        SealKey::from_hex(&"ab".repeat(32)).expect("key")
    }

    const KEY: &str = "offworld/@v1/real/a/cmd";

    #[test]
    fn a_sealed_message_opens_once_and_keeps_its_inner_attachment() {
        let sealer = Sealer::new(key());
        let opener = Opener::new(key(), DEFAULT_MAX_AGE);
        let sealed = sealer.seal(KEY, b"go", b"tag");
        assert_eq!(sealed.len(), 3 + TRAILER_LEN);
        assert_eq!(inner(&sealed), b"tag");
        assert_eq!(opener.open(KEY, b"go", Some(&sealed)), Ok(&b"tag"[..]));
        assert!(matches!(
            opener.open(KEY, b"go", Some(&sealed)),
            Err(SealError::Replayed { counter: 1, .. })
        ));
    }

    #[test]
    fn anything_altered_or_unsealed_is_refused() {
        let sealer = Sealer::new(key());
        let opener = Opener::new(key(), DEFAULT_MAX_AGE);
        let sealed = sealer.seal(KEY, b"go", b"");
        assert_eq!(opener.open(KEY, b"go", None), Err(SealError::Unsealed));
        assert_eq!(
            opener.open(KEY, b"go", Some(b"x")),
            Err(SealError::Unsealed)
        );
        assert_eq!(
            opener.open(KEY, b"GO", Some(&sealed)),
            Err(SealError::BadTag)
        );
        let other = "offworld/@v1/real/b/cmd";
        assert_eq!(
            opener.open(other, b"go", Some(&sealed)),
            Err(SealError::BadTag)
        );
        for i in 0..TRAILER_LEN - MAGIC.len() {
            let mut bad = sealed.clone();
            bad[i] ^= 1;
            assert_eq!(
                opener.open(KEY, b"go", Some(&bad)),
                Err(SealError::BadTag),
                "byte {i}"
            );
        }
        let stranger = Sealer::new(SealKey::generate()).seal(KEY, b"go", b"");
        assert_eq!(
            opener.open(KEY, b"go", Some(&stranger)),
            Err(SealError::BadTag)
        );
    }

    #[test]
    fn reordering_within_the_window_passes_and_replays_do_not() {
        let sealer = Sealer::new(key());
        let opener = Opener::new(key(), DEFAULT_MAX_AGE);
        let sealed: Vec<Vec<u8>> = (0..100).map(|_| sealer.seal(KEY, b"m", b"")).collect();
        // 2, 1, 3, then 100 (the window moves), then 40 is too old.
        for i in [1, 0, 2, 99] {
            assert!(opener.open(KEY, b"m", Some(&sealed[i])).is_ok(), "{i}");
        }
        for i in [0, 1, 2, 99, 30] {
            assert!(
                matches!(
                    opener.open(KEY, b"m", Some(&sealed[i])),
                    Err(SealError::Replayed { .. })
                ),
                "{i}"
            );
        }
        assert!(opener.open(KEY, b"m", Some(&sealed[98])).is_ok());
    }

    #[test]
    fn a_restarted_sealer_supersedes_the_old_epoch() {
        let opener = Opener::new(key(), DEFAULT_MAX_AGE);
        let old = Sealer::new(key());
        let captured = old.seal(KEY, b"m", b"");
        std::thread::sleep(Duration::from_millis(5));
        let new = Sealer::new(key());
        assert!(opener
            .open(KEY, b"m", Some(&new.seal(KEY, b"m", b"")))
            .is_ok());
        assert!(matches!(
            opener.open(KEY, b"m", Some(&captured)),
            Err(SealError::Replayed { counter: 1, .. })
        ));
        assert!(opener
            .open(KEY, b"m", Some(&new.seal(KEY, b"m", b"")))
            .is_ok());
    }

    #[test]
    fn a_stale_seal_is_refused() {
        let opener = Opener::new(key(), Duration::ZERO);
        let sealed = Sealer::new(key()).seal(KEY, b"m", b"");
        std::thread::sleep(Duration::from_millis(3));
        assert!(matches!(
            opener.open(KEY, b"m", Some(&sealed)),
            Err(SealError::Stale { max_ms: 0, .. })
        ));
    }

    #[test]
    fn key_files_round_trip_and_must_be_private() {
        let dir = std::env::temp_dir().join(format!("offworld-seal-{}", rand::random::<u64>()));
        std::fs::create_dir_all(&dir).expect("dir");
        let path = dir.join("command.key");
        let key = SealKey::generate();
        key.save(&path).expect("save");
        assert_eq!(SealKey::load(&path).expect("load").to_hex(), key.to_hex());
        assert!(key.save(&path).is_err(), "never overwrites a key");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o644)).expect("chmod");
            let err = SealKey::load(&path).expect_err("world-readable");
            assert!(
                err.to_string().contains("readable by others (mode 644)"),
                "{err}"
            );
        }
        std::fs::write(dir.join("short.key"), "abcd").expect("write");
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let short = dir.join("short.key");
            std::fs::set_permissions(&short, std::fs::Permissions::from_mode(0o600))
                .expect("chmod");
            let err = SealKey::load(&short).expect_err("short");
            assert!(err.to_string().contains("expected 64 hex digits"), "{err}");
        }
        assert_eq!(format!("{key:?}"), "SealKey(…)");
        std::fs::remove_dir_all(&dir).expect("clean");
    }
}
