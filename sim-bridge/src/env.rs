//! [`Env`]: one episode-based task simulation, the way the planner sees the task.
//!
//! The environment owns the bookkeeping that must be identical for every task: action validation
//! and clamping, the reward and termination from proto's catalog (the very functions the planner
//! applies to imagined transitions, so the real and the imagined reward cannot drift apart), the
//! time limit, and seeded resets. The physics lives behind [`crate::tasks`].

use crate::error::SimError;
use crate::tasks::{self, TaskSim};
use proto::{Builtin, Task};
use rand::SeedableRng;
use rand::rngs::StdRng;

/// The result of one control step.
#[derive(Debug, Clone, PartialEq)]
pub struct StepOutcome {
    /// The observation the action led to.
    pub obs: Vec<f32>,
    /// `Task::reward(obs_before, clamped_action, obs)`.
    pub reward: f32,
    /// The task's terminal condition holds for `obs` (no reward accrues after it).
    pub terminated: bool,
    /// The episode reached its time limit (`episode_len` steps, or the cap set with
    /// [`Env::cap_episode_length`]) without terminating.
    pub truncated: bool,
    /// The action the simulator applied: the one given, clamped into the task's bounds.
    pub applied: Vec<f32>,
}

impl StepOutcome {
    /// Whether the episode ended with this step, for either reason.
    pub fn done(&self) -> bool {
        self.terminated || self.truncated
    }
}

/// A simulated task: reset to a seeded initial state, step with actions, read observations.
pub struct Env {
    builtin: Builtin,
    spec: &'static Task,
    sim: Box<dyn TaskSim>,
    obs: Vec<f32>,
    /// The observation before the last step (the reward's `obs` argument); reused buffer.
    prev_obs: Vec<f32>,
    action: Vec<f32>,
    steps: u32,
    /// Steps after which an episode is truncated: the task's episode length unless capped.
    time_limit: u32,
    done: bool,
    /// Frames of every state from the next reset on, when asked for.
    #[cfg(feature = "render")]
    frames: Option<crate::render::FrameRecorder>,
}

impl std::fmt::Debug for Env {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Env")
            .field("task", &self.builtin)
            .field("obs", &self.obs)
            .field("steps", &self.steps)
            .field("done", &self.done)
            .finish()
    }
}

impl Env {
    /// Builds the simulator for `task` and resets it with seed 0, so [`Env::observation`] is
    /// valid from the start.
    ///
    /// # Errors
    /// [`SimError::NoSimulator`] for a catalog task sim-bridge cannot simulate yet, or a
    /// model error if the task's MJCF does not load or disagrees with the catalog.
    pub fn new(task: Builtin) -> Result<Self, SimError> {
        let spec = task.task();
        let sim = tasks::simulator(task)?;
        let mut env = Self {
            builtin: task,
            spec,
            sim,
            obs: vec![0.0; spec.obs_dim],
            prev_obs: vec![0.0; spec.obs_dim],
            action: vec![0.0; spec.act_dim],
            steps: 0,
            time_limit: spec.episode_len,
            done: false,
            #[cfg(feature = "render")]
            frames: None,
        };
        env.reset(0);
        Ok(env)
    }

    /// The task this environment simulates.
    pub fn task(&self) -> Builtin {
        self.builtin
    }

    /// The task's catalog entry (dimensions, bounds, episode length, control rate).
    pub fn spec(&self) -> &'static Task {
        self.spec
    }

    /// Starts an episode from an initial state drawn with `seed`; the same seed always gives the
    /// same state. Returns the first observation.
    pub fn reset(&mut self, seed: u64) -> &[f32] {
        self.sim.reset(&mut StdRng::seed_from_u64(seed));
        self.sim.observe(&mut self.obs);
        #[cfg(feature = "render")]
        if let Some(frames) = &mut self.frames {
            frames.begin_episode();
            frames.capture(self.sim.physics().qpos());
        }
        self.steps = 0;
        self.done = false;
        &self.obs
    }

    /// The current observation.
    pub fn observation(&self) -> &[f32] {
        &self.obs
    }

    /// Control steps taken in the current episode.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// Truncates episodes after at most `max_steps` steps (reported as `truncated`, like the
    /// task's own time limit), or restores the task's episode length with `None`. A cap above
    /// the task's episode length changes nothing: episodes are short runs of the real task, for
    /// quick tests and demos, never longer ones.
    pub fn cap_episode_length(&mut self, max_steps: Option<u32>) {
        self.time_limit =
            max_steps.map_or(self.spec.episode_len, |m| m.clamp(1, self.spec.episode_len));
    }

    /// Writes a PNG frame of every state from the next [`Env::reset`] on, one folder per
    /// episode under `dir` (see [`crate::render`]).
    ///
    /// # Errors
    /// The folder cannot be created, or the machine offers no offscreen OpenGL context; the
    /// environment then runs as before, without frames.
    #[cfg(feature = "render")]
    pub fn record_frames(
        &mut self,
        dir: &std::path::Path,
    ) -> Result<(), crate::render::RenderError> {
        let recorder = crate::render::FrameRecorder::start(self.sim.physics().xml(), dir)?;
        self.frames = Some(recorder);
        Ok(())
    }

    /// Steps after which the current settings truncate an episode.
    pub fn time_limit(&self) -> u32 {
        self.time_limit
    }

    /// Advances one control step with `action`, clamped into the task's bounds.
    ///
    /// # Errors
    /// A wrong-length or non-finite action (the state is left unchanged), a step after the
    /// episode ended, or a simulation that produced a non-finite observation.
    pub fn step(&mut self, action: &[f32]) -> Result<StepOutcome, SimError> {
        if self.done {
            return Err(SimError::EpisodeOver { steps: self.steps });
        }
        self.check_action(action)?;
        self.action.copy_from_slice(action);
        self.spec.clamp_action(&mut self.action);

        std::mem::swap(&mut self.prev_obs, &mut self.obs);
        let stable = self.sim.step(&self.action).is_ok();
        self.sim.observe(&mut self.obs);
        #[cfg(feature = "render")]
        if let Some(frames) = &mut self.frames {
            frames.capture(self.sim.physics().qpos());
        }
        self.steps += 1;
        if !stable || self.obs.iter().any(|v| !v.is_finite()) {
            self.done = true;
            return Err(SimError::Diverged {
                step: self.steps,
                obs: self.obs.clone(),
            });
        }

        let reward = self.spec.reward(&self.prev_obs, &self.action, &self.obs);
        let terminated = self.spec.is_terminal(&self.obs);
        let truncated = !terminated && self.steps >= self.time_limit;
        self.done = terminated || truncated;
        Ok(StepOutcome {
            obs: self.obs.clone(),
            reward,
            applied: self.action.clone(),
            terminated,
            truncated,
        })
    }

    /// Places the system in the state the observation `obs` describes, as the first state of a
    /// fresh episode (step count 0). For tests and tools that need a particular situation, e.g.
    /// the pole upright.
    ///
    /// # Errors
    /// A wrong-length state, or a task whose observation does not determine its physics state.
    pub fn set_state(&mut self, obs: &[f32]) -> Result<&[f32], SimError> {
        if obs.len() != self.spec.obs_dim {
            return Err(SimError::StateDimension {
                task: self.builtin,
                expected: self.spec.obs_dim,
                got: obs.len(),
            });
        }
        self.sim.set_state(obs)?;
        self.sim.observe(&mut self.obs);
        self.steps = 0;
        self.done = false;
        Ok(&self.obs)
    }

    fn check_action(&self, action: &[f32]) -> Result<(), SimError> {
        if action.len() != self.spec.act_dim {
            return Err(SimError::ActionDimension {
                task: self.builtin,
                expected: self.spec.act_dim,
                got: action.len(),
            });
        }
        match action.iter().position(|a| !a.is_finite()) {
            Some(index) => Err(SimError::NonFiniteAction {
                index,
                value: action[index],
            }),
            None => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::RngExt;
    use std::f32::consts::PI;

    fn cartpole() -> Env {
        Env::new(Builtin::Cartpole).unwrap()
    }

    #[test]
    fn every_catalog_task_builds_or_says_it_has_no_simulator() {
        for &task in Builtin::ALL {
            match Env::new(task) {
                Ok(env) => {
                    assert!(tasks::SIMULATED.contains(&task));
                    assert_eq!(env.task(), task);
                    assert_eq!(env.observation().len(), task.task().obs_dim);
                }
                Err(SimError::NoSimulator { task: t, known }) => {
                    assert_eq!(t, task);
                    assert!(
                        !tasks::SIMULATED.contains(&task),
                        "{task} listed but missing"
                    );
                    assert!(known.contains("cartpole"), "{known}");
                }
                Err(e) => panic!("{task}: {e}"),
            }
        }
    }

    #[test]
    fn dimensions_follow_the_catalog() {
        let mut env = cartpole();
        let spec = env.spec();
        assert_eq!(env.reset(3).len(), spec.obs_dim);
        let out = env.step(&[0.5]).unwrap();
        assert_eq!(out.obs.len(), spec.obs_dim);
        assert_eq!(out.obs, env.observation());
        assert_eq!(env.steps(), 1);
    }

    #[test]
    fn bad_actions_are_rejected_and_leave_the_state_alone() {
        let mut env = cartpole();
        let before = env.reset(1).to_vec();
        assert!(matches!(
            env.step(&[1.0, 2.0]),
            Err(SimError::ActionDimension {
                expected: 1,
                got: 2,
                ..
            })
        ));
        assert!(matches!(
            env.step(&[]),
            Err(SimError::ActionDimension { got: 0, .. })
        ));
        assert!(matches!(
            env.step(&[f32::NAN]),
            Err(SimError::NonFiniteAction { index: 0, .. })
        ));
        assert!(matches!(
            env.step(&[f32::INFINITY]),
            Err(SimError::NonFiniteAction { .. })
        ));
        assert_eq!(env.observation(), &before[..]);
        assert_eq!(env.steps(), 0);
        let err = env.set_state(&[0.0; 3]).unwrap_err();
        assert!(matches!(
            err,
            SimError::StateDimension {
                expected: 4,
                got: 3,
                ..
            }
        ));
    }

    #[test]
    fn actions_are_clamped_to_the_bounds() {
        let (mut a, mut b) = (cartpole(), cartpole());
        a.reset(5);
        b.reset(5);
        let big = a.step(&[100.0]).unwrap();
        let max = b.step(&[3.0]).unwrap();
        assert_eq!(
            big, max,
            "force 100 acts as the bound 3, and is penalised as 3"
        );
        let small = a.step(&[-1e9]).unwrap();
        let min = b.step(&[-3.0]).unwrap();
        assert_eq!(small, min);
    }

    /// Every task: the same seed and actions replay the same episode, bit for bit; resetting
    /// replays the same start, and another seed gives another one.
    #[test]
    fn a_seed_determines_the_episode() {
        for &task in Builtin::ALL {
            let (mut a, mut b) = (Env::new(task).unwrap(), Env::new(task).unwrap());
            let spec = a.spec();
            assert_eq!(a.reset(42), b.reset(42), "{task}");
            let mut rng = StdRng::seed_from_u64(7);
            for _ in 0..spec.episode_len.min(150) {
                let act: Vec<f32> = (0..spec.act_dim)
                    .map(|d| rng.random_range(spec.action_low[d]..spec.action_high[d]))
                    .collect();
                let (x, y) = (a.step(&act).unwrap(), b.step(&act).unwrap());
                assert_eq!(x, y, "{task}");
                if x.done() {
                    break;
                }
            }
            let start = a.reset(42).to_vec();
            assert_eq!(b.reset(42), &start[..], "{task}");
            assert_ne!(b.reset(43), &start[..], "{task}");
        }
    }

    #[test]
    fn a_random_episode_runs_to_its_time_limit() {
        let mut env = cartpole();
        env.reset(11);
        let spec = env.spec();
        let mut rng = StdRng::seed_from_u64(11);
        let mut prev = env.observation().to_vec();
        for step in 1..=spec.episode_len {
            let act = [rng.random_range(-3.0..3.0)];
            let out = env.step(&act).unwrap();
            assert!(
                out.obs.iter().all(|v| v.is_finite()),
                "step {step}: {:?}",
                out.obs
            );
            assert!(out.reward.is_finite() && out.reward <= 1.0);
            // The reported reward is the catalog's, on the reported transition.
            assert_eq!(out.reward, spec.reward(&prev, &act, &out.obs));
            assert!(!out.terminated, "cartpole has no terminal states");
            assert_eq!(out.truncated, step == spec.episode_len, "step {step}");
            prev = out.obs;
        }
        assert!(matches!(
            env.step(&[0.0]),
            Err(SimError::EpisodeOver { steps: 200 })
        ));
        env.reset(12);
        assert!(env.step(&[0.0]).is_ok());
    }

    #[test]
    fn a_capped_episode_is_truncated_early() {
        let mut env = cartpole();
        env.cap_episode_length(Some(30));
        assert_eq!(env.time_limit(), 30);
        for _ in 0..2 {
            env.reset(1);
            for step in 1..=30 {
                let out = env.step(&[0.5]).unwrap();
                assert_eq!(out.truncated, step == 30, "step {step}");
                assert!(!out.terminated);
            }
            assert!(matches!(
                env.step(&[0.0]),
                Err(SimError::EpisodeOver { steps: 30 })
            ));
        }
        // Caps never lengthen an episode, and never make it empty.
        env.cap_episode_length(Some(5000));
        assert_eq!(env.time_limit(), 200);
        env.cap_episode_length(Some(0));
        assert_eq!(env.time_limit(), 1);
        env.cap_episode_length(None);
        assert_eq!(env.time_limit(), 200);
    }

    #[test]
    fn a_blown_up_simulation_is_an_error_not_a_silent_reset() {
        let mut env = cartpole();
        env.set_state(&[0.0, 0.0, 1e12, 0.0]).unwrap();
        let err = env.step(&[0.0]).unwrap_err();
        assert!(matches!(err, SimError::Diverged { step: 1, .. }), "{err}");
        // The episode is over; a reset starts a sane one.
        assert!(matches!(
            env.step(&[0.0]),
            Err(SimError::EpisodeOver { .. })
        ));
        env.reset(0);
        assert!(env.step(&[0.0]).is_ok());
    }

    #[test]
    fn reward_is_one_upright_at_the_origin_and_low_hanging() {
        let mut env = cartpole();
        env.set_state(&[0.0, PI, 0.0, 0.0]).unwrap();
        let upright = env.step(&[0.0]).unwrap();
        // One control step (0.04 s) barely moves an upright pole at rest.
        assert!(upright.reward > 0.999, "{upright:?}");

        env.set_state(&[0.0, 0.0, 0.0, 0.0]).unwrap();
        let hanging = env.step(&[0.0]).unwrap();
        assert!(hanging.reward < 0.02, "{hanging:?}");
        assert_eq!(hanging.obs, [0.0; 4], "hanging at rest is an equilibrium");

        env.set_state(&[1.0, PI, 0.0, 0.0]).unwrap();
        let aside = env.step(&[0.0]).unwrap();
        assert!(hanging.reward < aside.reward && aside.reward < upright.reward);
    }
}
