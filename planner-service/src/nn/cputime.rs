//! CPU time, to time work on a machine whose cores other processes share.
//!
//! The project's machine has two cores shared with other jobs: a product or a planning call
//! that took twice its usual wall time may simply have had half a core. The CPU time the
//! process's threads received is what the work itself cost; comparing it with
//! `threads × wall time` shows how much of the machine the measurement actually had. Both
//! clocks are read with `clock_gettime`, to the nanosecond (`/proc` `schedstat` is only
//! updated at scheduler ticks, too coarse for the millisecond batches of `bench kernel`).

use std::time::Duration;

/// Total time on a CPU of every thread of this process (`CLOCK_PROCESS_CPUTIME_ID`); `None`
/// where the platform does not provide the clock.
pub fn process_cpu_time() -> Option<Duration> {
    read(libc::CLOCK_PROCESS_CPUTIME_ID)
}

/// Time the calling thread has spent on a CPU (`CLOCK_THREAD_CPUTIME_ID`); `None` where the
/// platform does not provide the clock.
pub fn thread_cpu_time() -> Option<Duration> {
    read(libc::CLOCK_THREAD_CPUTIME_ID)
}

fn read(clock: libc::clockid_t) -> Option<Duration> {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid timespec for the call to fill.
    let ok = unsafe { libc::clock_gettime(clock, &mut t) } == 0;
    ok.then(|| Duration::new(t.tv_sec as u64, t.tv_nsec as u32))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Instant;

    /// Spins the calling thread for about `ms` of wall time.
    fn spin(ms: u64) -> f64 {
        let mut x = 1.0f64;
        let start = Instant::now();
        while start.elapsed() < Duration::from_millis(ms) {
            x = std::hint::black_box(x * 1.000_001 + 1e-9);
        }
        x
    }

    #[test]
    fn cpu_time_grows_with_work_and_not_with_sleep() {
        let (Some(process), Some(thread)) = (process_cpu_time(), thread_cpu_time()) else {
            return; // no CPU clocks on this platform: nothing to measure
        };
        let x = spin(30);
        let (process_after, thread_after) =
            (process_cpu_time().unwrap(), thread_cpu_time().unwrap());
        assert!(thread_after > thread, "{thread:?} → {thread_after:?} ({x})");
        // The process's clock counts this thread's time too (the two pairs of readings are
        // a few instructions apart, hence the slack).
        let slack = Duration::from_micros(100);
        assert!(process_after - process + slack >= thread_after - thread);

        // A sleeping thread costs no CPU time: far less than the 50 ms slept.
        let before = thread_cpu_time().unwrap();
        std::thread::sleep(Duration::from_millis(50));
        let slept = thread_cpu_time().unwrap() - before;
        assert!(slept < Duration::from_millis(25), "{slept:?}");
    }
}
