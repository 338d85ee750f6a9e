//! What CEM, iCEM and Adam planning share as searches over action sequences: the objective
//! that scores a population, the box a sequence lives in (and the MPC shift of a plan), and
//! what one solve did.

use super::settings::ConfigError;

/// Scores a whole population of action sequences at once (higher is better).
///
/// Batching is the point: the objective behind the planner pushes all candidates through the
/// networks together, step by step, instead of one sequence at a time.
pub trait PopulationObjective {
    /// `actions` holds `returns.len()` candidates, each `horizon × act_dim` numbers, row-major.
    /// Write one score per candidate into `returns`. Non-finite scores are allowed: the
    /// optimiser ranks them below every finite one.
    fn evaluate(&mut self, actions: &[f32], returns: &mut [f32]);
}

/// What one solve did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CemOutcome {
    /// Iterations run: at least 1 unless a deadline left no time for one (then the
    /// distribution is the warm start, untouched).
    pub iterations: u32,
    /// Iterations were left out because the next one would have crossed the deadline.
    pub cut: bool,
    /// Mean score of the last iteration's elites; `-inf` if every one of them was non-finite.
    pub elite_return: f32,
}

/// The box an action sequence lives in: the per-step bounds, checked once and tiled over the
/// horizon. CEM and iCEM both start from it.
pub(super) struct SequenceBox {
    pub act_dim: usize,
    /// Bounds per coordinate (`horizon × act_dim`).
    pub lower: Vec<f32>,
    pub upper: Vec<f32>,
}

impl SequenceBox {
    /// Tiles `lower`/`upper` (one entry per action dimension) over `horizon` steps, or refuses
    /// bounds that are empty, of different lengths, not finite or not increasing.
    pub fn new(lower: &[f32], upper: &[f32], horizon: usize) -> Result<Self, ConfigError> {
        let bounds_ok = lower.len() == upper.len()
            && !lower.is_empty()
            && lower
                .iter()
                .zip(upper)
                .all(|(l, u)| l.is_finite() && u.is_finite() && l < u);
        if !bounds_ok {
            return Err(ConfigError::Bounds);
        }
        let dim = horizon * lower.len();
        Ok(Self {
            act_dim: lower.len(),
            lower: lower.iter().copied().cycle().take(dim).collect(),
            upper: upper.iter().copied().cycle().take(dim).collect(),
        })
    }

    /// `f(lower, upper)` for every coordinate: an optimiser's initial mean or spread.
    pub fn per_coordinate(lower: &[f32], upper: &[f32], f: impl Fn(f32, f32) -> f32) -> Vec<f32> {
        lower.iter().zip(upper).map(|(&l, &u)| f(l, u)).collect()
    }

    /// The warm start of the next time step, in place: `plan` (`horizon × act_dim`) drops its
    /// first action, moves the rest one step forward and ends with `initial`'s last action.
    /// The one MPC shift that CEM, iCEM and Adam share.
    pub fn shift_plan(plan: &mut [f32], act_dim: usize, initial: &[f32]) {
        let dim = plan.len();
        plan.copy_within(act_dim.., 0);
        plan[dim - act_dim..].copy_from_slice(&initial[dim - act_dim..]);
    }
}
