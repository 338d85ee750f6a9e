//! `bench plan`: milliseconds per full MPC planning call and the matrix throughput achieved.

use super::cputime::process_cpu_time;
use super::peak::{Peak, percent};
use super::{BenchError, describe, flops_per_row, median_ms, preset, random_transitions};
use crate::dynamics::Ensemble;
use crate::energy::{Regularizer, RegularizerKind};
use crate::plan::MpcPlanner;
use proto::{Builtin, InferencePrecision};
use rand::SeedableRng;
use rand::rngs::StdRng;
use std::fmt;
use std::time::Instant;

/// What `bench plan` was asked to do.
pub(super) struct Settings {
    pub task: Builtin,
    pub regularizer: RegularizerKind,
    pub timed: usize,
    pub warmup: usize,
    pub pets: bool,
    pub threads: Option<usize>,
    pub chunks: Option<usize>,
    pub precision: InferencePrecision,
    pub seed: u64,
    pub optimizer: proto::Optimizer,
    pub population: Option<usize>,
    pub elites: Option<usize>,
    pub iterations: Option<usize>,
}

/// Timing of full planning calls.
#[derive(Clone, Debug, PartialEq)]
pub struct PlanReport {
    pub task: Builtin,
    pub regularizer: RegularizerKind,
    /// Dynamics layer sizes and ensemble members.
    pub dynamics_sizes: Vec<usize>,
    pub members: usize,
    /// Energy network layer sizes (empty without a regulariser).
    pub energy_sizes: Vec<usize>,
    pub optimizer: proto::Optimizer,
    pub horizon: usize,
    pub population: usize,
    pub particles: usize,
    pub threads: usize,
    /// Population chunks planned in parallel.
    pub chunks: usize,
    /// The number format inference actually ran in.
    pub precision: InferencePrecision,
    /// Planning calls timed.
    pub calls: usize,
    /// Mean iterations per call (early stopping may cut some).
    pub mean_iterations: f64,
    /// Mean candidate sequences scored per call (iCEM's population decays).
    pub mean_candidates: f64,
    pub median_ms: f64,
    pub min_ms: f64,
    /// Matrix-product GFLOP/s at the median call time.
    pub gflops: f64,
    /// Matrix-product GFLOP/s at the best call time.
    pub best_gflops: f64,
    /// Share of `threads × wall time` that this process's threads spent on a CPU during the
    /// timed calls (below ~0.95: other work took cores away and the times are pessimistic).
    /// `None` where the platform does not report it.
    pub cpu_share: Option<f64>,
    /// Matrix-product GFLOP/s per second of CPU time the threads received over all timed
    /// calls: the rate while running, which other processes on the cores do not lower (time
    /// the pool's threads spend spinning for work counts against it).
    pub cpu_gflops: Option<f64>,
    /// Mean CPU time of one timed call, every thread's summed, in milliseconds. `None` where
    /// the platform does not report it.
    pub cpu_ms_per_call: Option<f64>,
    /// This core's peak, measured before and after the calls (the higher of the two).
    pub peak: Peak,
}

pub(super) fn run(s: &Settings) -> Result<PlanReport, BenchError> {
    if s.timed == 0 {
        return Err(BenchError::Zero("iterations-to-time"));
    }
    let mut preset = preset(s.task, s.regularizer, s.pets)?;
    preset.cem.optimizer = s.optimizer;
    let cem = &mut preset.cem;
    cem.population = s.population.unwrap_or(cem.population);
    cem.elites = s.elites.unwrap_or(cem.elites);
    cem.iterations = s.iterations.unwrap_or(cem.iterations);
    let spec = s.task.task();
    let mut rng = StdRng::seed_from_u64(s.seed);
    let data = random_transitions(s.task, 512, &mut rng);
    let mut dynamics = Ensemble::new(spec, &preset.dynamics, &mut rng);
    dynamics.fit(&data, 1, &mut rng);
    let mut regularizer = Regularizer::new(
        preset.regularizer,
        &preset.energy,
        spec.obs_dim,
        spec.act_dim,
        &mut rng,
    );
    regularizer.fit(&data, 1, &mut rng);
    dynamics.set_inference_precision(s.precision);
    regularizer.set_inference_precision(s.precision);
    let precision = dynamics.member(0).mlp().inference_precision();
    let peak = Peak::measure();
    let obs = data.row(0).0.to_vec();

    // Planning runs inside its own pool: one population chunk per thread, and no trips
    // through rayon's global injector.
    let threads = s
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let chunks = s.chunks.unwrap_or(threads);
    if threads == 0 || chunks == 0 {
        return Err(BenchError::Zero(if threads == 0 {
            "threads"
        } else {
            "chunks"
        }));
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let (times, iterations, candidates, cpu_share, cpu_seconds) =
        pool.install(|| -> Result<_, BenchError> {
            let mut planner = MpcPlanner::new(
                spec,
                preset.cem.clone(),
                preset.energy_weight,
                preset.sample_dynamics,
                s.seed,
            )?;
            for _ in 0..s.warmup {
                planner.plan(&obs, &dynamics, &regularizer, None, None);
            }
            let mut times = Vec::with_capacity(s.timed);
            let mut iterations = 0u64;
            let mut candidates = 0usize;
            let (cpu_before, wall_start) = (process_cpu_time(), Instant::now());
            for _ in 0..s.timed {
                let start = Instant::now();
                let outcome = planner.plan(&obs, &dynamics, &regularizer, None, None);
                times.push(start.elapsed());
                iterations += u64::from(outcome.iterations);
                candidates += preset.cem.candidates_scored(outcome.iterations as usize);
            }
            let wall = wall_start.elapsed().as_secs_f64() * threads as f64;
            let cpu_seconds = cpu_before
                .zip(process_cpu_time())
                .map(|(before, after)| after.saturating_sub(before).as_secs_f64());
            Ok((
                times,
                iterations,
                candidates,
                cpu_seconds.map(|c| c / wall),
                cpu_seconds,
            ))
        })?;
    let peak = peak.max(Peak::measure());
    let mut times = times;
    let min_ms = times.iter().min().map_or(0.0, |t| t.as_secs_f64() * 1e3);
    let median = median_ms(&mut times);

    let dynamics_sizes = dynamics.member(0).mlp().sizes().to_vec();
    let energy_sizes = match &regularizer {
        Regularizer::None => Vec::new(),
        Regularizer::Dae(m) => m.mlp().sizes().to_vec(),
        Regularizer::Deen(m) => m.mlp().sizes().to_vec(),
    };
    let cem = &preset.cem;
    let mean_iterations = iterations as f64 / s.timed as f64;
    let mean_candidates = candidates as f64 / s.timed as f64;
    let rows_per_call = mean_candidates * (cem.particles * cem.horizon) as f64;
    let flops = rows_per_call * (flops_per_row(&dynamics_sizes) + flops_per_row(&energy_sizes));
    Ok(PlanReport {
        task: s.task,
        regularizer: s.regularizer,
        members: dynamics.members(),
        dynamics_sizes,
        energy_sizes,
        optimizer: cem.optimizer,
        horizon: cem.horizon,
        population: cem.population,
        particles: cem.particles,
        threads,
        chunks,
        precision,
        calls: s.timed,
        mean_iterations,
        mean_candidates,
        median_ms: median,
        min_ms,
        gflops: flops / (median * 1e-3) / 1e9,
        best_gflops: flops / (min_ms * 1e-3) / 1e9,
        cpu_share,
        cpu_ms_per_call: cpu_seconds.map(|c| c * 1e3 / s.timed as f64),
        cpu_gflops: cpu_seconds
            .filter(|&c| c > 0.0)
            .map(|c| flops * s.timed as f64 / c / 1e9),
        peak,
    })
}

impl fmt::Display for PlanReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "bench plan: {} with regularizer {}",
            self.task, self.regularizer
        )?;
        writeln!(
            f,
            "  dynamics   {} × {} member(s)",
            describe(&self.dynamics_sizes),
            self.members
        )?;
        if !self.energy_sizes.is_empty() {
            writeln!(f, "  energy     {}", describe(&self.energy_sizes))?;
        }
        writeln!(
            f,
            "  {:<10} horizon {}, population {}, {} particle(s), {:.1} iterations and {:.0} \
             candidates per call",
            self.optimizer.to_string().to_uppercase(),
            self.horizon,
            self.population,
            self.particles,
            self.mean_iterations,
            self.mean_candidates
        )?;
        writeln!(
            f,
            "  parallel   {} thread(s), {} population chunk(s), {} inference",
            self.threads, self.chunks, self.precision
        )?;
        writeln!(
            f,
            "  per plan   {:.2} ms median, {:.2} ms best, over {} calls",
            self.median_ms, self.min_ms, self.calls
        )?;
        write!(
            f,
            "  throughput {:.1} GFLOP/s median, {:.1} GFLOP/s best (matrix products)",
            self.gflops, self.best_gflops
        )?;
        if let Some(share) = self.cpu_share {
            write!(
                f,
                "\n  CPU        the threads ran {:.0}% of the time{}",
                share * 100.0,
                if share < 0.95 {
                    " (other work shared the cores: times are pessimistic)"
                } else {
                    ""
                }
            )?;
        }
        let peak = self.peak.for_precision(self.precision);
        let all_cores = peak.map(|p| p * self.threads as f64);
        write!(
            f,
            "\n  peak       {}\n  of peak    {} best, {} median ({} thread(s) × the {} peak)",
            self.peak,
            percent(self.best_gflops, all_cores),
            percent(self.gflops, all_cores),
            self.threads,
            self.precision
        )?;
        if let Some(g) = self.cpu_gflops {
            write!(
                f,
                "; per CPU second {g:.1} GFLOP/s per core = {} of peak",
                percent(g, peak)
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_real_planning_calls() {
        let settings = Settings {
            task: Builtin::Cartpole,
            regularizer: RegularizerKind::Deen,
            timed: 2,
            warmup: 1,
            pets: false,
            threads: Some(2),
            chunks: None,
            precision: InferencePrecision::Bf16,
            seed: 1,
            optimizer: proto::Optimizer::Cem,
            population: None,
            elites: None,
            iterations: None,
        };
        let report = run(&settings).unwrap();
        assert_eq!(report.dynamics_sizes, vec![6, 200, 200, 200, 8]);
        assert_eq!(report.energy_sizes, vec![9, 200, 200, 200, 1]);
        assert_eq!(
            (
                report.population,
                report.horizon,
                report.particles,
                report.calls
            ),
            (400, 25, 1, 2)
        );
        assert!(report.mean_iterations >= 1.0 && report.mean_iterations <= 5.0);
        assert_eq!(report.mean_candidates, 400.0 * report.mean_iterations);
        let icem = run(&Settings {
            optimizer: proto::Optimizer::Icem,
            population: Some(100),
            elites: Some(10),
            iterations: Some(3),
            timed: 1,
            ..settings
        })
        .unwrap();
        assert_eq!(
            (icem.population, icem.optimizer),
            (100, proto::Optimizer::Icem)
        );
        assert!(icem.mean_candidates <= (100 + 80 + 64) as f64, "{icem:?}");
        assert!(icem.to_string().contains("ICEM"), "{icem}");
        assert!(report.median_ms > 0.0 && report.min_ms <= report.median_ms);
        assert!(report.gflops.is_finite() && report.gflops > 0.0);
        assert!(report.best_gflops >= report.gflops);
        assert!(report.cpu_share.is_none_or(|c| c > 0.0));
        assert!(report.cpu_gflops.is_none_or(|g| g.is_finite() && g > 0.0));
        assert_eq!(
            report.peak.bf16_gflops.is_some(),
            report.precision == InferencePrecision::Bf16
        );
        let text = report.to_string();
        assert!(
            text.contains("6→3×200→8")
                && text.contains("9→3×200→1")
                && text.contains("of peak")
                && !text.contains("PyTorch"),
            "{text}"
        );
    }
}
