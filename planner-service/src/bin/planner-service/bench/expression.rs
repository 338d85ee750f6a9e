//! `bench expression`: what a reward written as a formula costs next to the plan it serves.
//!
//! A planning call evaluates the reward once per imagined step of every candidate, i.e. for
//! `population × horizon × particles` rows per iteration. This times the formula on that
//! many rows (values alone, and values with the gradient Adam needs) on one thread, then times
//! full planning calls of the task's preset, and puts the formula's cost per plan
//! (iterations × one evaluation) beside the plan's time. The comparison is conservative: the
//! formula is timed on one thread while the plan uses every core, and the planner splits its
//! reward evaluations across them too.

use super::BenchError;
use super::plan::{self, BenchReward, PlanReport, RewardTiming};
use super::timing::{Clock, Timing, measure_for};
use planner_service::energy::RegularizerKind;
use proto::task::expression::{Dims, Expression, ExpressionError, Gradients, Inputs};
use proto::{Builtin, InferencePrecision};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::fmt;
use std::time::Duration;

/// What `bench expression` was asked to do.
pub(super) struct Settings {
    pub task: Builtin,
    pub source: String,
    pub batch: Duration,
    pub plans: usize,
    pub seed: u64,
}

/// The formula's cost and the plan's.
#[derive(Clone, Debug, PartialEq)]
pub struct ExpressionReport {
    pub source: String,
    /// Scalar operations per row after compilation.
    pub operations: usize,
    /// Rows per evaluation: one iteration's rewards.
    pub rows: usize,
    /// One evaluation of `rows` rows, one thread, CPU time.
    pub eval: Timing,
    /// One evaluation with the gradient, one thread, CPU time.
    pub gradient: Timing,
    pub plan: PlanReport,
}

pub(super) fn run(s: &Settings) -> Result<ExpressionReport, BenchError> {
    if s.plans == 0 {
        return Err(BenchError::Zero("plans"));
    }
    let spec = s.task.task();
    let dims = Dims {
        obs_dim: spec.obs_dim,
        act_dim: spec.act_dim,
    };
    let expression = Expression::parse(&s.source, dims)?;
    let plan = plan::run(&plan::Settings {
        task: s.task,
        regularizer: RegularizerKind::None,
        rewards: vec![BenchReward::Builtin],
        timed: s.plans,
        warmup: 2,
        pets: false,
        threads: None,
        chunks: None,
        shared: false,
        precision: InferencePrecision::Bf16,
        seed: s.seed,
        optimizer: proto::Optimizer::Cem,
        population: None,
        elites: None,
        iterations: None,
    })?;
    let rows = plan.population * plan.horizon * plan.particles;

    let mut rng = StdRng::seed_from_u64(s.seed);
    let mut draw = |n: usize| -> Vec<f32> { (0..n).map(|_| rng.random_range(-1.0..1.0)).collect() };
    let (states, actions, next) = (
        draw(rows * dims.obs_dim),
        draw(rows * dims.act_dim),
        draw(rows * dims.obs_dim),
    );
    let inputs = Inputs {
        s: &states,
        a: &actions,
        s_next: &next,
    };
    let mut out = vec![0.0; rows];
    let mut scratch = expression.scratch();
    let eval = measure_for(Clock::Thread, s.batch, || {
        expression.eval_batch(inputs, &mut out, &mut scratch);
        std::hint::black_box(&out);
    });
    let (mut ds, mut da, mut dn) = (
        vec![0.0; states.len()],
        vec![0.0; actions.len()],
        vec![0.0; next.len()],
    );
    let gradient = measure_for(Clock::Thread, s.batch, || {
        let grads = Gradients {
            s: &mut ds,
            a: &mut da,
            s_next: &mut dn,
        };
        expression.eval_grad(inputs, &mut out, grads, &mut scratch);
        std::hint::black_box(&out);
    });
    Ok(ExpressionReport {
        source: s.source.clone(),
        operations: expression.operations(),
        rows,
        eval,
        gradient,
        plan,
    })
}

impl From<ExpressionError> for BenchError {
    fn from(e: ExpressionError) -> Self {
        BenchError::Expression(Box::new(e))
    }
}

impl ExpressionReport {
    /// The formula's time per plan (iterations × one evaluation, one thread's CPU time) as a
    /// share of the plan's wall time, at the best and at the median of both.
    pub fn share_of_plan(&self) -> (f64, f64) {
        (
            self.per_plan_ms(self.eval.min_ms) / self.builtin().min_ms,
            self.per_plan_ms(self.eval.median_ms) / self.builtin().median_ms,
        )
    }

    /// The same share of the plan's CPU time (every thread's, mean per call), for the best and
    /// the median evaluation: the share of the work, whatever the load on the machine.
    pub fn share_of_plan_cpu(&self) -> Option<(f64, f64)> {
        self.builtin().cpu_ms_per_call.map(|cpu| {
            (
                self.per_plan_ms(self.eval.min_ms) / cpu,
                self.per_plan_ms(self.eval.median_ms) / cpu,
            )
        })
    }

    fn per_plan_ms(&self, eval_ms: f64) -> f64 {
        eval_ms * self.builtin().mean_iterations
    }

    /// The plans' timing (with the builtin reward, the only one this benchmark plans with).
    fn builtin(&self) -> &RewardTiming {
        &self.plan.rewards[0]
    }
}

impl fmt::Display for ExpressionReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (p, t) = (&self.plan, self.builtin());
        writeln!(f, "bench expression: {} reward `{}`", p.task, self.source)?;
        writeln!(
            f,
            "  formula    {} operations per row, {} rows per evaluation (population {} × horizon {} × {} particle(s))",
            self.operations, self.rows, p.population, p.horizon, p.particles
        )?;
        writeln!(f, "  values     {} per evaluation, one thread", self.eval)?;
        writeln!(
            f,
            "  + gradient {} per evaluation, one thread",
            self.gradient
        )?;
        write!(
            f,
            "  plan       {:.2} ms best, {:.2} ms median over {} calls, wall clock ({} thread(s), {:.1} iterations per call)",
            t.min_ms, t.median_ms, p.calls, p.threads, t.mean_iterations
        )?;
        if let (Some(cpu), Some(share)) = (t.cpu_ms_per_call, p.cpu_share) {
            write!(
                f,
                "; {cpu:.2} ms CPU per call, the threads ran {:.0} % of the time",
                share * 100.0
            )?;
        }
        let (best, median) = self.share_of_plan();
        write!(
            f,
            "\n  share      {:.1} evaluations per plan: the formula's values cost {:.2} % of a plan's wall time at the best, {:.2} % at the median",
            t.mean_iterations,
            best * 100.0,
            median * 100.0,
        )?;
        if let Some((best, median)) = self.share_of_plan_cpu() {
            write!(
                f,
                "; {:.2} % (best evaluation), {:.2} % (median) of its CPU time",
                best * 100.0,
                median * 100.0
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn times_a_formula_beside_real_plans() {
        let report = run(&Settings {
            task: Builtin::Cartpole,
            source: "exp(-s_next[0]^2) - 0.01*dot(a, a)".into(),
            batch: Duration::ZERO,
            plans: 1,
            seed: 3,
        })
        .unwrap();
        assert_eq!(report.rows, 400 * 25);
        assert_eq!(
            report.operations, 9,
            "load, square, negation, exp; load, product, constant 0.01, product; difference"
        );
        assert!(report.eval.min_ms > 0.0 && report.eval.min_ms <= report.eval.median_ms);
        let (best, median) = report.share_of_plan();
        assert!(best > 0.0 && median > 0.0 && best.is_finite() && median.is_finite());
        if let Some((best, median)) = report.share_of_plan_cpu() {
            assert!(best > 0.0 && best <= median && median.is_finite());
        }
        assert!(report.to_string().contains("share"), "{report}");

        let bad = run(&Settings {
            source: "s[4]".into(),
            plans: 1,
            ..Settings {
                task: Builtin::Cartpole,
                source: String::new(),
                batch: Duration::ZERO,
                plans: 1,
                seed: 3,
            }
        });
        let err = bad.unwrap_err().to_string();
        assert!(
            err.contains("index 4 out of range for s (obs_dim 4)"),
            "{err}"
        );
    }
}
