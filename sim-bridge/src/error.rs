//! The errors of the simulation library.

use proto::Builtin;

/// Why a simulator could not be built or could not take a step.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The task is in proto's catalog but sim-bridge has no MuJoCo model for it yet.
    #[error("task `{task}` has no simulator in sim-bridge yet (simulated tasks: {known})")]
    NoSimulator { task: Builtin, known: String },

    /// MuJoCo rejected the task's MJCF model (a bug in `assets/`, or a mismatched libmujoco).
    #[error("MuJoCo could not load the `{task}` model: {source}")]
    ModelLoad {
        task: Builtin,
        #[source]
        source: mujoco_rs::error::MjModelError,
    },

    /// The MJCF model disagrees with proto's task catalog (dimensions, timing, bounds).
    #[error("the `{task}` model disagrees with the task catalog: {detail}")]
    ModelMismatch { task: Builtin, detail: String },

    /// An action of the wrong length.
    #[error("action has {got} numbers, task `{task}` takes {expected}")]
    ActionDimension {
        task: Builtin,
        expected: usize,
        got: usize,
    },

    /// An action containing NaN or an infinity.
    #[error("action[{index}] = {value} is not finite")]
    NonFiniteAction { index: usize, value: f32 },

    /// A state of the wrong length handed to `Env::set_state`.
    #[error("state has {got} numbers, task `{task}` observes {expected}")]
    StateDimension {
        task: Builtin,
        expected: usize,
        got: usize,
    },

    /// The task cannot place its simulator in an arbitrary observed state.
    #[error("task `{task}` cannot set its state from an observation")]
    SetStateUnsupported { task: Builtin },

    /// `step` after the episode ended (terminated or hit its time limit) without a `reset`.
    #[error("episode is over after {steps} steps; call reset before stepping again")]
    EpisodeOver { steps: u32 },

    /// The physics blew up (an unstable model or an absurd state): MuJoCo had to reset the
    /// simulation, or the observation is not finite. `obs` is what the simulator holds now.
    #[error(
        "simulation diverged at step {step} (MuJoCo reset it or it went non-finite): now at {obs:?}"
    )]
    Diverged { step: u32, obs: Vec<f32> },
}
