//! Retraining's threads: work that must not take the cores from plans.
//!
//! The scheduler keeps a retraining from *starting* a minibatch while a plan holds or waits
//! for the cores, but a minibatch already running when a plan arrives would otherwise share
//! the two cores with the plan's threads as an equal. A background thread runs at a lower OS
//! priority ([`BACKGROUND_NICE`]), so the kernel gives a plan's threads the cores first and
//! the minibatch only what they leave; threads it spawns (an ensemble's members) inherit the
//! priority. Products large enough to be split across rayon's pool still run there at normal
//! priority: that is the limit of this policy (see [`crate::sched`]).

use thiserror::Error;

/// The niceness of background threads: with Linux's weights a nice-10 thread gets about a
/// tenth of a core that a nice-0 thread wants, so a retraining beside continuous planning still
/// progresses.
pub const BACKGROUND_NICE: i32 = 10;

/// Why background work produced no result.
#[derive(Debug, Error)]
pub enum BackgroundError {
    #[error("cannot start a background thread: {0}")]
    Spawn(std::io::Error),
    #[error("background work panicked: {0}")]
    Panicked(String),
}

/// Runs `work` on a new thread named `name` at background priority and awaits its result
/// without blocking the async runtime.
pub async fn run_in_background<T, F>(name: String, work: F) -> Result<T, BackgroundError>
where
    T: Send + 'static,
    F: FnOnce() -> T + Send + 'static,
{
    let (done, result) = tokio::sync::oneshot::channel();
    std::thread::Builder::new()
        .name(name)
        .spawn(move || {
            lower_thread_priority();
            let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(work));
            // The awaiting side may be gone (the run was dropped): nothing to tell then.
            let _ = done.send(outcome.map_err(|panic| panic_message(&*panic)));
        })
        .map_err(BackgroundError::Spawn)?;
    match result.await {
        Ok(outcome) => outcome.map_err(BackgroundError::Panicked),
        Err(_) => Err(BackgroundError::Panicked(
            "the thread ended without a result".into(),
        )),
    }
}

fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".into())
}

/// Lowers the calling thread's priority to [`BACKGROUND_NICE`] (Linux: niceness is per
/// thread), never raising it (a daemon started with `nice 19` keeps 19). Best effort: where it
/// fails or the OS has no per-thread niceness, the thread keeps its priority and only the
/// scheduler's waits between minibatches protect the plans.
pub fn lower_thread_priority() {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: plain system calls on the calling thread's own id; no memory is shared.
        let failed = unsafe {
            let tid = libc::gettid() as libc::id_t;
            let current = libc::getpriority(libc::PRIO_PROCESS, tid);
            current < BACKGROUND_NICE
                && libc::setpriority(libc::PRIO_PROCESS, tid, BACKGROUND_NICE) != 0
        };
        if failed {
            tracing::debug!(
                error = %std::io::Error::last_os_error(),
                "cannot lower a background thread's priority"
            );
        }
    }
}

/// This thread's niceness (Linux), for tests.
#[cfg(all(test, target_os = "linux"))]
fn thread_niceness() -> i32 {
    // SAFETY: as above; `getpriority` can return -1 legitimately, which no test here expects.
    unsafe { libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn background_work_returns_its_result_and_reports_a_panic() {
        let value = run_in_background("bg-test".into(), || 6 * 7).await.unwrap();
        assert_eq!(value, 42);
        let err = run_in_background("bg-panic".into(), || -> u8 { panic!("boom") })
            .await
            .unwrap_err();
        assert!(err.to_string().contains("boom"), "{err}");
    }

    #[cfg(target_os = "linux")]
    #[tokio::test]
    async fn background_threads_and_their_children_run_below_plans() {
        let caller = thread_niceness();
        let (own, child) = run_in_background("bg-nice".into(), || {
            let own = thread_niceness();
            let child = std::thread::spawn(thread_niceness).join().unwrap();
            (own, child)
        })
        .await
        .unwrap();
        assert_eq!(own, caller.max(BACKGROUND_NICE));
        assert_eq!(child, own, "threads spawned by background work inherit it");
        assert_eq!(thread_niceness(), caller, "the caller keeps its priority");
    }
}
