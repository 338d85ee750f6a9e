//! `bench train`: CPU milliseconds per training step (one minibatch) of the dynamics model and
//! of DEEN, at the preset's sizes and batch sizes, their matrix-product rate as a fraction of
//! the per-core f32 peak, and how a DEEN step splits into its phases.
//!
//! Steps run their products on rayon's pool (`matmul_par`), so they are timed in the whole
//! process's CPU time: every thread's time counts, spinning for work included, and the rate per
//! CPU second compares with one core's peak however many threads took part and however loaded
//! the machine was. The CPU share says how much of `threads × wall time` that was, and the
//! wall time per step what a trainer waits.
//!
//! The steps run on a rayon worker thread of a pool of their own, as the service's retraining
//! runs on its background pool (`sched::background`): a product split across two threads is
//! then a warm join, its second half pushed on the worker's own deque for the other worker to
//! take. Timed from the main thread instead, every split product was a cold join: the calling
//! thread handed the whole product to the pool and slept on a lock until both halves were done,
//! two thread wake-ups per product that the service never pays (`perf record` of the
//! half-cheetah steps: 8.8 % of the samples in the kernel's task switch, 1.5 % in a contended
//! mutex, 1.8 % in `sched_yield`).

use super::timing::{BATCHES, Clock, Samples, Timing, measure};
use super::{BenchError, describe, preset, random_transitions};
use planner_service::dynamics::{Ensemble, TrainWorkspace, TrainingSet};
use planner_service::energy::{Deen, DeenWorkspace, RegularizerKind, transition_rows};
use planner_service::nn::peak::{Peak, percent};
use planner_service::nn::{Adam, FlushDenormals, InputGradTape, Mlp, Normalizer, TrainPath};
use proto::Builtin;
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::fmt;

/// Timing of one network's training steps.
#[derive(Clone, Debug, PartialEq)]
pub struct StepTiming {
    pub sizes: Vec<usize>,
    pub batch: usize,
    /// The kernels the step's products ran on (measured fastest for this shape, see
    /// [`TrainPath::measured`]).
    pub path: TrainPath,
    /// CPU time per step (all threads), fastest and median step.
    pub time: Timing,
    /// Floating-point operations of the step's matrix products (`2·m·n·k` each).
    pub flops: f64,
}

impl StepTiming {
    /// Matrix-product GFLOP/s per CPU second at the fastest and at the median step.
    pub fn gflops(&self) -> (f64, f64) {
        let rate = |ms: f64| self.flops / (ms * 1e-3) / 1e9;
        (rate(self.time.min_ms), rate(self.time.median_ms))
    }
}

/// Products per sample of a dynamics step (`Mlp::backward` without the input gradient): every
/// layer's forward product and weight gradient, every layer's but the first's backward product.
pub fn dynamics_step_flops(sizes: &[usize]) -> f64 {
    layer_flops(sizes)
        .enumerate()
        .map(|(l, f)| if l == 0 { 2.0 * f } else { 3.0 * f })
        .sum()
}

/// Products per sample of a DEEN step (`Mlp::input_gradient_train` then
/// `input_gradient_backward`): every layer's forward product; for every layer but the scalar
/// output one, the input-gradient product `W·δ`, the tangent forward `Wᵀ·ḣ` and the weight
/// gradient `[ḣ h]·[δ; δ̇]ᵀ` (twice the batch as depth); and for those but the first the tangent
/// backward `W·δ̇`.
pub fn deen_step_flops(sizes: &[usize]) -> f64 {
    let top = sizes.len().saturating_sub(2);
    layer_flops(sizes)
        .enumerate()
        .map(|(l, f)| match l {
            l if l == top => f,
            0 => 5.0 * f,
            _ => 6.0 * f,
        })
        .sum()
}

/// `2·in·out` per layer: one product of a layer on one sample.
fn layer_flops(sizes: &[usize]) -> impl Iterator<Item = f64> + '_ {
    sizes.windows(2).map(|w| 2.0 * w[0] as f64 * w[1] as f64)
}

/// Timing of training steps of both models of a task's preset.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainReport {
    pub task: Builtin,
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

/// Transitions to draw minibatches from: enough for several distinct batches.
const SAMPLES: usize = 2048;

pub(super) fn run(
    task: Builtin,
    steps: usize,
    warmup: usize,
    seed: u64,
) -> Result<TrainReport, BenchError> {
    if steps == 0 {
        return Err(BenchError::Zero("steps"));
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(rayon::current_num_threads())
        .build()?;
    pool.install(|| run_on_worker(task, steps, warmup, seed))
}

/// [`run`] on a worker thread of the pool the steps split their products over.
fn run_on_worker(
    task: Builtin,
    steps: usize,
    warmup: usize,
    seed: u64,
) -> Result<TrainReport, BenchError> {
    let _flush = FlushDenormals::new(); // as the trainers run
    let peak = Peak::measure();
    let preset = preset(task, RegularizerKind::Deen, false)?;
    let spec = task.task();
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
    let dynamics_time = time_steps(&dynamics_batches, warmup, |batch| {
        model.train_step(&set, batch, &mut workspace);
    });
    let dynamics_sizes = model.mlp().sizes().to_vec();
    let dynamics_path = workspace.path();

    let energy_batch = preset.energy.batch_size;
    let rows = transition_rows(&data);
    let mut deen = Deen::new(2 * spec.obs_dim + spec.act_dim, &preset.energy, &mut rng);
    deen.fit(&rows, 1, &mut rng); // fits the normaliser
    let mut set = rows;
    deen.normalizer().normalize_rows(&mut set);
    let mut workspace = DeenWorkspace::new(&deen, energy_batch);
    let energy_batches = batches(energy_batch, &mut rng);
    let mut noise_rng = StdRng::seed_from_u64(seed.wrapping_add(1));
    let deen_time = time_steps(&energy_batches, warmup, |batch| {
        deen.train_step(&set, batch, &mut workspace, &mut noise_rng);
    });
    let deen_path = workspace.path();
    let deen_phases = deen_phases(deen.mlp(), &set, &energy_batches[0], steps);

    Ok(TrainReport {
        task,
        steps,
        dynamics: StepTiming {
            flops: dynamics_step_flops(&dynamics_sizes) * dynamics_batch as f64,
            sizes: dynamics_sizes,
            batch: dynamics_batch,
            path: dynamics_path,
            time: dynamics_time,
        },
        deen: StepTiming {
            sizes: deen.mlp().sizes().to_vec(),
            batch: energy_batch,
            path: deen_path,
            time: deen_time,
            flops: deen_step_flops(deen.mlp().sizes()) * energy_batch as f64,
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
    let mut tape = InputGradTape::for_training(mlp, samples);
    let ld = tape.ld();
    let input = tape.input_mut();
    for (col, &idx) in batch.iter().enumerate() {
        for (f, &x) in set[idx * dim..(idx + 1) * dim].iter().enumerate() {
            input[f * ld + col] = x;
        }
    }
    let reps = steps.div_ceil(BATCHES);
    let forward = measure(Clock::Process, reps, || {
        mlp.input_gradient_train(&mut tape, samples);
    });
    let mut grads = vec![0.0; mlp.params().len()];
    let backward = measure(Clock::Process, reps, || {
        mlp.input_gradient_backward(&mut tape, &mut grads)
    });
    let mut params = mlp.params().to_vec();
    let mut adam = Adam::new(params.len(), 1e-3);
    let optimiser = measure(Clock::Process, reps, || adam.step(&mut params, &grads));
    DeenPhases {
        forward,
        backward,
        optimiser,
    }
}

/// Runs `step` on every batch and times those after the first `warmup`, one step each, in the
/// process's CPU time.
fn time_steps(batches: &[Vec<usize>], warmup: usize, mut step: impl FnMut(&[usize])) -> Timing {
    let mut samples = Samples::new(Clock::Process, batches.len().saturating_sub(warmup));
    for (i, batch) in batches.iter().enumerate() {
        samples.time(i >= warmup, 1, || step(batch));
    }
    samples.timing()
}

impl fmt::Display for TrainReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "bench train: {} ({} timed steps each, {} thread(s); CPU ms per step, all threads' \
             time summed; GFLOP/s of the matrix products per CPU second, as a fraction of one \
             core's f32 peak; each network's training path measured fastest for its shape)\n  {}",
            self.task, self.steps, self.threads, self.peak
        )?;
        let f32_peak = self.peak.f32_at(planner_service::nn::simd::level());
        for (name, t) in [("dynamics", &self.dynamics), ("DEEN", &self.deen)] {
            let (best, median) = t.gflops();
            write!(
                f,
                "\n  {name:<9} {:<16} batch {:>3} on {:<8}: {:.3} ms best, {:.3} ms median; \
                 {best:.1} GFLOP/s best = {} of peak, {median:.1} median = {}",
                describe(&t.sizes),
                t.batch,
                t.path.name(),
                t.time.min_ms,
                t.time.median_ms,
                percent(best, f32_peak),
                percent(median, f32_peak),
            )?;
            if let Some(share) = t.time.cpu_share {
                write!(f, "; CPU share {:.0}%", share * 100.0)?;
            }
            write!(f, "; wall {:.3} ms median", t.time.wall_median_ms)?;
        }
        let p = &self.deen_phases;
        write!(
            f,
            "\n  DEEN step phases (CPU ms, best of {BATCHES} batches): forward + input gradient \
             {:.3} ms, double backprop {:.3} ms, Adam {:.3} ms",
            p.forward.min_ms, p.backward.min_ms, p.optimiser.min_ms
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_real_training_steps() {
        let report = run(Builtin::Cartpole, 3, 1, 0).unwrap();
        assert_eq!((report.dynamics.batch, report.deen.batch), (32, 32));
        assert_eq!(report.dynamics.sizes, vec![6, 200, 200, 200, 8]);
        assert_eq!(report.deen.sizes, vec![9, 200, 200, 200, 1]);
        for t in [&report.dynamics, &report.deen] {
            assert!(
                t.time.min_ms > 0.0 && t.time.min_ms <= t.time.median_ms,
                "{t:?}"
            );
            let (best, median) = t.gflops();
            assert!(best >= median && median > 0.0 && best.is_finite(), "{t:?}");
            assert!(t.time.cpu_share.is_none_or(|s| s > 0.0), "{t:?}");
            assert!(
                t.time.wall_median_ms > 0.0 && t.time.wall_median_ms.is_finite(),
                "{t:?}"
            );
        }
        // 6·200·200 + 4·200·200 + 2·(6·200 + 200·8) flops per sample, batch 32.
        assert_eq!(
            report.dynamics.flops,
            32.0 * dynamics_step_flops(&[6, 200, 200, 200, 8])
        );
        let p = &report.deen_phases;
        for t in [p.forward, p.backward, p.optimiser] {
            assert!(t.min_ms > 0.0 && t.min_ms <= t.median_ms && t.median_ms.is_finite());
        }
        let text = report.to_string();
        assert!(
            text.contains("DEEN")
                && text.contains("double backprop")
                && text.contains("f32 peak")
                && text.contains("of peak")
                && text.contains("CPU ms")
                && text.contains("wall")
                && !text.contains("PyTorch"),
            "{text}"
        );
        assert!(matches!(
            run(Builtin::Cartpole, 0, 0, 0),
            Err(BenchError::Zero("steps"))
        ));
    }

    #[test]
    fn counts_the_products_of_each_step() {
        // in 3 → 4 → 5 → 1: layer flops 24, 40, 10 per sample.
        let sizes = [3, 4, 5, 1];
        // Dynamics: forward and weight gradient everywhere, backward product above layer 0.
        assert_eq!(
            dynamics_step_flops(&sizes),
            2.0 * 24.0 + 3.0 * 40.0 + 3.0 * 10.0
        );
        // DEEN, in units of one layer product: the scalar output layer only its forward one;
        // layer 0 forward, W·δ, Wᵀ·ḣ and the double-depth weight gradient (1 + 1 + 1 + 2); the
        // middle layer those plus W·δ̇.
        assert_eq!(deen_step_flops(&sizes), 5.0 * 24.0 + 6.0 * 40.0 + 10.0);
        assert_eq!(deen_step_flops(&[3, 1]), 6.0);
    }
}
