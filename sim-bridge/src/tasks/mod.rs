//! One simulator per task of proto's catalog, each in its own module.
//!
//! A task module owns its MJCF (in `assets/`), the mapping from physics state to the catalog's
//! observation, and its initial-state distribution. Rewards and termination are *not* here: they
//! come from proto's [`proto::Task`], the one definition the planner uses as well. Adding a
//! task means adding a module, an arm in `simulator` and its name in [`SIMULATED`].

mod ant;
mod cartpole;
mod halfcheetah;
mod pusher;
mod reacher3d;

use crate::error::SimError;
use crate::mujoco::Unstable;
use proto::Builtin;
use rand::rngs::StdRng;

/// The physics of one task, driven by [`crate::Env`].
///
/// `Env` validates and clamps actions before they get here, and keeps the observation, step count
/// and episode bookkeeping, so implementations only do physics.
pub(crate) trait TaskSim: Send {
    /// Samples an episode's initial state from `rng`.
    fn reset(&mut self, rng: &mut StdRng);

    /// Advances one control step holding `action` (finite, within the task's bounds).
    fn step(&mut self, action: &[f32]) -> Result<(), Unstable>;

    /// Writes the current observation (`obs_dim` numbers) into `out`.
    fn observe(&self, out: &mut [f32]);

    /// Puts the system in the state described by `obs` (`obs_dim` numbers, already checked).
    /// Tasks whose observation does not determine the physics state say so with an error.
    fn set_state(&mut self, obs: &[f32]) -> Result<(), SimError>;

    /// The task's MuJoCo model and state, for drawing it.
    #[cfg(feature = "render")]
    fn physics(&self) -> &crate::mujoco::MjSim;
}

/// The tasks that have a simulator, in catalog order.
pub const SIMULATED: &[Builtin] = &[
    Builtin::Cartpole,
    Builtin::Reacher3d,
    Builtin::Pusher,
    Builtin::HalfCheetah,
    Builtin::Ant,
];

/// Builds the simulator for `task`, or says clearly that it has none yet.
pub(crate) fn simulator(task: Builtin) -> Result<Box<dyn TaskSim>, SimError> {
    // The wildcard keeps sim-bridge compiling when proto's catalog grows before the
    // simulator for a new task is written: such a task gets `NoSimulator` at run time.
    #[allow(unreachable_patterns)]
    match task {
        Builtin::Cartpole => Ok(Box::new(cartpole::Cartpole::new()?)),
        Builtin::Reacher3d => Ok(Box::new(reacher3d::Reacher3d::new()?)),
        Builtin::HalfCheetah => Ok(Box::new(halfcheetah::HalfCheetah::new()?)),
        Builtin::Ant => Ok(Box::new(ant::Ant::new()?)),
        Builtin::Pusher => Ok(Box::new(pusher::Pusher::new()?)),
        _ => Err(SimError::NoSimulator {
            task,
            known: SIMULATED
                .iter()
                .map(|t| t.name())
                .collect::<Vec<_>>()
                .join(", "),
        }),
    }
}
