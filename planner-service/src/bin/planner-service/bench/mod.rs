//! `planner-service bench plan|train|kernel|expression`: how fast the planner plans and the
//! models train, with networks of a task preset's sizes (the paper's Table 2), how fast the
//! matrix kernels underneath run on those networks' layer shapes, and what a reward written as
//! a formula costs next to a plan.
//!
//! The models are fitted briefly on random transitions: the weights only need to be realistic
//! numbers, since the cost of a planning call does not depend on what the networks learned.
//! Timings are medians over repeated calls after a warm-up. Throughput counts `2·in·out`
//! floating-point operations per linear layer per row (the matrix products; activations and
//! the per-row reward are extra work not counted).

mod expression;
mod kernel;
mod plan;
mod timing;
mod train;

pub use expression::ExpressionReport;
pub use kernel::KernelReport;
pub use plan::{BenchReward, PlanReport};
pub use train::TrainReport;

use planner_service::config::{Preset, PresetError};
use planner_service::data::Transitions;
use planner_service::energy::RegularizerKind;
use planner_service::plan::ConfigError;
use proto::{Builtin, InferencePrecision};
use rand::RngExt;
use rand::rngs::StdRng;
use std::fmt;
use std::time::Duration;

/// The benchmarks.
#[derive(clap::Subcommand, Clone, Debug, PartialEq)]
pub enum BenchCommand {
    /// Time full MPC planning calls (all CEM iterations) from one observation, with the task's
    /// reward given one or more ways (timed in turns, call by call, and put side by side).
    Plan {
        /// Task whose preset sizes the networks and the CEM search.
        #[arg(long, default_value = "cartpole")]
        task: Builtin,
        /// The task's reward as builtin (its Rust code), expression (the same reward written
        /// as a formula; every task but reacher3d) or learned (a reward model of the preset's
        /// sizes), comma-separated: e.g. `builtin,expression,learned`.
        #[arg(long, value_delimiter = ',', default_value = "builtin")]
        rewards: Vec<BenchReward>,
        /// Regulariser in the objective: none, dae or deen (sizes from the preset).
        #[arg(long, default_value = "none")]
        regularizer: RegularizerKind,
        /// Planning calls to time, after the warm-up.
        #[arg(long, default_value_t = 20)]
        iterations_to_time: usize,
        /// Untimed planning calls first (allocating the scratch, waking the threads).
        #[arg(long, default_value_t = 3)]
        warmup: usize,
        /// PETS instead of the paper's single model: a 5-member ensemble, 20 sampled particles.
        #[arg(long)]
        pets: bool,
        /// Threads; default: every core.
        #[arg(long)]
        threads: Option<usize>,
        /// Population chunks planned in parallel; default: the daemon's, two per thread from 4
        /// threads up where each keeps at least 12 candidates, else one per thread.
        #[arg(long)]
        chunks: Option<usize>,
        /// Plan as the daemon does, on cores shared through its scheduler (each call takes a
        /// turn; with no rival plan, nothing pauses it): times the scheduler's checks between
        /// iterations and imagined steps along with the plan.
        #[arg(long)]
        shared: bool,
        /// Number format of inference: auto (the service's default: every kernel path this
        /// CPU has is timed on each network's layers and the fastest runs), bf16 (the faster
        /// bf16 path; f32 where the CPU lacks AVX-512 BF16) or f32.
        #[arg(long, default_value = "auto")]
        precision: InferencePrecision,
        /// Seed of the random transitions the models are fitted on and of the planner.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Planning optimiser: cem (the preset's, Table 2) or icem (default iCEM parameters,
        /// the preset's population, elites and iterations).
        #[arg(long, default_value = "cem")]
        optimizer: proto::Optimizer,
        /// Candidates per iteration instead of the preset's (e.g. a smaller iCEM population).
        #[arg(long)]
        population: Option<usize>,
        /// Elites instead of the preset's.
        #[arg(long)]
        elites: Option<usize>,
        /// Maximum iterations per plan instead of the preset's.
        #[arg(long)]
        iterations: Option<usize>,
        /// Agents of one run, each with its own observation and planner: with more than one,
        /// each timed call plans every agent's observation, one by one and (in turns with it)
        /// batched in one solve, as the daemon plans a vector environment's copies.
        #[arg(long, default_value_t = 1)]
        agents: usize,
    },
    /// Time single training steps (one minibatch of the preset's batch size) of the dynamics
    /// model and of DEEN.
    Train {
        /// Task whose preset sizes the networks and the minibatches.
        #[arg(long, default_value = "cartpole")]
        task: Builtin,
        /// Training steps to time for each model, after the warm-up.
        #[arg(long, default_value_t = 50)]
        steps: usize,
        /// Untimed steps first.
        #[arg(long, default_value_t = 5)]
        warmup: usize,
        /// Seed of the random transitions, the minibatches and the weights.
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Time the matrix kernels alone on one thread: each hidden-layer shape of the planner's
    /// networks through the general kernel plus an activation pass, the packed f32 kernel and
    /// the packed bf16 kernel (both with the activation fused); dense training products
    /// against the gemm crate; the weight-gradient transpose.
    Kernel {
        /// Milliseconds each timed batch of calls should last (the calls per batch follow from
        /// one untimed call); every figure is the best and the median of 15 such batches.
        #[arg(long, default_value_t = 20)]
        batch_ms: u64,
        /// Seed of the random matrices.
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Time a reward formula (`proto::task::expression`) on one planning iteration's rows of
    /// the task's preset (population × horizon × particles), with and without its gradient,
    /// beside full planning calls of that preset, and print the formula's share of a plan.
    Expression {
        /// Task whose dimensions the formula reads and whose preset sizes the plan.
        #[arg(long, default_value = "halfcheetah")]
        task: Builtin,
        /// The reward formula; the default is half-cheetah's reward written as one.
        #[arg(long, default_value = "s_next[0] - 0.1*dot(a, a)")]
        expression: String,
        /// Milliseconds each timed batch of evaluations should last; every figure is the best
        /// and the median of 15 such batches.
        #[arg(long, default_value_t = 20)]
        batch_ms: u64,
        /// Planning calls to time, after two untimed ones.
        #[arg(long, default_value_t = 10)]
        plans: usize,
        /// Seed of the random inputs, the models' training data and the planner.
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
}

/// What a benchmark measured; `Display` prints it for people.
#[derive(Clone, Debug, PartialEq)]
pub enum BenchReport {
    Plan(PlanReport),
    Train(TrainReport),
    Kernel(KernelReport),
    Expression(ExpressionReport),
}

impl fmt::Display for BenchReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            BenchReport::Plan(r) => r.fmt(f),
            BenchReport::Train(r) => r.fmt(f),
            BenchReport::Kernel(r) => r.fmt(f),
            BenchReport::Expression(r) => r.fmt(f),
        }
    }
}

/// Why a benchmark could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    #[error(transparent)]
    Preset(#[from] PresetError),
    #[error(transparent)]
    Planner(#[from] ConfigError),
    #[error("cannot start a thread pool: {0}")]
    Threads(#[from] rayon::ThreadPoolBuildError),
    #[error("{0} must be at least 1")]
    Zero(&'static str),
    #[error("the formula: {0}")]
    Expression(Box<proto::task::expression::ExpressionError>),
    #[error("{0}'s reward has no formula to compare (`--rewards builtin,learned` works)")]
    NoFormula(Builtin),
    #[error(transparent)]
    Task(Box<proto::task::TaskError>),
}

/// Runs one benchmark.
pub fn run(cmd: &BenchCommand) -> Result<BenchReport, BenchError> {
    match *cmd {
        BenchCommand::Plan {
            task,
            ref rewards,
            regularizer,
            iterations_to_time,
            warmup,
            pets,
            threads,
            chunks,
            shared,
            precision,
            seed,
            optimizer,
            population,
            elites,
            iterations,
            agents,
        } => {
            let settings = plan::Settings {
                agents,
                optimizer,
                population,
                elites,
                iterations,
                task,
                regularizer,
                rewards: rewards.clone(),
                timed: iterations_to_time,
                warmup,
                pets,
                threads,
                chunks,
                shared,
                precision,
                seed,
            };
            plan::run(&settings).map(BenchReport::Plan)
        }
        BenchCommand::Train {
            task,
            steps,
            warmup,
            seed,
        } => train::run(task, steps, warmup, seed).map(BenchReport::Train),
        BenchCommand::Kernel { batch_ms, seed } => {
            let settings = kernel::Settings {
                layers: kernel::PLANNER_LAYERS.to_vec(),
                first_layers: kernel::FIRST_LAYERS.to_vec(),
                products: kernel::PRODUCTS.to_vec(),
                transposes: kernel::TRANSPOSES.to_vec(),
                batch: Duration::from_millis(batch_ms),
                seed,
            };
            kernel::run(&settings).map(BenchReport::Kernel)
        }
        BenchCommand::Expression {
            task,
            ref expression,
            batch_ms,
            plans,
            seed,
        } => expression::run(&expression::Settings {
            task,
            source: expression.clone(),
            batch: Duration::from_millis(batch_ms),
            plans,
            seed,
        })
        .map(BenchReport::Expression),
    }
}

/// The preset of `task` for the paper's method with `regularizer` (PETS' ensemble if `pets`).
fn preset(task: Builtin, regularizer: RegularizerKind, pets: bool) -> Result<Preset, PresetError> {
    let method = match (pets, regularizer) {
        (false, RegularizerKind::None) => "cem",
        (false, RegularizerKind::Dae) => "cem+dae",
        (false, RegularizerKind::Deen) => "cem+deen",
        (true, _) => "pets",
    };
    let mut preset = Preset::new(task.task(), Some(method))?;
    preset.regularizer = regularizer;
    Ok(preset)
}

/// `n` transitions with observations and next observations drawn around the origin and
/// uniformly random actions: enough to give the networks' normalisers and weights
/// realistic values.
fn random_transitions(task: Builtin, n: usize, rng: &mut StdRng) -> Transitions {
    let spec = task.task();
    let mut data = Transitions::new(spec.obs_dim, spec.act_dim);
    let mut obs = vec![0.0; spec.obs_dim];
    let mut act = vec![0.0; spec.act_dim];
    let mut next = vec![0.0; spec.obs_dim];
    for _ in 0..n {
        for o in &mut obs {
            *o = rng.random_range(-1.0..1.0);
        }
        for (d, a) in act.iter_mut().enumerate() {
            *a = rng.random_range(spec.action_low[d]..spec.action_high[d]);
        }
        for (n, o) in next.iter_mut().zip(&obs) {
            *n = o + rng.random_range(-0.1..0.1);
        }
        data.push(&obs, &act, 0.0, &next);
    }
    data
}

/// Floating-point operations of one row through an MLP with these layer sizes: `2·in·out`
/// per linear layer.
fn flops_per_row(sizes: &[usize]) -> f64 {
    sizes
        .windows(2)
        .map(|w| 2.0 * w[0] as f64 * w[1] as f64)
        .sum()
}

/// The median of some durations, in milliseconds.
fn median_ms(times: &mut [Duration]) -> f64 {
    times.sort_unstable();
    let n = times.len();
    let mid = if n % 2 == 1 {
        times[n / 2]
    } else {
        (times[n / 2 - 1] + times[n / 2]) / 2
    };
    mid.as_secs_f64() * 1e3
}

/// `[in, hidden × layers, out]` as `in-h×l-out` for reports.
fn describe(sizes: &[usize]) -> String {
    let hidden = &sizes[1..sizes.len() - 1];
    match hidden.first() {
        Some(h) if hidden.iter().all(|x| x == h) => {
            format!(
                "{}→{}×{}→{}",
                sizes[0],
                hidden.len(),
                h,
                sizes[sizes.len() - 1]
            )
        }
        _ => sizes
            .iter()
            .map(|s| s.to_string())
            .collect::<Vec<_>>()
            .join("→"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(subcommand)]
        bench: BenchCommand,
    }

    #[test]
    fn parses_the_command_line() {
        let cli = Cli::try_parse_from([
            "bench",
            "plan",
            "--task",
            "halfcheetah",
            "--regularizer",
            "deen",
            "--iterations-to-time",
            "7",
            "--precision",
            "f32",
        ])
        .unwrap();
        assert_eq!(
            cli.bench,
            BenchCommand::Plan {
                task: Builtin::HalfCheetah,
                rewards: vec![BenchReward::Builtin],
                regularizer: RegularizerKind::Deen,
                iterations_to_time: 7,
                warmup: 3,
                pets: false,
                threads: None,
                chunks: None,
                shared: false,
                precision: InferencePrecision::F32,
                seed: 0,
                optimizer: proto::Optimizer::Cem,
                population: None,
                elites: None,
                iterations: None,
                agents: 1,
            }
        );
        assert!(Cli::try_parse_from(["bench", "plan", "--task", "walker"]).is_err());
        let all = Cli::try_parse_from(["bench", "plan", "--rewards", "builtin,expression,learned"]);
        assert!(matches!(
            all.unwrap().bench,
            BenchCommand::Plan { rewards, .. } if rewards
                == [BenchReward::Builtin, BenchReward::Expression, BenchReward::Learned]
        ));
        assert!(Cli::try_parse_from(["bench", "plan", "--rewards", "oracle"]).is_err());
        let train = Cli::try_parse_from(["bench", "train", "--task", "ant"]).unwrap();
        assert!(matches!(
            train.bench,
            BenchCommand::Train {
                task: Builtin::Ant,
                steps: 50,
                ..
            }
        ));
        let kernel = Cli::try_parse_from(["bench", "kernel", "--batch-ms", "5"]).unwrap();
        assert_eq!(
            kernel.bench,
            BenchCommand::Kernel {
                batch_ms: 5,
                seed: 0
            }
        );
        let kernel = Cli::try_parse_from(["bench", "kernel"]).unwrap();
        assert_eq!(
            kernel.bench,
            BenchCommand::Kernel {
                batch_ms: 20,
                seed: 0
            }
        );
        assert!(Cli::try_parse_from(["bench", "kernel", "--batch-ms", "-1"]).is_err());
        let expression = Cli::try_parse_from(["bench", "expression", "--expression", "a[0]"]);
        assert_eq!(
            expression.unwrap().bench,
            BenchCommand::Expression {
                task: Builtin::HalfCheetah,
                expression: "a[0]".into(),
                batch_ms: 20,
                plans: 10,
                seed: 0
            }
        );
    }

    #[test]
    fn counts_two_flops_per_weight() {
        assert_eq!(flops_per_row(&[3, 4, 2]), 2.0 * (12.0 + 8.0));
        assert_eq!(describe(&[23, 200, 200, 200, 8]), "23→3×200→8");
        assert_eq!(describe(&[5, 7, 9, 1]), "5→7→9→1");
    }

    #[test]
    fn medians() {
        let ms = Duration::from_millis;
        assert_eq!(median_ms(&mut [ms(5), ms(1), ms(3)]), 3.0);
        assert_eq!(median_ms(&mut [ms(4), ms(1), ms(2), ms(3)]), 2.5);
    }
}
