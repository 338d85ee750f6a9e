//! Test-only wall-clock measurement for the ignored timing tests, robust to a shared machine:
//! the work runs in batches and both the fastest and the median batch are reported (the
//! fastest is the least disturbed by other processes).

use std::time::Instant;

/// Per-call milliseconds of the fastest and of the median batch.
#[derive(Clone, Copy, Debug)]
pub struct Timing {
    pub min_ms: f64,
    pub median_ms: f64,
}

impl std::fmt::Display for Timing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.3} ms (median {:.3} ms)", self.min_ms, self.median_ms)
    }
}

/// Times `f` in 15 batches of `reps` calls each, after one warm-up batch.
pub fn measure(reps: usize, mut f: impl FnMut()) -> Timing {
    let mut batches: Vec<f64> = (0..16)
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
