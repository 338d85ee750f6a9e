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
//!   each chunk owns its buffers and scratch and runs single-threaded kernels.
//! - **Scoring in blocks of steps.** Only the dynamics must run step by step (each step's
//!   states come from the last). The reward, the termination and the energy of a transition
//!   depend on that transition alone, so a chunk keeps its imagined trajectory and scores
//!   several steps' transitions in one network call, at least `SCORE_ROWS` (512) rows. With many
//!   threads a chunk holds few candidates (500 over 16 threads: 32 rows), and a network called
//!   on so few rows streams all its weights (the paper's energy network: 2 MB in bf16, more
//!   than a core's L2) from the shared cache for every 32 rows; a block of steps reuses them
//!   over hundreds. The returns are summed step by step in the same order, so they are exactly
//!   those of scoring each step as it is imagined. Within a chunk
//!   the rows are ordered particle-major with particles grouped by ensemble member, so each
//!   member sees one contiguous block of rows.
//! - **Several agents at once** ([`evaluate_batch`]). The populations of several agents of one
//!   run (each with its own observation) are stacked: chunk `c` holds every agent's chunk `c`,
//!   and each ensemble member's rows of all agents form one block, so one matrix product per
//!   layer and member serves them all. An agent's rows get the noise of its own random stream
//!   in the order it draws it alone, and every operation is row by row, so each agent's
//!   returns are exactly those of evaluating it alone: [`Imagination::evaluate`] is the batch
//!   of one.
//! - **What is whose.** An [`Imagination`] is one agent's: its random streams (one per chunk)
//!   and what it scored last. The buffers the rows are imagined in are a [`Workspace`], which a
//!   batch of agents shares (an imagination keeps one of its own for its solo evaluations).
//! - **No allocation.** Every buffer, the task's formula scratch included, is allocated on the
//!   first evaluation (and again only for a larger batch, or a model of another shape).

use crate::dynamics::{DynamicsScratch, Ensemble};
use crate::energy::{EnergyScratch, Regularizer};
use crate::plan::Learned;
use crate::plan::sequence::stream_seed;
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

/// One agent's imagination: its random streams and what its last evaluation scored. The rows
/// themselves are imagined in a [`Workspace`].
pub struct Imagination {
    ctx: Context,
    /// Candidates scored per call at most.
    population: usize,
    /// Candidates per chunk for the full population (the last chunk may use fewer).
    chunk_len: usize,
    /// Candidates per chunk in the last evaluation: a smaller population (iCEM's decay) is
    /// spread evenly over the chunks, so that every thread keeps working.
    split: usize,
    /// One per chunk: the chunk's noise and its candidates' energies.
    streams: Vec<Stream>,
    /// The workspace of this imagination's solo evaluations, made on the first.
    own: Option<Workspace>,
}

/// What every chunk needs to know, shared read-only across threads.
#[derive(Clone, Copy, PartialEq)]
struct Context {
    task: &'static Task,
    horizon: usize,
    particles: usize,
    energy_weight: f32,
    sample: bool,
}

/// One agent's share of one chunk that outlives an evaluation.
struct Stream {
    rng: StdRng,
    /// Per candidate of the chunk: the particles' mean energy per step in the last evaluation.
    candidate_energy: Vec<f32>,
}

impl Stream {
    /// A stand-in that a workspace holds while no agent's stream is lent to it.
    fn placeholder() -> Self {
        Self {
            rng: StdRng::seed_from_u64(0),
            candidate_energy: Vec::new(),
        }
    }
}

/// The memory rows are imagined in: one work chunk per chunk. One agent's imagination or a
/// batch of agents' (of one task and configuration) uses it; it grows to the largest batch.
#[derive(Default)]
pub struct Workspace {
    chunks: Vec<WorkChunk>,
}

impl std::fmt::Debug for Workspace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Workspace")
            .field("chunks", &self.chunks.len())
            .field("rows", &self.chunks.first().map_or(0, |c| c.rows))
            .finish()
    }
}

/// One agent's candidates within one chunk of a batch.
#[derive(Clone, Copy, Debug, Default)]
struct Segment {
    /// The agent's first candidate in this chunk, and how many it has here.
    first: usize,
    len: usize,
    /// Candidates of the agents before it in this chunk.
    offset: usize,
}

/// One thread's share of the batch and all the memory it works in.
struct WorkChunk {
    /// Rows every buffer has room for.
    rows: usize,
    /// Candidates of the batch in hand (all agents), and each agent's segment.
    candidates: usize,
    segments: Vec<Segment>,
    /// The agents' streams of this chunk, lent for the evaluation in hand.
    streams: Vec<Stream>,
    /// Per agent: its observation (`obs_dim`).
    obs: Vec<f32>,
    /// Per candidate: its action sequence (`horizon × act_dim`) and its return.
    seqs: Vec<f32>,
    out: Vec<f32>,
    /// Rows are `particles × candidates`, stored step-major: the imagined states of steps
    /// `0..=horizon` (step 0 the observation), the actions of steps `0..horizon`, and per
    /// step and row the transition's reward, energy and whether its next state ends the
    /// episode. Step `t`'s transitions are `states[t]`, `acts[t]` → `states[t + 1]`, so a
    /// block of steps is one contiguous slice of each.
    states: Vec<f32>,
    acts: Vec<f32>,
    reward: Vec<f32>,
    energy: Vec<f32>,
    terminal: Vec<bool>,
    /// Gaussian noise of one step's rows, for sampling.
    noise: Vec<f32>,
    /// Per row: accumulated regularised return, accumulated energy, still alive.
    ret: Vec<f32>,
    energy_sum: Vec<f32>,
    alive: Vec<bool>,
    /// The first time step the chunk has not imagined yet in the evaluation in hand, and
    /// the first it has not scored yet.
    next_step: usize,
    scored: usize,
    /// Ensemble members of the models last imagined with.
    members: usize,
    /// The task's formulas' working memory (it depends on the task only).
    formulas: FormulaScratch,
    task: &'static Task,
    scratch: Option<Scratch>,
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

/// One agent's part of a batched evaluation: `actions` holds `returns.len()` candidates
/// (`n × horizon × act_dim`) to imagine from `obs`, scored into `returns`.
pub struct Rollouts<'a> {
    pub imagination: &'a mut Imagination,
    pub obs: &'a [f32],
    pub actions: &'a [f32],
    pub returns: &'a mut [f32],
}

/// A member of a batched evaluation: its part, or `None` when it sits this evaluation out.
pub trait Rollout {
    fn rollouts(&mut self) -> Option<Rollouts<'_>>;
}

impl Rollout for Rollouts<'_> {
    fn rollouts(&mut self) -> Option<Rollouts<'_>> {
        Some(Rollouts {
            imagination: &mut *self.imagination,
            obs: self.obs,
            actions: self.actions,
            returns: &mut *self.returns,
        })
    }
}

impl Imagination {
    /// Imagination for `config.population` candidates of `config.horizon` steps with
    /// `config.particles` particles each, split into `chunks` parallel chunks (at least 1;
    /// [`crate::plan::default_chunks`] of the rayon threads is the natural choice). `seed` seeds
    /// the sampling noise.
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
        let streams = (0..population.div_ceil(chunk_len))
            .map(|c| Stream {
                rng: StdRng::seed_from_u64(stream_seed(seed, c)),
                candidate_energy: vec![0.0; chunk_len],
            })
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
            streams,
            own: None,
        }
    }

    /// Candidates this imagination scores per call.
    pub fn population(&self) -> usize {
        self.population
    }

    /// Scores every candidate of `actions` (`n × horizon × act_dim`) from `obs` into `returns`
    /// (`n`), for any `n` up to [`Imagination::population`] (iCEM's population shrinks from one
    /// iteration to the next): [`evaluate_batch`] of this agent alone, in its own workspace.
    /// `learned`: the run's reward and termination models, each exactly when the task learns
    /// that part.
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
        let mut workspace = self.take_workspace();
        evaluate_batch(
            &mut workspace,
            &mut [Rollouts {
                imagination: self,
                obs,
                actions,
                returns,
            }],
            dynamics,
            regularizer,
            learned,
            preempt,
        );
        self.own = Some(workspace);
    }

    /// Mean energy per imagined step of candidate `i` in the last evaluation (averaged over
    /// particles; 0 without a regulariser).
    pub fn candidate_energy(&self, i: usize) -> f32 {
        self.streams[i / self.split].candidate_energy[i % self.split]
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
        let mut workspace = self.take_workspace();
        workspace.reserve(&ctx, 1, 1);
        workspace.chunks[0].candidates = 1;
        workspace.prepare(&ctx, 1, (dynamics, regularizer, learned));
        let chunk = &mut workspace.chunks[0];
        chunk.segments.clear();
        chunk.lay_out(&ctx, 0, 0, obs, actions, 0..1);
        std::mem::swap(&mut chunk.streams[0], &mut self.streams[0]);
        chunk.imagine(
            &ctx,
            (dynamics, regularizer, learned),
            Some((rewards, energies)),
            0..ctx.horizon,
        );
        std::mem::swap(&mut chunk.streams[0], &mut self.streams[0]);
        let ret = chunk.candidate_return(&ctx, 0, 0);
        self.own = Some(workspace);
        ret
    }

    /// The workspace of this imagination's solo evaluations (an empty one the first time),
    /// to be given back with [`Imagination::keep_workspace`].
    pub fn take_workspace(&mut self) -> Workspace {
        self.own.take().unwrap_or_default()
    }

    /// Keeps `workspace` for this imagination's solo evaluations.
    pub fn keep_workspace(&mut self, workspace: Workspace) {
        self.own = Some(workspace);
    }

    /// Candidates per chunk for an evaluation of `n`: the full population keeps its fixed
    /// split; a smaller one is spread evenly, which fits every chunk (⌈n/c⌉ ≤ chunk_len).
    fn split_for(&self, n: usize) -> usize {
        if n == self.population {
            self.chunk_len
        } else {
            n.div_ceil(self.streams.len()).max(1)
        }
    }
}

/// Scores every agent's candidates of `batch` (each [`Imagination::evaluate`] would score its
/// own) in one pass over the horizon through `workspace`: each chunk imagines every agent's
/// share of it together, so each network call is one matrix product over all their rows.
/// Every agent's returns (and candidate energies) are exactly those it gets alone.
///
/// The agents must share their task and configuration (the agents of one run do): one
/// horizon, particle count, energy weight, sampling and chunk count. Each may score its own
/// number of candidates.
pub fn evaluate_batch<R: Rollout>(
    workspace: &mut Workspace,
    batch: &mut [R],
    dynamics: &Ensemble,
    regularizer: &Regularizer,
    learned: Learned<'_>,
    preempt: Option<&dyn Preempt>,
) {
    let Some(ctx) = batch
        .iter_mut()
        .find_map(|r| r.rollouts().map(|r| r.imagination.ctx))
    else {
        return;
    };
    let mut chunks = 0;
    let mut agents = 0;
    let seq = ctx.horizon * ctx.task.act_dim;
    for r in batch.iter_mut().filter_map(|r| r.rollouts()) {
        let im = r.imagination;
        if agents == 0 {
            chunks = im.streams.len();
        }
        assert!(
            im.ctx == ctx && im.streams.len() == chunks,
            "a batch shares one task and configuration"
        );
        assert_eq!(r.obs.len(), ctx.task.obs_dim, "observation dimension");
        assert!(r.returns.len() <= im.population, "population");
        assert_eq!(r.actions.len(), r.returns.len() * seq, "action sequences");
        im.split = im.split_for(r.returns.len());
        agents += 1;
    }
    workspace.reserve(&ctx, chunks, agents);
    for (c, chunk) in workspace.chunks[..chunks].iter_mut().enumerate() {
        chunk.candidates = batch
            .iter_mut()
            .filter_map(|r| r.rollouts())
            .map(|r| {
                let (n, split) = (r.returns.len(), r.imagination.split);
                n.saturating_sub(c * split).min(split)
            })
            .sum();
    }
    workspace.prepare(&ctx, chunks, (dynamics, regularizer, learned));
    // Chunks that hold candidates this time (a smaller population may leave some idle).
    let active = workspace.chunks[..chunks]
        .iter()
        .take_while(|c| c.candidates > 0)
        .count();
    for (c, chunk) in workspace.chunks[..active].iter_mut().enumerate() {
        chunk.segments.clear();
        let mut offset = 0;
        for (b, r) in batch.iter_mut().filter_map(|r| r.rollouts()).enumerate() {
            let (n, split) = (r.returns.len(), r.imagination.split);
            let range = (c * split).min(n)..((c + 1) * split).min(n);
            chunk.lay_out(&ctx, b, offset, r.obs, r.actions, range);
            offset += chunk.segments[b].len;
            std::mem::swap(&mut chunk.streams[b], &mut r.imagination.streams[c]);
        }
        debug_assert_eq!(offset, chunk.candidates);
        chunk.next_step = 0;
    }
    let horizon = ctx.horizon;
    loop {
        workspace.chunks[..active].par_iter_mut().for_each(|chunk| {
            let first = chunk.next_step;
            let mut t = first;
            while t < horizon {
                // Alone on the cores the chunk runs the whole horizon; shared, it stops after
                // the step at which a more urgent plan waits.
                let last = match preempt {
                    None => horizon,
                    Some(_) => t + 1,
                };
                chunk.imagine(&ctx, (dynamics, regularizer, learned), None, t..last);
                t = last;
                if t < horizon && preempt.is_some_and(|p| p.outranked()) {
                    break;
                }
            }
            chunk.next_step = t;
            if first < horizon && t == horizon {
                chunk.write_returns(&ctx);
            }
        });
        let done = workspace.chunks[..active]
            .iter()
            .all(|c| c.next_step == horizon);
        match preempt {
            Some(preempt) if !done => preempt.step_back(),
            _ => break,
        }
    }
    for (c, chunk) in workspace.chunks[..active].iter_mut().enumerate() {
        for (b, r) in batch.iter_mut().filter_map(|r| r.rollouts()).enumerate() {
            std::mem::swap(&mut chunk.streams[b], &mut r.imagination.streams[c]);
            let s = chunk.segments[b];
            r.returns[s.first..s.first + s.len]
                .copy_from_slice(&chunk.out[s.offset..s.offset + s.len]);
        }
    }
}

impl Workspace {
    /// An empty workspace; it takes its memory on its first evaluation.
    pub fn new() -> Self {
        Self::default()
    }

    /// Makes room for `chunks` chunks of a batch of `agents` agents of `ctx`'s task (the
    /// rows come with [`Workspace::prepare`], once the chunks' candidates are counted).
    fn reserve(&mut self, ctx: &Context, chunks: usize, agents: usize) {
        while self.chunks.len() < chunks {
            self.chunks.push(WorkChunk::new(ctx.task));
        }
        for chunk in &mut self.chunks[..chunks] {
            if !std::ptr::eq(chunk.task, ctx.task) {
                *chunk = WorkChunk::new(ctx.task);
            }
            if chunk.streams.len() < agents {
                chunk.streams.resize_with(agents, Stream::placeholder);
                chunk.segments.reserve(agents);
                chunk.obs.resize(agents * ctx.task.obs_dim, 0.0);
            }
            chunk.candidates = 0;
        }
    }

    /// Makes sure each of the first `chunks` chunks has rows for its candidates and network
    /// scratch space that fits these models.
    fn prepare(
        &mut self,
        ctx: &Context,
        chunks: usize,
        (dynamics, regularizer, learned): (&Ensemble, &Regularizer, Learned<'_>),
    ) {
        learned.assert_matches(ctx.task);
        let Learned {
            reward,
            termination,
        } = learned;
        let (o, a, h) = (ctx.task.obs_dim, ctx.task.act_dim, ctx.horizon);
        for chunk in &mut self.chunks[..chunks] {
            let n = chunk.candidates;
            let rows = ctx.particles * n;
            grow(&mut chunk.states, (h + 1) * rows * o, 0.0);
            grow(&mut chunk.acts, h * rows * a, 0.0);
            grow(&mut chunk.reward, h * rows, 0.0);
            grow(&mut chunk.energy, h * rows, 0.0);
            grow(&mut chunk.terminal, h * rows, false);
            grow(&mut chunk.noise, rows * o, 0.0);
            grow(&mut chunk.ret, rows, 0.0);
            grow(&mut chunk.energy_sum, rows, 0.0);
            grow(&mut chunk.alive, rows, true);
            grow(&mut chunk.seqs, n * h * a, 0.0);
            grow(&mut chunk.out, n, 0.0);
            chunk.rows = chunk.rows.max(rows);
            let (rows, scored) = (chunk.rows, rows * steps_per_score(rows, h));
            let fits = chunk.scratch.as_ref().is_some_and(|s| {
                s.dynamics.fits(dynamics, rows)
                    && s.energy.fits(regularizer, scored)
                    && match (reward, &s.reward) {
                        (None, _) => true,
                        (Some(m), Some(r)) => r.fits(m, scored),
                        (Some(_), None) => false,
                    }
                    && match (termination, &s.termination) {
                        (None, _) => true,
                        (Some(m), Some(t)) => t.fits(m, scored),
                        (Some(_), None) => false,
                    }
            });
            if !fits {
                // Room for the largest block this chunk has scored or may score: a batch of
                // fewer rows scores more steps at once, up to the same row count.
                // (⌈SCORE_ROWS / r⌉ steps of r ≤ rows rows are fewer than SCORE_ROWS + rows.)
                let scored = (SCORE_ROWS + rows - 1).min(rows * h).max(scored);
                chunk.scratch = Some(Scratch {
                    dynamics: dynamics.scratch(rows),
                    energy: regularizer.scratch(scored),
                    reward: reward.map(|m| m.scratch(scored)),
                    termination: termination.map(|m| m.scratch(scored)),
                });
            }
        }
    }
}

impl WorkChunk {
    fn new(task: &'static Task) -> Self {
        Self {
            rows: 0,
            candidates: 0,
            segments: Vec::new(),
            streams: Vec::new(),
            obs: Vec::new(),
            seqs: Vec::new(),
            out: Vec::new(),
            states: Vec::new(),
            acts: Vec::new(),
            reward: Vec::new(),
            energy: Vec::new(),
            terminal: Vec::new(),
            noise: Vec::new(),
            ret: Vec::new(),
            energy_sum: Vec::new(),
            alive: Vec::new(),
            next_step: 0,
            scored: 0,
            members: 1,
            formulas: task.formula_scratch(),
            task,
            scratch: None,
        }
    }

    /// Takes agent `b`'s share of this chunk, after the `offset` candidates of the agents
    /// before it: its observation and its candidates `range` of `actions` (its whole
    /// population's sequences).
    fn lay_out(
        &mut self,
        ctx: &Context,
        b: usize,
        offset: usize,
        obs: &[f32],
        actions: &[f32],
        range: Range<usize>,
    ) {
        let (o, seq) = (ctx.task.obs_dim, ctx.horizon * ctx.task.act_dim);
        debug_assert_eq!(self.segments.len(), b);
        self.obs[b * o..(b + 1) * o].copy_from_slice(obs);
        let len = range.len();
        self.seqs[offset * seq..(offset + len) * seq]
            .copy_from_slice(&actions[range.start * seq..range.end * seq]);
        self.segments.push(Segment {
            first: range.start,
            len,
            offset,
        });
    }

    /// The rows of member `member`'s particles of agent `b`: within the member's block (its
    /// `slots` particle slots of every candidate of the chunk, from slot `first_slot`), the
    /// agent's candidates, slot-major.
    fn block(&self, first_slot: usize, slots: usize, b: usize) -> Range<usize> {
        let s = self.segments[b];
        let start = first_slot * self.candidates + slots * s.offset;
        start..start + slots * s.len
    }

    /// Rolls the chunk's candidates forward over the time `steps` (a solve's steps in order,
    /// from 0: a range starting at 0 starts the rollout over), scoring the imagined steps in
    /// blocks of [`steps_per_score`] (and the last ones once the horizon is
    /// reached) and accumulating per-row returns; with `record`, also writes each step's mean
    /// reward and energy over all rows.
    fn imagine(
        &mut self,
        ctx: &Context,
        models: (&Ensemble, &Regularizer, Learned<'_>),
        mut record: Option<(&mut [f32], &mut [f32])>,
        steps: Range<usize>,
    ) {
        let (dynamics, _, _) = models;
        let (o, a, h) = (ctx.task.obs_dim, ctx.task.act_dim, ctx.horizon);
        let n = self.candidates;
        let rows = ctx.particles * n;
        let members = dynamics.members();
        let used = members.min(ctx.particles);
        if steps.start == 0 {
            let mut first_slot = 0;
            for member in 0..used {
                let slots = particles_of_member(ctx.particles, members, member);
                for b in 0..self.segments.len() {
                    let block = self.block(first_slot, slots, b);
                    let obs = &self.obs[b * o..(b + 1) * o];
                    for s in self.states[block.start * o..block.end * o].chunks_exact_mut(o) {
                        s.copy_from_slice(obs);
                    }
                }
                first_slot += slots;
            }
            self.ret[..rows].fill(0.0);
            self.energy_sum[..rows].fill(0.0);
            self.alive[..rows].fill(true);
            self.scored = 0;
        }
        for t in steps {
            // Step t's rows of the trajectory buffers.
            let (st, at) = (t * rows * o, t * rows * a);
            // Per member and agent: row `k·len + i` of the block is the member's particle slot
            // `k` of the agent's candidate `i`. Each agent draws its rows' noise from its own
            // stream, member by member, in the order it draws it alone.
            let mut first_slot = 0;
            for member in 0..used {
                let slots = particles_of_member(ctx.particles, members, member);
                for b in 0..self.segments.len() {
                    let seg = self.segments[b];
                    let start = first_slot * n + slots * seg.offset;
                    let block = start..start + slots * seg.len;
                    for slot in self.acts[at + block.start * a..at + block.end * a]
                        .chunks_exact_mut(seg.len * a)
                    {
                        for (i, row) in slot.chunks_exact_mut(a).enumerate() {
                            let from = (seg.offset + i) * h * a + t * a;
                            row.copy_from_slice(&self.seqs[from..from + a]);
                        }
                    }
                    if ctx.sample {
                        let rng = &mut self.streams[b].rng;
                        for z in &mut self.noise[block.start * o..block.end * o] {
                            *z = rng.sample(StandardNormal);
                        }
                    }
                }
                first_slot += slots;
            }
            let scratch = self.scratch.as_mut().expect("prepared before imagining");
            let (now, later) = self.states.split_at_mut(st + rows * o);
            let mut first_slot = 0;
            for member in 0..used {
                let slots = particles_of_member(ctx.particles, members, member);
                let (r0, r1) = (first_slot * n, (first_slot + slots) * n);
                let noise = ctx.sample.then(|| &self.noise[r0 * o..r1 * o]);
                dynamics.predict_next(
                    member,
                    &now[st + r0 * o..st + r1 * o],
                    &self.acts[at + r0 * a..at + r1 * a],
                    r1 - r0,
                    &mut scratch.dynamics,
                    noise,
                    &mut later[r0 * o..r1 * o],
                );
                first_slot += slots;
            }
            if t + 1 - self.scored == steps_per_score(rows, h) || t + 1 == h {
                self.score(ctx, models, record.as_mut(), self.scored..t + 1);
                self.scored = t + 1;
            }
        }
        self.members = members;
    }

    /// Scores the imagined transitions of `steps` (the next ones not scored yet) in one call
    /// per network or formula, then adds them to the rows' returns step by step, in order.
    fn score(
        &mut self,
        ctx: &Context,
        (_, regularizer, learned): (&Ensemble, &Regularizer, Learned<'_>),
        mut record: Option<&mut (&mut [f32], &mut [f32])>,
        steps: Range<usize>,
    ) {
        let (o, a) = (ctx.task.obs_dim, ctx.task.act_dim);
        let rows = ctx.particles * self.candidates;
        let m = steps.len() * rows;
        let (t0, t1) = (steps.start, steps.end);
        let state = &self.states[t0 * rows * o..t1 * rows * o];
        let next = &self.states[(t0 + 1) * rows * o..(t1 + 1) * rows * o];
        let act = &self.acts[t0 * rows * a..t1 * rows * a];
        let (reward, energy) = (
            &mut self.reward[t0 * rows..t1 * rows],
            &mut self.energy[t0 * rows..t1 * rows],
        );
        let scratch = self.scratch.as_mut().expect("prepared before imagining");
        if matches!(regularizer, Regularizer::None) {
            energy.fill(0.0);
        } else {
            regularizer.energy(state, act, next, m, &mut scratch.energy, energy);
        }
        // The rewards and terminations of the whole block: the reward model's forward pass, or
        // the task's formula through the block evaluator (builtin code row by row). Rows that
        // ended earlier are scored too and then ignored: cheaper than gathering the live ones.
        if let Some(model) = learned.reward {
            let scratch = scratch
                .reward
                .as_mut()
                .expect("prepared for the reward model");
            model.predict(state, act, next, m, scratch, reward);
        } else {
            ctx.task
                .rewards(state, act, next, &mut self.formulas, reward);
        }
        ended(
            ctx.task,
            learned.termination,
            next,
            m,
            (&mut self.formulas, scratch.termination.as_mut()),
            &mut self.terminal[t0 * rows..t1 * rows],
        );
        for t in steps {
            let step = t * rows..(t + 1) * rows;
            let (reward, energy) = (
                &mut self.reward[step.clone()],
                &mut self.energy[step.clone()],
            );
            let terminal = &self.terminal[step];
            for r in 0..rows {
                if !self.alive[r] {
                    reward[r] = 0.0;
                    energy[r] = 0.0;
                    continue;
                }
                self.ret[r] += reward[r] - ctx.energy_weight * energy[r];
                self.energy_sum[r] += energy[r];
                if terminal[r] {
                    self.alive[r] = false;
                }
            }
            if let Some((rewards, energies)) = record.as_mut() {
                let inv = 1.0 / rows as f32;
                rewards[t] = reward.iter().sum::<f32>() * inv;
                energies[t] = energy.iter().sum::<f32>() * inv;
            }
        }
    }

    /// The rows of agent `b`'s candidate `i`, particle slot by slot.
    fn rows_of(&self, ctx: &Context, b: usize, i: usize) -> impl Iterator<Item = usize> + '_ {
        let used = self.members.min(ctx.particles);
        let (members, particles) = (self.members, ctx.particles);
        (0..used)
            .scan(0, move |first_slot, member| {
                let slots = particles_of_member(particles, members, member);
                let block = self.block(*first_slot, slots, b);
                *first_slot += slots;
                let len = self.segments[b].len;
                Some((0..slots).map(move |k| block.start + k * len + i))
            })
            .flatten()
    }

    /// Per agent: its candidates' particles' mean returns (non-finite → `-inf`) into `out`, and
    /// their mean energy per step into the agent's stream.
    fn write_returns(&mut self, ctx: &Context) {
        let inv_step = 1.0 / (ctx.particles * ctx.horizon) as f32;
        for b in 0..self.segments.len() {
            let seg = self.segments[b];
            for i in 0..seg.len {
                self.out[seg.offset + i] = self.candidate_return(ctx, b, i);
                let energy: f32 = self.rows_of(ctx, b, i).map(|r| self.energy_sum[r]).sum();
                self.streams[b].candidate_energy[i] = energy * inv_step;
            }
        }
    }

    /// The particles' mean return of agent `b`'s candidate `i`; a non-finite mean (a diverging
    /// model) is `-inf`, so it never wins.
    fn candidate_return(&self, ctx: &Context, b: usize, i: usize) -> f32 {
        let sum: f32 = self.rows_of(ctx, b, i).map(|r| self.ret[r]).sum();
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

/// Rows a chunk scores per network call at least (when its horizon has that many): enough
/// that the networks' weights are reused over many rows once loaded into a core's caches.
const SCORE_ROWS: usize = 512;

/// Steps scored together by a chunk of `rows` rows over a horizon of `horizon` steps.
fn steps_per_score(rows: usize, horizon: usize) -> usize {
    SCORE_ROWS.div_ceil(rows.max(1)).clamp(1, horizon.max(1))
}

/// Makes `v` at least `len` long (new elements `value`); never shrinks, so a buffer sized
/// for a larger batch serves a smaller one without allocating.
fn grow<T: Clone>(v: &mut Vec<T>, len: usize, value: T) {
    if v.len() < len {
        v.resize(len, value);
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

    /// The returns of `actions` from `obs` scored by `imagination` alone (no other agent, no
    /// rival plan), with the task's own reward and termination.
    fn scores(
        imagination: &mut Imagination,
        obs: &[f32],
        actions: &[f32],
        dynamics: &Ensemble,
        regularizer: &Regularizer,
    ) -> Vec<f32> {
        scores_shared(imagination, obs, actions, (dynamics, regularizer), None)
    }

    /// [`scores`], for a plan sharing the cores with `preempt` when given.
    fn scores_shared(
        imagination: &mut Imagination,
        obs: &[f32],
        actions: &[f32],
        (dynamics, regularizer): (&Ensemble, &Regularizer),
        preempt: Option<&dyn Preempt>,
    ) -> Vec<f32> {
        let ctx = imagination.ctx;
        let mut returns = vec![0.0; actions.len() / (ctx.horizon * ctx.task.act_dim)];
        imagination.evaluate(
            obs,
            actions,
            dynamics,
            regularizer,
            crate::plan::Learned::NONE,
            &mut returns,
            preempt,
        );
        returns
    }

    /// What the shared-plan tests score: cartpole with sampled transitions (each chunk's
    /// random stream) and a DEEN, everything that could drift if stepping through the horizon
    /// in pieces changed the order of the work.
    struct SharedCase {
        obs: [f32; 4],
        horizon: usize,
        actions: Vec<f32>,
        dynamics: Ensemble,
        energy: Regularizer,
        config: CemConfig,
    }

    impl SharedCase {
        fn new() -> Self {
            let (horizon, population) = (6, 9);
            Self {
                obs: [0.1, 2.0, 0.0, 0.3],
                horizon,
                actions: random_sequences(Builtin::Cartpole.task(), population, horizon, 3),
                dynamics: ensemble(Builtin::Cartpole, 2, 5),
                energy: deen(Builtin::Cartpole, 6),
                config: cem(horizon, population, 2),
            }
        }

        fn imagination(&self, chunks: usize) -> Imagination {
            Imagination::new(
                Builtin::Cartpole.task(),
                &self.config,
                0.01,
                true,
                chunks,
                11,
            )
        }

        fn scores(&self, imagination: &mut Imagination, preempt: Option<&dyn Preempt>) -> Vec<f32> {
            let models = (&self.dynamics, &self.energy);
            scores_shared(imagination, &self.obs, &self.actions, models, preempt)
        }
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
                let returns = scores(&mut imagination, &obs, &actions, &dynamics, &regularizer);
                for (i, (r, e)) in returns.iter().zip(&expected).enumerate() {
                    assert_close(
                        *r,
                        *e,
                        &format!("B={members} P={particles} chunks={chunks} candidate {i}"),
                    );
                }
                // A second call reuses every buffer and gives the same answer.
                let again = scores(&mut imagination, &obs, &actions, &dynamics, &regularizer);
                assert_eq!(returns, again);
            }
        }
    }

    /// A chunk scores its imagined steps in blocks of at least `SCORE_ROWS` rows: one step per
    /// block when it has that many rows, ragged blocks of several steps (6, then 3) for 100
    /// rows, the whole horizon in one block for a single row. The returns are identical
    /// whatever the blocks, and those of the step-by-step reading.
    #[test]
    fn returns_do_not_depend_on_how_steps_are_grouped_for_scoring() {
        let task = Builtin::Cartpole.task();
        let (horizon, population, alpha) = (9, SCORE_ROWS + 88, 0.3);
        assert_eq!(
            (
                steps_per_score(population, horizon),
                steps_per_score(100, horizon)
            ),
            (1, 6)
        );
        let obs = [0.1, 2.5, -0.2, 0.4];
        let actions = random_sequences(task, population, horizon, 4);
        let regularizer = deen(Builtin::Cartpole, 2);
        let dynamics = ensemble(Builtin::Cartpole, 1, 3);
        let config = cem(horizon, population, 1);
        let mut by_chunks = Vec::new();
        for chunks in [1, population / 100, population] {
            let mut imagination = Imagination::new(task, &config, alpha, false, chunks, 0);
            let returns = scores(&mut imagination, &obs, &actions, &dynamics, &regularizer);
            by_chunks.push(returns);
        }
        assert_eq!(by_chunks[0], by_chunks[1], "one step per block vs 6 + 3");
        assert_eq!(
            by_chunks[0], by_chunks[2],
            "one step per block vs the whole horizon"
        );
        for (i, seq) in actions
            .chunks_exact(horizon * task.act_dim)
            .enumerate()
            .step_by(97)
        {
            let (expected, _) = reference(task, &obs, seq, &dynamics, 0, &regularizer, alpha);
            assert_close(by_chunks[0][i], expected, &format!("candidate {i}"));
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
            let returns = scores(&mut imagination, &obs, &actions, &dynamics, reg);
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
        let returns = scores(
            &mut imagination,
            &obs,
            &actions,
            &dynamics,
            &Regularizer::None,
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
        let upright = scores(
            &mut imagination,
            &obs,
            &actions,
            &standing,
            &Regularizer::None,
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
            let returns = scores(
                &mut imagination,
                &obs,
                &actions,
                &dynamics,
                &Regularizer::None,
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
        let returns = scores(
            &mut imagination,
            &obs,
            &actions,
            &dynamics,
            &Regularizer::None,
        );
        assert!(
            returns.iter().all(|&r| r == f32::NEG_INFINITY),
            "{returns:?}"
        );
    }

    #[test]
    fn a_shared_plan_may_step_back_between_imagined_steps_and_scores_exactly_the_same() {
        let case = SharedCase::new();
        let mut alone = case.imagination(2);
        let mut shared = case.imagination(2);
        let preempt = crate::plan::anytime::CountingPreempt::default();
        for round in 1..=2 {
            let a = case.scores(&mut alone, None);
            let b = case.scores(&mut shared, Some(&preempt));
            assert_eq!(a, b, "round {round}");
            assert!(a.iter().all(|r| r.is_finite()), "{a:?}");
            // Between every two of the horizon's steps, never before the first.
            assert_eq!(
                preempt.0.load(std::sync::atomic::Ordering::SeqCst),
                round * (case.horizon - 1)
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
        let case = SharedCase::new();
        let a = case.scores(&mut case.imagination(3), None);
        // Nobody waits: every chunk looks after each of its steps but the last, nobody meets.
        // A rival at the 4th look: one step-back, the stopped chunk then finishes its steps.
        for at in [0, 4] {
            let rival = RivalOnce {
                at,
                ..Default::default()
            };
            let b = case.scores(&mut case.imagination(3), Some(&rival));
            assert_eq!(a, b, "rival at look {at}");
            let step_backs = rival.step_backs.load(std::sync::atomic::Ordering::SeqCst);
            let looks = rival.looks.load(std::sync::atomic::Ordering::SeqCst);
            assert_eq!(step_backs, usize::from(at > 0), "rival at look {at}");
            assert_eq!(looks, 3 * (case.horizon - 1), "rival at look {at}");
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
        let full = scores(&mut imagination, &obs, &actions, &dynamics, &energy);
        let full_energy: Vec<f32> = (0..population)
            .map(|i| imagination.candidate_energy(i))
            .collect();
        let seq = horizon * task.act_dim;
        for n in [9, 4, 1] {
            let part = scores(
                &mut imagination,
                &obs,
                &actions[..n * seq],
                &dynamics,
                &energy,
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
            scores(
                &mut imagination,
                &obs,
                &actions,
                &dynamics,
                &Regularizer::None,
            )
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
