//! Wall-clock measurement of short, repeatable operations, robust to a shared machine.
//!
//! One call of a kernel lasts microseconds, too short to time alone, and the project's machine
//! is shared: any single measurement may have lost its core for a while. So the work runs in
//! batches of many calls, after one untimed warm-up batch (caches, page faults, clock ramp-up),
//! and both the fastest and the median batch are reported: the fastest is the least disturbed
//! by other processes, the median shows how typical that was.

use std::time::{Duration, Instant};

/// Timed batches per measurement (after one warm-up batch).
pub const BATCHES: usize = 15;

/// Per-call milliseconds of the fastest and of the median batch.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Timing {
    pub min_ms: f64,
    pub median_ms: f64,
}

impl std::fmt::Display for Timing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.3} ms (median {:.3} ms)", self.min_ms, self.median_ms)
    }
}

/// Times `f` in [`BATCHES`] batches of `reps` calls each (at least one), after one warm-up
/// batch.
pub fn measure(reps: usize, mut f: impl FnMut()) -> Timing {
    let reps = reps.max(1);
    let mut batches: Vec<f64> = (0..=BATCHES)
        .map(|_| {
            let t = Instant::now();
            for _ in 0..reps {
                f();
            }
            t.elapsed().as_secs_f64() * 1e3 / reps as f64
        })
        .skip(1)
        .collect();
    batches.sort_by(f64::total_cmp);
    Timing {
        min_ms: batches[0],
        median_ms: batches[batches.len() / 2],
    }
}

/// [`measure`] with batches of about `batch` each: the calls per batch are estimated from one
/// untimed call, so that products of very different sizes are all timed over batches long
/// enough to dwarf the clock's resolution and overhead. A zero `batch` gives one call per
/// batch.
pub fn measure_for(batch: Duration, mut f: impl FnMut()) -> Timing {
    let t = Instant::now();
    f();
    let once = t.elapsed().as_secs_f64().max(1e-9);
    let reps = (batch.as_secs_f64() / once).ceil() as usize;
    measure(reps, f)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn measures_every_batch_after_a_warm_up() {
        let mut calls = 0;
        let t = measure(3, || {
            calls += 1;
            std::hint::black_box(calls);
        });
        assert_eq!(calls, 3 * (BATCHES + 1));
        assert!(t.min_ms >= 0.0 && t.min_ms <= t.median_ms, "{t}");
        assert!(t.median_ms.is_finite());

        let mut calls = 0;
        measure(0, || calls += 1);
        assert_eq!(calls, BATCHES + 1, "at least one call per batch");
    }

    #[test]
    fn sizes_batches_from_one_call() {
        let mut calls = 0;
        measure_for(Duration::ZERO, || calls += 1);
        assert_eq!(
            calls,
            1 + BATCHES + 1,
            "one calibrating call, then one per batch"
        );

        // A call of at least 1 ms against a 3 ms batch: at most 3 calls per batch.
        let mut calls = 0;
        let t = measure_for(Duration::from_millis(3), || {
            calls += 1;
            std::thread::sleep(Duration::from_millis(1));
        });
        assert!(calls > BATCHES && calls <= 1 + 3 * (BATCHES + 1), "{calls}");
        assert!(t.min_ms >= 1.0, "{t}");
    }
}
