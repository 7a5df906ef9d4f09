//! The events a twin node has yet to simulate, in arrival order.
//!
//! Unlike a channel, taking an event is separate from waiting for one: the
//! simulation's state is behind its own lock, and only whoever holds it
//! takes events ([`Inbox::pop`]). So the node's thread and a Zenoh callback
//! that simulates a command where it arrives
//! ([`super::Stepping::OnArrival`]) never reorder events (an e-stop queued
//! before a command is applied before it), and the thread need not be woken
//! for work its caller does itself.

use std::collections::VecDeque;
use std::sync::{Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

/// Why an event was not queued; it is handed back.
#[derive(Debug)]
pub(super) enum Refused<E> {
    /// The queue holds its bound already.
    Full(E),
    /// The node is stopping (or its thread ended).
    Closed(E),
}

/// What [`Inbox::wait`] saw.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Waited {
    /// An event is queued (or was: a caller may have taken it since).
    Ready,
    /// The timeout passed first.
    TimedOut,
    /// Woken to look at its timers again ([`Inbox::wake`]).
    Woken,
    /// The node is stopping.
    Closed,
}

struct Queue<E> {
    events: VecDeque<E>,
    closed: bool,
    /// The thread waits with a timeout (it will look again by itself).
    polling: bool,
    /// [`Inbox::wake`] was called since the last wait returned.
    woken: bool,
}

/// A bounded FIFO of events with a condition the node's thread waits on.
pub(super) struct Inbox<E> {
    queue: Mutex<Queue<E>>,
    arrived: Condvar,
    bound: usize,
}

impl<E> Inbox<E> {
    pub(super) fn new(bound: usize) -> Self {
        Self {
            queue: Mutex::new(Queue {
                events: VecDeque::with_capacity(bound),
                closed: false,
                polling: false,
                woken: false,
            }),
            arrived: Condvar::new(),
            bound,
        }
    }

    fn queue(&self) -> MutexGuard<'_, Queue<E>> {
        self.queue.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Queues `event`, waking the thread if `wake` (a caller about to take
    /// the simulation and work through the queue itself need not).
    pub(super) fn push(&self, event: E, wake: bool) -> Result<(), Refused<E>> {
        let mut queue = self.queue();
        if queue.closed {
            return Err(Refused::Closed(event));
        }
        if queue.events.len() >= self.bound {
            return Err(Refused::Full(event));
        }
        queue.events.push_back(event);
        drop(queue);
        if wake {
            self.arrived.notify_one();
        }
        Ok(())
    }

    /// The oldest event; only the holder of the simulation takes one.
    pub(super) fn pop(&self) -> Option<E> {
        self.queue().events.pop_front()
    }

    /// Wakes the thread to look at its timers again: its wait returns
    /// [`Waited::Woken`] (or what it saw first).
    pub(super) fn wake(&self) {
        self.queue().woken = true;
        self.arrived.notify_one();
    }

    /// Whether the thread waits with a timeout, so will look again by itself.
    pub(super) fn polled(&self) -> bool {
        self.queue().polling
    }

    /// Refuses every later event and wakes the thread to stop; the events
    /// already queued stay (a lockstep thread takes them before it ends).
    pub(super) fn close(&self) {
        self.queue().closed = true;
        self.arrived.notify_all();
    }

    /// Waits until an event is queued, `timeout` (if any) passes, the
    /// thread is woken or the inbox closes.
    pub(super) fn wait(&self, timeout: Option<Duration>) -> Waited {
        let deadline = timeout.map(|t| Instant::now() + t);
        let mut queue = self.queue();
        loop {
            if queue.closed {
                return Waited::Closed;
            }
            if !queue.events.is_empty() {
                queue.polling = false;
                queue.woken = false;
                return Waited::Ready;
            }
            if std::mem::take(&mut queue.woken) {
                queue.polling = false;
                return Waited::Woken;
            }
            queue.polling = deadline.is_some();
            queue = match deadline {
                None => self
                    .arrived
                    .wait(queue)
                    .unwrap_or_else(PoisonError::into_inner),
                Some(deadline) => {
                    let left = deadline.saturating_duration_since(Instant::now());
                    if left.is_zero() {
                        queue.polling = false;
                        return Waited::TimedOut;
                    }
                    self.arrived
                        .wait_timeout(queue, left)
                        .unwrap_or_else(PoisonError::into_inner)
                        .0
                }
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn events_come_out_in_order_up_to_the_bound() {
        let inbox = Inbox::new(2);
        inbox.push(1, true).expect("room");
        inbox.push(2, false).expect("room");
        assert!(matches!(inbox.push(3, true), Err(Refused::Full(3))));
        assert_eq!(inbox.wait(None), Waited::Ready);
        assert_eq!(
            (inbox.pop(), inbox.pop(), inbox.pop()),
            (Some(1), Some(2), None)
        );
    }

    #[test]
    fn a_closed_inbox_refuses_new_events_and_keeps_the_queued_ones() {
        let inbox = Inbox::new(4);
        inbox.push(1, false).expect("room");
        inbox.close();
        assert_eq!(inbox.wait(None), Waited::Closed);
        assert!(matches!(inbox.push(2, true), Err(Refused::Closed(2))));
        assert_eq!((inbox.pop(), inbox.pop()), (Some(1), None));
    }

    #[test]
    fn closing_ends_a_wait() {
        let inbox = Arc::new(Inbox::<u8>::new(1));
        let waiter = {
            let inbox = inbox.clone();
            std::thread::spawn(move || inbox.wait(None))
        };
        inbox.close();
        assert_eq!(waiter.join().expect("waiter"), Waited::Closed);
    }

    #[test]
    fn a_wake_ends_a_wait_without_a_timeout_once() {
        let inbox = Arc::new(Inbox::<u8>::new(1));
        let waiter = {
            let inbox = inbox.clone();
            std::thread::spawn(move || inbox.wait(None))
        };
        inbox.wake();
        assert_eq!(waiter.join().expect("waiter"), Waited::Woken);
        assert_eq!(inbox.wait(Some(Duration::ZERO)), Waited::TimedOut);
    }

    #[test]
    fn a_timed_wait_says_it_polls_meanwhile() {
        let inbox = Arc::new(Inbox::<u8>::new(1));
        assert!(!inbox.polled());
        let waiter = {
            let inbox = inbox.clone();
            std::thread::spawn(move || inbox.wait(Some(Duration::from_secs(30))))
        };
        let until = Instant::now() + Duration::from_secs(10);
        while !inbox.polled() && Instant::now() < until {
            std::thread::yield_now();
        }
        assert!(inbox.polled(), "a waiter with a timeout polls");
        inbox.push(1, true).expect("room");
        assert_eq!(waiter.join().expect("waiter"), Waited::Ready);
        assert!(!inbox.polled());
    }

    #[test]
    fn an_event_pushed_without_waking_is_still_seen_by_a_later_wait() {
        let inbox = Inbox::new(1);
        inbox.push(7, false).expect("room");
        assert_eq!(inbox.wait(Some(Duration::ZERO)), Waited::Ready);
        assert_eq!(inbox.pop(), Some(7));
        assert_eq!(inbox.wait(Some(Duration::ZERO)), Waited::TimedOut);
    }
}
