//! Pose sources: where [`TrackerSample`]s come from.
//!
//! Every source speaks the [line protocol](crate::protocol) and implements
//! [`PoseSource`]. Sources are chosen with a [`SourceSpec`]:
//!
//! | spec | behaviour |
//! |---|---|
//! | `stdin` (or `-`) | lines on standard input; ends at end of file |
//! | `tcp://HOST:PORT` | connects as a client to a server that streams lines; reconnects with bounded exponential backoff when the connection drops or cannot be made; never ends |
//! | `udp://BIND:PORT` | listens; each datagram holds one or more lines (a datagram's last line needs no `\n`); never ends |
//! | `replay:PATH[?rate=R]` | a recorded file of protocol lines, replayed with its original inter-sample timing scaled by `R` (default 1; 2 = twice as fast); ends at end of file |

use std::collections::VecDeque;
use std::fmt;
use std::future::Future;
use std::path::PathBuf;
use std::pin::Pin;
use std::str::FromStr;
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncReadExt};
use tokio::net::{TcpStream, UdpSocket};
use tokio::time::Instant;

use crate::protocol::{LineDecoder, ProtocolError, TrackerSample};

/// Why a source failed.
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// One malformed line, skipped: call [`PoseSource::next`] again.
    #[error(transparent)]
    Malformed(#[from] ProtocolError),
    /// The source cannot go on (unreadable stdin, missing replay file,
    /// UDP port in use, …).
    #[error("{what}: {error}")]
    Io {
        /// Which source and which operation.
        what: String,
        /// The I/O error.
        #[source]
        error: std::io::Error,
    },
}

impl SourceError {
    /// Whether the source is unusable after this error (a malformed line is
    /// not fatal).
    pub fn is_fatal(&self) -> bool {
        !matches!(self, SourceError::Malformed(_))
    }
}

/// The future returned by [`PoseSource::next`].
pub type NextSample<'a> =
    Pin<Box<dyn Future<Output = Result<Option<TrackerSample>, SourceError>> + Send + 'a>>;

/// A stream of tracker samples.
///
/// `next` yields `Ok(Some(sample))` per pose, `Err(SourceError::Malformed)`
/// for a skipped line (the stream goes on), `Ok(None)` once the source has
/// ended for good, and a fatal error ([`SourceError::is_fatal`]) when it
/// cannot go on. Boxed futures keep the trait object-safe, so a
/// `Box<dyn PoseSource>` can hold any source.
pub trait PoseSource: Send {
    /// The next sample.
    fn next(&mut self) -> NextSample<'_>;
    /// A human-readable name for logs (`tcp://…`, `stdin`, …).
    fn describe(&self) -> String;
}

impl PoseSource for Box<dyn PoseSource> {
    fn next(&mut self) -> NextSample<'_> {
        (**self).next()
    }
    fn describe(&self) -> String {
        (**self).describe()
    }
}

type Parsed = Result<TrackerSample, ProtocolError>;

fn pop(pending: &mut VecDeque<Parsed>) -> Option<Result<Option<TrackerSample>, SourceError>> {
    pending
        .pop_front()
        .map(|r| r.map(Some).map_err(SourceError::Malformed))
}

const READ_CHUNK: usize = 8 * 1024;

/// Lines from any byte stream (stdin, a file, a pipe, an in-memory
/// stream); ends at end of stream. A last line without `\n` still counts.
pub struct LineSource<R> {
    reader: R,
    name: String,
    decoder: LineDecoder,
    pending: VecDeque<Parsed>,
    chunk: Vec<u8>,
    scratch: Vec<Parsed>,
    ended: bool,
}

impl<R: AsyncRead + Unpin + Send> LineSource<R> {
    /// Reads protocol lines from `reader`; `name` is used in logs.
    pub fn new(reader: R, name: impl Into<String>) -> Self {
        Self {
            reader,
            name: name.into(),
            decoder: LineDecoder::new(),
            pending: VecDeque::new(),
            chunk: vec![0; READ_CHUNK],
            scratch: Vec::new(),
            ended: false,
        }
    }

    async fn next_line(&mut self) -> Result<Option<TrackerSample>, SourceError> {
        loop {
            if let Some(item) = pop(&mut self.pending) {
                return item;
            }
            if self.ended {
                return Ok(None);
            }
            let n = self
                .reader
                .read(&mut self.chunk)
                .await
                .map_err(|error| SourceError::Io {
                    what: format!("reading {}", self.name),
                    error,
                })?;
            if n == 0 {
                self.ended = true;
                self.decoder.flush(&mut self.scratch);
            } else {
                self.decoder.push(&self.chunk[..n], &mut self.scratch);
            }
            self.pending.extend(self.scratch.drain(..));
        }
    }
}

impl<R: AsyncRead + Unpin + Send> PoseSource for LineSource<R> {
    fn next(&mut self) -> NextSample<'_> {
        Box::pin(self.next_line())
    }
    fn describe(&self) -> String {
        self.name.clone()
    }
}

/// Lines on standard input.
pub fn stdin_source() -> LineSource<tokio::io::Stdin> {
    LineSource::new(tokio::io::stdin(), "stdin")
}

/// Reconnection delays of [`TcpLineSource`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Backoff {
    /// First delay after a failure.
    pub initial: Duration,
    /// The delay doubles per consecutive failure up to this bound.
    pub max: Duration,
}

impl Default for Backoff {
    fn default() -> Self {
        Self {
            initial: Duration::from_millis(100),
            max: Duration::from_secs(2),
        }
    }
}

/// A TCP client reading lines from a server; reconnects forever with
/// bounded backoff. A partial line cut by a disconnect is dropped; line
/// numbers restart with each connection.
pub struct TcpLineSource {
    addr: String,
    backoff: Backoff,
    delay: Duration,
    stream: Option<TcpStream>,
    /// A connection had been up; its loss is worth a warning.
    was_connected: bool,
    decoder: LineDecoder,
    pending: VecDeque<Parsed>,
    chunk: Vec<u8>,
    scratch: Vec<Parsed>,
}

impl TcpLineSource {
    /// A client of `addr` (`host:port`); connects on the first `next`.
    pub fn new(addr: impl Into<String>, backoff: Backoff) -> Self {
        Self {
            addr: addr.into(),
            backoff,
            delay: backoff.initial,
            stream: None,
            was_connected: false,
            decoder: LineDecoder::new(),
            pending: VecDeque::new(),
            chunk: vec![0; READ_CHUNK],
            scratch: Vec::new(),
        }
    }

    async fn wait_before_retry(&mut self) {
        tokio::time::sleep(self.delay).await;
        self.delay = (self.delay * 2).min(self.backoff.max);
    }

    fn disconnected(&mut self, why: &str) {
        self.stream = None;
        if self.decoder.has_partial() {
            tracing::debug!(addr = %self.addr, "dropped a partial line cut by the disconnect");
        }
        self.decoder.reset();
        if self.was_connected {
            tracing::warn!(addr = %self.addr, "tracker stream lost ({why}); reconnecting");
            self.was_connected = false;
        }
    }

    async fn next_line(&mut self) -> Result<Option<TrackerSample>, SourceError> {
        loop {
            if let Some(item) = pop(&mut self.pending) {
                return item;
            }
            let Some(stream) = self.stream.as_mut() else {
                match TcpStream::connect(&self.addr).await {
                    Ok(stream) => {
                        // Poses are small and latency matters.
                        let _ = stream.set_nodelay(true);
                        tracing::info!(addr = %self.addr, "connected to the tracker stream");
                        self.stream = Some(stream);
                        self.was_connected = true;
                    }
                    Err(e) => {
                        tracing::debug!(addr = %self.addr, "connect failed: {e}; retrying in {:?}", self.delay);
                        self.wait_before_retry().await;
                    }
                }
                continue;
            };
            match stream.read(&mut self.chunk).await {
                Ok(0) => {
                    self.disconnected("closed by the server");
                    self.wait_before_retry().await;
                }
                Ok(n) => {
                    // Data flows: the next failure starts the backoff over.
                    self.delay = self.backoff.initial;
                    self.decoder.push(&self.chunk[..n], &mut self.scratch);
                    self.pending.extend(self.scratch.drain(..));
                }
                Err(e) => {
                    self.disconnected(&e.to_string());
                    self.wait_before_retry().await;
                }
            }
        }
    }
}

impl PoseSource for TcpLineSource {
    fn next(&mut self) -> NextSample<'_> {
        Box::pin(self.next_line())
    }
    fn describe(&self) -> String {
        format!("tcp://{}", self.addr)
    }
}

/// Largest datagram accepted.
const MAX_DATAGRAM: usize = 64 * 1024;

/// Datagrams of lines received on a bound UDP socket. Line numbers count
/// across datagrams.
pub struct UdpLineSource {
    socket: UdpSocket,
    name: String,
    decoder: LineDecoder,
    pending: VecDeque<Parsed>,
    buffer: Vec<u8>,
    scratch: Vec<Parsed>,
}

impl UdpLineSource {
    /// Binds `addr` (`host:port`; port 0 picks a free one).
    pub async fn bind(addr: &str) -> Result<Self, SourceError> {
        let socket = UdpSocket::bind(addr)
            .await
            .map_err(|error| SourceError::Io {
                what: format!("binding udp://{addr}"),
                error,
            })?;
        let name = match socket.local_addr() {
            Ok(local) => format!("udp://{local}"),
            Err(_) => format!("udp://{addr}"),
        };
        Ok(Self {
            socket,
            name,
            decoder: LineDecoder::new(),
            pending: VecDeque::new(),
            buffer: vec![0; MAX_DATAGRAM],
            scratch: Vec::new(),
        })
    }

    /// The bound address.
    pub fn local_addr(&self) -> Option<std::net::SocketAddr> {
        self.socket.local_addr().ok()
    }

    async fn next_line(&mut self) -> Result<Option<TrackerSample>, SourceError> {
        loop {
            if let Some(item) = pop(&mut self.pending) {
                return item;
            }
            match self.socket.recv_from(&mut self.buffer).await {
                Ok((n, _from)) => {
                    self.decoder.push(&self.buffer[..n], &mut self.scratch);
                    // A datagram ends its last line.
                    self.decoder.flush(&mut self.scratch);
                    self.pending.extend(self.scratch.drain(..));
                }
                // Transient on some platforms (ICMP port unreachable of an
                // earlier send); the socket stays usable.
                Err(e) => {
                    tracing::warn!(source = %self.name, "receive failed: {e}");
                    tokio::time::sleep(Duration::from_millis(10)).await;
                }
            }
        }
    }
}

impl PoseSource for UdpLineSource {
    fn next(&mut self) -> NextSample<'_> {
        Box::pin(self.next_line())
    }
    fn describe(&self) -> String {
        self.name.clone()
    }
}

/// A recorded file replayed with its original timing (scaled by `rate`).
///
/// The first sample comes at once; each later one when
/// `(t − t_first) / rate` has elapsed. A timestamp going backwards
/// (another device, a restarted clock) re-anchors the timing at once.
pub struct ReplaySource {
    lines: LineSource<tokio::fs::File>,
    rate: f64,
    anchor: Option<(f64, Instant)>,
    last_timestamp: f64,
}

impl ReplaySource {
    /// Opens `path`; `rate` must be finite and > 0.
    pub async fn open(path: &std::path::Path, rate: f64) -> Result<Self, SourceError> {
        if !(rate.is_finite() && rate > 0.0) {
            return Err(SourceError::Io {
                what: format!("replay {}", path.display()),
                error: std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    format!("rate must be finite and > 0, got {rate}"),
                ),
            });
        }
        let file = tokio::fs::File::open(path)
            .await
            .map_err(|error| SourceError::Io {
                what: format!("opening {}", path.display()),
                error,
            })?;
        Ok(Self {
            lines: LineSource::new(file, format!("replay:{}", path.display())),
            rate,
            anchor: None,
            last_timestamp: f64::NEG_INFINITY,
        })
    }

    async fn next_paced(&mut self) -> Result<Option<TrackerSample>, SourceError> {
        let Some(sample) = self.lines.next_line().await? else {
            return Ok(None);
        };
        let t = sample.timestamp_s;
        match self.anchor {
            Some((t0, wall0)) if t >= self.last_timestamp => {
                let offset = Duration::try_from_secs_f64((t - t0) / self.rate).unwrap_or_default();
                tokio::time::sleep_until(wall0 + offset).await;
            }
            _ => self.anchor = Some((t, Instant::now())),
        }
        self.last_timestamp = t;
        Ok(Some(sample))
    }
}

impl PoseSource for ReplaySource {
    fn next(&mut self) -> NextSample<'_> {
        Box::pin(self.next_paced())
    }
    fn describe(&self) -> String {
        format!("{} (rate {})", self.lines.name, self.rate)
    }
}

/// Why a source spec did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SourceSpecError {
    /// Not `stdin`, `tcp://`, `udp://` or `replay:`.
    #[error("unknown source `{0}`: expected stdin, tcp://HOST:PORT, udp://BIND:PORT or replay:PATH[?rate=R]")]
    UnknownScheme(String),
    /// `HOST:PORT` is missing a host or a valid port.
    #[error("bad address `{addr}`: {reason}")]
    BadAddress {
        /// The address part.
        addr: String,
        /// What is wrong.
        reason: String,
    },
    /// `replay:` without a path.
    #[error("replay needs a file path: replay:PATH[?rate=R]")]
    EmptyPath,
    /// `rate=` is not a finite number > 0.
    #[error("replay rate must be a finite number > 0, got `{0}`")]
    BadRate(String),
    /// An option other than `rate=`.
    #[error("unknown replay option `{0}` (only rate=R)")]
    UnknownOption(String),
}

/// A parsed source spec (see the [module docs](self) for the forms).
#[derive(Debug, Clone, PartialEq)]
pub enum SourceSpec {
    /// Standard input.
    Stdin,
    /// A TCP server to connect to (`host:port`).
    Tcp {
        /// `host:port`.
        addr: String,
    },
    /// A UDP address to bind (`host:port`).
    Udp {
        /// `host:port`.
        bind: String,
    },
    /// A recorded file.
    Replay {
        /// The file.
        path: PathBuf,
        /// Speed factor (1 = original timing).
        rate: f64,
    },
}

fn check_addr(addr: &str) -> Result<String, SourceSpecError> {
    let bad = |reason: &str| SourceSpecError::BadAddress {
        addr: addr.to_owned(),
        reason: reason.to_owned(),
    };
    let (host, port) = addr.rsplit_once(':').ok_or_else(|| bad("missing :PORT"))?;
    if host.is_empty() {
        return Err(bad("missing host"));
    }
    if host.contains('/') || host.chars().any(char::is_whitespace) {
        return Err(bad("host contains `/` or whitespace"));
    }
    port.parse::<u16>()
        .map_err(|_| bad("port must be a number 0-65535"))?;
    Ok(addr.to_owned())
}

impl FromStr for SourceSpec {
    type Err = SourceSpecError;
    fn from_str(spec: &str) -> Result<Self, Self::Err> {
        let spec = spec.trim();
        if spec == "stdin" || spec == "-" {
            return Ok(SourceSpec::Stdin);
        }
        if let Some(addr) = spec.strip_prefix("tcp://") {
            return Ok(SourceSpec::Tcp {
                addr: check_addr(addr)?,
            });
        }
        if let Some(addr) = spec.strip_prefix("udp://") {
            return Ok(SourceSpec::Udp {
                bind: check_addr(addr)?,
            });
        }
        if let Some(rest) = spec.strip_prefix("replay:") {
            let (path, options) = match rest.rsplit_once('?') {
                Some((path, options)) => (path, Some(options)),
                None => (rest, None),
            };
            if path.is_empty() {
                return Err(SourceSpecError::EmptyPath);
            }
            let mut rate = 1.0;
            for option in options.into_iter().flat_map(|o| o.split('&')) {
                match option.split_once('=') {
                    Some(("rate", value)) => {
                        rate = value
                            .parse::<f64>()
                            .ok()
                            .filter(|r| r.is_finite() && *r > 0.0)
                            .ok_or_else(|| SourceSpecError::BadRate(value.to_owned()))?;
                    }
                    _ => return Err(SourceSpecError::UnknownOption(option.to_owned())),
                }
            }
            return Ok(SourceSpec::Replay {
                path: PathBuf::from(path),
                rate,
            });
        }
        Err(SourceSpecError::UnknownScheme(spec.to_owned()))
    }
}

impl fmt::Display for SourceSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SourceSpec::Stdin => write!(f, "stdin"),
            SourceSpec::Tcp { addr } => write!(f, "tcp://{addr}"),
            SourceSpec::Udp { bind } => write!(f, "udp://{bind}"),
            SourceSpec::Replay { path, rate } => {
                write!(f, "replay:{}?rate={rate}", path.display())
            }
        }
    }
}

impl SourceSpec {
    /// Opens the source (binds UDP, opens the replay file; TCP connects on
    /// first use).
    pub async fn open(&self) -> Result<Box<dyn PoseSource>, SourceError> {
        Ok(match self {
            SourceSpec::Stdin => Box::new(stdin_source()),
            SourceSpec::Tcp { addr } => Box::new(TcpLineSource::new(addr, Backoff::default())),
            SourceSpec::Udp { bind } => Box::new(UdpLineSource::bind(bind).await?),
            SourceSpec::Replay { path, rate } => Box::new(ReplaySource::open(path, *rate).await?),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn source_specs_parse() {
        let table = [
            ("stdin", SourceSpec::Stdin),
            ("-", SourceSpec::Stdin),
            (
                "tcp://127.0.0.1:6969",
                SourceSpec::Tcp {
                    addr: "127.0.0.1:6969".into(),
                },
            ),
            (
                "tcp://lighthouse-pc.local:7000",
                SourceSpec::Tcp {
                    addr: "lighthouse-pc.local:7000".into(),
                },
            ),
            (
                "udp://0.0.0.0:5005",
                SourceSpec::Udp {
                    bind: "0.0.0.0:5005".into(),
                },
            ),
            (
                "udp://[::1]:5005",
                SourceSpec::Udp {
                    bind: "[::1]:5005".into(),
                },
            ),
            (
                "replay:/data/run 1.txt",
                SourceSpec::Replay {
                    path: "/data/run 1.txt".into(),
                    rate: 1.0,
                },
            ),
            (
                "replay:rec.txt?rate=2.5",
                SourceSpec::Replay {
                    path: "rec.txt".into(),
                    rate: 2.5,
                },
            ),
        ];
        for (text, expected) in table {
            let parsed: SourceSpec = text.parse().expect(text);
            assert_eq!(parsed, expected, "{text}");
            // Display parses back to the same spec.
            assert_eq!(parsed.to_string().parse::<SourceSpec>(), Ok(expected));
        }
    }

    #[test]
    fn bad_source_specs_are_typed_errors() {
        use SourceSpecError as E;
        let bad_addr = |s: &str| matches!(s.parse::<SourceSpec>(), Err(E::BadAddress { .. }));
        assert!(matches!(
            "serial:/dev/ttyACM0".parse::<SourceSpec>(),
            Err(E::UnknownScheme(_))
        ));
        assert!(matches!("".parse::<SourceSpec>(), Err(E::UnknownScheme(_))));
        assert!(bad_addr("tcp://127.0.0.1"));
        assert!(bad_addr("tcp://:6969"));
        assert!(bad_addr("tcp://host:70000"));
        assert!(bad_addr("udp://0.0.0.0:port"));
        assert!(bad_addr("tcp://host/path:1"));
        assert_eq!("replay:".parse::<SourceSpec>(), Err(E::EmptyPath));
        assert_eq!("replay:?rate=2".parse::<SourceSpec>(), Err(E::EmptyPath));
        for rate in ["0", "-1", "inf", "NaN", "fast", ""] {
            assert_eq!(
                format!("replay:r.txt?rate={rate}").parse::<SourceSpec>(),
                Err(E::BadRate(rate.into())),
                "{rate}"
            );
        }
        assert_eq!(
            "replay:r.txt?loop=1".parse::<SourceSpec>(),
            Err(E::UnknownOption("loop=1".into()))
        );
    }
}
