//! Transitions compared bit for bit: what an agent was acknowledged against what a planner
//! stored in its replay. The exact `f32` bits, not the values: a transition changed on its way
//! to the log by as little as a rounding cannot pass for the one acknowledged, and the keys can
//! be hashed (a NaN still equals itself).

use planner_service::replay::ReplayBuffer;
use std::collections::HashSet;

/// A transition `(s, a, s')` as the bits of its numbers, in that order.
pub type TransitionKey = Vec<u32>;

/// The key of one transition.
pub fn transition_key(obs: &[f32], act: &[f32], next: &[f32]) -> TransitionKey {
    obs.iter()
        .chain(act)
        .chain(next)
        .map(|x| x.to_bits())
        .collect()
}

/// The keys of every transition a replay buffer holds.
pub fn stored_keys(buffer: &ReplayBuffer) -> HashSet<TransitionKey> {
    let stored = buffer.transitions();
    (0..stored.len())
        .map(|i| {
            let (obs, act, next) = stored.row(i);
            transition_key(obs, act, next)
        })
        .collect()
}
