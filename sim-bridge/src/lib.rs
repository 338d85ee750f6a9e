//! ebmpc's simulator side: MuJoCo tasks behind one [`Env`] API, and the bridge that connects an
//! environment to a planner over Zenoh.
//!
//! Each task of proto's catalog that has a simulator lives in its own module under `tasks/`
//! with its own MJCF in `assets/` (embedded in the binary); rewards and termination always come
//! from proto, the definitions the planner shares.

pub mod bench;
pub mod bridge;
pub mod csv;
pub mod deadline;
pub mod env;
pub mod error;
mod link;
mod mujoco;
#[cfg(feature = "render")]
pub mod render;
pub mod tasks;

pub use bridge::{BridgeConfig, BridgeError, EpisodeRecord};
pub use deadline::EpisodeDeadline;
pub use env::{Env, StepOutcome};
pub use error::SimError;
pub use tasks::SIMULATED;
