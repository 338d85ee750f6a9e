//! `bench train`: milliseconds per training step (one minibatch) of the dynamics model and of
//! DEEN, at the preset's sizes and batch sizes, and how a DEEN step splits into its phases.

use super::peak::{Peak, percent};
use super::timing::{BATCHES, Timing, measure};
use super::{BenchError, describe, flops_per_row, median_ms, preset, random_transitions};
use crate::dynamics::{Ensemble, TrainWorkspace, TrainingSet};
use crate::energy::{Deen, DeenWorkspace, RegularizerKind, transition_rows};
use crate::nn::{Adam, FlushDenormals, InputGradTape, Mlp, Normalizer};
use proto::TaskId;
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::fmt;
use std::time::{Duration, Instant};

/// Timing of one network's training steps.
#[derive(Clone, Debug, PartialEq)]
pub struct StepTiming {
    pub sizes: Vec<usize>,
    pub batch: usize,
    pub median_ms: f64,
    pub min_ms: f64,
    /// Matrix-product GFLOP/s at the median, where the step's operation count is simple to
    /// state (dynamics: forward plus backward, `6·in·out` per layer per sample).
    pub gflops: Option<f64>,
}

/// Timing of training steps of both models of a task's preset.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainReport {
    pub task: TaskId,
    pub steps: usize,
    /// One ensemble member (members train in parallel, each with steps like this one).
    pub dynamics: StepTiming,
    pub deen: StepTiming,
    pub deen_phases: DeenPhases,
    /// This core's peak, measured before and after the steps (the higher; training runs in f32).
    pub peak: Peak,
    /// Threads the training products may use (rayon's pool): the fraction of peak is taken
    /// of this many cores.
    pub threads: usize,
}

/// Where a DEEN step's time goes: its double backprop is the costliest training pass of the
/// project, and these show which part to work on. Per call, fastest and median of
/// [`BATCHES`] batches; the rest of a step (drawing the noise, the loss) is the difference.
#[derive(Clone, Debug, PartialEq)]
pub struct DeenPhases {
    /// Forward pass with the input gradient `∂E/∂y` (the score).
    pub forward: Timing,
    /// Double backprop: the loss's parameter gradient through the score.
    pub backward: Timing,
    /// One Adam update of every parameter.
    pub optimiser: Timing,
}

/// The fastest of some durations, in milliseconds.
fn min_ms(times: &[Duration]) -> f64 {
    times.iter().min().map_or(0.0, |t| t.as_secs_f64() * 1e3)
}

/// Transitions to draw minibatches from: enough for several distinct batches.
const SAMPLES: usize = 2048;

pub(super) fn run(
    task: TaskId,
    steps: usize,
    warmup: usize,
    seed: u64,
) -> Result<TrainReport, BenchError> {
    if steps == 0 {
        return Err(BenchError::Zero("steps"));
    }
    let _flush = FlushDenormals::new(); // as the trainers run
    let peak = Peak::measure();
    let preset = preset(task, RegularizerKind::Deen, false)?;
    let spec = task.spec();
    let mut rng = StdRng::seed_from_u64(seed);
    let data = random_transitions(task, SAMPLES, &mut rng);
    let batches = |batch: usize, rng: &mut StdRng| -> Vec<Vec<usize>> {
        (0..warmup + steps)
            .map(|_| (0..batch).map(|_| rng.random_range(0..SAMPLES)).collect())
            .collect()
    };

    let dynamics_batch = preset.dynamics.batch_size;
    let mut ensemble = Ensemble::new(spec, &preset.dynamics, &mut rng);
    let (inputs, targets) = TrainingSet::raw(spec, &data);
    let input_norm = Normalizer::fit(&inputs, spec.state_feature_dim + spec.act_dim);
    let target_norm = Normalizer::fit(&targets, spec.obs_dim);
    let set = TrainingSet::standardised(inputs, targets, &input_norm, &target_norm);
    let model = ensemble.member_mut(0);
    model.set_normalizers(input_norm, target_norm);
    let mut workspace = TrainWorkspace::new(model, dynamics_batch);
    let dynamics_batches = batches(dynamics_batch, &mut rng);
    let mut dynamics_times = time_steps(&dynamics_batches, warmup, |batch| {
        model.train_step(&set, batch, &mut workspace);
    });
    let dynamics_sizes = model.mlp().sizes().to_vec();
    let dynamics_ms = median_ms(&mut dynamics_times);
    let dynamics_flops = 3.0 * flops_per_row(&dynamics_sizes) * dynamics_batch as f64;

    let energy_batch = preset.energy.batch_size;
    let rows = transition_rows(&data);
    let mut deen = Deen::new(2 * spec.obs_dim + spec.act_dim, &preset.energy, &mut rng);
    deen.fit(&rows, 1, &mut rng); // fits the normaliser
    let mut set = rows;
    deen.normalizer().normalize_rows(&mut set);
    let mut workspace = DeenWorkspace::new(&deen, energy_batch);
    let energy_batches = batches(energy_batch, &mut rng);
    let mut noise_rng = StdRng::seed_from_u64(seed.wrapping_add(1));
    let mut deen_times = time_steps(&energy_batches, warmup, |batch| {
        deen.train_step(&set, batch, &mut workspace, &mut noise_rng);
    });
    let deen_phases = deen_phases(deen.mlp(), &set, &energy_batches[0], steps);

    Ok(TrainReport {
        task,
        steps,
        dynamics: StepTiming {
            sizes: dynamics_sizes,
            batch: dynamics_batch,
            median_ms: dynamics_ms,
            min_ms: min_ms(&dynamics_times),
            gflops: Some(dynamics_flops / (dynamics_ms * 1e-3) / 1e9),
        },
        deen: StepTiming {
            sizes: deen.mlp().sizes().to_vec(),
            batch: energy_batch,
            median_ms: median_ms(&mut deen_times),
            min_ms: min_ms(&deen_times),
            gflops: None,
        },
        deen_phases,
        peak: peak.max(Peak::measure()),
        threads: rayon::current_num_threads(),
    })
}

/// Times the phases of a DEEN step on one minibatch of `set` (rows of `mlp`'s input), in
/// batches of about `steps / BATCHES` calls.
fn deen_phases(mlp: &Mlp, set: &[f32], batch: &[usize], steps: usize) -> DeenPhases {
    let (dim, samples) = (mlp.in_dim(), batch.len());
    let mut tape = InputGradTape::new(mlp, samples);
    let ld = tape.ld();
    let input = tape.input_mut();
    for (col, &idx) in batch.iter().enumerate() {
        for (f, &x) in set[idx * dim..(idx + 1) * dim].iter().enumerate() {
            input[f * ld + col] = x;
        }
    }
    let reps = steps.div_ceil(BATCHES);
    let forward = measure(reps, || {
        mlp.input_gradient_train(&mut tape, samples);
    });
    let mut grads = vec![0.0; mlp.params().len()];
    let backward = measure(reps, || mlp.input_gradient_backward(&mut tape, &mut grads));
    let mut params = mlp.params().to_vec();
    let mut adam = Adam::new(params.len(), 1e-3);
    let optimiser = measure(reps, || adam.step(&mut params, &grads));
    DeenPhases {
        forward,
        backward,
        optimiser,
    }
}

/// Runs `step` on every batch and returns the durations of those after the first `warmup`.
fn time_steps(
    batches: &[Vec<usize>],
    warmup: usize,
    mut step: impl FnMut(&[usize]),
) -> Vec<Duration> {
    let mut times = Vec::with_capacity(batches.len().saturating_sub(warmup));
    for (i, batch) in batches.iter().enumerate() {
        let start = Instant::now();
        step(batch);
        if i >= warmup {
            times.push(start.elapsed());
        }
    }
    times
}

impl fmt::Display for TrainReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "bench train: {} ({} timed steps each)\n  {}",
            self.task, self.steps, self.peak
        )?;
        for (name, t) in [("dynamics", &self.dynamics), ("DEEN", &self.deen)] {
            write!(
                f,
                "\n  {name:<9} {:<16} batch {:>3}: {:.3} ms per step median, {:.3} ms best",
                describe(&t.sizes),
                t.batch,
                t.median_ms,
                t.min_ms
            )?;
            if let Some(g) = t.gflops {
                write!(
                    f,
                    ", {g:.1} GFLOP/s = {} of the f32 peak of {} core(s)",
                    percent(g, self.peak.f32_gflops.map(|p| p * self.threads as f64)),
                    self.threads
                )?;
            }
        }
        let p = &self.deen_phases;
        write!(
            f,
            "\n  DEEN step phases (best of {BATCHES} batches): forward + input gradient {:.3} ms, \
             double backprop {:.3} ms, Adam {:.3} ms",
            p.forward.min_ms, p.backward.min_ms, p.optimiser.min_ms
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_real_training_steps() {
        let report = run(TaskId::Cartpole, 3, 1, 0).unwrap();
        assert_eq!((report.dynamics.batch, report.deen.batch), (32, 32));
        assert_eq!(report.dynamics.sizes, vec![6, 200, 200, 200, 8]);
        assert_eq!(report.deen.sizes, vec![9, 200, 200, 200, 1]);
        assert!(report.dynamics.median_ms > 0.0 && report.deen.median_ms > 0.0);
        assert!(report.deen.min_ms > 0.0 && report.deen.min_ms <= report.deen.median_ms);
        assert!(report.dynamics.gflops.is_some_and(|g| g > 0.0));
        let p = &report.deen_phases;
        for t in [p.forward, p.backward, p.optimiser] {
            assert!(t.min_ms > 0.0 && t.min_ms <= t.median_ms && t.median_ms.is_finite());
        }
        let text = report.to_string();
        assert!(
            text.contains("DEEN")
                && text.contains("double backprop")
                && text.contains("of the f32 peak")
                && !text.contains("PyTorch"),
            "{text}"
        );
        assert!(matches!(
            run(TaskId::Cartpole, 0, 0, 0),
            Err(BenchError::Zero("steps"))
        ));
    }
}
