//! Retraining's threads: work that must not take the cores from plans.
//!
//! The scheduler keeps a retraining from *starting* a minibatch while a plan holds or waits
//! for the cores, but a minibatch already running when a plan arrives would otherwise share
//! the two cores with the plan's threads as an equal. Background work therefore runs on a rayon
//! pool of its own ([`run_in_background`]) whose threads the OS schedules only when no normal
//! thread wants a core (Linux `SCHED_IDLE`): a plan's threads take the cores back at once, and
//! the products a fit splits across threads (`matmul_par`, Adam's update, an ensemble's
//! members) run on that pool too, never on the planning pool.
//!
//! Why `SCHED_IDLE` and not a higher niceness: the kernel still gives a niced thread its share
//! in slices of a few milliseconds, and a plan is a chain of fork-joins over both cores (one per
//! imagined step), so one core losing a slice stalls the whole plan. Side by side (`bench plan
//! --task cartpole --regularizer deen`, two busy loops beside it): 27.7 ms per plan alone, 50 ms
//! beside nice-10 loops, 33 ms beside nice-19 loops, 28–29 ms beside `SCHED_IDLE` loops (see
//! docs/performance.md, "Retraining beside a plan").
//!
//! What must not run here: anything that holds a lock the serving path takes (the replay
//! buffer, the run's ownership). A thread of this pool can sit preempted for a whole plan, and
//! a lock it held would stall that run's agents as long. The trainer takes its snapshot of the
//! buffer and writes its checkpoint at normal priority, around the background fit.

use rayon::{ThreadPool, ThreadPoolBuilder};
use std::cell::Cell;
use std::sync::OnceLock;
use thiserror::Error;

/// Why background work produced no result.
#[derive(Debug, Error)]
pub enum BackgroundError {
    #[error("cannot start the background threads: {0}")]
    Pool(String),
    #[error("background work panicked: {0}")]
    Panicked(String),
}

thread_local! {
    static ON_BACKGROUND_POOL: Cell<bool> = const { Cell::new(false) };
}

/// The background pool: as many threads as cores (a lone retraining uses the whole machine when
/// nothing plans), all at the lowest priority.
fn pool() -> Result<&'static ThreadPool, BackgroundError> {
    static POOL: OnceLock<Result<ThreadPool, String>> = OnceLock::new();
    POOL.get_or_init(|| {
        ThreadPoolBuilder::new()
            .thread_name(|i| format!("ebmpc-background-{i}"))
            .start_handler(|_| {
                ON_BACKGROUND_POOL.with(|on| on.set(true));
                lower_thread_priority();
            })
            .build()
            .map_err(|e| e.to_string())
    })
    .as_ref()
    .map_err(|e| BackgroundError::Pool(e.clone()))
}

/// True on a thread of the background pool.
pub fn on_background_pool() -> bool {
    ON_BACKGROUND_POOL.with(Cell::get)
}

/// True where a thread may block waiting for plans: anywhere but the planning pool's (rayon's
/// global pool) worker threads, which the plans need.
pub fn may_wait_for_plans() -> bool {
    on_background_pool() || rayon::current_thread_index().is_none()
}

/// Runs `work` on the background pool and awaits its result without blocking the async
/// runtime. Parallel work inside `work` (rayon joins and iterators) stays on that pool.
pub async fn run_in_background<T, F>(work: F) -> Result<T, BackgroundError>
where
    T: Send + 'static,
    F: FnOnce() -> T + Send + 'static,
{
    let (done, result) = tokio::sync::oneshot::channel();
    pool()?.spawn(move || {
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(work));
        // The awaiting side may be gone (the run was dropped): nothing to tell then.
        let _ = done.send(outcome.map_err(|panic| panic_message(&*panic)));
    });
    match result.await {
        Ok(outcome) => outcome.map_err(BackgroundError::Panicked),
        Err(_) => Err(BackgroundError::Panicked(
            "the work ended without a result".into(),
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

/// The niceness a background thread falls back to where `SCHED_IDLE` cannot be set.
pub const FALLBACK_NICE: i32 = 19;

/// Moves the calling thread to `SCHED_IDLE` (Linux: the policy is per thread and inherited by
/// threads it spawns). Where that fails, lowers its niceness to [`FALLBACK_NICE`], never raising
/// it. Best effort: where both fail or the OS has neither, the thread keeps its priority and
/// only the scheduler's waits between minibatches protect the plans.
pub fn lower_thread_priority() {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: plain system calls on the calling thread's own id; `param` outlives the call.
        let failed = unsafe {
            let tid = libc::gettid();
            let param = libc::sched_param { sched_priority: 0 };
            libc::sched_setscheduler(tid, libc::SCHED_IDLE, &param) != 0 && {
                let current = libc::getpriority(libc::PRIO_PROCESS, tid as libc::id_t);
                current < FALLBACK_NICE
                    && libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, FALLBACK_NICE) != 0
            }
        };
        if failed {
            tracing::debug!(
                error = %std::io::Error::last_os_error(),
                "cannot lower a background thread's priority"
            );
        }
    }
}

/// This thread's scheduling policy (Linux), for tests.
#[cfg(all(test, target_os = "linux"))]
fn thread_policy() -> i32 {
    // SAFETY: a plain system call on the calling thread.
    unsafe { libc::sched_getscheduler(0) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn background_work_returns_its_result_and_reports_a_panic() {
        let value = run_in_background(|| 6 * 7).await.unwrap();
        assert_eq!(value, 42);
        let err = run_in_background(|| -> u8 { panic!("boom") })
            .await
            .unwrap_err();
        assert!(err.to_string().contains("boom"), "{err}");
        // The pool survives a panic.
        assert_eq!(run_in_background(|| 1).await.unwrap(), 1);
    }

    #[cfg(target_os = "linux")]
    #[tokio::test]
    async fn background_work_and_its_parallel_parts_run_below_plans_off_the_planning_pool() {
        let caller = thread_policy();
        let ((own, own_pool), (helper, helper_pool), (child, child_pool)) =
            run_in_background(|| {
                let probe = || (thread_policy(), on_background_pool());
                let (own, helper) = rayon::join(probe, probe);
                let child = std::thread::spawn(probe).join().unwrap();
                (own, helper, child)
            })
            .await
            .unwrap();
        assert_eq!(own, libc::SCHED_IDLE);
        assert!(own_pool);
        assert_eq!(
            helper,
            libc::SCHED_IDLE,
            "rayon work inside stays below plans"
        );
        assert!(
            helper_pool,
            "rayon work inside stays on the background pool"
        );
        assert_eq!(
            child,
            libc::SCHED_IDLE,
            "threads spawned by background work inherit it"
        );
        assert!(!child_pool);
        assert_eq!(thread_policy(), caller, "the caller keeps its priority");
        assert!(!on_background_pool());
        assert!(may_wait_for_plans(), "a plain thread may wait for plans");
        let on_planning_pool = rayon::scope(|_| may_wait_for_plans());
        assert!(
            !on_planning_pool,
            "a planning-pool thread never waits for plans"
        );
    }
}
