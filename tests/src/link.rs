//! A TCP link whose quality a test controls: a forwarding proxy between the
//! site and the robot that can cut the link, delay it or make it lossy
//! while every connection through it stays open, as a radio link does.
//!
//! The kernel's `netem` qdisc is not available everywhere (not on this
//! project's CI machine), so the impairments are emulated on the byte
//! stream, as TCP shows them to its user:
//! - **cut**: nothing gets through; what was sent is held and delivered
//!   when the link returns (TCP retransmits until then);
//! - **delay**: each chunk is delivered a fixed time after it was sent, in
//!   each direction;
//! - **loss**: a byte stream cannot lose bytes; a lost segment holds back
//!   everything after it until its retransmission, after a timeout of at
//!   least 200 ms (Linux's minimum RTO) that doubles while losses repeat.
//!   Each chunk is lost with the given probability (a seeded generator).

use std::io::{Read, Write};
use std::net::{IpAddr, Shutdown, SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// What the link does to traffic now.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Impairment {
    /// Everything passes at once.
    Clear,
    /// Nothing passes; held traffic is delivered when the link clears.
    Cut,
    /// Each chunk arrives this long after it was sent.
    Delay(Duration),
    /// This percentage of chunks is lost and retransmitted.
    Loss {
        /// 0–100.
        percent: u8,
    },
}

/// Linux's minimum retransmission timeout.
const MIN_RTO: Duration = Duration::from_millis(200);
/// Cap of the doubling retransmission timeout.
const MAX_RTO: Duration = Duration::from_millis(3_200);

struct Shared {
    impairment: Mutex<Impairment>,
    stop: AtomicBool,
    streams: Mutex<Vec<TcpStream>>,
    seed: u64,
}

impl Shared {
    fn impairment(&self) -> Impairment {
        *self
            .impairment
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

/// The proxy; every connection through it is closed when dropped.
pub struct ImpairedLink {
    addr: SocketAddr,
    shared: Arc<Shared>,
}

impl ImpairedLink {
    /// Listens on a free port of `listen` and forwards each connection to
    /// `upstream`; `seed` fixes which chunks a lossy link loses.
    pub fn start(listen: IpAddr, upstream: SocketAddr, seed: u64) -> std::io::Result<Self> {
        let listener = TcpListener::bind((listen, 0))?;
        let addr = listener.local_addr()?;
        let shared = Arc::new(Shared {
            impairment: Mutex::new(Impairment::Clear),
            stop: AtomicBool::new(false),
            streams: Mutex::new(Vec::new()),
            seed,
        });
        let accepting = shared.clone();
        std::thread::Builder::new()
            .name("impaired-link".into())
            .spawn(move || {
                for (n, downstream) in (0u64..).zip(listener.incoming()) {
                    if accepting.stop.load(Ordering::SeqCst) {
                        return;
                    }
                    let Ok(downstream) = downstream else { continue };
                    let Ok(upstream) = TcpStream::connect_timeout(&upstream, MIN_RTO * 10) else {
                        continue;
                    };
                    let _ = connect(&accepting, downstream, upstream, n);
                }
            })?;
        Ok(Self { addr, shared })
    }

    /// Where the site connects (`tcp/<addr>` as a Zenoh endpoint).
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The Zenoh endpoint of the link.
    pub fn endpoint(&self) -> String {
        format!("tcp/{}", self.addr)
    }

    /// Changes what the link does from now on.
    pub fn impair(&self, impairment: Impairment) {
        *self
            .shared
            .impairment
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = impairment;
    }
}

impl Drop for ImpairedLink {
    fn drop(&mut self) {
        self.shared.stop.store(true, Ordering::SeqCst);
        for stream in self
            .shared
            .streams
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .drain(..)
        {
            let _ = stream.shutdown(Shutdown::Both);
        }
        // Wake the acceptor so it sees the flag.
        let _ = TcpStream::connect_timeout(&self.addr, Duration::from_millis(100));
    }
}

/// Pumps both directions of one connection, each through its own queue.
fn connect(
    shared: &Arc<Shared>,
    downstream: TcpStream,
    upstream: TcpStream,
    n: u64,
) -> std::io::Result<()> {
    for stream in [&downstream, &upstream] {
        stream.set_nodelay(true)?;
    }
    {
        let mut streams = shared
            .streams
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        streams.push(downstream.try_clone()?);
        streams.push(upstream.try_clone()?);
    }
    let directions = [
        (downstream.try_clone()?, upstream.try_clone()?, 2 * n),
        (upstream, downstream, 2 * n + 1),
    ];
    for (from, to, stream_id) in directions {
        let (queue, queued) = mpsc::channel::<(Instant, Vec<u8>)>();
        let reading = shared.clone();
        let writing = shared.clone();
        let to_close = to.try_clone()?;
        std::thread::spawn(move || read_side(&reading, from, &queue, stream_id));
        std::thread::spawn(move || {
            write_side(&writing, to, &queued);
            let _ = to_close.shutdown(Shutdown::Both);
        });
    }
    Ok(())
}

/// Reads chunks and stamps each with when it may be delivered.
fn read_side(
    shared: &Shared,
    mut from: TcpStream,
    queue: &mpsc::Sender<(Instant, Vec<u8>)>,
    stream_id: u64,
) {
    let mut rng = ChaCha8Rng::seed_from_u64(shared.seed);
    rng.set_stream(stream_id);
    let mut buffer = vec![0u8; 64 * 1024];
    let mut last_release = Instant::now();
    let mut losses_in_a_row = 0u32;
    loop {
        let n = match from.read(&mut buffer) {
            Ok(0) | Err(_) => return,
            Ok(n) => n,
        };
        let now = Instant::now();
        let release = match shared.impairment() {
            Impairment::Clear | Impairment::Cut => now,
            Impairment::Delay(d) => now + d,
            Impairment::Loss { percent } => {
                if rng.random_range(0..100u8) < percent {
                    losses_in_a_row += 1;
                    let rto = MIN_RTO.saturating_mul(1 << (losses_in_a_row - 1).min(4));
                    now + rto.min(MAX_RTO)
                } else {
                    losses_in_a_row = 0;
                    now
                }
            }
        };
        // In order: nothing overtakes a held chunk.
        last_release = last_release.max(release);
        if queue.send((last_release, buffer[..n].to_vec())).is_err() {
            return;
        }
    }
}

/// Delivers chunks when due, holding them all while the link is cut.
fn write_side(shared: &Shared, mut to: TcpStream, queued: &mpsc::Receiver<(Instant, Vec<u8>)>) {
    while let Ok((release, chunk)) = queued.recv() {
        loop {
            if shared.stop.load(Ordering::SeqCst) {
                return;
            }
            let now = Instant::now();
            if now < release {
                std::thread::sleep((release - now).min(Duration::from_millis(5)));
            } else if shared.impairment() == Impairment::Cut {
                std::thread::sleep(Duration::from_millis(5));
            } else {
                break;
            }
        }
        if to.write_all(&chunk).is_err() {
            return;
        }
    }
}
