//! Transitions `(s, a, r, s')` laid out as dense row-major `f32` matrices.
//!
//! This is the one currency between the replay buffer (which owns the data), the trainers of the
//! dynamics and energy models (which read it in minibatches) and the tests (which build it from
//! known distributions). Row-major matrices feed `gemm` directly without copies.

/// A set of transitions: row `i` of `obs`, `act`, `rewards`, `next_obs` and `terminated` is one
/// transition. The reward is the one the agent reported for it: what a learned reward model
/// trains on; `terminated` says that its agent ended the episode there as `terminated` (the
/// system's own end, not a time limit): what a learned termination trains on.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Transitions {
    obs_dim: usize,
    act_dim: usize,
    obs: Vec<f32>,
    act: Vec<f32>,
    rewards: Vec<f32>,
    next_obs: Vec<f32>,
    terminated: Vec<bool>,
}

impl Transitions {
    /// An empty set for observations of `obs_dim` and actions of `act_dim` numbers.
    pub fn new(obs_dim: usize, act_dim: usize) -> Self {
        Self {
            obs_dim,
            act_dim,
            ..Self::default()
        }
    }

    /// Appends one transition `obs --act--> next_obs` that earned `reward`. Panics if a slice
    /// has the wrong length: callers validate untrusted input before it gets here.
    pub fn push(&mut self, obs: &[f32], act: &[f32], reward: f32, next_obs: &[f32]) {
        assert_eq!(obs.len(), self.obs_dim, "observation dimension");
        assert_eq!(act.len(), self.act_dim, "action dimension");
        assert_eq!(next_obs.len(), self.obs_dim, "next observation dimension");
        self.obs.extend_from_slice(obs);
        self.act.extend_from_slice(act);
        self.rewards.push(reward);
        self.next_obs.extend_from_slice(next_obs);
        self.terminated.push(false);
    }

    /// Marks transition `i` as the one its episode terminated with (see [`Transitions::terminated`]).
    pub fn mark_terminated(&mut self, i: usize) {
        self.terminated[i] = true;
    }

    /// Appends every transition of `other` (same dimensions).
    pub fn extend(&mut self, other: &Transitions) {
        assert_eq!((self.obs_dim, self.act_dim), (other.obs_dim, other.act_dim));
        self.obs.extend_from_slice(&other.obs);
        self.act.extend_from_slice(&other.act);
        self.rewards.extend_from_slice(&other.rewards);
        self.next_obs.extend_from_slice(&other.next_obs);
        self.terminated.extend_from_slice(&other.terminated);
    }

    /// Keeps the transitions whose row index `keep` accepts, in order.
    pub fn retain(&mut self, mut keep: impl FnMut(usize) -> bool) {
        let (od, ad) = (self.obs_dim, self.act_dim);
        let mut kept = 0;
        for i in 0..self.len() {
            if !keep(i) {
                continue;
            }
            if kept != i {
                self.obs.copy_within(i * od..(i + 1) * od, kept * od);
                self.next_obs.copy_within(i * od..(i + 1) * od, kept * od);
                self.act.copy_within(i * ad..(i + 1) * ad, kept * ad);
                self.rewards[kept] = self.rewards[i];
                self.terminated[kept] = self.terminated[i];
            }
            kept += 1;
        }
        self.obs.truncate(kept * od);
        self.next_obs.truncate(kept * od);
        self.act.truncate(kept * ad);
        self.rewards.truncate(kept);
        self.terminated.truncate(kept);
    }

    pub fn len(&self) -> usize {
        self.obs.len().checked_div(self.obs_dim).unwrap_or(0)
    }

    pub fn is_empty(&self) -> bool {
        self.obs.is_empty()
    }

    pub fn obs_dim(&self) -> usize {
        self.obs_dim
    }

    pub fn act_dim(&self) -> usize {
        self.act_dim
    }

    /// All observations, `len() × obs_dim`, row-major.
    pub fn obs(&self) -> &[f32] {
        &self.obs
    }

    /// All actions, `len() × act_dim`, row-major.
    pub fn act(&self) -> &[f32] {
        &self.act
    }

    /// Every transition's reward, as its agent reported it.
    pub fn rewards(&self) -> &[f32] {
        &self.rewards
    }

    /// Whether each transition ended its episode as `terminated` (the system's own end: nothing
    /// follows its next observation), as its agent reported it.
    pub fn terminated(&self) -> &[bool] {
        &self.terminated
    }

    /// All next observations, `len() × obs_dim`, row-major.
    pub fn next_obs(&self) -> &[f32] {
        &self.next_obs
    }

    /// Transition `i` as `(s, a, s')`.
    pub fn row(&self, i: usize) -> (&[f32], &[f32], &[f32]) {
        let (o, a) = (self.obs_dim, self.act_dim);
        (
            &self.obs[i * o..(i + 1) * o],
            &self.act[i * a..(i + 1) * a],
            &self.next_obs[i * o..(i + 1) * o],
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_round_trip() {
        let mut t = Transitions::new(2, 1);
        t.push(&[1.0, 2.0], &[0.5], 0.25, &[3.0, 4.0]);
        t.push(&[5.0, 6.0], &[-0.5], -1.0, &[7.0, 8.0]);
        assert_eq!(t.len(), 2);
        assert_eq!(t.row(1), (&[5.0, 6.0][..], &[-0.5][..], &[7.0, 8.0][..]));
        assert_eq!(t.rewards(), &[0.25, -1.0]);
        t.mark_terminated(1);
        assert_eq!(t.terminated(), &[false, true]);
        let mut u = Transitions::new(2, 1);
        u.extend(&t);
        assert_eq!(u, t);
        u.retain(|i| i == 1);
        assert_eq!(u.rewards(), &[-1.0]);
        assert_eq!(u.terminated(), &[true]);
        assert_eq!(u.row(0).0, &[5.0, 6.0]);
    }
}
