//! Background threads (recorders, monitors) that must not take CPU from
//! the step path on a busy machine.

/// Niceness of background threads (Linux: per thread; 0 is normal, 19 the
/// lowest priority): they still run, but yield to the step path whenever
/// both want a core.
pub const BACKGROUND_NICENESS: i32 = 10;

/// Gives the calling thread (and the threads it starts afterwards) the
/// priority [`BACKGROUND_NICENESS`]. Best effort: where it cannot (another
/// platform, a sandbox refusing it) the thread runs at normal priority and
/// the reason is logged at debug level.
#[allow(unsafe_code)] // one libc call, see SAFETY below
pub fn lower_current_thread() {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: gettid and setpriority only read their arguments; on Linux
        // PRIO_PROCESS with a thread id changes that one thread.
        let result = unsafe {
            let tid = libc::gettid();
            libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, BACKGROUND_NICENESS)
        };
        if result != 0 {
            tracing::debug!(
                "a background thread runs at normal priority: {}",
                std::io::Error::last_os_error()
            );
        }
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    #[test]
    fn a_lowered_thread_has_the_background_niceness_and_others_keep_theirs() {
        #[allow(unsafe_code)]
        // SAFETY: getpriority only reads its arguments; errno is reset first
        // because -1 is also a valid niceness.
        fn niceness() -> i32 {
            unsafe {
                *libc::__errno_location() = 0;
                libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t)
            }
        }
        let before = niceness();
        let lowered = std::thread::spawn(|| {
            super::lower_current_thread();
            niceness()
        })
        .join()
        .expect("thread");
        // Raising it back is not allowed to an unprivileged user, and a
        // thread already nicer than 10 stays where it was.
        assert_eq!(lowered, super::BACKGROUND_NICENESS.max(before));
        assert_eq!(niceness(), before, "the calling thread is unchanged");
    }
}
