//! A task with its code: a validated [`TaskSpec`] whose reward, termination and model transforms
//! are ready to run row by row over a planner's population.
//!
//! Tasks are interned: [`Task::intern`] compiles a spec once per process and hands out a
//! `&'static Task`, the same one for every equal spec. Runs, models and planners hold their
//! task for as long as the daemon lives, and a daemon knows few distinct tasks; interning
//! makes the task as cheap to share as the compiled-in catalog was. The number of distinct
//! tasks a process may intern is bounded ([`MAX_DISTINCT_TASKS`]), so clients sending ever new
//! specs cannot grow it without limit.

use super::spec::{ModelTransforms, RewardKind, SpecBounds, SpecError, TaskSpec, TerminationKind};
use super::transforms::Declared;
use super::{Builtin, BuiltinCode};
use std::fmt;
use std::ops::Deref;
use std::sync::Mutex;

/// Most distinct task specs one process compiles.
pub const MAX_DISTINCT_TASKS: usize = 1024;

/// Why a spec cannot become a task.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TaskError {
    #[error(transparent)]
    Spec(#[from] SpecError),
    #[error("task {task}: expression rewards are not available in this build ({part} expression)")]
    ExpressionsUnavailable { task: String, part: &'static str },
    #[error("task {task}: learned rewards are not available in this build")]
    LearnedUnavailable { task: String },
    #[error(
        "this planner has compiled {MAX_DISTINCT_TASKS} distinct task specs, its most; restart it or reuse a spec"
    )]
    TooManyTasks,
}

/// An expression compiled against a task's dimensions, as the expression language provides it
/// (`proto/src/task/expression.rs`): evaluated per transition, with its gradient for planners
/// that descend it.
pub trait CompiledExpression: Send + Sync + fmt::Debug {
    /// The value at `(s, a, s')`.
    fn value(&self, obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32;
    /// The value and its gradient: `∂/∂a` into `d_act`, `∂/∂s'` into `d_next_obs` (overwritten).
    fn gradient(
        &self,
        obs: &[f32],
        act: &[f32],
        next_obs: &[f32],
        d_act: &mut [f32],
        d_next_obs: &mut [f32],
    ) -> f32;
}

/// The one way from a spec's expression source to code: parsed and checked against the task's
/// dimensions once, when the task is compiled. This build has no expression language, so every
/// expression is refused with a clear error.
pub fn compile_expression(
    task: &TaskSpec,
    part: &'static str,
    _source: &str,
) -> Result<Box<dyn CompiledExpression>, TaskError> {
    Err(TaskError::ExpressionsUnavailable {
        task: task.name.clone(),
        part,
    })
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
    Expression(Box<dyn CompiledExpression>),
}

#[derive(Debug)]
enum Termination {
    Never,
    Builtin(&'static BuiltinCode),
    Expression(Box<dyn CompiledExpression>),
}

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

/// Every task this process compiled.
static INTERNED: Mutex<Vec<&'static Task>> = Mutex::new(Vec::new());

impl Task {
    /// The task of `spec` (validated against `bounds`), compiled on its first use in this
    /// process and shared after.
    pub fn intern(spec: TaskSpec, bounds: &SpecBounds) -> Result<&'static Task, TaskError> {
        spec.validate(bounds)?;
        let mut interned = INTERNED.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(task) = interned.iter().find(|t| t.spec == spec) {
            return Ok(task);
        }
        if interned.len() >= MAX_DISTINCT_TASKS {
            return Err(TaskError::TooManyTasks);
        }
        let task: &'static Task = Box::leak(Box::new(Task::compile(spec)?));
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
            RewardKind::Learned => {
                return Err(TaskError::LearnedUnavailable {
                    task: spec.name.clone(),
                });
            }
        };
        let termination = match &spec.termination {
            TerminationKind::Never => Termination::Never,
            TerminationKind::Builtin(b) => Termination::Builtin(b.code()),
            TerminationKind::Expression(source) => {
                Termination::Expression(compile_expression(&spec, "termination", source)?)
            }
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

    /// Reward of the transition `obs --act--> next_obs`. The simulator reports exactly this.
    pub fn reward(&self, obs: &[f32], act: &[f32], next_obs: &[f32]) -> f32 {
        match &self.reward {
            Reward::Builtin(code) => (code.reward)(obs, act, next_obs),
            Reward::Expression(e) => e.value(obs, act, next_obs),
        }
    }

    /// The reward of `obs --act--> next_obs` (exactly [`Task::reward`]) and its gradient:
    /// `∂r/∂act` into `d_act` and `∂r/∂next_obs` into `d_next_obs` (both overwritten). Every
    /// catalog reward reads only the action and the new observation, so there is no `∂r/∂obs`
    /// (the finite-difference tests check that too). Where a reward has a kink (pusher's L1
    /// distances) the gradient is the one-sided one of `signum`, 0 exactly at the kink.
    /// Gradient-based planning (Adam + DAE) back-propagates through it.
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
        }
    }

    /// Whether `next_obs` ends the episode (no reward accrues after it, in reality or imagination).
    pub fn is_terminal(&self, next_obs: &[f32]) -> bool {
        match &self.termination {
            Termination::Never => false,
            Termination::Builtin(code) => (code.is_terminal)(next_obs),
            // A termination expression reads `s_next` only; `s` and `a` are passed as `s_next`
            // and an empty action so that no index of them can be valid.
            Termination::Expression(e) => e.value(next_obs, &[], next_obs) > 0.0,
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

    #[test]
    fn expression_and_learned_kinds_are_refused_in_this_build() {
        let mut spec = custom("expr");
        spec.reward = RewardKind::Expression("-s_next[0]^2".into());
        let err = Task::intern(spec, &SpecBounds::default()).unwrap_err();
        assert_eq!(
            err.to_string(),
            "task expr: expression rewards are not available in this build (reward expression)"
        );
        let mut spec = custom("learned");
        spec.reward = RewardKind::Learned;
        let err = Task::intern(spec, &SpecBounds::default()).unwrap_err();
        assert!(
            err.to_string()
                .contains("learned rewards are not available")
        );
        let mut spec = custom("bad");
        spec.obs_dim = 0;
        assert!(matches!(
            Task::intern(spec, &SpecBounds::default()),
            Err(TaskError::Spec(_))
        ));
    }
}
