//! What CEM, iCEM and Adam planning share as searches over action sequences: the objective
//! that scores a population, the box a sequence lives in (and the MPC shift of a plan), and
//! what one solve did.

use super::anytime::IterationClock;
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

/// Decorrelated seeds for the random streams a search or an imagination splits its draws
/// into, so that each stream can be drawn on its own thread (splitmix64 of seed and index).
pub fn stream_seed(seed: u64, index: usize) -> u64 {
    let mut z = seed.wrapping_add(0x9E37_79B9_7F4A_7C15u64.wrapping_mul(index as u64 + 1));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
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

/// A population search run one iteration at a time, so that several agents' solves can share
/// each iteration's evaluation ([`solve_lockstep`]): CEM and iCEM.
pub trait SteppedSearch {
    /// Starts a solve from the warm-start mean.
    fn begin(&mut self);
    /// Candidates the next iteration scores; `None` once the solve is over (every configured
    /// iteration run, or the distribution converged).
    fn next_population(&self) -> Option<usize>;
    /// Draws the next iteration's `n` candidates (`n` as [`SteppedSearch::next_population`]
    /// said).
    fn draw(&mut self, n: usize);
    /// The candidates drawn last (`n × horizon × act_dim`) and room for their scores (`n`).
    fn drawn(&mut self) -> (&[f32], &mut [f32]);
    /// Moves the distribution towards the elites of the scored candidates.
    fn refit(&mut self);
    /// Iterations run in the solve in hand, and the mean score of the last one's elites
    /// (`-inf` before the first).
    fn progress(&self) -> (u32, f32);
}

/// Where one member of a lockstep solve stands.
#[derive(Clone, Copy, Debug, Default)]
pub struct Lockstep {
    /// Its solve goes on.
    pub running: bool,
    /// It scores candidates in the iteration in hand.
    pub joined: bool,
    /// Iterations were left out because the next one would have crossed its deadline.
    pub cut: bool,
}

/// One solve of a lockstep: its search (`None`: not a population search, it sits the lockstep
/// out), its clock and its standing.
pub trait LockstepMember {
    fn parts(
        &mut self,
    ) -> (
        Option<&mut dyn SteppedSearch>,
        &mut IterationClock,
        &mut Lockstep,
    );
}

/// Runs the solves of `members` together, iteration by iteration: every member whose solve
/// goes on draws its candidates, `evaluate` scores those of every member that
/// [`Lockstep::joined`] at once, and each refits to its own. A member's iteration starts when
/// its clock lets an iteration of all the members' candidates start (they share the cores for
/// it); one that it refuses is cut, and the others go on. A member's draws and refits are
/// those of its solve alone, so without deadlines each ends exactly where it would alone; a
/// solve alone is the lockstep of one.
pub fn solve_lockstep<M: LockstepMember>(members: &mut [M], mut evaluate: impl FnMut(&mut [M])) {
    for m in members.iter_mut() {
        let (search, _, step) = m.parts();
        *step = Lockstep {
            running: search.is_some(),
            ..Lockstep::default()
        };
        if let Some(search) = search {
            search.begin();
        }
    }
    loop {
        let mut wanted = 0;
        for m in members.iter_mut() {
            let (search, _, step) = m.parts();
            step.joined = false;
            match search.filter(|_| step.running).map(|s| s.next_population()) {
                Some(Some(n)) => wanted += n,
                Some(None) => step.running = false,
                None => {}
            }
        }
        if wanted == 0 {
            return;
        }
        let mut joined = 0;
        for m in members.iter_mut() {
            let (Some(search), clock, step) = m.parts() else {
                continue;
            };
            if !step.running {
                continue;
            }
            let n = search
                .next_population()
                .expect("a running solve wants an iteration");
            if clock.may_start(wanted, search.progress().0 == 0) {
                search.draw(n);
                step.joined = true;
                joined += n;
            } else {
                step.cut = true;
                step.running = false;
            }
        }
        if joined == 0 {
            return;
        }
        evaluate(members);
        for m in members.iter_mut() {
            let (Some(search), clock, step) = m.parts() else {
                continue;
            };
            if step.joined {
                search.refit();
                clock.finished(joined);
            }
        }
    }
}

/// One search's solve over `objective`: the lockstep of one.
pub fn solve_alone<S: SteppedSearch, O: PopulationObjective + ?Sized>(
    search: &mut S,
    objective: &mut O,
    clock: &mut IterationClock,
) -> CemOutcome {
    struct Alone<'a, S> {
        search: &'a mut S,
        clock: &'a mut IterationClock,
        step: Lockstep,
    }
    impl<S: SteppedSearch> LockstepMember for Alone<'_, S> {
        fn parts(
            &mut self,
        ) -> (
            Option<&mut dyn SteppedSearch>,
            &mut IterationClock,
            &mut Lockstep,
        ) {
            (Some(&mut *self.search), &mut *self.clock, &mut self.step)
        }
    }
    let mut one = [Alone {
        search,
        clock,
        step: Lockstep::default(),
    }];
    solve_lockstep(&mut one, |members| {
        let (candidates, returns) = members[0].search.drawn();
        objective.evaluate(candidates, returns);
    });
    let (iterations, elite_return) = one[0].search.progress();
    CemOutcome {
        iterations,
        elite_return,
        cut: one[0].step.cut,
    }
}
