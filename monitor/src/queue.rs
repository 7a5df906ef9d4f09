//! The one hand-off between Zenoh callbacks and the logging worker: a
//! bounded, never-blocking queue with two lanes.
//!
//! - **frames** (camera frames, overhead images): a few slots; when full the
//!   *oldest* queued frame is evicted, so the viewer always gets the latest
//!   picture and a slow viewer costs frames, never the step. A live view
//!   pushes with [`Queue::push_newest`]: a camera's frame still waiting is
//!   replaced by its next one, so at most one per camera waits.
//! - **messages** (poses, commands, rewards, status, …): many slots; when
//!   full the new message is dropped and counted.
//!
//! Control events (world specs resolved by a helper thread) bypass both
//! limits: there are a handful per env. Items are popped in arrival order
//! across lanes. Pushing takes one short mutex and never waits for the
//! worker; a push after [`Queue::close`] is dropped.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::Duration;

/// Which lane an item travels in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Lane {
    /// Big and expendable: evict the oldest when full.
    Frame,
    /// Small: drop the newest when full.
    Message,
    /// Unbounded, never dropped (rare control events).
    Control,
}

/// Counters the queue keeps (shared with the monitor's stats).
#[derive(Debug, Default)]
pub(crate) struct QueueCounters {
    /// Items offered by callbacks.
    pub received: AtomicU64,
    /// Frames evicted or refused.
    pub dropped_frames: AtomicU64,
    /// Messages refused.
    pub dropped_messages: AtomicU64,
    /// Frames replaced while queued by a newer frame of the same camera
    /// ([`Queue::push_newest`]).
    pub superseded_frames: AtomicU64,
}

struct State<T> {
    next_ticket: u64,
    frames: VecDeque<(u64, T)>,
    messages: VecDeque<(u64, T)>,
    control: VecDeque<(u64, T)>,
    closed: bool,
}

/// A bounded multi-producer, single-consumer queue (see the module docs).
pub(crate) struct Queue<T> {
    state: Mutex<State<T>>,
    ready: Condvar,
    frame_capacity: usize,
    message_capacity: usize,
    pub counters: QueueCounters,
}

impl<T> Queue<T> {
    /// A queue holding at most `frame_capacity` frames and
    /// `message_capacity` messages (each at least 1).
    pub fn new(frame_capacity: usize, message_capacity: usize) -> Self {
        Self {
            state: Mutex::new(State {
                next_ticket: 0,
                frames: VecDeque::with_capacity(frame_capacity.max(1)),
                messages: VecDeque::new(),
                control: VecDeque::new(),
                closed: false,
            }),
            ready: Condvar::new(),
            frame_capacity: frame_capacity.max(1),
            message_capacity: message_capacity.max(1),
            counters: QueueCounters::default(),
        }
    }

    fn lock(&self) -> MutexGuard<'_, State<T>> {
        // A panic while holding this lock cannot leave the deques invalid;
        // keep going rather than propagate the poison into Zenoh callbacks.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Offers an item; never blocks beyond one uncontended mutex. Returns
    /// false when the item (or, for frames, an older frame) was dropped.
    pub fn push(&self, lane: Lane, item: T) -> bool {
        self.offer(lane, item, None::<fn(&T, &T) -> bool>)
    }

    /// Offers a frame that replaces any queued frame it `supersedes` (a
    /// live view shows each camera's newest: the older one is dropped now,
    /// in the caller's thread, not after the worker's batch — a frame's
    /// last reference hands its buffer back to the publisher's pool).
    /// Returns false when an older frame was evicted to make room.
    pub fn push_newest(&self, item: T, supersedes: impl Fn(&T, &T) -> bool) -> bool {
        self.offer(Lane::Frame, item, Some(supersedes))
    }

    fn offer(&self, lane: Lane, item: T, supersedes: Option<impl Fn(&T, &T) -> bool>) -> bool {
        if lane != Lane::Control {
            self.counters.received.fetch_add(1, Ordering::Relaxed);
        }
        let mut state = self.lock();
        if state.closed {
            drop(state);
            self.count_drop(lane);
            return false;
        }
        // The consumer waits only on an empty queue: a push to a non-empty
        // one needs no wake-up (std's notify is a syscall every time, and a
        // push runs inline in the publisher's thread for a local one).
        let was_empty = Self::is_empty(&state);
        let ticket = state.next_ticket;
        state.next_ticket += 1;
        // Dropped after the lock is released.
        let mut replaced = None;
        let mut evicted = None;
        match lane {
            Lane::Frame => {
                if let Some(supersedes) = supersedes {
                    let older = state.frames.iter().position(|(_, q)| supersedes(&item, q));
                    replaced = older.and_then(|at| state.frames.remove(at));
                }
                if replaced.is_none() && state.frames.len() >= self.frame_capacity {
                    // Evict the oldest frame: the viewer wants the newest.
                    evicted = state.frames.pop_front();
                }
                state.frames.push_back((ticket, item));
            }
            Lane::Message => {
                if state.messages.len() >= self.message_capacity {
                    drop(state);
                    self.count_drop(lane);
                    return false;
                }
                state.messages.push_back((ticket, item));
            }
            Lane::Control => state.control.push_back((ticket, item)),
        }
        drop(state);
        if replaced.is_some() {
            self.counters
                .superseded_frames
                .fetch_add(1, Ordering::Relaxed);
        }
        let kept_all = evicted.is_none();
        if !kept_all {
            self.count_drop(lane);
        }
        drop((replaced, evicted));
        if was_empty {
            self.ready.notify_one();
        }
        kept_all
    }

    fn count_drop(&self, lane: Lane) {
        let counter = match lane {
            Lane::Frame => &self.counters.dropped_frames,
            Lane::Message | Lane::Control => &self.counters.dropped_messages,
        };
        counter.fetch_add(1, Ordering::Relaxed);
    }

    /// Takes the oldest item of any lane, waiting up to `timeout`. Returns
    /// `Err(())` once the queue is closed *and* empty.
    #[cfg(test)]
    pub fn pop(&self, timeout: Duration) -> Result<Option<T>, ()> {
        let mut state = self.lock();
        loop {
            if let Some(item) = Self::take_oldest(&mut state) {
                return Ok(Some(item));
            }
            if state.closed {
                return Err(());
            }
            let (next, result) = self
                .ready
                .wait_timeout(state, timeout)
                .unwrap_or_else(|p| p.into_inner());
            state = next;
            if result.timed_out() {
                return Ok(Self::take_oldest(&mut state));
            }
        }
    }

    /// Waits up to `timeout` for something to arrive, then lets more arrive
    /// for `coalesce` and takes everything queued, oldest first. Batches keep
    /// the consumer (and rerun's threads behind it) from waking once per
    /// message. Returns `Err(())` once the queue is closed *and* empty.
    #[allow(clippy::result_unit_err)]
    pub fn pop_batch(&self, timeout: Duration, coalesce: Duration) -> Result<Vec<T>, ()> {
        let mut state = self.lock();
        if Self::is_empty(&state) {
            if state.closed {
                return Err(());
            }
            let (next, _) = self
                .ready
                .wait_timeout_while(state, timeout, |s| Self::is_empty(s) && !s.closed)
                .unwrap_or_else(|p| p.into_inner());
            state = next;
            if Self::is_empty(&state) {
                return if state.closed {
                    Err(())
                } else {
                    Ok(Vec::new())
                };
            }
        }
        if !state.closed && !coalesce.is_zero() {
            drop(state);
            std::thread::sleep(coalesce);
            state = self.lock();
        }
        let mut batch =
            Vec::with_capacity(state.frames.len() + state.messages.len() + state.control.len());
        while let Some(item) = Self::take_oldest(&mut state) {
            batch.push(item);
        }
        Ok(batch)
    }

    fn is_empty(state: &State<T>) -> bool {
        state.frames.is_empty() && state.messages.is_empty() && state.control.is_empty()
    }

    fn take_oldest(state: &mut State<T>) -> Option<T> {
        let heads = [
            state.frames.front().map(|(t, _)| *t),
            state.messages.front().map(|(t, _)| *t),
            state.control.front().map(|(t, _)| *t),
        ];
        let lane = heads
            .iter()
            .enumerate()
            .filter_map(|(i, t)| t.map(|t| (t, i)))
            .min()?
            .1;
        let queue = match lane {
            0 => &mut state.frames,
            1 => &mut state.messages,
            _ => &mut state.control,
        };
        queue.pop_front().map(|(_, item)| item)
    }

    /// Refuses further pushes; the consumer drains what is queued.
    pub fn close(&self) {
        self.lock().closed = true;
        self.ready.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_evict_oldest_messages_drop_newest_order_is_kept() {
        let q = Queue::new(2, 2);
        assert!(q.push(Lane::Message, "m1"));
        assert!(q.push(Lane::Frame, "f1"));
        assert!(q.push(Lane::Frame, "f2"));
        assert!(!q.push(Lane::Frame, "f3")); // evicts f1
        assert!(q.push(Lane::Message, "m2"));
        assert!(!q.push(Lane::Message, "m3")); // refused
        assert!(q.push(Lane::Control, "c1"));
        let c = &q.counters;
        assert_eq!(c.received.load(Ordering::Relaxed), 6);
        assert_eq!(c.dropped_frames.load(Ordering::Relaxed), 1);
        assert_eq!(c.dropped_messages.load(Ordering::Relaxed), 1);
        let mut got = Vec::new();
        while let Ok(Some(x)) = q.pop(Duration::from_millis(1)) {
            got.push(x);
        }
        assert_eq!(got, ["m1", "f2", "f3", "m2", "c1"]);
        assert!(q.push(Lane::Message, "m4"));
        assert!(q.push(Lane::Frame, "f4"));
        let batch = q.pop_batch(Duration::from_millis(1), Duration::from_millis(1));
        assert_eq!(batch, Ok(vec!["m4", "f4"]));
        assert_eq!(
            q.pop_batch(Duration::from_millis(1), Duration::ZERO),
            Ok(vec![])
        );
        q.close();
        assert!(q.pop(Duration::from_millis(1)).is_err());
        assert!(q
            .pop_batch(Duration::from_millis(1), Duration::ZERO)
            .is_err());
        assert!(!q.push(Lane::Message, "late"));
    }

    #[test]
    fn a_newer_frame_replaces_the_queued_one_of_its_camera_in_arrival_order() {
        // Items are "camera n"; a message is "reward n".
        fn supersedes(new: &&str, old: &&str) -> bool {
            let camera = |item: &str| item.split_once(' ').map(|(c, _)| c.to_owned());
            !new.starts_with("reward") && camera(new) == camera(old)
        }
        let q = Queue::new(2, 10);
        assert!(q.push_newest("a/obs 1", supersedes));
        assert!(q.push(Lane::Message, "reward 1"));
        assert!(q.push_newest("b/obs 1", supersedes));
        assert!(q.push_newest("a/obs 2", supersedes)); // replaces a/obs 1
        assert!(q.push(Lane::Message, "reward 2"));
        // A third camera: no older frame of its own, the queue is full.
        assert!(!q.push_newest("a/overhead/top 1", supersedes)); // evicts b/obs 1
        assert!(q.push_newest("a/obs 3", supersedes)); // replaces a/obs 2
        let c = &q.counters;
        assert_eq!(c.received.load(Ordering::Relaxed), 7);
        assert_eq!(c.superseded_frames.load(Ordering::Relaxed), 2);
        assert_eq!(c.dropped_frames.load(Ordering::Relaxed), 1);
        let batch = q.pop_batch(Duration::from_millis(1), Duration::ZERO);
        assert_eq!(
            batch,
            Ok(vec!["reward 1", "reward 2", "a/overhead/top 1", "a/obs 3"])
        );
    }

    #[test]
    fn a_waiting_consumer_is_woken_by_every_push_to_an_empty_queue() {
        // Far longer than any wake-up takes: a wait that lasts it was not
        // woken (a missed notify), whatever the machine's load.
        const PATIENCE: Duration = Duration::from_secs(30);
        let q = std::sync::Arc::new(Queue::new(4, 1000));
        let (taken, batch_taken) = std::sync::mpsc::channel::<()>();
        let producer = {
            let q = q.clone();
            std::thread::spawn(move || {
                for i in 0..50 {
                    // The consumer is waiting on an empty queue (or about
                    // to): this push must wake it.
                    q.push(Lane::Message, i);
                    if batch_taken.recv_timeout(PATIENCE).is_err() {
                        break;
                    }
                }
                q.close();
            })
        };
        let mut got = Vec::new();
        loop {
            let started = std::time::Instant::now();
            let Ok(batch) = q.pop_batch(PATIENCE, Duration::ZERO) else {
                break;
            };
            assert!(
                started.elapsed() < PATIENCE,
                "a push did not wake the consumer"
            );
            got.extend(batch);
            let _ = taken.send(());
        }
        producer.join().expect("the producer ends");
        assert_eq!(got, (0..50).collect::<Vec<_>>());
    }
}
