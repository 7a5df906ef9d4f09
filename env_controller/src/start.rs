//! Starting a step's work on the thread that received it.
//!
//! A step's first stretch (decode, lease and episode checks, the command
//! put on `cmd`) needs no worker of the controller's runtime. Handed to a
//! task, it would first wait for one to wake: on a 2-core host ~25 µs of
//! the ~90 µs an 84×84 step took above a raw Zenoh get
//! (`docs/performance.md`, "A step starts where it arrives").
//! [`start_here`] polls the work once on the calling thread (Zenoh's
//! receive thread for a remote client) and gives it to the runtime only
//! when it is woken after that poll: no worker is woken just to find it
//! waiting. What may block that thread for long (SQLite, a
//! stop command) first awaits [`hand_off`].
//!
//! A twin that simulates a command where it arrives
//! (`sim_twin::node::Stepping::OnArrival`: `gymnasium.make`'s one embedded
//! env) runs within the command's put, and the controller's `obs` callback
//! replies within it too: the whole step then finishes in this first
//! poll, and only an episode's end or a progress save (SQLite) reaches the
//! runtime.

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{
    AtomicU8,
    Ordering::{AcqRel, Acquire, Release},
};
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context, Poll, Wake, Waker};

use tokio::runtime::Handle;

type Work = Pin<Box<dyn Future<Output = ()> + Send>>;

/// Runs `work` on this thread until it first returns `Pending`, then on
/// `runtime` once it is woken.
///
/// During that first poll `runtime` is entered, so timers and tasks made
/// there belong to it; the poll is free of tokio's cooperative budget (the
/// caller's task, Zenoh's receive loop, may have spent it). `work` must not
/// block this thread for long: the caller is a Zenoh callback, and the
/// link it reads waits meanwhile.
pub fn start_here(runtime: &Handle, work: impl Future<Output = ()> + Send + 'static) {
    let mut work: Work = Box::pin(work);
    let _entered = runtime.enter();
    let parked = Arc::new(Parked {
        runtime: runtime.clone(),
        state: AtomicU8::new(POLLING),
        work: Mutex::new(None),
    });
    let waker = Waker::from(parked.clone());
    let first = std::pin::pin!(tokio::task::unconstrained(work.as_mut()))
        .poll(&mut Context::from_waker(&waker));
    if first.is_ready() {
        return;
    }
    *parked.slot() = Some(work);
    // Woken while it was being polled (from another thread, or by itself):
    // it goes to the runtime now.
    if !parked.advance(POLLING, PARKED) {
        parked.spawn();
    }
}

/// Being polled by [`start_here`]'s caller.
const POLLING: u8 = 0;
/// Woken during that poll: spawned as soon as the poll returns.
const WOKEN_WHILE_POLLING: u8 = 1;
/// Waiting in [`Parked::work`] for its first wake-up.
const PARKED: u8 = 2;
/// Handed to the runtime, which polls it from now on with its own waker.
const SPAWNED: u8 = 3;

/// Work that waits for its first wake-up; the waker given to its first poll.
struct Parked {
    runtime: Handle,
    state: AtomicU8,
    work: Mutex<Option<Work>>,
}

impl Parked {
    fn slot(&self) -> std::sync::MutexGuard<'_, Option<Work>> {
        self.work.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Moves the state from `from` to `to`; false if it was not `from`.
    fn advance(&self, from: u8, to: u8) -> bool {
        self.state
            .compare_exchange(from, to, AcqRel, Acquire)
            .is_ok()
    }

    fn spawn(&self) {
        self.state.store(SPAWNED, Release);
        let work = self.slot().take();
        if let Some(work) = work {
            // Polled again on a worker: whatever woke it is seen there, and
            // from then on it registers the task's waker.
            self.runtime.spawn(work);
        }
    }
}

impl Wake for Parked {
    fn wake(self: Arc<Self>) {
        self.wake_by_ref();
    }

    fn wake_by_ref(self: &Arc<Self>) {
        if self.advance(POLLING, WOKEN_WHILE_POLLING) {
            return;
        }
        // Only the first wake-up after the poll spawns it; later ones (a
        // stale waker kept by a resource) find it spawned.
        if self.advance(PARKED, SPAWNED) {
            self.spawn();
        }
    }
}

/// Leaves the thread [`start_here`] runs a step's first stretch on before
/// work that may block it (a SQLite write, a stop command): the work goes
/// on on a runtime worker. On a worker already, one yield.
pub async fn hand_off() {
    let mut yielded = false;
    std::future::poll_fn(|cx| {
        if yielded {
            return Poll::Ready(());
        }
        yielded = true;
        // Our own waker, not tokio's deferred yield: on the caller's thread
        // (a worker of Zenoh's runtime) that would wait until it parks.
        cx.waker().wake_by_ref();
        Poll::Pending
    })
    .await
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::thread::ThreadId;
    use std::time::Duration;
    use tokio::sync::oneshot;

    fn runtime() -> tokio::runtime::Runtime {
        tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .expect("runtime")
    }

    /// Where each stretch of the work ran: (before its wait, after it).
    type Threads = (ThreadId, Option<ThreadId>);

    #[test]
    fn work_that_never_waits_runs_on_the_calling_thread() {
        let rt = runtime();
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        start_here(rt.handle(), async move {
            done_tx.send(std::thread::current().id()).expect("send");
        });
        // Done before start_here returned: no other thread was involved.
        assert_eq!(done_rx.try_recv(), Ok(std::thread::current().id()));
    }

    #[test]
    fn work_starts_here_and_goes_on_on_the_runtime_once_woken() {
        let rt = runtime();
        let (wake_tx, wake_rx) = oneshot::channel::<u32>();
        let (done_tx, done_rx) = std::sync::mpsc::channel::<(Threads, u32)>();
        let caller = std::thread::current().id();
        start_here(rt.handle(), async move {
            let first = std::thread::current().id();
            let value = wake_rx.await.expect("sender kept");
            let _ = done_tx.send(((first, Some(std::thread::current().id())), value));
        });
        // Parked: nothing ran past its wait.
        assert!(done_rx.try_recv().is_err());
        std::thread::spawn(move || wake_tx.send(7).expect("receiver kept"))
            .join()
            .expect("waker thread");
        let ((first, then), value) = done_rx
            .recv_timeout(Duration::from_secs(30))
            .expect("woken work finished on the runtime");
        assert_eq!(value, 7);
        assert_eq!(first, caller);
        assert_ne!(then, Some(caller), "the rest ran on a runtime worker");
    }

    #[test]
    fn from_a_worker_of_another_runtime_timers_and_hand_offs_belong_to_ours() {
        // The caller is a worker of a runtime not ours, as Zenoh's are.
        let ours = runtime();
        let theirs = runtime();
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        let handle = ours.handle().clone();
        theirs.block_on(async move {
            tokio::spawn(async move {
                let caller = std::thread::current().id();
                start_here(&handle, async move {
                    tokio::time::sleep(Duration::from_millis(5)).await;
                    let after_sleep = std::thread::current().id();
                    hand_off().await;
                    done_tx
                        .send((caller, after_sleep, tokio::runtime::Handle::current().id()))
                        .expect("send");
                });
            })
            .await
            .expect("caller task");
        });
        let (caller, after_sleep, runtime_id) = done_rx
            .recv_timeout(Duration::from_secs(30))
            .expect("the timer fired and the work finished");
        assert_ne!(after_sleep, caller);
        assert_eq!(runtime_id, ours.handle().id(), "went on on our runtime");
    }

    #[test]
    fn a_hand_off_moves_the_rest_off_the_calling_thread_at_once() {
        let rt = runtime();
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        let caller = std::thread::current().id();
        start_here(rt.handle(), async move {
            hand_off().await;
            done_tx.send(std::thread::current().id()).expect("send");
        });
        let then = done_rx
            .recv_timeout(Duration::from_secs(30))
            .expect("handed off and finished");
        assert_ne!(then, caller);
    }

    #[test]
    fn work_woken_from_another_thread_during_its_first_poll_is_spawned() {
        let rt = runtime();
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        let mut polls = 0;
        start_here(
            rt.handle(),
            std::future::poll_fn(move |cx| {
                polls += 1;
                if polls == 1 {
                    // Woken, and the waker's thread gone, before this poll
                    // returns: the state is WOKEN_WHILE_POLLING.
                    let waker = cx.waker().clone();
                    std::thread::spawn(move || waker.wake())
                        .join()
                        .expect("waker thread");
                    return Poll::Pending;
                }
                done_tx.send(polls).expect("send");
                Poll::Ready(())
            }),
        );
        assert_eq!(done_rx.recv_timeout(Duration::from_secs(30)), Ok(2));
    }

    #[test]
    fn work_woken_while_it_is_first_polled_is_not_lost() {
        let rt = runtime();
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        start_here(rt.handle(), async move {
            // Wakes itself inside the first poll, then waits.
            tokio::task::yield_now().await;
            done_tx.send(()).expect("send");
        });
        done_rx
            .recv_timeout(Duration::from_secs(30))
            .expect("a wake-up during the first poll spawned it");
    }

    #[test]
    fn every_one_of_many_racing_starts_finishes_exactly_once() {
        let rt = runtime();
        let n = 2_000;
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        for i in 0..n {
            let (wake_tx, wake_rx) = oneshot::channel::<()>();
            let done_tx = done_tx.clone();
            // Woken from the runtime as the caller parks it: the race
            // between the first poll's return and the wake-up.
            rt.spawn(async move {
                let _ = wake_tx.send(());
            });
            start_here(rt.handle(), async move {
                let _ = wake_rx.await;
                done_tx.send(i).expect("send");
            });
        }
        let mut finished: Vec<usize> = (0..n)
            .map(|_| {
                done_rx
                    .recv_timeout(Duration::from_secs(30))
                    .expect("every start finishes")
            })
            .collect();
        finished.sort_unstable();
        assert_eq!(finished, (0..n).collect::<Vec<_>>());
    }
}
