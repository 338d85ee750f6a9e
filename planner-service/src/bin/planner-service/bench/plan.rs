//! `bench plan`: milliseconds per full MPC planning call and the matrix throughput achieved,
//! for the task's reward as builtin code, as the equivalent formula and as a reward model.
//!
//! With more than one reward (`--rewards builtin,expression,learned`) the planners take turns
//! call by call on the same models and observation, so that every reward's calls see the same
//! load on a shared machine; the report puts them side by side and states the formula's cost
//! on the planner's path as the difference from the builtin code.

use super::{BenchError, describe, flops_per_row, median_ms, preset, random_transitions};
use planner_service::dynamics::Ensemble;
use planner_service::energy::{Regularizer, RegularizerKind};
use planner_service::nn::KernelPath;
use planner_service::nn::cputime::process_cpu_time;
use planner_service::nn::kernel_path::Measurement;
use planner_service::nn::peak::{Peak, percent};
use planner_service::plan::{MpcPlanner, PlanRequest, default_chunks};
use planner_service::reward::RewardModel;
use proto::task::{RewardKind, SpecBounds};
use proto::{Builtin, InferencePrecision, Task};
use rand::SeedableRng;
use rand::rngs::StdRng;
use std::fmt;
use std::time::{Duration, Instant};

/// What `bench plan` was asked to do.
pub(super) struct Settings {
    pub task: Builtin,
    pub regularizer: RegularizerKind,
    /// The rewards to plan with, timed in turns (at least one).
    pub rewards: Vec<BenchReward>,
    pub timed: usize,
    pub warmup: usize,
    pub pets: bool,
    pub threads: Option<usize>,
    pub chunks: Option<usize>,
    /// Plan through the daemon's scheduler (a turn per call, no rival).
    pub shared: bool,
    pub precision: InferencePrecision,
    pub seed: u64,
    pub optimizer: proto::Optimizer,
    pub population: Option<usize>,
    pub elites: Option<usize>,
    pub iterations: Option<usize>,
    /// Agents planned per call (more than one: one by one and batched, in turns).
    pub agents: usize,
}

/// How the benchmarked task's reward is given to the planner.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum BenchReward {
    /// The catalog's Rust code.
    Builtin,
    /// The same reward written as a formula ([`Builtin::reward_formula`]).
    Expression,
    /// A reward model of the preset's sizes (untrained weights plan at the same cost).
    Learned,
}

impl fmt::Display for BenchReward {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            BenchReward::Builtin => "builtin",
            BenchReward::Expression => "expression",
            BenchReward::Learned => "learned",
        })
    }
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
    /// Whether the plans took turns through the daemon's scheduler.
    pub shared: bool,
    /// The number format inference actually ran in (the dynamics model's).
    pub precision: InferencePrecision,
    /// The number format asked for (`auto`: the kernel paths were chosen by measurement).
    pub asked: InferencePrecision,
    /// The kernel path each network ran: the dynamics model's, and the regulariser's.
    pub dynamics_path: KernelPath,
    pub energy_path: Option<KernelPath>,
    /// The kernel-path measurements this process made (each network shape's candidates).
    pub measurements: Vec<Measurement>,
    /// Planning calls timed per reward.
    pub calls: usize,
    /// Agents (observations) planned per call.
    pub agents: usize,
    /// One entry per reward asked for, in the order asked.
    pub rewards: Vec<RewardTiming>,
    /// Share of `threads × wall time` that this process's threads spent on a CPU during the
    /// timed calls (below ~0.95: other work took cores away and the times are pessimistic).
    /// `None` where the platform does not report it.
    pub cpu_share: Option<f64>,
    /// This core's peak, measured before and after the calls (the higher of the two).
    pub peak: Peak,
}

/// The planning calls of one reward (and, with several agents, one way of planning them).
#[derive(Clone, Debug, PartialEq)]
pub struct RewardTiming {
    pub reward: BenchReward,
    /// With several agents: whether each call planned them in one batch (else one by one).
    pub batched: Option<bool>,
    /// With several agents, for the batched calls: each call's one-by-one time over its
    /// batched time (the one-by-one call just before it), best and median.
    pub speedup: Option<(f64, f64)>,
    /// The formula, for [`BenchReward::Expression`].
    pub formula: Option<String>,
    /// The reward model's layer sizes, for [`BenchReward::Learned`].
    pub model_sizes: Vec<usize>,
    /// Mean iterations per call (early stopping may cut some).
    pub mean_iterations: f64,
    /// Mean candidate sequences scored per call (iCEM's population decays).
    pub mean_candidates: f64,
    pub median_ms: f64,
    pub min_ms: f64,
    /// Matrix-product GFLOP/s at the median call time (the reward model's included).
    pub gflops: f64,
    /// Matrix-product GFLOP/s at the best call time.
    pub best_gflops: f64,
    /// Matrix-product GFLOP/s per second of CPU time the threads received over this reward's
    /// calls: the rate while running, which other processes on the cores do not lower (time
    /// the pool's threads spend spinning for work counts against it).
    pub cpu_gflops: Option<f64>,
    /// Mean CPU time of one call, every thread's summed, in milliseconds. `None` where the
    /// platform does not report it.
    pub cpu_ms_per_call: Option<f64>,
}

impl Contender {
    /// Plans every agent's observation (batched or one by one); the iterations of each plan.
    fn plan_all(
        &mut self,
        observations: &[Vec<f32>],
        (dynamics, regularizer): (&Ensemble, &Regularizer),
        shared: Option<std::sync::Arc<dyn planner_service::sched::Preempt>>,
    ) -> Vec<u32> {
        let learned = planner_service::plan::Learned::reward(self.model.as_ref());
        if self.batched == Some(true) {
            let mut requests: Vec<PlanRequest<'_>> = self
                .planners
                .iter_mut()
                .zip(observations)
                .map(|(p, o)| PlanRequest::new(p, o, None))
                .collect();
            MpcPlanner::plan_batch(
                &mut requests,
                &mut self.workspace,
                (dynamics, regularizer, learned),
                shared,
            );
            requests.iter().map(|r| r.outcome().iterations).collect()
        } else {
            self.planners
                .iter_mut()
                .zip(observations)
                .map(|(p, o)| {
                    p.plan_shared(o, dynamics, regularizer, learned, None, shared.clone())
                        .iterations
                })
                .collect()
        }
    }
}

impl PlanReport {
    /// The timing of `reward`, if it was asked for.
    pub fn of(&self, reward: BenchReward) -> Option<&RewardTiming> {
        self.rewards.iter().find(|t| t.reward == reward)
    }

    /// The formula's cost on the planner's path: what the expression reward's calls took beyond
    /// the builtin code's, as a share of the expression's calls, at the best and at the median
    /// (`None` unless both were timed). Negative where the difference drowned in noise.
    pub fn expression_share(&self) -> Option<(f64, f64)> {
        let (b, e) = (
            self.of(BenchReward::Builtin)?,
            self.of(BenchReward::Expression)?,
        );
        Some((
            (e.min_ms - b.min_ms) / e.min_ms,
            (e.median_ms - b.median_ms) / e.median_ms,
        ))
    }

    /// [`PlanReport::expression_share`] of the mean CPU time per call.
    pub fn expression_cpu_share(&self) -> Option<f64> {
        let (b, e) = (
            self.of(BenchReward::Builtin)?.cpu_ms_per_call?,
            self.of(BenchReward::Expression)?.cpu_ms_per_call?,
        );
        Some((e - b) / e)
    }
}

/// One reward's planner and what it has measured so far.
struct Contender {
    reward: BenchReward,
    formula: Option<String>,
    model: Option<RewardModel>,
    /// One planner per agent, and whether a call plans them in one batch.
    planners: Vec<MpcPlanner>,
    batched: Option<bool>,
    workspace: planner_service::plan::Workspace,
    times: Vec<Duration>,
    iterations: u64,
    candidates: usize,
    cpu: Option<Duration>,
}

/// The benchmarked task with its reward given as `reward`.
fn task_with(task: Builtin, reward: BenchReward) -> Result<&'static Task, BenchError> {
    let kind = match reward {
        BenchReward::Builtin => return Ok(task.task()),
        BenchReward::Expression => RewardKind::Expression(
            task.reward_formula()
                .ok_or(BenchError::NoFormula(task))?
                .to_string(),
        ),
        BenchReward::Learned => RewardKind::Learned,
    };
    let mut spec = task.spec();
    spec.name = format!("{}-{reward}-reward", task.name());
    spec.reward = kind;
    Task::intern(spec, &SpecBounds::default()).map_err(|e| BenchError::Task(Box::new(e)))
}

pub(super) fn run(s: &Settings) -> Result<PlanReport, BenchError> {
    if s.timed == 0 {
        return Err(BenchError::Zero("iterations-to-time"));
    }
    if s.rewards.is_empty() {
        return Err(BenchError::Zero("rewards"));
    }
    if s.agents == 0 {
        return Err(BenchError::Zero("agents"));
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
    let dynamics_path = dynamics.member(0).mlp().kernel_path();
    let energy_path = match &regularizer {
        Regularizer::None => None,
        Regularizer::Dae(m) => Some(m.mlp().kernel_path()),
        Regularizer::Deen(m) => Some(m.mlp().kernel_path()),
    };
    let peak = Peak::measure();
    let observations: Vec<Vec<f32>> = (0..s.agents).map(|k| data.row(k).0.to_vec()).collect();

    // Planning runs inside its own pool, with the daemon's chunks per thread, and no trips
    // through rayon's global injector.
    let threads = s
        .threads
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    let chunks = s
        .chunks
        .unwrap_or_else(|| default_chunks(threads, preset.cem.population));
    if threads == 0 || chunks == 0 {
        return Err(BenchError::Zero(if threads == 0 {
            "threads"
        } else {
            "chunks"
        }));
    }
    let mut contenders = Vec::with_capacity(s.rewards.len());
    for &reward in &s.rewards {
        let task = task_with(s.task, reward)?;
        let model = task.reward_is_learned().then(|| {
            let mut model = RewardModel::new(task, &preset.reward, &preset.dynamics, &mut rng);
            model.fit(&data, 1, &mut rng);
            model.set_inference_precision(s.precision);
            model
        });
        let modes: &[Option<bool>] = if s.agents > 1 {
            &[Some(false), Some(true)]
        } else {
            &[None]
        };
        for &batched in modes {
            let planners = (0..s.agents as u64)
                .map(|k| {
                    MpcPlanner::with_chunks(
                        task,
                        preset.cem.clone(),
                        preset.energy_weight,
                        preset.sample_dynamics,
                        s.seed + k,
                        chunks,
                    )
                })
                .collect::<Result<Vec<_>, _>>()?;
            contenders.push(Contender {
                reward,
                formula: (reward == BenchReward::Expression)
                    .then(|| s.task.reward_formula().map(str::to_string))
                    .flatten(),
                model: model.clone(),
                planners,
                batched,
                workspace: planner_service::plan::Workspace::new(),
                times: Vec::with_capacity(s.timed),
                iterations: 0,
                candidates: 0,
                cpu: Some(Duration::ZERO),
            });
        }
    }
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()?;
    let scheduler = std::sync::Arc::new(planner_service::sched::Scheduler::new(0.0));
    let turn = || -> Option<std::sync::Arc<dyn planner_service::sched::Preempt>> {
        s.shared.then(|| {
            let turn = scheduler.turn(None, None, &planner_service::sched::Waiting::default());
            std::sync::Arc::new(turn) as std::sync::Arc<dyn planner_service::sched::Preempt>
        })
    };
    let (cpu_share, contenders) = pool.install(|| {
        for c in &mut contenders {
            for _ in 0..s.warmup {
                c.plan_all(&observations, (&dynamics, &regularizer), turn());
            }
        }
        let (cpu_before, wall_start) = (process_cpu_time(), Instant::now());
        // In turns, call by call: every reward (and way of planning) sees the same load.
        for _ in 0..s.timed {
            for c in &mut contenders {
                let shared = turn();
                let cpu_start = process_cpu_time();
                let start = Instant::now();
                let iterations = c.plan_all(&observations, (&dynamics, &regularizer), shared);
                c.times.push(start.elapsed());
                c.cpu = c
                    .cpu
                    .zip(cpu_start.zip(process_cpu_time()))
                    .map(|(sum, (before, after))| sum + after.saturating_sub(before));
                for i in iterations {
                    c.iterations += u64::from(i);
                    c.candidates += preset.cem.candidates_scored(i as usize);
                }
            }
        }
        let wall = wall_start.elapsed().as_secs_f64() * threads as f64;
        let cpu_share = cpu_before
            .zip(process_cpu_time())
            .map(|(before, after)| after.saturating_sub(before).as_secs_f64() / wall);
        (cpu_share, contenders)
    });
    let peak = peak.max(Peak::measure());

    let dynamics_sizes = dynamics.member(0).mlp().sizes().to_vec();
    let energy_sizes = match &regularizer {
        Regularizer::None => Vec::new(),
        Regularizer::Dae(m) => m.mlp().sizes().to_vec(),
        Regularizer::Deen(m) => m.mlp().sizes().to_vec(),
    };
    let cem = &preset.cem;
    // Each batched call against the one-by-one call of the same reward just before it.
    let speedups: Vec<Option<(f64, f64)>> = contenders
        .iter()
        .enumerate()
        .map(|(i, c)| {
            let alone = contenders[..i]
                .iter()
                .rfind(|o| o.reward == c.reward && o.batched == Some(false))
                .filter(|_| c.batched == Some(true))?;
            let mut ratios: Vec<f64> = alone
                .times
                .iter()
                .zip(&c.times)
                .map(|(a, b)| a.as_secs_f64() / b.as_secs_f64())
                .collect();
            ratios.sort_by(f64::total_cmp);
            let best = *ratios.last()?;
            let n = ratios.len();
            let median = if n % 2 == 1 {
                ratios[n / 2]
            } else {
                (ratios[n / 2 - 1] + ratios[n / 2]) / 2.0
            };
            Some((best, median))
        })
        .collect();
    let rewards = contenders
        .into_iter()
        .zip(speedups)
        .map(|(mut c, speedup)| {
            let model_sizes = c
                .model
                .as_ref()
                .map_or(Vec::new(), |m| m.mlp().sizes().to_vec());
            let min_ms = c.times.iter().min().map_or(0.0, |t| t.as_secs_f64() * 1e3);
            let median = median_ms(&mut c.times);
            let mean_iterations = c.iterations as f64 / s.timed as f64;
            let mean_candidates = c.candidates as f64 / s.timed as f64;
            let rows_per_call = mean_candidates * (cem.particles * cem.horizon) as f64;
            let flops = rows_per_call
                * (flops_per_row(&dynamics_sizes)
                    + flops_per_row(&energy_sizes)
                    + flops_per_row(&model_sizes));
            let cpu_seconds = c.cpu.map(|d| d.as_secs_f64());
            RewardTiming {
                reward: c.reward,
                batched: c.batched,
                speedup,
                formula: c.formula,
                model_sizes,
                mean_iterations,
                mean_candidates,
                median_ms: median,
                min_ms,
                gflops: flops / (median * 1e-3) / 1e9,
                best_gflops: flops / (min_ms * 1e-3) / 1e9,
                cpu_ms_per_call: cpu_seconds.map(|c| c * 1e3 / s.timed as f64),
                cpu_gflops: cpu_seconds
                    .filter(|&c| c > 0.0)
                    .map(|c| flops * s.timed as f64 / c / 1e9),
            }
        })
        .collect();
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
        shared: s.shared,
        precision,
        asked: s.precision,
        dynamics_path,
        energy_path,
        measurements: planner_service::nn::kernel_path::measurements(),
        calls: s.timed,
        agents: s.agents,
        rewards,
        cpu_share,
        peak,
    })
}

impl fmt::Display for PlanReport {
    fn fmt(&self, out: &mut fmt::Formatter<'_>) -> fmt::Result {
        // Written line by line, printed without the last line's end.
        let mut text = String::new();
        let f = &mut text;
        use std::fmt::Write;
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
            "  {:<10} horizon {}, population {}, {} particle(s)",
            self.optimizer.to_string().to_uppercase(),
            self.horizon,
            self.population,
            self.particles,
        )?;
        writeln!(
            f,
            "  parallel   {} thread(s), {} population chunk(s), {} inference (asked: {}){}",
            self.threads,
            self.chunks,
            self.precision,
            self.asked,
            if self.shared {
                ", shared through the scheduler"
            } else {
                ""
            }
        )?;
        write!(f, "  kernels    dynamics {}", self.dynamics_path)?;
        if let Some(p) = self.energy_path {
            write!(f, ", energy {p}")?;
        }
        writeln!(f)?;
        for m in &self.measurements {
            writeln!(
                f,
                "    measured {}: {} per forward of {} samples (best)",
                describe(&m.sizes),
                m.timings
                    .iter()
                    .map(|t| format!("{} {:.1} µs", t.path, t.seconds * 1e6))
                    .collect::<Vec<_>>()
                    .join(", "),
                planner_service::nn::kernel_path::BATCH
            )?;
        }
        if let Some(share) = self.cpu_share {
            writeln!(
                f,
                "  CPU        the threads ran {:.0}% of the time{}",
                share * 100.0,
                if share < 0.95 {
                    " (other work shared the cores: times are pessimistic)"
                } else {
                    ""
                }
            )?;
        }
        let peak = self.peak.for_path(self.dynamics_path);
        let all_cores = peak.map(|p| p * self.threads as f64);
        writeln!(f, "  peak       {}", self.peak)?;
        for t in &self.rewards {
            write!(f, "  reward     {}", t.reward)?;
            if let Some(formula) = &t.formula {
                write!(f, " `{formula}`")?;
            }
            if !t.model_sizes.is_empty() {
                write!(f, " (reward model {})", describe(&t.model_sizes))?;
            }
            match t.batched {
                Some(true) => write!(f, ", {} agents batched in one solve", self.agents)?,
                Some(false) => write!(f, ", {} agents planned one by one", self.agents)?,
                None => {}
            }
            writeln!(
                f,
                "\n    per call   {:.2} ms median, {:.2} ms best, over {} calls ({:.1} iterations and \
                 {:.0} candidates per call)",
                t.median_ms, t.min_ms, self.calls, t.mean_iterations, t.mean_candidates
            )?;
            if let Some(cpu) = t.cpu_ms_per_call {
                writeln!(f, "    CPU        {cpu:.2} ms per call, every thread's")?;
            }
            if let Some((best, median)) = t.speedup {
                writeln!(
                    f,
                    "    batched    one by one / batched: x{best:.2} best, x{median:.2} median \
                     over {} paired calls",
                    self.calls
                )?;
            }
            write!(
                f,
                "    throughput {:.1} GFLOP/s median, {:.1} GFLOP/s best (matrix products) = \
                 {} best, {} median of {} thread(s) × the {} peak",
                t.gflops,
                t.best_gflops,
                percent(t.best_gflops, all_cores),
                percent(t.gflops, all_cores),
                self.threads,
                self.dynamics_path
            )?;
            if let Some(g) = t.cpu_gflops {
                write!(
                    f,
                    "; per CPU second {g:.1} GFLOP/s per core = {} of peak",
                    percent(g, peak)
                )?;
            }
            writeln!(f)?;
        }
        if let Some((best, median)) = self.expression_share() {
            write!(
                f,
                "  formula    expression − builtin: {:+.2} % (best), {:+.2} % (median) of the \
                 expression's wall time per plan",
                best * 100.0,
                median * 100.0
            )?;
            if let Some(cpu) = self.expression_cpu_share() {
                write!(f, ", {:+.2} % of its CPU time per plan", cpu * 100.0)?;
            }
            writeln!(f, " (a cost below the noise can come out negative)")?;
        }
        out.write_str(text.trim_end())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings() -> Settings {
        Settings {
            task: Builtin::Cartpole,
            regularizer: RegularizerKind::Deen,
            rewards: vec![BenchReward::Builtin],
            timed: 2,
            warmup: 1,
            pets: false,
            threads: Some(2),
            chunks: None,
            shared: false,
            precision: InferencePrecision::Bf16,
            seed: 1,
            optimizer: proto::Optimizer::Cem,
            population: None,
            elites: None,
            iterations: None,
            agents: 1,
        }
    }

    #[test]
    fn several_agents_are_timed_one_by_one_and_batched_in_turns() {
        let report = run(&Settings {
            agents: 3,
            shared: true,
            ..settings()
        })
        .unwrap();
        let [alone, batched] = &report.rewards[..] else {
            panic!("one reward, two ways: {:?}", report.rewards)
        };
        assert_eq!((alone.batched, batched.batched), (Some(false), Some(true)));
        assert!(alone.speedup.is_none(), "{alone:?}");
        let (best, median) = batched.speedup.expect("paired with the one-by-one calls");
        assert!(best >= median && median > 0.0, "{batched:?}");
        // The same agents' plans, seed for seed: the same iterations and candidates.
        assert_eq!(alone.mean_candidates, batched.mean_candidates);
        assert_eq!(alone.mean_iterations, batched.mean_iterations);
        assert!(report.to_string().contains("3 agents batched in one solve"));
    }

    #[test]
    fn plans_through_the_scheduler_as_the_daemon_does() {
        let report = run(&Settings {
            shared: true,
            ..settings()
        })
        .unwrap();
        assert!(report.shared);
        let [timing] = &report.rewards[..] else {
            panic!("one reward asked for")
        };
        assert!(timing.min_ms > 0.0 && timing.median_ms >= timing.min_ms);
        assert!(timing.mean_iterations >= 1.0, "{timing:?}");
        assert!(
            report.to_string().contains("shared through the scheduler"),
            "{report}"
        );
    }

    #[test]
    fn times_real_planning_calls() {
        let report = run(&settings()).unwrap();
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
        let [timing] = &report.rewards[..] else {
            panic!("one reward: {report:?}")
        };
        assert_eq!(timing.reward, BenchReward::Builtin);
        assert!(timing.mean_iterations >= 1.0 && timing.mean_iterations <= 5.0);
        assert_eq!(timing.mean_candidates, 400.0 * timing.mean_iterations);
        assert_eq!(report.expression_share(), None);
        let icem = run(&Settings {
            optimizer: proto::Optimizer::Icem,
            population: Some(100),
            elites: Some(10),
            iterations: Some(3),
            timed: 1,
            ..settings()
        })
        .unwrap();
        assert_eq!(
            (icem.population, icem.optimizer),
            (100, proto::Optimizer::Icem)
        );
        assert!(
            icem.rewards[0].mean_candidates <= (100 + 80 + 64) as f64,
            "{icem:?}"
        );
        assert!(icem.to_string().contains("ICEM"), "{icem}");
        assert!(timing.median_ms > 0.0 && timing.min_ms <= timing.median_ms);
        assert!(timing.gflops.is_finite() && timing.gflops > 0.0);
        assert!(timing.best_gflops >= timing.gflops);
        assert!(report.cpu_share.is_none_or(|c| c > 0.0));
        assert!(timing.cpu_gflops.is_none_or(|g| g.is_finite() && g > 0.0));
        assert_eq!(
            report.peak.bf16_gflops.is_some(),
            planner_service::nn::simd::bf16_dot_available() && report.peak.f32_gflops.is_some()
        );
        assert_eq!(report.precision, report.dynamics_path.precision());
        assert!(text_has_paths(&report.to_string(), &report));
        let text = report.to_string();
        assert!(
            text.contains("6→3×200→8")
                && text.contains("9→3×200→1")
                && text.contains("of peak")
                && !text.contains("formula")
                && !text.contains("PyTorch"),
            "{text}"
        );
    }

    /// The three ways of giving the reward plan side by side on the same models; the formula
    /// is the builtin reward's, the reward model has the preset's sizes, and its products
    /// count in the throughput.
    fn text_has_paths(text: &str, report: &PlanReport) -> bool {
        text.contains(&format!("kernels    dynamics {}", report.dynamics_path))
    }

    #[test]
    fn times_each_reward_in_turns() {
        let report = run(&Settings {
            task: Builtin::HalfCheetah,
            regularizer: RegularizerKind::None,
            rewards: vec![
                BenchReward::Builtin,
                BenchReward::Expression,
                BenchReward::Learned,
            ],
            timed: 2,
            population: Some(40),
            elites: Some(4),
            iterations: Some(2),
            ..settings()
        })
        .unwrap();
        let kinds: Vec<_> = report.rewards.iter().map(|t| t.reward).collect();
        assert_eq!(
            kinds,
            [
                BenchReward::Builtin,
                BenchReward::Expression,
                BenchReward::Learned
            ]
        );
        let expression = report.of(BenchReward::Expression).unwrap();
        assert_eq!(
            expression.formula.as_deref(),
            Some("s_next[0] - 0.1*dot(a, a)")
        );
        // Half-cheetah's state features are 18 wide: [features(s), a, features(s')].
        let learned = report.of(BenchReward::Learned).unwrap();
        assert_eq!(learned.model_sizes, vec![18 + 6 + 18, 200, 200, 1]);
        let builtin = report.of(BenchReward::Builtin).unwrap();
        assert!(builtin.model_sizes.is_empty() && builtin.formula.is_none());
        for t in &report.rewards {
            assert_eq!(t.mean_candidates, 40.0 * t.mean_iterations, "{t:?}");
            assert!(t.min_ms > 0.0 && t.min_ms <= t.median_ms, "{t:?}");
        }
        // The reward model's products are counted beside the dynamics'.
        let per_candidate = |t: &RewardTiming| t.gflops * t.median_ms / t.mean_candidates;
        let dynamics = flops_per_row(&report.dynamics_sizes);
        let ratio = per_candidate(learned) / per_candidate(builtin);
        let want = (dynamics + flops_per_row(&learned.model_sizes)) / dynamics;
        assert!((ratio - want).abs() < 1e-9, "{ratio} vs {want}");
        let (best, median) = report.expression_share().unwrap();
        assert!(best.is_finite() && median.is_finite() && best < 1.0 && median < 1.0);
        let text = report.to_string();
        assert!(
            text.contains("reward     expression `s_next[0] - 0.1*dot(a, a)`")
                && text.contains("reward model 42→2×200→1")
                && text.contains("expression − builtin: "),
            "{text}"
        );

        let reacher = run(&Settings {
            task: Builtin::Reacher3d,
            rewards: vec![BenchReward::Expression],
            ..settings()
        });
        assert!(
            matches!(reacher, Err(BenchError::NoFormula(Builtin::Reacher3d))),
            "{reacher:?}"
        );
        let none = run(&Settings {
            rewards: Vec::new(),
            ..settings()
        });
        assert!(matches!(none, Err(BenchError::Zero("rewards"))));
    }
}
