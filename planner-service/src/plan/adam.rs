//! Gradient-based trajectory optimisation: Adam on the action sequence, back-propagating the
//! regularised imagined return through the learned dynamics over the whole horizon — the
//! paper's "Adam + DAE" baseline (Boney et al. 2019, "Regularizing trajectory optimization
//! with denoising autoencoders").
//!
//! **What it optimises.** For a candidate sequence `a₀…a_{H−1}` from the observation `s₀`,
//! `J = Σ_t alive_t [ r(s_t, a_t, s_{t+1}) − α·E(s_t, a_t, s_{t+1}) ]`, `s_{t+1} = f(s_t, a_t)`,
//! the objective [`super::imagine`] scores for CEM, with `f` the dynamics' **mean** prediction:
//! with an ensemble, particle `p` follows member `p mod B` as in imagination, and since
//! without sampling the particles of one member are identical, each member is rolled out once
//! and weighted by its share of the particles. PETS' sampled particles (TS∞) are not used:
//! Boney et al. plan through the mean of a single model, and a sampled objective would make
//! every Adam step follow a different function. The reward's gradient is the task's own (for
//! the whole population per step, [`proto::Task::reward_gradients`]: a formula through the
//! expression language's block evaluator, with its `∂r/∂s_t` where it reads `s`) or, for a
//! task whose reward is learned, the reward model's ([`crate::reward::RewardModel::predict_with_gradient`],
//! which unlike the catalog's rewards also depends on `s_t`); the regulariser's is
//! [`Regularizer::energy_and_gradient`]: for the DAE, the penalty `‖g(x) − x‖²` with the
//! gradient stopped at the autoencoder, as the paper describes Boney et al.'s method (§3).
//! Termination (the ant falling; a learned termination's prediction) stops a row accruing, as
//! in imagination; its gradient does not pass through the termination test.
//!
//! **Back-propagation through the horizon.** The forward pass keeps every step's network
//! activations (one [`MeanTape`] per step and member) and the gradients of each step's own
//! terms; the backward pass carries `λ_t = ∂J/∂s_t` from the last step to the first,
//! `λ_t = ∂J_t/∂s_t + (∂f/∂s_t)ᵀ (∂J_t/∂s_{t+1} + λ_{t+1})`, and collects
//! `∂J/∂a_t = ∂J_t/∂a_t + (∂f/∂a_t)ᵀ (∂J_t/∂s_{t+1} + λ_{t+1})`.
//!
//! **Search.** `population` candidates are optimised together (one batch through the
//! networks): candidate 0 starts from the warm start, the others from the warm start plus
//! Gaussian noise of standard deviation `(ub − lb)/4` (CEM's initial spread), clamped into
//! the bounds. Each of `iterations` Adam steps (β = 0.9, 0.999, ε = 1e-8, ascent) moves
//! every coordinate by about `learning_rate × (ub − lb)/2`, then projects it back into the
//! bounds (clamping, not a tanh reparameterisation: no saturation to climb out of, and a
//! plan at a bound stays there only while the gradient pushes it outwards). The answer is
//! the best sequence seen at any iterate, scored once more after the last step. The plan is
//! warm-started like CEM's: the previous best, shifted by one step, the neutral action
//! appended.
//!
//! **Deviations and choices.** Neither the paper nor this project's sources give Boney et
//! al.'s Adam settings; the `adam+dae` preset's (see `config/preset.rs`) are documented
//! choices. Gradients are computed through the training pass of the networks, whose products
//! run in the number format of the run's inference ([`crate::nn::Tape::for_planning`]): exact f32
//! where inference is f32, the training path measured fastest (the AMX tiles where they win
//! clearly, which at the preset's 16 sequences they do not) where it is bf16. All buffers are allocated when the planner is built
//! and on the first call with a model (again only for a model of another shape);
//! [`AdamPlanner::optimize`] allocates nothing.

use super::Learned;
use super::anytime::IterationClock;
use super::sequence::{CemOutcome, SequenceBox};
use super::settings::{CemConfig, ConfigError};
use crate::dynamics::{Ensemble, MeanTape};
use crate::energy::{EnergyGradScratch, Regularizer};
use crate::reward::RewardTape;
use crate::termination::TerminationScratch;
use proto::Task;
use proto::task::FormulaScratch;
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;

const BETA1: f32 = 0.9;
const BETA2: f32 = 0.999;
const EPSILON: f32 = 1e-8;

/// The gradient-based planner: one agent's Adam state, warm start and rollout memory.
#[derive(Debug)]
pub struct AdamPlanner {
    config: CemConfig,
    task: &'static Task,
    /// Bounds, half-ranges and the neutral action per coordinate (`horizon × act_dim`).
    lower: Vec<f32>,
    upper: Vec<f32>,
    half_range: Vec<f32>,
    neutral: Vec<f32>,
    /// The warm start of the next solve.
    warm: Vec<f32>,
    /// Candidates (`population × horizon × act_dim`), their gradient and Adam's moments.
    params: Vec<f32>,
    grad: Vec<f32>,
    m: Vec<f32>,
    v: Vec<f32>,
    /// Per candidate: objective and mean energy per step of the last forward pass.
    returns: Vec<f32>,
    energies: Vec<f32>,
    /// The best sequence seen in the last solve, its objective and mean energy per step.
    best: Vec<f32>,
    best_return: f32,
    best_energy: f32,
    rollout: Option<Rollout>,
    rng: StdRng,
    energy_weight: f32,
}

/// The memory of one differentiable rollout of every candidate, tied to the models' shapes.
/// Rows are `member × candidates` (row `m·C + i`: candidate `i` through member `m`).
#[derive(Debug)]
struct Rollout {
    members: usize,
    /// Share of the particles following each member.
    weight: Vec<f32>,
    /// `states[t]`: the rows' states at step `t` (`H + 1` of them).
    states: Vec<Vec<f32>>,
    /// The step's action per row.
    act: Vec<f32>,
    /// `tapes[t][m]`: member `m`'s network activations at step `t`.
    tapes: Vec<Vec<MeanTape>>,
    energy_scratch: EnergyGradScratch,
    /// Per step, per row: the gradient of the step's own term w.r.t. `s_t`, `a_t`, `s_{t+1}`
    /// (already weighted by the member's share and zero once a row has terminated).
    g_obs: Vec<Vec<f32>>,
    g_act: Vec<Vec<f32>>,
    g_next: Vec<Vec<f32>>,
    /// Per row: accumulated objective, accumulated energy, still alive; the step's energy.
    ret: Vec<f32>,
    energy_sum: Vec<f32>,
    alive: Vec<bool>,
    energy: Vec<f32>,
    /// Back-propagation buffers (rows × dims).
    lambda: Vec<f32>,
    d_next: Vec<f32>,
    d_obs: Vec<f32>,
    d_act: Vec<f32>,
    /// The step's reward per row and its gradient w.r.t. `s_t`, `a_t`, `s_{t+1}` (rows × dims).
    reward: Vec<f32>,
    r_obs: Vec<f32>,
    r_act: Vec<f32>,
    r_next: Vec<f32>,
    /// The reward model's training pass, for a learned reward.
    reward_tape: Option<RewardTape>,
    /// The termination model's working memory, for a learned termination.
    termination_scratch: Option<TerminationScratch>,
    /// Per row: whether the step's next state ends the episode.
    terminal: Vec<bool>,
    /// The task's formulas' working memory.
    formulas: FormulaScratch,
}

impl AdamPlanner {
    /// A planner for actions bounded by `lower`/`upper` (one entry per action dimension),
    /// scoring plans as `Σ reward − energy_weight · energy`, seeded for reproducible solves.
    pub fn new(
        task: &'static Task,
        config: CemConfig,
        energy_weight: f32,
        seed: u64,
    ) -> Result<Self, ConfigError> {
        config.validate()?;
        config.adam.validate()?;
        if !(energy_weight.is_finite() && energy_weight >= 0.0) {
            return Err(ConfigError::EnergyWeight(energy_weight));
        }
        let SequenceBox { lower, upper, .. } =
            SequenceBox::new(&task.action_low, &task.action_high, config.horizon)?;
        let half_range = SequenceBox::per_coordinate(&lower, &upper, |l, u| 0.5 * (u - l));
        let neutral = SequenceBox::per_coordinate(&lower, &upper, |l, u| 0.5 * (l + u));
        let (dim, c) = (lower.len(), config.population);
        Ok(Self {
            warm: neutral.clone(),
            best: neutral.clone(),
            params: vec![0.0; c * dim],
            grad: vec![0.0; c * dim],
            m: vec![0.0; c * dim],
            v: vec![0.0; c * dim],
            returns: vec![0.0; c],
            energies: vec![0.0; c],
            best_return: f32::NEG_INFINITY,
            best_energy: 0.0,
            rollout: None,
            rng: StdRng::seed_from_u64(seed),
            config,
            task,
            lower,
            upper,
            half_range,
            neutral,
            energy_weight,
        })
    }

    pub fn config(&self) -> &CemConfig {
        &self.config
    }

    /// Forgets the warm start; call at the start of an episode.
    pub fn reset(&mut self) {
        self.warm.copy_from_slice(&self.neutral);
    }

    /// Moves the warm start one step forward: the best plan without its first action, the
    /// neutral action appended.
    pub fn shift(&mut self) {
        self.warm.copy_from_slice(&self.best);
        SequenceBox::shift_plan(&mut self.warm, self.task.act_dim, &self.neutral);
    }

    /// The warm start of the next solve.
    pub fn mean(&self) -> &[f32] {
        &self.warm
    }

    pub fn set_mean(&mut self, mean: &[f32]) {
        self.warm.copy_from_slice(mean);
    }

    /// The best sequence of the last solve.
    pub fn best(&self) -> &[f32] {
        &self.best
    }

    pub fn first_action(&self) -> &[f32] {
        &self.best[..self.task.act_dim]
    }

    /// Mean energy per imagined step of the last solve's best sequence.
    pub fn best_energy(&self) -> f32 {
        self.best_energy
    }

    /// Optimises the plan from `obs` with the given models; the answer is in
    /// [`AdamPlanner::best`]. `elite_return` is the best sequence's objective (`-inf` if every
    /// iterate diverged, in which case the warm start is the plan).
    pub fn optimize(
        &mut self,
        obs: &[f32],
        dynamics: &Ensemble,
        regularizer: &Regularizer,
        learned: Learned<'_>,
        clock: &mut IterationClock,
    ) -> CemOutcome {
        assert_eq!(obs.len(), self.task.obs_dim, "observation dimension");
        self.prepare(dynamics, regularizer, learned);
        let dim = self.warm.len();
        for (i, candidate) in self.params.chunks_exact_mut(dim).enumerate() {
            candidate.copy_from_slice(&self.warm);
            if i > 0 {
                for (k, x) in candidate.iter_mut().enumerate() {
                    let z: f32 = self.rng.sample(StandardNormal);
                    *x = (*x + 0.5 * self.half_range[k] * z).clamp(self.lower[k], self.upper[k]);
                }
            }
        }
        self.m.fill(0.0);
        self.v.fill(0.0);
        self.best.copy_from_slice(&self.warm);
        self.best_return = f32::NEG_INFINITY;
        self.best_energy = 0.0;
        let (iterations, population) = (self.config.iterations, self.config.population);
        let mut done = 0;
        let mut cut = false;
        for step in 1..=iterations + 1 {
            // One iteration is a forward and a backward pass; the last forward pass only
            // scores the final step. A deadline stops before an iteration that would cross it
            // (the step taken last is then left unscored: the best scored sequence answers).
            let scores_only = step > iterations;
            if !scores_only && !clock.may_start(population, step == 1) {
                cut = true;
                break;
            }
            self.forward(obs, dynamics, regularizer, learned);
            self.keep_best();
            if scores_only {
                break;
            }
            self.backward(dynamics);
            self.adam_step(step as i32);
            clock.finished(population);
            done += 1;
        }
        CemOutcome {
            iterations: done,
            elite_return: self.best_return,
            cut,
        }
    }

    /// Records the best candidate of the last forward pass if it beats the best so far.
    fn keep_best(&mut self) {
        let dim = self.warm.len();
        for (i, &ret) in self.returns.iter().enumerate() {
            if ret.is_finite() && ret > self.best_return {
                self.best_return = ret;
                self.best_energy = self.energies[i];
                self.best
                    .copy_from_slice(&self.params[i * dim..(i + 1) * dim]);
            }
        }
    }

    /// One Adam ascent step on every candidate with a finite gradient, then the projection
    /// into the bounds.
    fn adam_step(&mut self, t: i32) {
        let dim = self.warm.len();
        let lr = self.config.adam.learning_rate;
        let (c1, c2) = (1.0 - BETA1.powi(t), 1.0 - BETA2.powi(t));
        for i in 0..self.config.population {
            let span = i * dim..(i + 1) * dim;
            if !self.grad[span.clone()].iter().all(|g| g.is_finite()) {
                continue; // a diverged rollout: this candidate stays where it is
            }
            for k in span {
                let c = k % dim;
                let g = self.grad[k];
                self.m[k] = BETA1 * self.m[k] + (1.0 - BETA1) * g;
                self.v[k] = BETA2 * self.v[k] + (1.0 - BETA2) * g * g;
                let step = lr * self.half_range[c] * (self.m[k] / c1)
                    / ((self.v[k] / c2).sqrt() + EPSILON);
                self.params[k] = (self.params[k] + step).clamp(self.lower[c], self.upper[c]);
            }
        }
    }

    /// Makes sure the rollout memory fits these models.
    fn prepare(&mut self, dynamics: &Ensemble, regularizer: &Regularizer, learned: Learned<'_>) {
        learned.assert_matches(self.task);
        let Learned {
            reward,
            termination,
        } = learned;
        let c = self.config.population;
        let members = dynamics.members().min(self.config.particles);
        let fits = self.rollout.as_ref().is_some_and(|r| {
            r.members == members
                && r.energy_scratch.fits(regularizer, members * c)
                && match (reward, &r.reward_tape) {
                    (None, _) => true,
                    (Some(m), Some(tape)) => tape.fits(m, members * c),
                    (Some(_), None) => false,
                }
                && match (termination, &r.termination_scratch) {
                    (None, _) => true,
                    (Some(m), Some(scratch)) => scratch.fits(m, members * c),
                    (Some(_), None) => false,
                }
                && r.tapes[0]
                    .iter()
                    .enumerate()
                    .all(|(m, tape)| tape.fits(dynamics.member(m), c))
        });
        if !fits {
            self.rollout = Some(Rollout::new(
                self.task,
                &self.config,
                members,
                (dynamics, regularizer, learned),
            ));
        }
    }

    /// Rolls every candidate forward through the mean dynamics, accumulating the objective and
    /// recording what [`AdamPlanner::backward`] needs.
    fn forward(
        &mut self,
        obs: &[f32],
        dynamics: &Ensemble,
        regularizer: &Regularizer,
        learned: Learned<'_>,
    ) {
        let (o, a, h) = (self.task.obs_dim, self.task.act_dim, self.config.horizon);
        let c = self.config.population;
        let r = self.rollout.as_mut().expect("prepared");
        let rows = r.members * c;
        for s in r.states[0].chunks_exact_mut(o) {
            s.copy_from_slice(obs);
        }
        r.ret.fill(0.0);
        r.energy_sum.fill(0.0);
        r.alive.fill(true);
        for t in 0..h {
            for (row, act) in r.act.chunks_exact_mut(a).enumerate() {
                let i = row % c;
                let at = i * h * a + t * a;
                act.copy_from_slice(&self.params[at..at + a]);
            }
            let (before, after) = r.states.split_at_mut(t + 1);
            let (state, next) = (&before[t], &mut after[0]);
            for m in 0..r.members {
                let block = m * c..(m + 1) * c;
                dynamics.member(m).predict_mean_recorded(
                    &state[block.start * o..block.end * o],
                    &r.act[block.start * a..block.end * a],
                    c,
                    &mut r.tapes[t][m],
                    &mut next[block.start * o..block.end * o],
                );
            }
            regularizer.energy_and_gradient(
                state,
                &r.act,
                next,
                rows,
                &mut r.energy_scratch,
                &mut r.energy,
                &mut r.g_obs[t],
                &mut r.g_act[t],
                &mut r.g_next[t],
            );
            if let Some(model) = learned.reward {
                model.predict_with_gradient(
                    state,
                    &r.act,
                    next,
                    rows,
                    r.reward_tape
                        .as_mut()
                        .expect("prepared for the reward model"),
                    &mut r.reward,
                    &mut r.r_obs,
                    &mut r.r_act,
                    &mut r.r_next,
                );
            }
            if learned.reward.is_none() {
                // The whole population's rewards and gradients at once: a formula through the
                // block evaluator (its `∂r/∂s` included), builtin code row by row.
                self.task.reward_gradients(
                    state,
                    &r.act,
                    next,
                    &mut r.formulas,
                    &mut r.reward,
                    &mut r.r_obs,
                    &mut r.r_act,
                    &mut r.r_next,
                );
            }
            super::imagine::ended(
                self.task,
                learned.termination,
                next,
                rows,
                (&mut r.formulas, r.termination_scratch.as_mut()),
                &mut r.terminal,
            );
            let alpha = self.energy_weight;
            for row in 0..rows {
                let (go, ga, gn) = (
                    &mut r.g_obs[t][row * o..(row + 1) * o],
                    &mut r.g_act[t][row * a..(row + 1) * a],
                    &mut r.g_next[t][row * o..(row + 1) * o],
                );
                if !r.alive[row] {
                    go.fill(0.0);
                    ga.fill(0.0);
                    gn.fill(0.0);
                    continue;
                }
                let (dr_obs, dr_act, dr_next) = (
                    &r.r_obs[row * o..(row + 1) * o],
                    &r.r_act[row * a..(row + 1) * a],
                    &r.r_next[row * o..(row + 1) * o],
                );
                let reward = r.reward[row];
                r.ret[row] += reward - alpha * r.energy[row];
                r.energy_sum[row] += r.energy[row];
                // ∂J_t = w · (∂r − α ∂E), the member's share `w` of the particles.
                let w = r.weight[row / c];
                for (g, dr) in go.iter_mut().zip(dr_obs) {
                    *g = w * (dr - alpha * *g);
                }
                for (g, dr) in ga.iter_mut().zip(dr_act) {
                    *g = w * (dr - alpha * *g);
                }
                for (g, dr) in gn.iter_mut().zip(dr_next) {
                    *g = w * (dr - alpha * *g);
                }
                if r.terminal[row] {
                    r.alive[row] = false;
                }
            }
        }
        let inv_steps = 1.0 / h as f32;
        for i in 0..c {
            let (mut ret, mut energy) = (0.0, 0.0);
            for m in 0..r.members {
                ret += r.weight[m] * r.ret[m * c + i];
                energy += r.weight[m] * r.energy_sum[m * c + i];
            }
            self.returns[i] = if ret.is_finite() {
                ret
            } else {
                f32::NEG_INFINITY
            };
            self.energies[i] = energy * inv_steps;
        }
    }

    /// Back-propagates the last forward pass's objective to every candidate's actions, into
    /// `grad`.
    fn backward(&mut self, dynamics: &Ensemble) {
        let (o, a, h) = (self.task.obs_dim, self.task.act_dim, self.config.horizon);
        let c = self.config.population;
        let r = self.rollout.as_mut().expect("prepared");
        let rows = r.members * c;
        r.lambda.fill(0.0);
        for t in (0..h).rev() {
            for ((d, g), l) in r.d_next.iter_mut().zip(&r.g_next[t]).zip(&r.lambda) {
                *d = g + l;
            }
            for m in 0..r.members {
                let block = m * c..(m + 1) * c;
                dynamics.member(m).mean_backward(
                    &r.states[t][block.start * o..block.end * o],
                    c,
                    &mut r.tapes[t][m],
                    &r.d_next[block.start * o..block.end * o],
                    &mut r.d_obs[block.start * o..block.end * o],
                    &mut r.d_act[block.start * a..block.end * a],
                );
            }
            for ((l, d), g) in r.lambda.iter_mut().zip(&r.d_obs).zip(&r.g_obs[t]) {
                *l = d + g;
            }
            for i in 0..c {
                let at = i * h * a + t * a;
                let grad = &mut self.grad[at..at + a];
                grad.fill(0.0);
                for row in (0..rows).skip(i).step_by(c) {
                    for ((g, d), e) in grad
                        .iter_mut()
                        .zip(&r.d_act[row * a..(row + 1) * a])
                        .zip(&r.g_act[t][row * a..(row + 1) * a])
                    {
                        *g += d + e;
                    }
                }
            }
        }
    }
}

impl Rollout {
    fn new(
        task: &'static Task,
        config: &CemConfig,
        members: usize,
        (dynamics, regularizer, learned): (&Ensemble, &Regularizer, Learned<'_>),
    ) -> Self {
        let (o, a, h, c) = (
            task.obs_dim,
            task.act_dim,
            config.horizon,
            config.population,
        );
        let rows = members * c;
        let p = config.particles;
        let weight = (0..members)
            .map(|m| {
                super::imagine::particles_of_member(p, dynamics.members(), m) as f32 / p as f32
            })
            .collect();
        let per_step = |width: usize| (0..h).map(|_| vec![0.0; rows * width]).collect();
        Self {
            members,
            weight,
            states: (0..=h).map(|_| vec![0.0; rows * o]).collect(),
            act: vec![0.0; rows * a],
            tapes: (0..h)
                .map(|_| {
                    (0..members)
                        .map(|m| dynamics.member(m).mean_tape(c))
                        .collect()
                })
                .collect(),
            energy_scratch: regularizer.grad_scratch(rows),
            g_obs: per_step(o),
            g_act: per_step(a),
            g_next: per_step(o),
            ret: vec![0.0; rows],
            energy_sum: vec![0.0; rows],
            alive: vec![true; rows],
            energy: vec![0.0; rows],
            lambda: vec![0.0; rows * o],
            d_next: vec![0.0; rows * o],
            d_obs: vec![0.0; rows * o],
            d_act: vec![0.0; rows * a],
            reward: vec![0.0; rows],
            r_obs: vec![0.0; rows * o],
            r_act: vec![0.0; rows * a],
            r_next: vec![0.0; rows * o],
            reward_tape: learned.reward.map(|m| m.tape(rows)),
            termination_scratch: learned.termination.map(|m| m.scratch(rows)),
            terminal: vec![false; rows],
            formulas: task.formula_scratch(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::data::Transitions;
    use crate::dynamics::DynamicsConfig;
    use crate::energy::{EnergyConfig, RegularizerKind};
    use crate::nn::TrainPath;
    use crate::plan::settings::{AdamConfig, MAX_LEARNING_RATE};
    use crate::plan::{IcemConfig, Optimizer};
    use proto::Builtin;

    fn config(horizon: usize, population: usize, iterations: usize, particles: usize) -> CemConfig {
        CemConfig {
            horizon,
            population,
            elites: 1,
            iterations,
            smoothing: 0.1,
            min_variance: 1e-3,
            particles,
            optimizer: Optimizer::Adam,
            icem: IcemConfig::default(),
            adam: AdamConfig::default(),
        }
    }

    /// Random transitions of `spec` whose next state moves with the action (so that a plan's
    /// later states, and a reward of them, depend on its earlier actions), each rewarded
    /// `Σ sin(s')` (what a learned reward learns).
    fn random_data(spec: &Task, n: usize, rng: &mut StdRng) -> Transitions {
        let mut data = Transitions::new(spec.obs_dim, spec.act_dim);
        for _ in 0..n {
            let obs: Vec<f32> = (0..spec.obs_dim)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let act: Vec<f32> = (0..spec.act_dim)
                .map(|d| rng.random_range(spec.action_low[d]..spec.action_high[d]))
                .collect();
            let push: f32 = act.iter().sum::<f32>() / spec.act_dim as f32;
            let next: Vec<f32> = obs
                .iter()
                .map(|o| o + 0.5 * push + 0.1 * rng.random_range(-1.0f32..1.0))
                .collect();
            let reward = next.iter().map(|x| x.sin()).sum();
            data.push(&obs, &act, reward, &next);
        }
        data
    }

    /// Cartpole whose reward is learned.
    fn learned_cartpole() -> &'static Task {
        let mut spec = Builtin::Cartpole.spec();
        spec.name = "adam-learned-cartpole".into();
        spec.reward = proto::task::RewardKind::Learned;
        Task::intern(spec, &proto::task::SpecBounds::default()).unwrap()
    }

    /// Cartpole whose reward is a formula that reads `s` as well as `s_next` and `a`.
    fn formula_cartpole() -> &'static Task {
        let mut spec = Builtin::Cartpole.spec();
        spec.name = "adam-formula-cartpole".into();
        spec.reward = proto::task::RewardKind::Expression(
            "exp(-s_next[0]^2) - 0.5*s[1]*s_next[1] + 2*sin(s[3]) - 0.01*dot(a, a)".into(),
        );
        Task::intern(spec, &proto::task::SpecBounds::default()).unwrap()
    }

    /// The whole-horizon gradient (dynamics of a two-member ensemble with three particles,
    /// task reward, a formula or a learned one (both of whose gradients reach `s_t` too), DAE
    /// penalty with its stopped gradient, DEEN's exact one) against central differences of the
    /// objective the forward pass computes.
    #[test]
    fn whole_horizon_gradient_matches_finite_differences() {
        for (spec, kind) in [
            (Builtin::Cartpole.task(), RegularizerKind::Dae),
            (Builtin::HalfCheetah.task(), RegularizerKind::Deen),
            (learned_cartpole(), RegularizerKind::Deen),
            (formula_cartpole(), RegularizerKind::Deen),
        ] {
            let task = spec.name();
            let mut rng = StdRng::seed_from_u64(17);
            let data = random_data(spec, 200, &mut rng);
            let dynamics_config = DynamicsConfig {
                hidden_layers: 2,
                hidden_size: 16,
                ensemble_size: 2,
                ..Default::default()
            };
            let mut dynamics = Ensemble::new(spec, &dynamics_config, &mut rng);
            dynamics.fit(&data, 2, &mut rng);
            let energy_config = EnergyConfig {
                hidden_layers: 2,
                hidden_size: 16,
                noise_sigma: 0.3,
                noise_units: Default::default(),
                ..Default::default()
            };
            let mut reg =
                Regularizer::new(kind, &energy_config, spec.obs_dim, spec.act_dim, &mut rng);
            reg.fit(&data, 2, &mut rng);
            let reward = spec.reward_is_learned().then(|| {
                let sizes = crate::reward::RewardConfig {
                    hidden_layers: 2,
                    hidden_size: 16,
                };
                let mut model = crate::reward::RewardModel::new(
                    spec,
                    &sizes,
                    &DynamicsConfig::default(),
                    &mut rng,
                );
                model.fit(&data, 3, &mut rng);
                model
            });
            let reward = reward.as_ref();
            // A frozen DAE output for the finite differences: the stopped gradient is the
            // gradient of the penalty with g held fixed, so compare only with DEEN's exact
            // gradient through the energy, and with the DAE at α = 0 plus its own test
            // (energy::tests) for the stopped term.
            let alpha = if kind == RegularizerKind::Deen {
                0.3
            } else {
                0.0
            };
            let mut planner = AdamPlanner::new(spec, config(4, 3, 1, 3), alpha, 5).unwrap();
            planner.prepare(&dynamics, &reg, crate::plan::Learned::reward(reward));
            let dim = planner.warm.len();
            for (k, p) in planner.params.iter_mut().enumerate() {
                let c = k % dim;
                *p = 0.5 * planner.upper[c] * (0.7 * (k as f32 * 1.3).sin());
            }
            let obs: Vec<f32> = (0..spec.obs_dim).map(|i| 0.2 * (i as f32).cos()).collect();
            planner.forward(&obs, &dynamics, &reg, crate::plan::Learned::reward(reward));
            planner.backward(&dynamics);
            let grad = planner.grad.clone();
            let base = planner.params.clone();
            for k in 0..base.len() {
                let h = 1e-2 * planner.half_range[k % dim];
                let mut at = |x: f32| {
                    planner.params.copy_from_slice(&base);
                    planner.params[k] = x;
                    planner.forward(&obs, &dynamics, &reg, crate::plan::Learned::reward(reward));
                    planner.returns[k / dim] as f64
                };
                let fd = ((at(base[k] + h) - at(base[k] - h)) / (2.0 * h as f64)) as f32;
                assert!(
                    (grad[k] - fd).abs() <= 2e-2 * (1.0 + fd.abs()),
                    "{task} {kind} coordinate {k}: {} vs {fd}",
                    grad[k]
                );
            }
        }
    }

    /// Half-cheetah's reward is the predicted forward velocity minus `0.1‖a‖²`. A model that
    /// has learned `v' = w·a` makes the best action of every step `a* = w / 0.2`, inside the
    /// bounds: Adam must find it, at every step of the horizon, from the neutral start, with
    /// the gradients' products on every path this CPU has (exact f32, and the AMX tiles'
    /// bf16 factors where a run's bf16 inference makes them the planning path).
    #[test]
    fn finds_the_known_optimum_through_a_learned_model() {
        for path in TrainPath::available() {
            finds_the_known_optimum_on(path);
        }
    }

    fn finds_the_known_optimum_on(path: TrainPath) {
        let task = Builtin::HalfCheetah;
        let spec = task.task();
        let w = [0.1f32, -0.05, 0.02, 0.0, 0.08, -0.1];
        let optimum: Vec<f32> = w.iter().map(|w| w / 0.2).collect();
        let mut rng = StdRng::seed_from_u64(3);
        let mut data = Transitions::new(spec.obs_dim, spec.act_dim);
        for _ in 0..3000 {
            let obs: Vec<f32> = (0..spec.obs_dim)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let act: Vec<f32> = (0..spec.act_dim)
                .map(|_| rng.random_range(-1.0..1.0))
                .collect();
            let mut next = obs.clone();
            next[0] = w.iter().zip(&act).map(|(w, a)| w * a).sum();
            for n in &mut next[1..] {
                *n += 0.01 * rng.random_range(-1.0f32..1.0);
            }
            data.push(&obs, &act, 0.0, &next);
        }
        let dynamics_config = DynamicsConfig {
            hidden_layers: 2,
            hidden_size: 32,
            ..Default::default()
        };
        let mut dynamics = Ensemble::new(spec, &dynamics_config, &mut rng);
        // (The other coordinates are unpredictable noise: the report's mean error is not the
        // velocity's; the optimum below is what shows the model learned `w`.)
        dynamics.fit(&data, 30, &mut rng);
        dynamics.member_mut(0).pin_train_path(Some(path));
        let mut planner = AdamPlanner::new(spec, config(5, 4, 60, 1), 0.0, 1).unwrap();
        let mut clock = IterationClock::default();
        let outcome = planner.optimize(
            &[0.0; 18],
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            &mut clock,
        );
        assert_eq!(outcome.iterations, 60);
        assert!(!outcome.cut);
        for (t, step) in planner.best().chunks_exact(6).enumerate() {
            for (d, (a, want)) in step.iter().zip(&optimum).enumerate() {
                assert!(
                    (a - want).abs() < 0.1,
                    "{path}: step {t} action {d}: {a} vs {want}: {step:?}"
                );
            }
        }
        // The objective at the optimum: 5 steps of Σ w²/0.4 (as the model predicts it).
        let best = 5.0 * w.iter().map(|w| w * w / 0.4).sum::<f32>();
        assert!(
            (outcome.elite_return - best).abs() < 0.05,
            "{path}: {outcome:?} vs {best}"
        );
        // The warm start is the plan shifted by one step with the neutral action appended.
        planner.shift();
        assert_eq!(&planner.mean()[..24], &planner.best()[6..]);
        assert_eq!(&planner.mean()[24..], &[0.0; 6]);
        // A deadline already passed leaves no time for a step: the answer is that warm start.
        let warm = planner.mean().to_vec();
        clock.start(Some(
            std::time::Instant::now() - std::time::Duration::from_millis(1),
        ));
        let outcome = planner.optimize(
            &[0.0; 18],
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            &mut clock,
        );
        assert_eq!((outcome.iterations, outcome.cut), (0, true));
        assert_eq!(planner.best(), &warm[..]);
        planner.reset();
        assert!(planner.mean().iter().all(|&a| a == 0.0));
    }

    #[test]
    fn refuses_bad_learning_rates() {
        let spec = Builtin::Cartpole.task();
        for lr in [0.0, -0.1, f32::NAN, f32::INFINITY, MAX_LEARNING_RATE * 2.0] {
            let mut c = config(3, 2, 2, 1);
            c.adam.learning_rate = lr;
            assert!(
                matches!(
                    AdamPlanner::new(spec, c, 0.0, 0),
                    Err(ConfigError::Adam(..))
                ),
                "{lr}"
            );
        }
    }
}
