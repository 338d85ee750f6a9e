//! A task with its code: a validated [`TaskSpec`] whose reward, termination and model transforms
//! are ready to run, one transition at a time (the simulator, an agent's checks) or for a
//! planner's whole population at once ([`Task::rewards`], [`Task::terminations`]).
//!
//! Tasks are interned: [`Task::intern`] compiles a spec once per process and hands out a
//! `&'static Task`, the same one for every equal spec. Runs, models and planners hold their
//! task for as long as the daemon lives, and a daemon knows few distinct tasks; interning
//! makes the task as cheap to share as the compiled-in catalog was. The number of distinct
//! tasks a process may intern is bounded ([`MAX_DISTINCT_TASKS`]), so clients sending ever new
//! specs cannot grow it without limit.

use super::expression::{Dims, Expression, Gradients, Input, Inputs, Scratch};
use super::spec::{ModelTransforms, RewardKind, SpecBounds, SpecError, TaskSpec, TerminationKind};
use super::transforms::Declared;
use super::{Builtin, BuiltinCode};
use std::cell::RefCell;
use std::ops::Deref;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Most distinct task specs one process compiles.
pub const MAX_DISTINCT_TASKS: usize = 1024;

/// Why a spec cannot become a task.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TaskError {
    #[error(transparent)]
    Spec(#[from] SpecError),
    /// A formula that does not parse or does not fit the task's dimensions; `message` points
    /// at the offending text (see [`super::expression::ExpressionError`]).
    #[error("task {task}: {part} expression: {message}")]
    Expression {
        task: String,
        part: &'static str,
        message: String,
    },
    #[error(
        "this planner has compiled {MAX_DISTINCT_TASKS} distinct task specs, its most; restart it or reuse a spec"
    )]
    TooManyTasks,
}

/// The one way from a spec's expression source to code: parsed and checked against the task's
/// dimensions once, when the task is compiled. A termination sees only `s_next`, so a
/// termination formula that reads `s` or `a` is refused here rather than misread later.
pub fn compile_expression(
    task: &TaskSpec,
    part: &'static str,
    source: &str,
) -> Result<Formula, TaskError> {
    let error = |message: String| TaskError::Expression {
        task: task.name.clone(),
        part,
        message,
    };
    let dims = Dims {
        obs_dim: task.obs_dim,
        act_dim: task.act_dim,
    };
    let expression = Expression::parse(source, dims).map_err(|e| error(e.to_string()))?;
    if part == "termination" && (expression.reads(Input::S) || expression.reads(Input::A)) {
        return Err(error(
            "a termination reads only s_next (the state the episode may end in)".into(),
        ));
    }
    Ok(Formula {
        expression,
        id: NEXT_FORMULA_ID.fetch_add(1, Ordering::Relaxed),
    })
}

/// Numbers each compiled formula, so a thread can keep one scratch per formula.
static NEXT_FORMULA_ID: AtomicUsize = AtomicUsize::new(0);

thread_local! {
    /// Each thread's evaluation scratch per formula it has evaluated: made on a thread's first
    /// evaluation of a formula and reused after, so evaluating in the planning loop does not
    /// allocate. Tasks are interned and few, so the list stays short.
    static SCRATCH: RefCell<Vec<(usize, Scratch)>> = const { RefCell::new(Vec::new()) };
}

/// A compiled formula of a task: evaluated for a whole population through the expression
/// language's block evaluator with the caller's scratch (`Formula::values`), or one
/// transition at a time with a per-thread scratch ([`Formula::value`], and the gradient for
/// planners that descend it).
#[derive(Debug)]
pub struct Formula {
    expression: Expression,
    id: usize,
}

impl Formula {
    /// Working memory for [`Formula::values`] on any number of rows.
    fn scratch(&self) -> Scratch {
        self.expression.scratch()
    }

    /// The value of every row of `inputs` into `out` (one per row), in blocks of rows: the
    /// population path, with no per-row dispatch.
    fn values(&self, inputs: Inputs, out: &mut [f32], scratch: &mut Scratch) {
        self.expression.eval_batch(inputs, out, scratch);
    }

    /// [`Formula::values`] and each row's gradient into `grads` (overwritten).
    fn values_and_gradients(
        &self,
        inputs: Inputs,
        out: &mut [f32],
        grads: Gradients,
        scratch: &mut Scratch,
    ) {
        self.expression.eval_grad(inputs, out, grads, scratch);
    }

    /// The one-row paths' scratch: this thread's for this formula.
    fn with_scratch<R>(&self, f: impl FnOnce(&mut Scratch) -> R) -> R {
        SCRATCH.with(|cell| {
            let mut all = cell.borrow_mut();
            let at = match all.iter().position(|(id, _)| *id == self.id) {
                Some(at) => at,
                None => {
                    all.push((self.id, self.expression.scratch()));
                    all.len() - 1
                }
            };
            f(&mut all[at].1)
        })
    }
}

impl Formula {
    /// The value at `(s, a, s')`.
    pub fn value(&self, obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
        let mut out = [0.0];
        let inputs = Inputs {
            s: obs,
            a: act,
            s_next: next_obs,
        };
        self.with_scratch(|scratch| self.expression.eval_batch(inputs, &mut out, scratch));
        out[0]
    }

    /// The value and its gradient: `∂/∂a` into `d_act`, `∂/∂s'` into `d_next_obs` (overwritten).
    pub fn gradient(
        &self,
        obs: &[f32],
        act: &[f32],
        next_obs: &[f32],
        d_act: &mut [f32],
        d_next_obs: &mut [f32],
    ) -> f32 {
        let mut out = [0.0];
        let inputs = Inputs {
            s: obs,
            a: act,
            s_next: next_obs,
        };
        // An empty gradient slice is skipped: no planner descends the reward in `s`.
        let grads = Gradients {
            s: &mut [],
            a: d_act,
            s_next: d_next_obs,
        };
        self.with_scratch(|scratch| self.expression.eval_grad(inputs, &mut out, grads, scratch));
        out[0]
    }
}

/// A task: its spec (reachable through `Deref`, so `task.obs_dim` reads the spec's field) and
/// the code its kinds name.
#[derive(Debug)]
pub struct Task {
    spec: TaskSpec,
    /// Length of [`Task::state_features`]: the observation as the dynamics model sees it.
    pub state_feature_dim: usize,
    model: Model,
    reward: Reward,
    termination: Termination,
}

#[derive(Debug)]
enum Model {
    Builtin(&'static BuiltinCode),
    Declared(Declared),
}

#[derive(Debug)]
enum Reward {
    Builtin(&'static BuiltinCode),
    Expression(Formula),
    /// Observed only: the run's reward model predicts it (see [`Task::reward_is_learned`]).
    Learned,
}

#[derive(Debug)]
enum Termination {
    Never,
    Builtin(&'static BuiltinCode),
    Expression(Formula),
    /// Observed only: the run's termination model predicts it (see
    /// [`Task::termination_is_learned`]).
    Learned,
}

/// Working memory for evaluating a task's formulas over a population ([`Task::rewards`],
/// [`Task::terminations`]): one per thread that evaluates, made once by
/// [`Task::formula_scratch`] before the planning loop, so that the loop does not allocate. It
/// holds nothing for builtin code, which needs none.
#[derive(Debug, Default)]
pub struct FormulaScratch {
    reward: Option<Scratch>,
    termination: Option<Scratch>,
}

/// Rows of a termination formula evaluated into one stack buffer before they become flags.
const TERMINATION_ROWS: usize = 64;

/// Two tasks are the same task when their specs are equal (interning makes them one object).
impl PartialEq for Task {
    fn eq(&self, other: &Self) -> bool {
        self.spec == other.spec
    }
}

impl Deref for Task {
    type Target = TaskSpec;

    fn deref(&self) -> &TaskSpec {
        &self.spec
    }
}

/// Why [`Task::reward`] cannot answer for a learned reward.
const LEARNED_HAS_NO_FORMULA: &str =
    "a learned reward has no formula: score transitions with the run's reward model";

/// Why [`Task::rewards`] or [`Task::terminations`] found no scratch for its formula.
const SCRATCH_OF_ANOTHER_TASK: &str =
    "formula scratch made by this task's `formula_scratch` (this one is another task's)";

/// Every task this process compiled.
static INTERNED: Mutex<Vec<&'static Task>> = Mutex::new(Vec::new());

impl Task {
    /// The task of `spec` (validated against `bounds`), compiled on its first use in this
    /// process and shared after.
    pub fn intern(spec: TaskSpec, bounds: &SpecBounds) -> Result<&'static Task, TaskError> {
        spec.validate(bounds)?;
        if let Some(task) = Task::interned(&spec) {
            return Ok(task);
        }
        Task::share(Task::compile(spec)?)
    }

    /// The task of `spec` if this process interned it already.
    pub fn interned(spec: &TaskSpec) -> Option<&'static Task> {
        let interned = INTERNED.lock().unwrap_or_else(|e| e.into_inner());
        interned.iter().find(|t| t.spec == *spec).copied()
    }

    /// Distinct tasks this process interned (at most [`MAX_DISTINCT_TASKS`]).
    pub fn interned_count() -> usize {
        INTERNED.lock().unwrap_or_else(|e| e.into_inner()).len()
    }

    /// The task of `spec` (validated against `bounds`), compiled but not interned: a caller
    /// that may still refuse the request it came with checks everything with it first and
    /// interns it ([`Task::share`]) only once it keeps it, so a refused request keeps nothing
    /// and takes none of the [`MAX_DISTINCT_TASKS`] slots. Dropping it frees it.
    pub fn compile_unshared(spec: TaskSpec, bounds: &SpecBounds) -> Result<Task, TaskError> {
        spec.validate(bounds)?;
        Task::compile(spec)
    }

    /// Interns a compiled task (see [`Task::compile_unshared`]): the one already interned
    /// for an equal spec, or this one, if a slot is free.
    pub fn share(task: Task) -> Result<&'static Task, TaskError> {
        let mut interned = INTERNED.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(known) = interned.iter().find(|t| t.spec == task.spec) {
            return Ok(known);
        }
        if interned.len() >= MAX_DISTINCT_TASKS {
            return Err(TaskError::TooManyTasks);
        }
        let task: &'static Task = Box::leak(Box::new(task));
        interned.push(task);
        Ok(task)
    }

    /// Compiles a validated spec.
    fn compile(spec: TaskSpec) -> Result<Task, TaskError> {
        let (model, state_feature_dim) = match &spec.model {
            ModelTransforms::Builtin(b) => (Model::Builtin(b.code()), b.code().state_feature_dim),
            ModelTransforms::Declared(d) => {
                let declared = Declared::new(spec.obs_dim, d);
                let dim = declared.feature_dim();
                (Model::Declared(declared), dim)
            }
        };
        let reward = match &spec.reward {
            RewardKind::Builtin(b) => Reward::Builtin(b.code()),
            RewardKind::Expression(source) => {
                Reward::Expression(compile_expression(&spec, "reward", source)?)
            }
            RewardKind::Learned => Reward::Learned,
        };
        let termination = match &spec.termination {
            TerminationKind::Never => Termination::Never,
            TerminationKind::Builtin(b) => Termination::Builtin(b.code()),
            TerminationKind::Expression(source) => {
                Termination::Expression(compile_expression(&spec, "termination", source)?)
            }
            TerminationKind::Learned => Termination::Learned,
        };
        Ok(Task {
            spec,
            state_feature_dim,
            model,
            reward,
            termination,
        })
    }

    /// The task's spec, as data.
    pub fn spec(&self) -> &TaskSpec {
        &self.spec
    }

    /// The task's name.
    pub fn name(&self) -> &str {
        &self.spec.name
    }

    /// The builtin task this is, if it is a catalog entry unchanged.
    pub fn builtin(&self) -> Option<Builtin> {
        Builtin::from_name(&self.spec.name).filter(|b| b.spec() == self.spec)
    }

    /// Whether this task's reward is learned: it has no formula, only the rewards agents send,
    /// and a planner scores imagined transitions with the run's reward model instead of
    /// [`Task::reward`].
    pub fn reward_is_learned(&self) -> bool {
        matches!(self.reward, Reward::Learned)
    }

    /// Whether this task's termination is learned: it has no rule, only the episodes agents
    /// end as `terminated`, and a planner ends imagined particles where the run's termination
    /// model predicts an end. [`Task::terminations`] and [`Task::is_terminal`] say `false`
    /// for it (the formula part of the task knows no end).
    pub fn termination_is_learned(&self) -> bool {
        matches!(self.termination, Termination::Learned)
    }

    /// Reward of the transition `obs --act--> next_obs`. The simulator reports exactly this.
    ///
    /// # Panics
    ///
    /// For a learned reward ([`Task::reward_is_learned`]): there is no formula to evaluate.
    pub fn reward(&self, obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
        match &self.reward {
            Reward::Builtin(code) => (code.reward)(obs, act, next_obs),
            Reward::Expression(e) => e.value(obs, act, next_obs),
            Reward::Learned => panic!("{}: {LEARNED_HAS_NO_FORMULA}", self.spec.name),
        }
    }

    /// The reward of `obs --act--> next_obs` (exactly [`Task::reward`]) and its gradient:
    /// `∂r/∂act` into `d_act` and `∂r/∂next_obs` into `d_next_obs` (both overwritten). Every
    /// catalog reward reads only the action and the new observation, so there is no `∂r/∂obs`
    /// (the finite-difference tests check that too). Where a reward has a kink (pusher's L1
    /// distances) the gradient is the one-sided one of `signum`, 0 exactly at the kink.
    /// Gradient-based planning (Adam + DAE) back-propagates through it.
    ///
    /// # Panics
    ///
    /// For a learned reward, as [`Task::reward`].
    pub fn reward_gradient(
        &self,
        obs: &[f32],
        act: &[f32],
        next_obs: &[f32],
        d_act: &mut [f32],
        d_next_obs: &mut [f32],
    ) -> f32 {
        match &self.reward {
            Reward::Builtin(code) => (code.reward_gradient)(obs, act, next_obs, d_act, d_next_obs),
            Reward::Expression(e) => e.gradient(obs, act, next_obs, d_act, d_next_obs),
            Reward::Learned => panic!("{}: {LEARNED_HAS_NO_FORMULA}", self.spec.name),
        }
    }

    /// Working memory for [`Task::rewards`] and [`Task::terminations`] on any number of rows.
    pub fn formula_scratch(&self) -> FormulaScratch {
        FormulaScratch {
            reward: match &self.reward {
                Reward::Expression(f) => Some(f.scratch()),
                Reward::Builtin(_) | Reward::Learned => None,
            },
            termination: match &self.termination {
                Termination::Expression(f) => Some(f.scratch()),
                Termination::Never | Termination::Builtin(_) | Termination::Learned => None,
            },
        }
    }

    /// [`Task::reward`] of every row of a population (row-major `obs`, `act`, `next_obs`) into
    /// `out`, one per row: a formula through the block evaluator, builtin code row by row. The
    /// values are exactly those of [`Task::reward`], row by row.
    ///
    /// # Panics
    ///
    /// For a learned reward, as [`Task::reward`]; if the inputs do not hold `out.len()` rows;
    /// if `scratch` was made for another task.
    pub fn rewards(
        &self,
        obs: &[f32],
        act: &[f32],
        next_obs: &[f32],
        scratch: &mut FormulaScratch,
        out: &mut [f32],
    ) {
        let (o, a, rows) = (self.spec.obs_dim, self.spec.act_dim, out.len());
        self.assert_rows(obs, act, next_obs, rows);
        match &self.reward {
            Reward::Builtin(code) => {
                let rows = obs
                    .chunks_exact(o)
                    .zip(act.chunks_exact(a))
                    .zip(next_obs.chunks_exact(o));
                for (r, ((s, u), s1)) in out.iter_mut().zip(rows) {
                    *r = (code.reward)(s, u, s1);
                }
            }
            Reward::Expression(f) => {
                let inputs = Inputs {
                    s: obs,
                    a: act,
                    s_next: next_obs,
                };
                let scratch = scratch.reward.as_mut().expect(SCRATCH_OF_ANOTHER_TASK);
                f.values(inputs, out, scratch);
            }
            Reward::Learned => panic!("{}: {LEARNED_HAS_NO_FORMULA}", self.spec.name),
        }
    }

    /// Panics unless `obs`, `act` and `next_obs` hold `rows` transitions of this task.
    fn assert_rows(&self, obs: &[f32], act: &[f32], next_obs: &[f32], rows: usize) {
        let (o, a) = (self.spec.obs_dim, self.spec.act_dim);
        assert_eq!(
            (obs.len(), act.len(), next_obs.len()),
            (rows * o, rows * a, rows * o),
            "{}: rows of the transitions",
            self.spec.name
        );
    }

    /// [`Task::rewards`] and each row's gradient: `∂r/∂obs` into `d_obs`, `∂r/∂act` into
    /// `d_act`, `∂r/∂next_obs` into `d_next_obs` (rows × dims, all overwritten). Builtin code
    /// reads no `obs` (its `d_obs` is 0); a formula may, and its `∂r/∂s` is exact.
    ///
    /// # Panics
    ///
    /// As [`Task::rewards`], and if a gradient does not hold `out.len()` rows.
    #[allow(clippy::too_many_arguments)]
    pub fn reward_gradients(
        &self,
        obs: &[f32],
        act: &[f32],
        next_obs: &[f32],
        scratch: &mut FormulaScratch,
        out: &mut [f32],
        d_obs: &mut [f32],
        d_act: &mut [f32],
        d_next_obs: &mut [f32],
    ) {
        let (o, a, rows) = (self.spec.obs_dim, self.spec.act_dim, out.len());
        self.assert_rows(obs, act, next_obs, rows);
        assert_eq!(
            (d_obs.len(), d_act.len(), d_next_obs.len()),
            (rows * o, rows * a, rows * o),
            "{}: rows of the gradients",
            self.spec.name
        );
        match &self.reward {
            Reward::Builtin(code) => {
                d_obs.fill(0.0);
                let inputs = obs
                    .chunks_exact(o)
                    .zip(act.chunks_exact(a))
                    .zip(next_obs.chunks_exact(o));
                let grads = d_act
                    .chunks_exact_mut(a)
                    .zip(d_next_obs.chunks_exact_mut(o));
                for ((r, ((s, u), s1)), (du, ds1)) in out.iter_mut().zip(inputs).zip(grads) {
                    *r = (code.reward_gradient)(s, u, s1, du, ds1);
                }
            }
            Reward::Expression(f) => {
                let inputs = Inputs {
                    s: obs,
                    a: act,
                    s_next: next_obs,
                };
                let grads = Gradients {
                    s: d_obs,
                    a: d_act,
                    s_next: d_next_obs,
                };
                let scratch = scratch.reward.as_mut().expect(SCRATCH_OF_ANOTHER_TASK);
                f.values_and_gradients(inputs, out, grads, scratch);
            }
            Reward::Learned => panic!("{}: {LEARNED_HAS_NO_FORMULA}", self.spec.name),
        }
    }

    /// [`Task::is_terminal`] of every row of `next_obs` (row-major) into `out`, one per row.
    ///
    /// # Panics
    ///
    /// If `next_obs` does not hold `out.len()` rows, or `scratch` was made for another task.
    pub fn terminations(&self, next_obs: &[f32], scratch: &mut FormulaScratch, out: &mut [bool]) {
        let o = self.spec.obs_dim;
        assert_eq!(
            next_obs.len(),
            out.len() * o,
            "{}: rows of the observations",
            self.spec.name
        );
        match &self.termination {
            Termination::Never | Termination::Learned => out.fill(false),
            Termination::Builtin(code) => {
                for (t, s1) in out.iter_mut().zip(next_obs.chunks_exact(o)) {
                    *t = (code.is_terminal)(s1);
                }
            }
            Termination::Expression(f) => {
                let scratch = scratch.termination.as_mut().expect(SCRATCH_OF_ANOTHER_TASK);
                let mut values = [0.0; TERMINATION_ROWS];
                let blocks = out
                    .chunks_mut(TERMINATION_ROWS)
                    .zip(next_obs.chunks(TERMINATION_ROWS * o));
                for (flags, s_next) in blocks {
                    let values = &mut values[..flags.len()];
                    // A termination reads `s_next` only (checked when compiled).
                    let inputs = Inputs {
                        s: &[],
                        a: &[],
                        s_next,
                    };
                    f.values(inputs, values, scratch);
                    for (t, v) in flags.iter_mut().zip(values.iter()) {
                        *t = *v != 0.0;
                    }
                }
            }
        }
    }

    /// Whether `next_obs` ends the episode (no reward accrues after it, in reality or imagination).
    pub fn is_terminal(&self, next_obs: &[f32]) -> bool {
        match &self.termination {
            Termination::Never | Termination::Learned => false,
            Termination::Builtin(code) => (code.is_terminal)(next_obs),
            // A termination expression reads `s_next` only; `s` and `a` are passed as `s_next`
            // and an empty action so that no index of them can be valid.
            // Formulas make comparisons 1 or 0: any value but 0 ends the episode.
            Termination::Expression(e) => e.value(&[], &[], next_obs) != 0.0,
        }
    }

    /// The observation as the dynamics model's input sees it (e.g. angles as sin/cos),
    /// `state_feature_dim` numbers written to `out`. The action is appended by the model.
    pub fn state_features(&self, obs: &[f32], out: &mut [f32]) {
        match &self.model {
            Model::Builtin(code) => (code.state_features)(obs, out),
            Model::Declared(d) => d.state_features(obs, out),
        }
    }

    /// The transpose of [`Task::state_features`]' Jacobian at `obs` applied to
    /// `d_features`, *added* to `d_obs`: back-propagation from the model's input to `obs`.
    pub fn state_features_backward(&self, obs: &[f32], d_features: &[f32], d_obs: &mut [f32]) {
        match &self.model {
            Model::Builtin(code) => (code.state_features_backward)(obs, d_features, d_obs),
            Model::Declared(d) => d.state_features_backward(obs, d_features, d_obs),
        }
    }

    /// What the dynamics model learns to predict for a transition (`obs_dim` numbers):
    /// usually the delta `next_obs − obs`.
    pub fn target(&self, obs: &[f32], next_obs: &[f32], out: &mut [f32]) {
        match &self.model {
            Model::Builtin(code) => (code.target)(obs, next_obs, out),
            Model::Declared(d) => d.target(obs, next_obs, out),
        }
    }

    /// The inverse of [`Task::target`]: the next observation from `obs` and a predicted target.
    pub fn next_obs_from_target(&self, obs: &[f32], target: &[f32], next_obs: &mut [f32]) {
        match &self.model {
            Model::Builtin(code) => (code.next_obs_from_target)(obs, target, next_obs),
            Model::Declared(d) => d.next_obs_from_target(obs, target, next_obs),
        }
    }

    /// Back-propagation through [`Task::next_obs_from_target`]: given `∂L/∂next_obs`, adds
    /// `∂L/∂obs` to `d_obs` and writes `∂L/∂target` into `d_target`.
    pub fn next_obs_from_target_backward(
        &self,
        obs: &[f32],
        d_next_obs: &[f32],
        d_obs: &mut [f32],
        d_target: &mut [f32],
    ) {
        match &self.model {
            Model::Builtin(code) => {
                (code.next_obs_from_target_backward)(obs, d_next_obs, d_obs, d_target)
            }
            Model::Declared(d) => d.next_obs_from_target_backward(d_next_obs, d_obs, d_target),
        }
    }

    /// Clamps an action into the task's bounds, in place.
    pub fn clamp_action(&self, act: &mut [f32]) {
        for ((a, lo), hi) in act
            .iter_mut()
            .zip(&self.spec.action_low)
            .zip(&self.spec.action_high)
        {
            *a = a.clamp(*lo, *hi);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::task::spec::DeclaredTransforms;

    fn custom(name: &str) -> TaskSpec {
        let mut spec = Builtin::Cartpole.spec();
        spec.name = name.into();
        spec.model = ModelTransforms::Declared(DeclaredTransforms {
            angles: vec![1],
            absolute: vec![3],
        });
        spec
    }

    #[test]
    fn equal_specs_share_one_task_and_declared_transforms_run() {
        let a = Task::intern(custom("interned"), &SpecBounds::default()).unwrap();
        let b = Task::intern(custom("interned"), &SpecBounds::default()).unwrap();
        assert!(std::ptr::eq(a, b));
        assert!(std::ptr::eq(
            Builtin::Ant.task(),
            Task::intern(Builtin::Ant.spec(), &SpecBounds::default()).unwrap()
        ));
        assert_eq!(a.state_feature_dim, 5);
        assert_eq!(a.builtin(), None);
        assert_eq!(Builtin::Ant.task().builtin(), Some(Builtin::Ant));
        let (obs, next) = ([0.1, 0.2, 0.3, 0.4], [1.0, 2.0, 3.0, 4.0]);
        let mut target = [0.0; 4];
        a.target(&obs, &next, &mut target);
        assert_eq!(target, [0.9, 1.8, 2.7, 4.0]);
        // The builtin reward still runs: the dimensions are cartpole's.
        assert_eq!(
            a.reward(&obs, &[1.0], &next),
            Builtin::Cartpole.task().reward(&obs, &[1.0], &next)
        );
    }

    /// `rows` random transitions of `task` (coordinates in ±2, actions in ±1.5) from `seed`.
    fn population(task: &Task, rows: usize, seed: u64) -> [Vec<f32>; 3] {
        use rand::rngs::StdRng;
        use rand::{RngExt, SeedableRng};
        let mut rng = StdRng::seed_from_u64(seed);
        let mut draw = |n: usize, range: f32| -> Vec<f32> {
            (0..n).map(|_| rng.random_range(-range..range)).collect()
        };
        [
            draw(rows * task.obs_dim, 2.0),
            draw(rows * task.act_dim, 1.5),
            draw(rows * task.obs_dim, 2.0),
        ]
    }

    /// The population entry points give exactly the row-by-row values, for builtin code and for
    /// formulas (the block evaluator against the one-row path), over a population that is not
    /// a whole number of blocks, with a NaN observation among the rows.
    #[test]
    fn population_rewards_and_terminations_are_the_row_by_row_ones() {
        let mut cheetah = Builtin::HalfCheetah.spec();
        cheetah.name = "population-cheetah-formula".into();
        cheetah.reward = RewardKind::Expression("s_next[0] - 0.1*dot(a, a)".into());
        let mut ant = Builtin::Ant.spec();
        ant.name = "population-ant-formulas".into();
        ant.reward = RewardKind::Expression("s_next[13] - 0.5*dot(a, a) + 1".into());
        ant.termination =
            TerminationKind::Expression("!(s_next[0] >= 0.2 && s_next[0] <= 1)".into());
        let formulas =
            [cheetah, ant].map(|spec| Task::intern(spec, &SpecBounds::default()).unwrap());
        let tasks = Builtin::ALL.iter().map(|b| b.task()).chain(formulas);
        for (seed, task) in tasks.enumerate() {
            let (o, a, rows) = (task.obs_dim, task.act_dim, 150);
            let [obs, act, mut next] = population(task, rows, seed as u64);
            // Ant's healthy heights lie in [0.2, 1]: half the rows end, half do not.
            for r in 0..rows {
                next[r * o] = if r % 2 == 0 { 0.5 } else { 1.5 };
            }
            next[77 * o] = f32::NAN;
            let mut scratch = task.formula_scratch();
            let mut rewards = vec![f32::NAN; rows];
            task.rewards(&obs, &act, &next, &mut scratch, &mut rewards);
            let mut ended = vec![false; rows];
            task.terminations(&next, &mut scratch, &mut ended);
            let (mut values, mut d_obs, mut d_act, mut d_next) = (
                vec![f32::NAN; rows],
                vec![f32::NAN; rows * o],
                vec![f32::NAN; rows * a],
                vec![f32::NAN; rows * o],
            );
            task.reward_gradients(
                &obs,
                &act,
                &next,
                &mut scratch,
                &mut values,
                &mut d_obs,
                &mut d_act,
                &mut d_next,
            );
            assert!(
                d_obs.iter().all(|&g| g == 0.0),
                "{}: no reward reads s",
                task.name()
            );
            let (mut want_da, mut want_dn) = (vec![0.0; a], vec![0.0; o]);
            for r in 0..rows {
                let (s, u, s1) = (&obs[r * o..][..o], &act[r * a..][..a], &next[r * o..][..o]);
                let want = task.reward_gradient(s, u, s1, &mut want_da, &mut want_dn);
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(
                    (
                        values[r].to_bits(),
                        bits(&d_act[r * a..][..a]),
                        bits(&d_next[r * o..][..o])
                    ),
                    (want.to_bits(), bits(&want_da), bits(&want_dn)),
                    "{} row {r}: value and gradient",
                    task.name()
                );
                let want = task.reward(s, u, s1);
                assert!(
                    rewards[r].to_bits() == want.to_bits(),
                    "{} row {r}: {} vs {want}",
                    task.name(),
                    rewards[r]
                );
                assert_eq!(ended[r], task.is_terminal(s1), "{} row {r}", task.name());
            }
        }
        let ant = formulas[1];
        let mut ended = vec![false; 3];
        ant.terminations(
            &[0.5, 0.1, f32::NAN]
                .map(|h| {
                    let mut row = vec![0.0; 27];
                    row[0] = h;
                    row
                })
                .concat(),
            &mut ant.formula_scratch(),
            &mut ended,
        );
        assert_eq!(ended, [false, true, true], "a NaN height is not healthy");
    }

    /// A formula that reads `s` has a gradient in `s` too, on the population path.
    #[test]
    fn population_gradients_include_the_previous_state() {
        let mut spec = custom("population-reads-s");
        spec.reward = RewardKind::Expression("s_next[0] - s[1]^2 + 0.5*a[0]*s[3]".into());
        let task = Task::intern(spec, &SpecBounds::default()).unwrap();
        let obs = [0.3, -0.7, 2.0, 1.5, 0.0, 0.4, 0.1, -2.0];
        let (act, next) = ([0.5, -1.0], [1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0]);
        let (mut out, mut d_obs, mut d_act, mut d_next) = ([0.0; 2], [9.0; 8], [9.0; 2], [9.0; 8]);
        task.reward_gradients(
            &obs,
            &act,
            &next,
            &mut task.formula_scratch(),
            &mut out,
            &mut d_obs,
            &mut d_act,
            &mut d_next,
        );
        assert!(
            (out[0] - 0.885).abs() < 1e-6 && (out[1] + 0.16).abs() < 1e-6,
            "{out:?}"
        );
        assert_eq!(d_obs, [0.0, 1.4, 0.0, 0.25, 0.0, -0.8, 0.0, -0.5]);
        assert_eq!(d_act, [0.75, -1.0]);
        assert_eq!(d_next, [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]);
    }

    /// A scratch is made by its task: another task's has no room for the formula.
    #[test]
    #[should_panic(expected = "formula scratch made by this task")]
    fn a_formula_needs_its_own_tasks_scratch() {
        let mut spec = custom("scratch-of-another");
        spec.reward = RewardKind::Expression("-s_next[0]^2".into());
        let task = Task::intern(spec, &SpecBounds::default()).unwrap();
        let mut other = Builtin::Cartpole.task().formula_scratch();
        task.rewards(&[0.0; 4], &[0.0], &[0.0; 4], &mut other, &mut [0.0]);
    }

    #[test]
    fn expression_and_learned_kinds_compile_and_run() {
        let mut spec = custom("expr");
        spec.reward = RewardKind::Expression("-s_next[0]^2 - 0.1*a[0]^2".into());
        spec.termination = TerminationKind::Expression("abs(s_next[2]) > 0.5".into());
        let task = Task::intern(spec, &SpecBounds::default()).unwrap();
        let (obs, act, next) = ([0.0; 4], [2.0], [3.0, 0.0, 0.1, 0.0]);
        assert!((task.reward(&obs, &act, &next) - (-9.0 - 0.4)).abs() < 1e-5);
        let (mut d_act, mut d_next) = ([0.0], [0.0; 4]);
        let r = task.reward_gradient(&obs, &act, &next, &mut d_act, &mut d_next);
        assert!((r - (-9.4)).abs() < 1e-5);
        assert!((d_act[0] - (-0.4)).abs() < 1e-5, "{d_act:?}");
        assert!((d_next[0] - (-6.0)).abs() < 1e-5, "{d_next:?}");
        assert_eq!(&d_next[1..], &[0.0; 3]);
        assert!(!task.is_terminal(&next));
        assert!(task.is_terminal(&[0.0, 0.0, -0.7, 0.0]));

        // A formula that does not fit is refused, naming the offending text.
        let mut spec = custom("expr-bad");
        spec.reward = RewardKind::Expression("-s_next[4]^2".into());
        let err = Task::intern(spec, &SpecBounds::default()).unwrap_err();
        let text = err.to_string();
        assert!(
            text.starts_with("task expr-bad: reward expression:"),
            "{text}"
        );
        assert!(text.contains("s_next[4]"), "{text}");
        // A termination sees only the state the episode may end in.
        let mut spec = custom("expr-term");
        spec.termination = TerminationKind::Expression("a[0] > 1".into());
        let err = Task::intern(spec, &SpecBounds::default()).unwrap_err();
        assert!(err.to_string().contains("reads only s_next"), "{err}");

        // A learned reward compiles: it has no formula, the run's reward model scores it.
        let mut spec = custom("learned");
        spec.reward = RewardKind::Learned;
        let task = Task::intern(spec, &SpecBounds::default()).unwrap();
        assert!(task.reward_is_learned());
        assert!(!Builtin::Cartpole.task().reward_is_learned());
        let formula = std::panic::catch_unwind(|| task.reward(&obs, &act, &next));
        assert!(
            formula.is_err(),
            "a learned reward has no formula to evaluate"
        );
        let mut spec = custom("bad");
        spec.obs_dim = 0;
        assert!(matches!(
            Task::intern(spec, &SpecBounds::default()),
            Err(TaskError::Spec(_))
        ));
    }
}
