//! What a solve that shares the cores looks at to make way for a more urgent plan.
//!
//! The scheduler implements it ([`super::Scheduler`]'s turn); the planners (`crate::plan`) call
//! it between iterations and imagined steps. It lives here, with the scheduler, so that the
//! planners depend on scheduling and never the other way round.

use std::time::Duration;

/// What may pause a solve: the scheduler, when a more urgent plan waits for the cores.
pub trait Preempt: Send + Sync + std::fmt::Debug {
    /// Blocks while a more urgent plan has the cores. Called between two iterations and
    /// between two imagined time steps (never inside a rayon job: the pause must leave the
    /// pool's threads free for the plan it makes way for).
    fn step_back(&self);

    /// Whether a more urgent plan waits for the cores now, so that [`Preempt::step_back`]
    /// would pause. Looked at after every imagined step by each population chunk, so it must
    /// not block; the chunks meet to step back only when it says so. The default, `true`,
    /// meets after every step.
    fn outranked(&self) -> bool {
        true
    }

    /// Everything this solve has spent stepped back so far, so that iteration timings can
    /// leave it out.
    fn paused(&self) -> Duration;
}
