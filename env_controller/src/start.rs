//! Starting a request's work on the thread that received it.
//!
//! A step's first stretch (decode, lease and episode checks, the command
//! put on `cmd`) never waits. Handed to a task, it would first wait for a
//! worker to wake: on a 2-core host tens of µs, a sixth of an 84×84 step's
//! overhead (`docs/performance.md`, "A step starts where it arrives").
//! [`start_here`] polls the work once on the calling thread (Zenoh's receive
//! thread for a remote client) and gives it to the runtime only when it is
//! woken after its first wait: no worker is woken just to find it waiting.

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{
    AtomicU8,
    Ordering::{AcqRel, Acquire, Release},
};
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context, Wake, Waker};

use tokio::runtime::Handle;

type Work = Pin<Box<dyn Future<Output = ()> + Send>>;

/// Runs `work` on this thread until it first waits, then on `runtime` once
/// it is woken. Timers and other resources it creates belong to `runtime`.
///
/// `work` must not block this thread for long: it runs inside the caller
/// (a Zenoh callback) until its first `.await` that waits.
pub fn start_here(runtime: &Handle, work: impl Future<Output = ()> + Send + 'static) {
    let mut work: Work = Box::pin(work);
    let _entered = runtime.enter();
    let parked = Arc::new(Parked {
        runtime: runtime.clone(),
        state: AtomicU8::new(POLLING),
        work: Mutex::new(None),
    });
    let waker = Waker::from(parked.clone());
    if work
        .as_mut()
        .poll(&mut Context::from_waker(&waker))
        .is_ready()
    {
        return;
    }
    *parked.slot() = Some(work);
    // Woken while it was being polled (from another thread, or by itself):
    // it goes to the runtime now.
    if parked
        .state
        .compare_exchange(POLLING, PARKED, AcqRel, Acquire)
        .is_err()
    {
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

    fn spawn(&self) {
        self.state.store(SPAWNED, Release);
        if let Some(work) = self.slot().take() {
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
        let woken_while_polling = self
            .state
            .compare_exchange(POLLING, WOKEN_WHILE_POLLING, AcqRel, Acquire)
            .is_ok();
        if woken_while_polling {
            return;
        }
        // Only the first wake-up after the poll spawns it; later ones (a
        // stale waker kept by a resource) find it spawned.
        if self
            .state
            .compare_exchange(PARKED, SPAWNED, AcqRel, Acquire)
            .is_ok()
        {
            self.spawn();
        }
    }
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
    fn a_timer_made_in_the_first_stretch_belongs_to_the_runtime() {
        let rt = runtime();
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        // The caller is no runtime thread (as Zenoh's are not ours).
        std::thread::spawn({
            let handle = rt.handle().clone();
            move || {
                start_here(&handle, async move {
                    tokio::time::sleep(Duration::from_millis(5)).await;
                    done_tx.send(()).expect("send");
                })
            }
        })
        .join()
        .expect("caller thread");
        done_rx
            .recv_timeout(Duration::from_secs(30))
            .expect("the timer fired and the work finished");
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
