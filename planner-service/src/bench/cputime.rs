//! CPU time consumed by this process, to tell a clean timing from one disturbed by other work.
//!
//! The project's machine has two cores shared with other jobs: a planning call that took twice
//! its usual time may simply have had one core instead of two. Comparing the CPU time the
//! process's threads received with `threads × wall time` shows how much of the machine the
//! measurement actually had.

use std::time::Duration;

/// Total time on a CPU of every live thread of this process (Linux `schedstat`, nanosecond
/// resolution); `None` where the kernel does not expose it.
pub(super) fn process_cpu_time() -> Option<Duration> {
    let mut total = 0u64;
    for entry in std::fs::read_dir("/proc/self/task").ok()? {
        let stat = std::fs::read_to_string(entry.ok()?.path().join("schedstat")).ok()?;
        total += stat.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(Duration::from_nanos(total))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_time_grows_with_work() {
        let Some(before) = process_cpu_time() else {
            return; // not Linux: nothing to measure
        };
        let mut x = 1.0f64;
        let start = std::time::Instant::now();
        while start.elapsed() < Duration::from_millis(30) {
            x = std::hint::black_box(x * 1.000_001 + 1e-9);
        }
        let after = process_cpu_time().expect("available a moment ago");
        assert!(after > before, "{before:?} → {after:?} ({x})");
    }
}
