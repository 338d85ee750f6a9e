//! CPU-time measurement of short, repeatable operations, robust to a shared machine.
//!
//! One call of a kernel lasts microseconds, too short to time alone, and the project's machine
//! is shared: any single measurement may have lost its core for a while. So the work runs in
//! batches of many calls, after one untimed warm-up batch (caches, page faults, clock ramp-up),
//! and each batch is timed in **CPU time** (see [`cputime`](planner_service::nn::cputime)): time in which
//! another process had the core does not count, so a kernel's rate is not halved because
//! someone was compiling on the same core. Work on the calling thread is timed on that thread's
//! clock; parallel work on the whole process's, so that every helper thread's time (spinning
//! for work included) counts. Both the fastest and the median batch are
//! reported, and the share of the wall time the process actually got on a CPU, so that a
//! reader sees how loaded the machine was. Where the platform has no CPU clock the wall clock
//! is used instead (and no share is reported).

use planner_service::nn::cputime::{process_cpu_time, thread_cpu_time};
use std::time::{Duration, Instant};

/// Which CPU time a measurement reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Clock {
    /// The calling thread's: for work that runs on it alone (other threads of the process,
    /// e.g. parallel tests, do not count).
    Thread,
    /// Every thread of the process: for work split across threads.
    Process,
}

impl Clock {
    fn read(self) -> Option<Duration> {
        match self {
            Clock::Thread => thread_cpu_time(),
            Clock::Process => process_cpu_time(),
        }
    }
}

/// Timed batches per measurement (after one warm-up batch).
pub const BATCHES: usize = 15;

/// Per-call milliseconds of the fastest and of the median batch, in CPU time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Timing {
    pub min_ms: f64,
    pub median_ms: f64,
    /// Per-call wall-clock milliseconds of the median batch (by wall time): what a caller
    /// waits, however many threads shared the work.
    pub wall_median_ms: f64,
    /// CPU time over wall time of all timed batches: 1.0 for one thread that had its core
    /// throughout, less where other processes took it, up to the thread count for parallel
    /// work. `None` where there is no CPU clock (the figures are then wall clock).
    pub cpu_share: Option<f64>,
}

impl std::fmt::Display for Timing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:.3} ms (median {:.3} ms)", self.min_ms, self.median_ms)?;
        if let Some(share) = self.cpu_share {
            write!(f, " CPU, {:.0}% CPU share", share * 100.0)?;
        }
        Ok(())
    }
}

/// A stopwatch on a CPU clock and the wall clock.
struct Stopwatch {
    clock: Clock,
    wall: Instant,
    cpu: Option<Duration>,
}

impl Stopwatch {
    fn start(clock: Clock) -> Self {
        Self {
            clock,
            cpu: clock.read(),
            wall: Instant::now(),
        }
    }

    /// Seconds elapsed on (the CPU clock, the wall clock) since the start.
    fn elapsed(&self) -> (Option<f64>, f64) {
        let wall = self.wall.elapsed().as_secs_f64();
        let cpu = self
            .cpu
            .zip(self.clock.read())
            .map(|(before, after)| after.saturating_sub(before).as_secs_f64());
        (cpu, wall)
    }
}

/// Collects timed runs (each of `calls` calls) and summarises them as a [`Timing`].
pub struct Samples {
    clock: Clock,
    /// Per-call seconds of each run on the CPU clock, or on the wall clock without one.
    per_call: Vec<f64>,
    /// Per-call wall-clock seconds of each run.
    wall_per_call: Vec<f64>,
    cpu_total: Option<f64>,
    wall_total: f64,
}

impl Samples {
    pub fn new(clock: Clock, runs: usize) -> Self {
        Self {
            clock,
            per_call: Vec::with_capacity(runs),
            wall_per_call: Vec::with_capacity(runs),
            cpu_total: Some(0.0),
            wall_total: 0.0,
        }
    }

    /// Runs `f` and, if `keep`, records it as one run of `calls` calls.
    pub fn time<R>(&mut self, keep: bool, calls: usize, f: impl FnOnce() -> R) -> R {
        let watch = Stopwatch::start(self.clock);
        let out = f();
        let (cpu, wall) = watch.elapsed();
        if keep {
            self.per_call
                .push(cpu.unwrap_or(wall) / calls.max(1) as f64);
            self.wall_per_call.push(wall / calls.max(1) as f64);
            self.cpu_total = self.cpu_total.zip(cpu).map(|(a, b)| a + b);
            self.wall_total += wall;
        }
        out
    }

    /// The fastest and the median run, per call. Panics without a run.
    pub fn timing(mut self) -> Timing {
        assert!(!self.per_call.is_empty(), "no timed run");
        self.per_call.sort_by(f64::total_cmp);
        self.wall_per_call.sort_by(f64::total_cmp);
        Timing {
            min_ms: self.per_call[0] * 1e3,
            median_ms: self.per_call[self.per_call.len() / 2] * 1e3,
            wall_median_ms: self.wall_per_call[self.wall_per_call.len() / 2] * 1e3,
            cpu_share: self
                .cpu_total
                .filter(|_| self.wall_total > 0.0)
                .map(|c| c / self.wall_total),
        }
    }
}

/// Times `f` on `clock` in [`BATCHES`] batches of `reps` calls each (at least one), after one
/// warm-up batch.
pub fn measure(clock: Clock, reps: usize, mut f: impl FnMut()) -> Timing {
    let reps = reps.max(1);
    let mut samples = Samples::new(clock, BATCHES);
    for batch in 0..=BATCHES {
        samples.time(batch > 0, reps, || {
            for _ in 0..reps {
                f();
            }
        });
    }
    samples.timing()
}

/// [`measure`] with batches of about `batch` each: the calls per batch are estimated from one
/// untimed call, so that products of very different sizes are all timed over batches long
/// enough to dwarf the clock's resolution and overhead. A zero `batch` gives one call per
/// batch.
pub fn measure_for(clock: Clock, batch: Duration, mut f: impl FnMut()) -> Timing {
    let t = Instant::now();
    f();
    let once = t.elapsed().as_secs_f64().max(1e-9);
    let reps = (batch.as_secs_f64() / once).ceil() as usize;
    measure(clock, reps, f)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn measures_every_batch_after_a_warm_up() {
        let mut calls = 0;
        let t = measure(Clock::Thread, 3, || {
            calls += 1;
            std::hint::black_box(calls);
        });
        assert_eq!(calls, 3 * (BATCHES + 1));
        assert!(t.min_ms >= 0.0 && t.min_ms <= t.median_ms, "{t}");
        assert!(t.median_ms.is_finite());

        let mut calls = 0;
        measure(Clock::Process, 0, || calls += 1);
        assert_eq!(calls, BATCHES + 1, "at least one call per batch");
    }

    #[test]
    fn sizes_batches_from_one_call() {
        let mut calls = 0;
        measure_for(Clock::Thread, Duration::ZERO, || calls += 1);
        assert_eq!(
            calls,
            1 + BATCHES + 1,
            "one calibrating call, then one per batch"
        );

        // A call of at least 1 ms against a 3 ms batch: at most 3 calls per batch.
        let mut calls = 0;
        let t = measure_for(Clock::Thread, Duration::from_millis(3), || {
            calls += 1;
            std::thread::sleep(Duration::from_millis(1));
        });
        assert!(calls > BATCHES && calls <= 1 + 3 * (BATCHES + 1), "{calls}");
        assert!(t.wall_median_ms >= 1.0, "each call slept 1 ms: {t:?}");
        // Sleeping costs no CPU time: a call is timed far below the 1 ms it lasted, and the
        // process was on a CPU for a small share of the wall time.
        if let Some(share) = t.cpu_share {
            assert!(t.min_ms < 0.5 && share < 0.5, "{t}");
        } else {
            assert!(t.min_ms >= 1.0, "{t}");
        }
    }

    #[test]
    fn times_busy_work_in_cpu_time() {
        // Spinning for 2 ms of wall time costs about 2 ms of CPU time if the thread kept its
        // core, less if it lost it: never more (plus clock granularity).
        let t = measure(Clock::Thread, 1, || {
            let start = Instant::now();
            while start.elapsed() < Duration::from_millis(2) {
                std::hint::black_box(0);
            }
        });
        assert!(t.min_ms > 0.0 && t.median_ms < 2.5, "{t}");
        assert!(t.cpu_share.is_none_or(|s| s > 0.0 && s <= 1.05), "{t}");
    }
}
