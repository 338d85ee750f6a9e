//! What a run records about itself while it serves: its plans against their deadlines, its
//! planning latencies, its last retraining, and the durations it times (replay fsyncs,
//! retrainings). The status report (`crate::service::status`) and the Prometheus registry
//! (`crate::service::metrics`) read these; they live with the run so that the run never
//! imports the service that hosts it.

use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex, PoisonError};

/// Planning latencies of the most recent actions, for percentiles.
#[derive(Debug, Default)]
pub struct LatencyWindow {
    samples: std::collections::VecDeque<f32>,
}

/// How many recent latencies the percentiles cover.
const WINDOW: usize = 2048;

impl LatencyWindow {
    pub fn record(&mut self, ms: f32) {
        if self.samples.len() == WINDOW {
            self.samples.pop_front();
        }
        self.samples.push_back(ms);
    }

    /// p50, p90 and p99 of the window (nearest rank), `None` when empty.
    pub fn percentiles(&self) -> Option<Latency> {
        if self.samples.is_empty() {
            return None;
        }
        let mut sorted: Vec<f32> = self.samples.iter().copied().collect();
        sorted.sort_by(f32::total_cmp);
        let at = |q: f32| {
            sorted[(((sorted.len() as f32) * q).ceil() as usize).clamp(1, sorted.len()) - 1]
        };
        Some(Latency {
            p50_ms: at(0.50),
            p90_ms: at(0.90),
            p99_ms: at(0.99),
            samples: sorted.len(),
        })
    }
}

/// How a run's plans went against its deadline, since the daemon started.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct PlanTally {
    /// Planned actions answered.
    pub plans: u64,
    /// Plans whose iterations were cut short by the deadline.
    pub cut: u64,
    /// Actions sent after the deadline, or with no iteration run before it.
    pub deadline_misses: u64,
    /// Iterations run, over all plans.
    pub iterations: u64,
    /// Times its plans stepped back from the cores for a more urgent plan (see `sched`).
    pub stepped_back: u64,
}

/// What one planned action adds to its run's tally and metrics.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PlanRecord {
    pub iterations: u32,
    /// The deadline cut its iterations short.
    pub cut: bool,
    /// It was sent after the deadline, or with no iteration run before it.
    pub missed: bool,
    /// Times it stepped back for a more urgent plan.
    pub stepped_back: u32,
}

impl PlanTally {
    pub fn record(&mut self, plan: PlanRecord) {
        self.plans += 1;
        self.cut += u64::from(plan.cut);
        self.deadline_misses += u64::from(plan.missed);
        self.iterations += u64::from(plan.iterations);
        self.stepped_back += u64::from(plan.stepped_back);
    }
}

/// The count and total of a timed operation since the run was opened here: the same figures
/// as its Prometheus histogram's `_count` and `_sum`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Timings {
    pub count: u64,
    pub seconds_total: f64,
}

/// The last retraining that produced models: how long it took and the final training loss of
/// each model (`None`: that model took no step).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct LastRetraining {
    pub models_version: u64,
    pub seconds: f32,
    /// The dynamics model's loss over its last epoch (the mean over the ensemble's members).
    pub dynamics_loss: Option<f32>,
    /// The regulariser's (DEEN or DAE) loss over its last epoch.
    pub energy_loss: Option<f32>,
    /// A learned termination's accuracy on the transitions held out of its training (absent
    /// unless the task's termination is learned and an episode has ended as `terminated`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub termination_accuracy: Option<proto::TerminationAccuracy>,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Latency {
    pub p50_ms: f32,
    pub p90_ms: f32,
    pub p99_ms: f32,
    pub samples: usize,
}

/// Replay log fsync buckets: 50 µs to about 1.6 s, doubling.
pub(crate) fn fsync_histogram() -> Histogram {
    Histogram::new(exponential_buckets(50e-6, 2.0, 16))
}

/// Retraining buckets: 10 ms to about 20 min, doubling.
pub(crate) fn retraining_histogram() -> Histogram {
    Histogram::new(exponential_buckets(0.01, 2.0, 18))
}

/// A timed operation: each duration goes into a Prometheus histogram and into the count and
/// total the status report shows (`prometheus-client` does not read a histogram back), from
/// one call.
#[derive(Clone, Debug)]
pub struct Timed {
    histogram: Histogram,
    totals: Arc<Mutex<Timings>>,
}

impl Timed {
    pub(crate) fn new(histogram: Histogram) -> Self {
        Self {
            histogram,
            totals: Arc::default(),
        }
    }

    pub fn observe(&self, seconds: f64) {
        self.histogram.observe(seconds);
        let mut totals = self.totals.lock().unwrap_or_else(PoisonError::into_inner);
        totals.count += 1;
        totals.seconds_total += seconds;
    }

    /// How many durations were observed, and their sum: the histogram's `_count` and `_sum`.
    pub fn timings(&self) -> Timings {
        *self.totals.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// The durations a run times itself, since it is the run that syncs its replay log and
/// retrains: the daemon's registry serves them (see [`crate::service::metrics::Metrics::for_run`]) and the status
/// report shows their count and total. The default ones are served nowhere (experiments,
/// tests).
#[derive(Clone, Debug)]
pub struct RunHistograms {
    /// Seconds per fsync of the run's replay log.
    pub fsync_seconds: Timed,
    /// Seconds per retraining that produced models.
    pub retraining_seconds: Timed,
}

impl Default for RunHistograms {
    fn default() -> Self {
        Self {
            fsync_seconds: Timed::new(fsync_histogram()),
            retraining_seconds: Timed::new(retraining_histogram()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn percentiles_by_nearest_rank() {
        let mut w = LatencyWindow::default();
        assert_eq!(w.percentiles(), None);
        for ms in 1..=100 {
            w.record(ms as f32);
        }
        let p = w.percentiles().unwrap();
        assert_eq!(
            (p.p50_ms, p.p90_ms, p.p99_ms, p.samples),
            (50.0, 90.0, 99.0, 100)
        );
        for _ in 0..WINDOW {
            w.record(7.0);
        }
        assert_eq!(w.percentiles().unwrap().p99_ms, 7.0);
    }
}
