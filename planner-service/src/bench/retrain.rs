//! The figure of `bench train` that matters for a run: a whole retraining as the daemon runs it
//! ([`crate::trainer::retrain`], yielding to a plan queue between minibatches), its wall time
//! and CPU time, and the matrix-product rate it achieved in aggregate on the process's threads.
//!
//! The retraining trains the preset's models (dynamics and DEEN) for the epochs of the preset's
//! first retraining, on a buffer of random transitions a few minibatches long (the cost is
//! linear in the buffer, the rate is not: a small buffer keeps the bench short and still runs
//! whole epochs of full minibatches). Its products are counted per sample from the networks'
//! sizes ([`dynamics_step_flops`], [`deen_step_flops`]) times samples × epochs (× members for
//! an ensemble); what a retraining does besides the steps (normalisers, the final evaluation,
//! packing for inference) is uncounted work in the measured time.

use super::cputime::process_cpu_time;
use super::peak::{Peak, percent};
use super::train::{deen_step_flops, dynamics_step_flops};
use super::{BenchError, random_transitions};
use crate::config::Preset;
use crate::energy::Regularizer;
use crate::models::Models;
use crate::sched::Scheduler;
use crate::trainer::{TrainLimits, retrain};
use proto::Builtin;
use rand::SeedableRng;
use rand::rngs::StdRng;
use std::fmt;
use std::sync::Arc;
use std::time::Instant;

/// Retrainings timed (the first one is timed too: every retraining starts from fresh buffers).
pub const RETRAININGS: usize = 3;

/// Minibatches of the larger model batch that the bench's buffer holds.
const BUFFER_BATCHES: usize = 2;

/// Timing of whole retrainings.
#[derive(Clone, Debug, PartialEq)]
pub struct RetrainTiming {
    pub transitions: usize,
    pub dynamics_epochs: usize,
    pub energy_epochs: usize,
    pub members: usize,
    /// Wall seconds per retraining, fastest and median.
    pub wall_s: (f64, f64),
    /// CPU seconds per retraining (every thread of the process), fastest and median.
    pub cpu_s: Option<(f64, f64)>,
    /// Floating-point operations of one retraining's training steps.
    pub flops: f64,
    /// Cores the retraining may use (rayon's pool: its products' helpers).
    pub threads: usize,
}

impl RetrainTiming {
    /// Aggregate GFLOP/s over wall time at the fastest and at the median retraining.
    pub fn wall_gflops(&self) -> (f64, f64) {
        (
            self.flops / self.wall_s.0 / 1e9,
            self.flops / self.wall_s.1 / 1e9,
        )
    }

    /// GFLOP/s per CPU second (every thread's), fastest and median.
    pub fn cpu_gflops(&self) -> Option<(f64, f64)> {
        self.cpu_s
            .map(|(best, median)| (self.flops / best / 1e9, self.flops / median / 1e9))
    }

    /// CPU time over wall time at the median: up to `threads` when every thread had a core.
    pub fn cpu_share(&self) -> Option<f64> {
        self.cpu_s.map(|(_, median)| median / self.wall_s.1)
    }
}

/// Times [`RETRAININGS`] retrainings of `preset`'s models (DEEN as the regulariser).
pub(super) fn time(task: Builtin, preset: &Preset, seed: u64) -> Result<RetrainTiming, BenchError> {
    let spec = task.task();
    let transitions = BUFFER_BATCHES * preset.dynamics.batch_size.max(preset.energy.batch_size);
    let mut rng = StdRng::seed_from_u64(seed);
    let data = random_transitions(task, transitions, &mut rng);
    let episodes = preset.exploration_episodes;
    let (dynamics_epochs, energy_epochs) = preset.epochs(episodes);
    let models = Models::untrained(spec, preset, seed);
    let members = models.dynamics.members();
    let dynamics_sizes = models.dynamics.member(0).mlp().sizes().to_vec();
    let energy_sizes = match &models.regularizer {
        Regularizer::Deen(deen) => deen.mlp().sizes().to_vec(),
        _ => Vec::new(),
    };
    let samples = transitions as f64;
    let flops = dynamics_step_flops(&dynamics_sizes) * samples * (dynamics_epochs * members) as f64
        + if energy_sizes.is_empty() {
            0.0
        } else {
            deen_step_flops(&energy_sizes) * samples * energy_epochs as f64
        };
    let limits = TrainLimits {
        yield_to: Some(Arc::new(Scheduler::default())),
        ..TrainLimits::unbounded()
    };
    let mut wall = Vec::with_capacity(RETRAININGS);
    let mut cpu = Some(Vec::with_capacity(RETRAININGS));
    for r in 0..RETRAININGS {
        let cpu_before = process_cpu_time();
        let started = Instant::now();
        retrain(&models, &data, preset, episodes, seed + r as u64, &limits)?;
        wall.push(started.elapsed().as_secs_f64());
        let used = cpu_before
            .zip(process_cpu_time())
            .map(|(a, b)| b.saturating_sub(a).as_secs_f64());
        cpu = cpu.zip(used).map(|(mut v, c)| {
            v.push(c);
            v
        });
    }
    Ok(RetrainTiming {
        transitions,
        dynamics_epochs,
        energy_epochs,
        members,
        wall_s: best_and_median(wall),
        cpu_s: cpu.map(best_and_median),
        flops,
        threads: rayon::current_num_threads(),
    })
}

fn best_and_median(mut v: Vec<f64>) -> (f64, f64) {
    v.sort_by(f64::total_cmp);
    (v[0], v[v.len() / 2])
}

/// A [`RetrainTiming`] beside the peak it is judged against.
pub struct WithPeak<'a>(pub &'a RetrainTiming, pub &'a Peak);

impl fmt::Display for WithPeak<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (t, peak) = (self.0, self.1);
        let threads_peak = peak.f32_gflops.map(|p| p * t.threads as f64);
        let (wall_best, wall_median) = t.wall_gflops();
        write!(
            f,
            "retraining ({} transitions; {} dynamics epoch(s) × {} member(s), {} DEEN epoch(s); \
             {:.1} GFLOP of products): {:.3} s best, {:.3} s median wall; aggregate {:.1} GFLOP/s \
             best = {} of {} × peak, {:.1} median = {}",
            t.transitions,
            t.dynamics_epochs,
            t.members,
            t.energy_epochs,
            t.flops / 1e9,
            t.wall_s.0,
            t.wall_s.1,
            wall_best,
            percent(wall_best, threads_peak),
            t.threads,
            wall_median,
            percent(wall_median, threads_peak),
        )?;
        if let (Some((best, median)), Some(share)) = (t.cpu_gflops(), t.cpu_share()) {
            write!(
                f,
                "; per CPU second {best:.1} GFLOP/s best = {} of one core's peak, {median:.1} \
                 median = {}; CPU share {:.0}% (of {} threads: {:.0}%)",
                percent(best, peak.f32_gflops),
                percent(median, peak.f32_gflops),
                share * 100.0,
                t.threads,
                share * 100.0 / t.threads as f64,
            )?;
        }
        Ok(())
    }
}
