//! Batched imagination: scores candidate action sequences by rolling the learned dynamics
//! forward from the current observation (eq. 5 of the paper),
//!
//! `return = Σ_τ [ r(s_τ, a_τ, s_τ₊₁) − α·E(s_τ, a_τ, s_τ₊₁) ]`,
//!
//! with `r` the task's own reward (the function the simulator uses, evaluated for the whole
//! chunk per step by [`proto::Task::rewards`]: a formula through the expression language's
//! block evaluator) or, for a task whose reward is learned, the run's reward model (one batched
//! forward pass per step for the whole chunk, [`crate::reward::RewardModel::predict`]), `E` the regulariser's
//! energy and `α` the energy weight.
//!
//! - **Particles (PETS TS∞).** Each candidate is imagined `P` times; particle `p` follows
//!   ensemble member `p mod B` for the whole horizon and, when sampling is on, draws its next
//!   state from the member's predicted Gaussian. The candidate's return is the particles' mean.
//!   `P = 1`, `B = 1` without sampling is the paper's single-model setting.
//! - **Termination.** Once a particle reaches a terminal state (`Task::is_terminal`, e.g. the
//!   ant falling; for the whole chunk per step by `Task::terminations`, or for a task whose
//!   termination is learned by the run's termination model, one batched forward pass per step,
//!   [`TerminationModel::predict`]) it stops accruing reward and energy; the transition into
//!   the terminal state still counts.
//! - **Non-finite returns** (a diverging model) are reported as `-inf`, so they never win.
//! - **Batching.** The whole population advances one horizon step at a time, so every network
//!   call is a large matrix product. The population is split into one chunk per rayon thread;
//!   each chunk owns its buffers and scratch and runs single-threaded kernels. Within a chunk
//!   the rows are ordered particle-major with particles grouped by ensemble member, so each
//!   member sees one contiguous block of rows.
//! - **No allocation.** Every buffer, the task's formula scratch included, is allocated when
//!   the imagination is built; the network scratch space is allocated on the first call with a
//!   model (and again only if a model of another shape arrives).

use crate::dynamics::{DynamicsScratch, Ensemble};
use crate::energy::{EnergyScratch, Regularizer};
use crate::plan::Learned;
use crate::plan::settings::CemConfig;
use crate::reward::RewardScratch;
use crate::sched::Preempt;
use crate::termination::{TerminationModel, TerminationScratch};
use proto::Task;
use proto::task::FormulaScratch;
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use rand_distr::StandardNormal;
use rayon::prelude::*;
use std::ops::Range;

/// Scores populations of action sequences with a learned model; owns all working memory.
pub struct Imagination {
    ctx: Context,
    /// Candidates scored per call at most.
    population: usize,
    /// Candidates per chunk for the full population (the last chunk may use fewer); every
    /// chunk has room for this many.
    chunk_len: usize,
    /// Candidates per chunk in the last [`Imagination::evaluate`]: a smaller population (iCEM's
    /// decay) is spread evenly over the chunks, so that every thread keeps working.
    split: usize,
    chunks: Vec<Chunk>,
}

/// What every chunk needs to know, shared read-only across threads.
#[derive(Clone, Copy)]
struct Context {
    task: &'static Task,
    horizon: usize,
    particles: usize,
    energy_weight: f32,
    sample: bool,
}

/// One thread's share of the population and all the memory it works in.
struct Chunk {
    /// Candidates this chunk holds.
    capacity: usize,
    /// Rows are `particles × candidates`: states before and after the step, the step's actions,
    /// Gaussian noise for sampling, and the step's reward and energy per row.
    state: Vec<f32>,
    next: Vec<f32>,
    act: Vec<f32>,
    noise: Vec<f32>,
    reward: Vec<f32>,
    energy: Vec<f32>,
    /// Per row: whether the step's next state ends the episode; accumulated regularised return,
    /// accumulated energy, still alive.
    terminal: Vec<bool>,
    ret: Vec<f32>,
    energy_sum: Vec<f32>,
    alive: Vec<bool>,
    /// Per candidate: the particles' mean return and mean energy per step.
    candidate_energy: Vec<f32>,
    /// The first time step the chunk has not imagined yet in the evaluation in hand.
    next_step: usize,
    /// The task's formulas' working memory (made with the chunk: it depends on the task only).
    formulas: FormulaScratch,
    scratch: Option<Scratch>,
    rng: StdRng,
}

/// Network working memory, tied to the shapes of the models it was made for.
struct Scratch {
    dynamics: DynamicsScratch,
    energy: EnergyScratch,
    /// For a learned reward only.
    reward: Option<RewardScratch>,
    /// For a learned termination only.
    termination: Option<TerminationScratch>,
}

impl Imagination {
    /// Imagination for `config.population` candidates of `config.horizon` steps with
    /// `config.particles` particles each, split into `chunks` parallel chunks (at least 1; the
    /// number of rayon threads is the natural choice). `seed` seeds the sampling noise.
    pub fn new(
        task: &'static Task,
        config: &CemConfig,
        energy_weight: f32,
        sample: bool,
        chunks: usize,
        seed: u64,
    ) -> Self {
        let population = config.population.max(1);
        let chunks = chunks.clamp(1, population);
        let chunk_len = population.div_ceil(chunks);
        let chunks = (0..population.div_ceil(chunk_len))
            .map(|c| Chunk::new(task, config.particles, chunk_len, seed_for_chunk(seed, c)))
            .collect();
        let ctx = Context {
            task,
            horizon: config.horizon,
            particles: config.particles,
            energy_weight,
            sample,
        };
        Self {
            ctx,
            population,
            chunk_len,
            split: chunk_len,
            chunks,
        }
    }

    /// Candidates this imagination scores per call.
    pub fn population(&self) -> usize {
        self.population
    }

    /// Scores every candidate of `actions` (`n × horizon × act_dim`) from `obs` into `returns`
    /// (`n`), for any `n` up to [`Imagination::population`] (iCEM's population shrinks from one
    /// iteration to the next; the chunks are filled in order, so a smaller population leaves
    /// the last chunks short or idle). `learned`: the run's reward and termination models,
    /// each exactly when the task learns that part.
    ///
    /// With `preempt` (a plan sharing the cores), each chunk looks after every imagined time
    /// step whether a more urgent plan waits ([`Preempt::outranked`], without blocking); only
    /// then do the chunks meet, outside rayon's jobs, where that plan may take the cores (see
    /// [`crate::sched`]). While nobody waits they run through the horizon and meet once, as a
    /// plan alone does: a fork-join of every thread per imagined step costs more, the more
    /// threads share a step's work. The chunks are independent, their random streams and
    /// arithmetic the same either way, so the returns are too.
    #[allow(clippy::too_many_arguments)]
    pub fn evaluate(
        &mut self,
        obs: &[f32],
        actions: &[f32],
        dynamics: &Ensemble,
        regularizer: &Regularizer,
        learned: Learned<'_>,
        returns: &mut [f32],
        preempt: Option<&dyn Preempt>,
    ) {
        let ctx = self.ctx;
        let seq = ctx.horizon * ctx.task.act_dim;
        assert_eq!(obs.len(), ctx.task.obs_dim, "observation dimension");
        assert!(returns.len() <= self.population(), "population");
        assert_eq!(actions.len(), returns.len() * seq, "action sequences");
        self.prepare(dynamics, regularizer, learned);
        // The full population keeps its fixed split; a smaller one is spread evenly, which fits
        // every chunk (⌈n/c⌉ ≤ chunk_len, the room of each).
        let n = returns.len();
        let chunk_len = if n == self.population() {
            self.chunk_len
        } else {
            n.div_ceil(self.chunks.len()).max(1)
        };
        self.split = chunk_len;
        let horizon = ctx.horizon;
        // Chunks that hold candidates this time (a smaller population may leave some idle).
        let active = n.div_ceil(chunk_len);
        for chunk in &mut self.chunks[..active] {
            chunk.next_step = 0;
        }
        loop {
            self.chunks[..active]
                .par_iter_mut()
                .zip(returns.par_chunks_mut(chunk_len))
                .zip(actions.par_chunks(chunk_len * seq))
                .for_each(|((chunk, returns), actions)| {
                    let first = chunk.next_step;
                    let mut t = first;
                    while t < horizon {
                        // Alone on the cores the chunk runs the whole horizon; shared, it
                        // stops after the step at which a more urgent plan waits.
                        let last = match preempt {
                            None => horizon,
                            Some(_) => t + 1,
                        };
                        chunk.imagine(
                            &ctx,
                            obs,
                            actions,
                            returns.len(),
                            (dynamics, regularizer, learned),
                            None,
                            t..last,
                        );
                        t = last;
                        if t < horizon && preempt.is_some_and(|p| p.outranked()) {
                            break;
                        }
                    }
                    chunk.next_step = t;
                    if first < horizon && t == horizon {
                        chunk.write_returns(&ctx, returns);
                    }
                });
            let done = self.chunks[..active].iter().all(|c| c.next_step == horizon);
            match preempt {
                Some(preempt) if !done => preempt.step_back(),
                _ => break,
            }
        }
    }

    /// Mean energy per imagined step of candidate `i` in the last [`Imagination::evaluate`]
    /// (averaged over particles; 0 without a regulariser).
    pub fn candidate_energy(&self, i: usize) -> f32 {
        self.chunks[i / self.split].candidate_energy[i % self.split]
    }

    /// Imagines one action sequence (`horizon × act_dim`) from `obs` and writes, per step, the
    /// particles' mean reward and mean energy. Returns the sequence's regularised return, scored
    /// exactly as [`Imagination::evaluate`] scores a candidate.
    #[allow(clippy::too_many_arguments)]
    pub fn rollout(
        &mut self,
        obs: &[f32],
        actions: &[f32],
        dynamics: &Ensemble,
        regularizer: &Regularizer,
        learned: Learned<'_>,
        rewards: &mut [f32],
        energies: &mut [f32],
    ) -> f32 {
        let ctx = self.ctx;
        assert_eq!(obs.len(), ctx.task.obs_dim, "observation dimension");
        assert_eq!(
            actions.len(),
            ctx.horizon * ctx.task.act_dim,
            "action sequence"
        );
        assert_eq!(
            (rewards.len(), energies.len()),
            (ctx.horizon, ctx.horizon),
            "per-step outputs"
        );
        self.prepare(dynamics, regularizer, learned);
        let chunk = &mut self.chunks[0];
        chunk.imagine(
            &ctx,
            obs,
            actions,
            1,
            (dynamics, regularizer, learned),
            Some((rewards, energies)),
            0..ctx.horizon,
        );
        chunk.candidate_return(&ctx, 1, 0)
    }

    /// Makes sure every chunk has network scratch space that fits these models.
    fn prepare(&mut self, dynamics: &Ensemble, regularizer: &Regularizer, learned: Learned<'_>) {
        learned.assert_matches(self.ctx.task);
        let Learned {
            reward,
            termination,
        } = learned;
        let rows_per_chunk = |c: &Chunk| c.capacity * self.ctx.particles;
        for chunk in &mut self.chunks {
            let rows = rows_per_chunk(chunk);
            let fits = chunk.scratch.as_ref().is_some_and(|s| {
                s.dynamics.fits(dynamics, rows)
                    && s.energy.fits(regularizer, rows)
                    && match (reward, &s.reward) {
                        (None, _) => true,
                        (Some(m), Some(r)) => r.fits(m, rows),
                        (Some(_), None) => false,
                    }
                    && match (termination, &s.termination) {
                        (None, _) => true,
                        (Some(m), Some(t)) => t.fits(m, rows),
                        (Some(_), None) => false,
                    }
            });
            if !fits {
                chunk.scratch = Some(Scratch {
                    dynamics: dynamics.scratch(rows),
                    energy: regularizer.scratch(rows),
                    reward: reward.map(|m| m.scratch(rows)),
                    termination: termination.map(|m| m.scratch(rows)),
                });
            }
        }
    }
}

/// Decorrelated seeds for the chunks' noise generators (splitmix64 of seed and chunk index).
fn seed_for_chunk(seed: u64, chunk: usize) -> u64 {
    let mut z = seed.wrapping_add(0x9E37_79B9_7F4A_7C15u64.wrapping_mul(chunk as u64 + 1));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl Chunk {
    fn new(task: &Task, particles: usize, capacity: usize, seed: u64) -> Self {
        let rows = particles * capacity;
        let (o, a) = (task.obs_dim, task.act_dim);
        Self {
            capacity,
            state: vec![0.0; rows * o],
            next: vec![0.0; rows * o],
            act: vec![0.0; rows * a],
            noise: vec![0.0; rows * o],
            reward: vec![0.0; rows],
            energy: vec![0.0; rows],
            terminal: vec![false; rows],
            ret: vec![0.0; rows],
            energy_sum: vec![0.0; rows],
            alive: vec![true; rows],
            candidate_energy: vec![0.0; capacity],
            next_step: 0,
            formulas: task.formula_scratch(),
            scratch: None,
            rng: StdRng::seed_from_u64(seed),
        }
    }

    /// Rolls `n` candidates (their sequences in `actions`, `n × horizon × act_dim`) forward
    /// from `obs` over the time `steps` (a solve's steps in order, from 0: a range starting at 0
    /// starts the rollout over), accumulating per-row returns; with `record`, also writes each
    /// step's mean reward and energy over all rows.
    #[allow(clippy::too_many_arguments)]
    fn imagine(
        &mut self,
        ctx: &Context,
        obs: &[f32],
        actions: &[f32],
        n: usize,
        (dynamics, regularizer, learned): (&Ensemble, &Regularizer, Learned<'_>),
        mut record: Option<(&mut [f32], &mut [f32])>,
        steps: Range<usize>,
    ) {
        let (o, a, h) = (ctx.task.obs_dim, ctx.task.act_dim, ctx.horizon);
        let rows = ctx.particles * n;
        let members = dynamics.members();
        let with_energy = !matches!(regularizer, Regularizer::None);
        if steps.start == 0 {
            for s in self.state[..rows * o].chunks_exact_mut(o) {
                s.copy_from_slice(obs);
            }
            self.ret[..rows].fill(0.0);
            self.energy_sum[..rows].fill(0.0);
            self.alive[..rows].fill(true);
            self.energy[..rows].fill(0.0);
        }
        let scratch = self.scratch.as_mut().expect("prepared before imagining");
        for t in steps {
            // Row `k·n + i` is particle slot `k` of candidate `i`.
            for slot in self.act[..rows * a].chunks_exact_mut(n * a) {
                for (i, row) in slot.chunks_exact_mut(a).enumerate() {
                    let at = i * h * a + t * a;
                    row.copy_from_slice(&actions[at..at + a]);
                }
            }
            if ctx.sample {
                for z in &mut self.noise[..rows * o] {
                    *z = self.rng.sample(StandardNormal);
                }
            }
            let mut first_slot = 0;
            for member in 0..members.min(ctx.particles) {
                let slots = particles_of_member(ctx.particles, members, member);
                let (r0, r1) = (first_slot * n, (first_slot + slots) * n);
                let noise = ctx.sample.then(|| &self.noise[r0 * o..r1 * o]);
                dynamics.predict_next(
                    member,
                    &self.state[r0 * o..r1 * o],
                    &self.act[r0 * a..r1 * a],
                    r1 - r0,
                    &mut scratch.dynamics,
                    noise,
                    &mut self.next[r0 * o..r1 * o],
                );
                first_slot += slots;
            }
            if with_energy {
                regularizer.energy(
                    &self.state[..rows * o],
                    &self.act[..rows * a],
                    &self.next[..rows * o],
                    rows,
                    &mut scratch.energy,
                    &mut self.energy[..rows],
                );
            }
            // The whole chunk's rewards and terminations per step: the reward model's forward
            // pass, or the task's formula through the block evaluator (builtin code row by row).
            // Rows that ended earlier are scored too and then ignored: cheaper than gathering
            // the live ones.
            if let Some(model) = learned.reward {
                let scratch = scratch
                    .reward
                    .as_mut()
                    .expect("prepared for the reward model");
                model.predict(
                    &self.state[..rows * o],
                    &self.act[..rows * a],
                    &self.next[..rows * o],
                    rows,
                    scratch,
                    &mut self.reward[..rows],
                );
            } else {
                ctx.task.rewards(
                    &self.state[..rows * o],
                    &self.act[..rows * a],
                    &self.next[..rows * o],
                    &mut self.formulas,
                    &mut self.reward[..rows],
                );
            }
            ended(
                ctx.task,
                learned.termination,
                &self.next[..rows * o],
                rows,
                (&mut self.formulas, scratch.termination.as_mut()),
                &mut self.terminal[..rows],
            );
            for r in 0..rows {
                if !self.alive[r] {
                    self.reward[r] = 0.0;
                    self.energy[r] = 0.0;
                    continue;
                }
                self.ret[r] += self.reward[r] - ctx.energy_weight * self.energy[r];
                self.energy_sum[r] += self.energy[r];
                if self.terminal[r] {
                    self.alive[r] = false;
                }
            }
            if let Some((rewards, energies)) = record.as_mut() {
                let inv = 1.0 / rows as f32;
                rewards[t] = self.reward[..rows].iter().sum::<f32>() * inv;
                energies[t] = self.energy[..rows].iter().sum::<f32>() * inv;
            }
            std::mem::swap(&mut self.state, &mut self.next);
        }
    }

    /// The particles' mean return per candidate (non-finite → `-inf`), and their mean energy
    /// per step into `candidate_energy`.
    fn write_returns(&mut self, ctx: &Context, returns: &mut [f32]) {
        let n = returns.len();
        let inv_step = 1.0 / (ctx.particles * ctx.horizon) as f32;
        for (i, out) in returns.iter_mut().enumerate() {
            *out = self.candidate_return(ctx, n, i);
            let energy: f32 = (0..ctx.particles).map(|k| self.energy_sum[k * n + i]).sum();
            self.candidate_energy[i] = energy * inv_step;
        }
    }

    /// The particles' mean return of candidate `i` of the `n` last imagined; a non-finite mean
    /// (a diverging model) is `-inf`, so it never wins.
    fn candidate_return(&self, ctx: &Context, n: usize, i: usize) -> f32 {
        let sum: f32 = (0..ctx.particles).map(|k| self.ret[k * n + i]).sum();
        let ret = sum / ctx.particles as f32;
        if ret.is_finite() {
            ret
        } else {
            f32::NEG_INFINITY
        }
    }
}

/// Whether each of `rows` imagined next states ends its episode, into `out`: the task's rule
/// ([`Task::terminations`]), or for a task whose termination is learned the run's model
/// (`scratch` is the model's, prepared with it). Shared by every planner that imagines.
pub(super) fn ended(
    task: &Task,
    model: Option<&TerminationModel>,
    next: &[f32],
    rows: usize,
    (formulas, scratch): (&mut FormulaScratch, Option<&mut TerminationScratch>),
    out: &mut [bool],
) {
    match model {
        Some(model) => model.predict(
            next,
            rows,
            scratch.expect("prepared for the termination model"),
            out,
        ),
        None => task.terminations(next, formulas, out),
    }
}

/// How many of `particles` particles follow ensemble member `member` of `members`
/// (particle `p` follows member `p mod members`).
pub(super) fn particles_of_member(particles: usize, members: usize, member: usize) -> usize {
    if member >= particles {
        0
    } else {
        (particles - member).div_ceil(members)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dynamics::DynamicsConfig;
    use crate::energy::{EnergyConfig, RegularizerKind};
    use crate::nn::Normalizer;
    use proto::Builtin;

    fn cem(horizon: usize, population: usize, particles: usize) -> CemConfig {
        CemConfig {
            horizon,
            population,
            elites: 1,
            iterations: 1,
            smoothing: 0.1,
            min_variance: 1e-3,
            particles,
            optimizer: crate::plan::Optimizer::Cem,
            icem: crate::plan::IcemConfig::default(),
            adam: crate::plan::AdamConfig::default(),
        }
    }

    fn ensemble(task: Builtin, members: usize, seed: u64) -> Ensemble {
        let config = DynamicsConfig {
            hidden_layers: 2,
            hidden_size: 24,
            ensemble_size: members,
            ..Default::default()
        };
        Ensemble::new(task.task(), &config, &mut StdRng::seed_from_u64(seed))
    }

    fn deen(task: Builtin, seed: u64) -> Regularizer {
        let spec = task.task();
        let config = EnergyConfig {
            hidden_layers: 2,
            hidden_size: 16,
            ..Default::default()
        };
        Regularizer::new(
            RegularizerKind::Deen,
            &config,
            spec.obs_dim,
            spec.act_dim,
            &mut StdRng::seed_from_u64(seed),
        )
    }

    fn random_sequences(task: &Task, n: usize, horizon: usize, seed: u64) -> Vec<f32> {
        let mut rng = StdRng::seed_from_u64(seed);
        (0..n * horizon)
            .flat_map(|_| {
                (0..task.act_dim)
                    .map(|d| rng.random_range(task.action_low[d]..task.action_high[d]))
                    .collect::<Vec<_>>()
            })
            .collect()
    }

    /// One sequence, one member, one row at a time, mean prediction: the plain reading of
    /// eq. 5 with termination. Returns the return and the number of steps that accrued.
    fn reference(
        task: &'static Task,
        obs: &[f32],
        seq: &[f32],
        dynamics: &Ensemble,
        member: usize,
        regularizer: &Regularizer,
        alpha: f32,
    ) -> (f32, usize) {
        let (o, a) = (task.obs_dim, task.act_dim);
        let mut scratch = dynamics.scratch(1);
        let mut energy_scratch = regularizer.scratch(1);
        let mut s = obs.to_vec();
        let mut s1 = vec![0.0; o];
        let mut ret = 0.0;
        for (t, u) in seq.chunks_exact(a).enumerate() {
            dynamics.predict_next(member, &s, u, 1, &mut scratch, None, &mut s1);
            let mut e = [0.0];
            regularizer.energy(&s, u, &s1, 1, &mut energy_scratch, &mut e);
            ret += task.reward(&s, u, &s1) - alpha * e[0];
            if task.is_terminal(&s1) {
                return (ret, t + 1);
            }
            std::mem::swap(&mut s, &mut s1);
        }
        (ret, seq.len() / a)
    }

    fn assert_close(a: f32, b: f32, what: &str) {
        assert!(
            (a - b).abs() <= 1e-4 * (1.0 + b.abs()),
            "{what}: {a} vs {b}"
        );
    }

    #[test]
    fn matches_the_sequential_reference_for_any_chunking_and_particle_layout() {
        let task = Builtin::Cartpole.task();
        let (horizon, population, alpha) = (6, 7, 0.3);
        let obs = [0.1, 2.5, -0.2, 0.4];
        let actions = random_sequences(task, population, horizon, 1);
        let regularizer = deen(Builtin::Cartpole, 2);
        for (members, particles) in [(1, 1), (2, 4), (3, 2), (2, 5)] {
            let dynamics = ensemble(Builtin::Cartpole, members, 3);
            let expected: Vec<f32> = actions
                .chunks_exact(horizon * task.act_dim)
                .map(|seq| {
                    (0..particles)
                        .map(|p| {
                            reference(task, &obs, seq, &dynamics, p % members, &regularizer, alpha)
                                .0
                        })
                        .sum::<f32>()
                        / particles as f32
                })
                .collect();
            for chunks in [1, 2, 3, 7] {
                let config = cem(horizon, population, particles);
                let mut imagination = Imagination::new(task, &config, alpha, false, chunks, 0);
                let mut returns = vec![0.0; population];
                imagination.evaluate(
                    &obs,
                    &actions,
                    &dynamics,
                    &regularizer,
                    crate::plan::Learned::NONE,
                    &mut returns,
                    None,
                );
                for (i, (r, e)) in returns.iter().zip(&expected).enumerate() {
                    assert_close(
                        *r,
                        *e,
                        &format!("B={members} P={particles} chunks={chunks} candidate {i}"),
                    );
                }
                // A second call reuses every buffer and gives the same answer.
                let mut again = vec![0.0; population];
                imagination.evaluate(
                    &obs,
                    &actions,
                    &dynamics,
                    &regularizer,
                    crate::plan::Learned::NONE,
                    &mut again,
                    None,
                );
                assert_eq!(returns, again);
            }
        }
    }

    /// With a learned reward, imagination scores every transition with the reward model (one
    /// batched call per step): the same returns as a sequential reading that asks the model
    /// one row at a time.
    #[test]
    fn a_learned_reward_is_scored_by_the_reward_model() {
        use crate::data::Transitions;
        use crate::reward::{RewardConfig, RewardModel};
        let mut spec = Builtin::Cartpole.spec();
        spec.name = "imagine-learned-cartpole".into();
        spec.reward = proto::task::RewardKind::Learned;
        let task = Task::intern(spec, &proto::task::SpecBounds::default()).unwrap();
        let mut rng = StdRng::seed_from_u64(11);
        let mut data = Transitions::new(4, 1);
        for _ in 0..200 {
            let s: Vec<f32> = (0..4).map(|_| rng.random_range(-1.0..1.0)).collect();
            let a = [rng.random_range(-3.0..3.0)];
            let s1: Vec<f32> = s.iter().map(|x| x + 0.1 * a[0]).collect();
            data.push(&s, &a, s1[0].cos() - 0.1 * a[0] * a[0], &s1);
        }
        let sizes = RewardConfig {
            hidden_layers: 2,
            hidden_size: 16,
        };
        let mut model = RewardModel::new(task, &sizes, &DynamicsConfig::default(), &mut rng);
        model.fit(&data, 5, &mut rng);
        let dynamics = Ensemble::new(
            task,
            &DynamicsConfig {
                hidden_layers: 2,
                hidden_size: 24,
                ..Default::default()
            },
            &mut rng,
        );
        let (horizon, population) = (5, 6);
        let obs = [0.1, 0.4, -0.2, 0.3];
        let actions = random_sequences(task, population, horizon, 3);
        let mut imagination =
            Imagination::new(task, &cem(horizon, population, 1), 0.0, false, 2, 0);
        let mut returns = vec![0.0; population];
        imagination.evaluate(
            &obs,
            &actions,
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::reward(Some(&model)),
            &mut returns,
            None,
        );
        let (mut scratch, mut reward_scratch) = (dynamics.scratch(1), model.scratch(1));
        for (seq, ret) in actions.chunks_exact(horizon).zip(&returns) {
            let (mut s, mut s1, mut expected) = (obs.to_vec(), vec![0.0; 4], 0.0);
            for u in seq.chunks_exact(1) {
                dynamics.predict_next(0, &s, u, 1, &mut scratch, None, &mut s1);
                let mut r = [0.0];
                model.predict(&s, u, &s1, 1, &mut reward_scratch, &mut r);
                expected += r[0];
                std::mem::swap(&mut s, &mut s1);
            }
            assert_close(*ret, expected, "return under the learned reward");
        }
    }

    /// A learned reward without its model (or a model for a task with a formula) is a bug in
    /// the caller, caught before any imagining.
    #[test]
    #[should_panic(expected = "a reward model is given exactly when the reward is learned")]
    fn a_learned_reward_needs_its_model() {
        let mut spec = Builtin::Cartpole.spec();
        spec.name = "imagine-learned-without-model".into();
        spec.reward = proto::task::RewardKind::Learned;
        let task = Task::intern(spec, &proto::task::SpecBounds::default()).unwrap();
        let dynamics = ensemble(Builtin::Cartpole, 1, 1);
        let mut imagination = Imagination::new(task, &cem(3, 2, 1), 0.0, false, 1, 0);
        let mut returns = vec![0.0; 2];
        let actions = random_sequences(task, 2, 3, 1);
        imagination.evaluate(
            &[0.0; 4],
            &actions,
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            &mut returns,
            None,
        );
    }

    #[test]
    fn energy_is_subtracted_with_its_weight() {
        let task = Builtin::Cartpole.task();
        let obs = [0.0, 0.3, 0.0, 0.0];
        let actions = random_sequences(task, 4, 5, 9);
        let dynamics = ensemble(Builtin::Cartpole, 1, 4);
        let regularizer = deen(Builtin::Cartpole, 5);
        let score = |alpha: f32, reg: &Regularizer| {
            let mut imagination = Imagination::new(task, &cem(5, 4, 1), alpha, false, 2, 0);
            let mut returns = vec![0.0; 4];
            imagination.evaluate(
                &obs,
                &actions,
                &dynamics,
                reg,
                crate::plan::Learned::NONE,
                &mut returns,
                None,
            );
            let energies: Vec<f32> = (0..4).map(|i| imagination.candidate_energy(i)).collect();
            (returns, energies)
        };
        let (plain, no_energy) = score(0.0, &Regularizer::None);
        assert!(no_energy.iter().all(|&e| e == 0.0));
        let (unweighted, energy) = score(0.0, &regularizer);
        assert_eq!(plain, unweighted);
        let (weighted, _) = score(2.0, &regularizer);
        for i in 0..4 {
            // candidate_energy is per step: the horizon's total is 5 times it.
            assert_close(
                weighted[i],
                plain[i] - 2.0 * 5.0 * energy[i],
                "regularised return",
            );
        }
    }

    /// An ant model that predicts the delta `delta` (to within ~1e-4) whatever the input: the
    /// target normaliser has a tiny spread around it, scaling the network's output away.
    fn constant_delta_ant(delta: &[f32]) -> Ensemble {
        constant_delta(Builtin::Ant.task(), delta)
    }

    /// [`constant_delta_ant`] for any task with ant's dimensions and model transforms.
    fn constant_delta(spec: &'static Task, delta: &[f32]) -> Ensemble {
        let config = DynamicsConfig {
            hidden_layers: 2,
            hidden_size: 24,
            ensemble_size: 1,
            ..Default::default()
        };
        let mut dynamics = Ensemble::new(spec, &config, &mut StdRng::seed_from_u64(6));
        let rows: Vec<f32> = [1e-5f32, -1e-5]
            .iter()
            .flat_map(|&jitter| delta.iter().map(move |d| d + jitter))
            .collect();
        let input = Normalizer::identity(spec.state_feature_dim + spec.act_dim);
        dynamics
            .member_mut(0)
            .set_normalizers(input, Normalizer::fit(&rows, spec.obs_dim));
        dynamics
    }

    #[test]
    fn terminal_states_stop_reward_accrual() {
        let task = Builtin::Ant.task();
        let mut delta = vec![0.0; task.obs_dim];
        delta[0] = -0.1; // the torso sinks 0.1 per step: 0.45, 0.35, 0.25, 0.15 (fallen)
        delta[13] = 0.5; // forward velocity grows, so every step's reward is positive
        let dynamics = constant_delta_ant(&delta);
        let mut obs = vec![0.0; task.obs_dim];
        obs[0] = 0.55;
        let (horizon, population) = (10, 5);
        let actions = random_sequences(task, population, horizon, 2);
        let mut imagination =
            Imagination::new(task, &cem(horizon, population, 2), 0.0, false, 2, 0);
        let mut returns = vec![0.0; population];
        imagination.evaluate(
            &obs,
            &actions,
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            &mut returns,
            None,
        );
        for (seq, r) in actions.chunks_exact(horizon * task.act_dim).zip(&returns) {
            let (expected, steps) =
                reference(task, &obs, seq, &dynamics, 0, &Regularizer::None, 0.0);
            assert_eq!(
                steps, 4,
                "the model should make the ant fall on the fourth step"
            );
            assert_close(*r, expected, "return up to the fall");
        }
        // Without the fall the same model earns strictly more over the horizon.
        delta[0] = 0.0;
        let standing = constant_delta_ant(&delta);
        let mut upright = vec![0.0; population];
        imagination.evaluate(
            &obs,
            &actions,
            &standing,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            &mut upright,
            None,
        );
        for (r, u) in returns.iter().zip(&upright) {
            assert!(u > r, "{u} should exceed {r}");
        }
    }

    /// Ant with its termination learned instead of given: a termination model trained on
    /// ant's own rule (torso height outside [0.2, 1]) ends the particles at the same fall,
    /// so the returns are the builtin termination's; a model that has seen no end ends none.
    #[test]
    fn a_learned_termination_ends_particles_where_its_model_predicts_an_end() {
        use crate::termination::TerminationModel;
        use rand_distr::Distribution;
        let mut spec = Builtin::Ant.spec();
        spec.name = "imagine-ant-learned-end".into();
        spec.termination = proto::task::TerminationKind::Learned;
        let task = Task::intern(spec, &proto::task::SpecBounds::default()).unwrap();
        let mut rng = StdRng::seed_from_u64(8);
        let mut data = crate::data::Transitions::new(task.obs_dim, task.act_dim);
        let noise = rand_distr::Normal::new(0.0f32, 0.1).unwrap();
        for _ in 0..3000 {
            let mut s1: Vec<f32> = (0..task.obs_dim).map(|_| noise.sample(&mut rng)).collect();
            s1[0] = rng.random_range(0.0f32..1.3);
            s1[13] = rng.random_range(0.0f32..5.0);
            data.push(&s1, &vec![0.0; task.act_dim], 0.0, &s1);
            if Builtin::Ant.task().is_terminal(&s1) {
                data.mark_terminated(data.len() - 1);
            }
        }
        let training = DynamicsConfig {
            batch_size: 64,
            learning_rate: 3e-3,
            weight_decay: 0.0,
            ..DynamicsConfig::default()
        };
        let mut model = TerminationModel::new(task, &training, &mut rng);
        let untrained = model.clone();
        model.fit(&data, 30, &mut rng);
        let held = model.held_out().unwrap();
        assert!(held.accuracy > 0.95 && held.recall > 0.9, "{held:?}");
        let mut delta = vec![0.0; task.obs_dim];
        delta[0] = -0.1; // falls on the fourth step, as in `terminal_states_stop_reward_accrual`
        delta[13] = 0.5;
        let mut obs = vec![0.0; task.obs_dim];
        obs[0] = 0.55;
        let (horizon, population) = (8, 6);
        let actions = random_sequences(task, population, horizon, 5);
        let score = |task: &'static Task, learned: crate::plan::Learned<'_>| {
            let dynamics = constant_delta(task, &delta);
            let mut imagination =
                Imagination::new(task, &cem(horizon, population, 2), 0.0, false, 2, 0);
            let mut returns = vec![0.0; population];
            imagination.evaluate(
                &obs,
                &actions,
                &dynamics,
                &Regularizer::None,
                learned,
                &mut returns,
                None,
            );
            returns
        };
        let builtin = score(Builtin::Ant.task(), crate::plan::Learned::NONE);
        let with_model = crate::plan::Learned {
            reward: None,
            termination: Some(&model),
        };
        let learned = score(task, with_model);
        for (l, b) in learned.iter().zip(&builtin) {
            assert_close(*l, *b, "return up to the learned fall");
        }
        // Knowing no end, the particles fall through the floor and keep earning.
        let blind = crate::plan::Learned {
            reward: None,
            termination: Some(&untrained),
        };
        for (u, b) in score(task, blind).iter().zip(&builtin) {
            assert!(u > b, "{u} should exceed {b}");
        }
    }

    /// Ant's reward and termination restated as formulas: imagination scores them for the whole
    /// chunk through the block evaluator, and the returns are exactly the builtin code's (the
    /// formulas compute the same operations in the same order), up to and including the fall
    /// that ends the particles, and the row-by-row reading's.
    #[test]
    fn formulas_score_the_population_as_the_builtin_code_they_restate() {
        let mut spec = Builtin::Ant.spec();
        spec.name = "imagine-ant-formulas".into();
        spec.reward = proto::task::RewardKind::Expression("s_next[13] - 0.5*dot(a, a) + 1".into());
        spec.termination = proto::task::TerminationKind::Expression(
            "!(s_next[0] >= 0.2 && s_next[0] <= 1)".into(),
        );
        let formulas = Task::intern(spec, &proto::task::SpecBounds::default()).unwrap();
        let mut delta = vec![0.0; formulas.obs_dim];
        delta[0] = -0.1; // falls on the fourth step, as in `terminal_states_stop_reward_accrual`
        delta[13] = 0.5;
        let mut obs = vec![0.0; formulas.obs_dim];
        obs[0] = 0.55;
        // 70 candidates × 2 particles in 2 chunks: 70 rows each, more than one block of rows.
        let (horizon, population) = (8, 70);
        let actions = random_sequences(formulas, population, horizon, 5);
        let score = |task: &'static Task| {
            let dynamics = constant_delta(task, &delta);
            let mut imagination =
                Imagination::new(task, &cem(horizon, population, 2), 0.0, false, 2, 0);
            let mut returns = vec![0.0; population];
            imagination.evaluate(
                &obs,
                &actions,
                &dynamics,
                &Regularizer::None,
                crate::plan::Learned::NONE,
                &mut returns,
                None,
            );
            (returns, dynamics)
        };
        let (builtin, _) = score(Builtin::Ant.task());
        let (written, dynamics) = score(formulas);
        assert_eq!(written, builtin);
        for (seq, r) in actions
            .chunks_exact(horizon * formulas.act_dim)
            .zip(&written)
        {
            let (expected, steps) =
                reference(formulas, &obs, seq, &dynamics, 0, &Regularizer::None, 0.0);
            assert_eq!(steps, 4, "the termination formula ends the fall");
            assert_close(*r, expected, "return of the row-by-row reading");
        }
    }

    #[test]
    fn diverging_models_score_minus_infinity() {
        let task = Builtin::Ant.task();
        let mut delta = vec![0.0; task.obs_dim];
        delta[13] = f32::MAX; // the forward velocity overflows to +inf after two steps
        let dynamics = constant_delta_ant(&delta);
        let mut obs = vec![0.0; task.obs_dim];
        obs[0] = 0.55;
        let actions = random_sequences(task, 3, 4, 0);
        let mut imagination = Imagination::new(task, &cem(4, 3, 1), 0.0, false, 1, 0);
        let mut returns = vec![0.0; 3];
        imagination.evaluate(
            &obs,
            &actions,
            &dynamics,
            &Regularizer::None,
            crate::plan::Learned::NONE,
            &mut returns,
            None,
        );
        assert!(
            returns.iter().all(|&r| r == f32::NEG_INFINITY),
            "{returns:?}"
        );
    }

    #[test]
    fn a_shared_plan_may_step_back_between_imagined_steps_and_scores_exactly_the_same() {
        // Sampled transitions (each chunk's random stream) and DEEN: everything that could
        // drift if stepping through the horizon in pieces changed the order of the work.
        let task = Builtin::Cartpole.task();
        let obs = [0.1, 2.0, 0.0, 0.3];
        let (horizon, population) = (6, 9);
        let actions = random_sequences(task, population, horizon, 3);
        let dynamics = ensemble(Builtin::Cartpole, 2, 5);
        let energy = deen(Builtin::Cartpole, 6);
        let config = cem(horizon, population, 2);
        let mut alone = Imagination::new(task, &config, 0.01, true, 2, 11);
        let mut shared = Imagination::new(task, &config, 0.01, true, 2, 11);
        let preempt = crate::plan::anytime::CountingPreempt::default();
        for round in 1..=2 {
            let (mut a, mut b) = (vec![0.0; population], vec![0.0; population]);
            alone.evaluate(
                &obs,
                &actions,
                &dynamics,
                &energy,
                crate::plan::Learned::NONE,
                &mut a,
                None,
            );
            shared.evaluate(
                &obs,
                &actions,
                &dynamics,
                &energy,
                crate::plan::Learned::NONE,
                &mut b,
                Some(&preempt),
            );
            assert_eq!(a, b, "round {round}");
            assert!(a.iter().all(|r| r.is_finite()), "{a:?}");
            // Between every two of the horizon's steps, never before the first.
            assert_eq!(
                preempt.0.load(std::sync::atomic::Ordering::SeqCst),
                round * (horizon - 1)
            );
        }
    }

    /// A shared plan whose rival waits exactly once: at the `at`-th look (counting from 1)
    /// after an imagined step; counts the plan's step-backs.
    #[derive(Debug, Default)]
    struct RivalOnce {
        at: usize,
        looks: std::sync::atomic::AtomicUsize,
        step_backs: std::sync::atomic::AtomicUsize,
    }

    impl Preempt for RivalOnce {
        fn step_back(&self) {
            self.step_backs
                .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        }

        fn paused(&self) -> std::time::Duration {
            std::time::Duration::ZERO
        }

        fn outranked(&self) -> bool {
            self.looks.fetch_add(1, std::sync::atomic::Ordering::SeqCst) + 1 == self.at
        }
    }

    #[test]
    fn shared_chunks_meet_only_when_a_rival_waits_and_score_exactly_the_same() {
        let task = Builtin::Cartpole.task();
        let obs = [0.1, 2.0, 0.0, 0.3];
        let (horizon, population) = (6, 9);
        let actions = random_sequences(task, population, horizon, 3);
        let dynamics = ensemble(Builtin::Cartpole, 2, 5);
        let energy = deen(Builtin::Cartpole, 6);
        let config = cem(horizon, population, 2);
        let mut alone = Imagination::new(task, &config, 0.01, true, 3, 11);
        let mut a = vec![0.0; population];
        alone.evaluate(
            &obs,
            &actions,
            &dynamics,
            &energy,
            Learned::NONE,
            &mut a,
            None,
        );
        // Nobody waits: every chunk looks after each of its steps but the last, nobody meets.
        // A rival at the 4th look: one step-back, the stopped chunk then finishes its steps.
        for at in [0, 4] {
            let mut shared = Imagination::new(task, &config, 0.01, true, 3, 11);
            let rival = RivalOnce {
                at,
                ..Default::default()
            };
            let mut b = vec![0.0; population];
            shared.evaluate(
                &obs,
                &actions,
                &dynamics,
                &energy,
                Learned::NONE,
                &mut b,
                Some(&rival),
            );
            assert_eq!(a, b, "rival at look {at}");
            let step_backs = rival.step_backs.load(std::sync::atomic::Ordering::SeqCst);
            let looks = rival.looks.load(std::sync::atomic::Ordering::SeqCst);
            assert_eq!(step_backs, usize::from(at > 0), "rival at look {at}");
            assert_eq!(looks, 3 * (horizon - 1), "rival at look {at}");
        }
        assert!(a.iter().all(|r| r.is_finite()), "{a:?}");
    }

    #[test]
    fn a_smaller_population_is_spread_over_every_chunk_and_scored_the_same() {
        // iCEM's population decays: 10 candidates in 3 chunks (4, 4, 2), then the first 9
        // (3, 3, 3: more than the last chunk held at full size), then 4 (2, 2).
        let task = Builtin::Cartpole.task();
        let obs = [0.1, 2.0, 0.0, 0.3];
        let (horizon, population) = (5, 10);
        let actions = random_sequences(task, population, horizon, 7);
        let dynamics = ensemble(Builtin::Cartpole, 1, 3);
        let energy = deen(Builtin::Cartpole, 4);
        let mut imagination =
            Imagination::new(task, &cem(horizon, population, 1), 0.01, false, 3, 0);
        let mut full = vec![0.0; population];
        imagination.evaluate(
            &obs,
            &actions,
            &dynamics,
            &energy,
            crate::plan::Learned::NONE,
            &mut full,
            None,
        );
        let full_energy: Vec<f32> = (0..population)
            .map(|i| imagination.candidate_energy(i))
            .collect();
        let seq = horizon * task.act_dim;
        for n in [9, 4, 1] {
            let mut part = vec![0.0; n];
            imagination.evaluate(
                &obs,
                &actions[..n * seq],
                &dynamics,
                &energy,
                crate::plan::Learned::NONE,
                &mut part,
                None,
            );
            for i in 0..n {
                assert_close(
                    part[i],
                    full[i],
                    "return of a candidate in a smaller population",
                );
                assert_close(
                    imagination.candidate_energy(i),
                    full_energy[i],
                    "its energy",
                );
            }
        }
    }

    #[test]
    fn sampling_is_reproducible_and_differs_from_the_mean() {
        let task = Builtin::Cartpole.task();
        let obs = [0.0, 1.0, 0.0, 0.0];
        let (horizon, population) = (8, 6);
        let actions = random_sequences(task, population, horizon, 4);
        let dynamics = ensemble(Builtin::Cartpole, 2, 8);
        let run = |sample: bool, seed: u64| {
            let mut imagination =
                Imagination::new(task, &cem(horizon, population, 4), 0.0, sample, 2, seed);
            let mut returns = vec![0.0; population];
            imagination.evaluate(
                &obs,
                &actions,
                &dynamics,
                &Regularizer::None,
                crate::plan::Learned::NONE,
                &mut returns,
                None,
            );
            returns
        };
        let sampled = run(true, 1);
        assert_eq!(sampled, run(true, 1));
        assert_ne!(sampled, run(true, 2));
        assert_ne!(sampled, run(false, 1));
        assert!(sampled.iter().all(|r| r.is_finite()));
    }

    #[test]
    fn rollout_records_the_steps_of_one_sequence() {
        let task = Builtin::Cartpole.task();
        let obs = [0.2, 0.5, 0.0, 0.1];
        let horizon = 5;
        let seq = random_sequences(task, 1, horizon, 3);
        let dynamics = ensemble(Builtin::Cartpole, 1, 1);
        let regularizer = deen(Builtin::Cartpole, 7);
        let mut imagination = Imagination::new(task, &cem(horizon, 9, 1), 0.5, false, 2, 0);
        let (mut rewards, mut energies) = (vec![0.0; horizon], vec![0.0; horizon]);
        let ret = imagination.rollout(
            &obs,
            &seq,
            &dynamics,
            &regularizer,
            crate::plan::Learned::NONE,
            &mut rewards,
            &mut energies,
        );
        let (expected, _) = reference(task, &obs, &seq, &dynamics, 0, &regularizer, 0.5);
        assert_close(ret, expected, "rollout return");
        let from_steps: f32 = rewards
            .iter()
            .zip(&energies)
            .map(|(r, e)| r - 0.5 * e)
            .sum();
        assert_close(from_steps, expected, "per-step record");
        assert!(energies.iter().all(|&e| e != 0.0));
    }
}
