//! Reacher3D: a 7-joint arm without gravity reaching a goal point resampled every episode.
//!
//! The model is `assets/reacher3d.xml` (our own MJCF): 0.01 s RK4 steps, two per 0.02 s control
//! step, no gravity, seven torque motors (gear 1, ±20 N·m). Deviation from PETS, whose arm is a
//! PR2's with its meshes and link offsets: ours is a plain serial chain with the same joint
//! sequence (shoulder pan, lift, upper-arm roll, elbow flex, forearm roll, wrist flex, wrist
//! roll), PR2-like link lengths (0.4, 0.321, 0.15 m) and no offsets, so that its forward
//! kinematics fit in a few lines in proto ([`proto::task::reacher3d::tip`]), next to the reward
//! that needs them; the goal is not a body of the model (PETS moves a free-floating goal
//! body) but a point the task keeps and observes.
//!
//! The observation is `[q (7), goal (3), q̇ (7)]`. Each episode starts with the arm at rest in a
//! bent pose ([`REST_POSE`]) and a goal at the tip of that pose plus N(0, 0.1) per axis
//! (tasks.md).

use super::TaskSim;
use crate::error::SimError;
use crate::mujoco::{MjSim, ModelConfig, Unstable};
use mujoco_rs::prelude::MjtIntegrator;
use proto::Builtin;
use proto::task::reacher3d::{GOAL, JOINTS, tip};
use rand::rngs::StdRng;
use rand_distr::{Distribution, Normal};

const MODEL: ModelConfig = ModelConfig {
    xml: include_str!("../../assets/reacher3d.xml"),
    substeps: 2,
    integrator: MjtIntegrator::mjINT_RK4,
};

/// Where every episode starts: the upper arm slightly lowered, elbow and wrist bent, well inside
/// the workspace (a straight arm is a singular pose at the edge of its reach).
pub(crate) const REST_POSE: [f32; JOINTS] = [0.0, 0.3, 0.0, -1.2, 0.0, -0.6, 0.0];

/// Standard deviation of the goal around the starting tip, per axis.
const GOAL_STD: f32 = 0.1;

/// The arm's physics and the episode's goal.
#[derive(Debug)]
pub(crate) struct Reacher3d {
    sim: MjSim,
    goal: [f32; 3],
}

impl Reacher3d {
    pub fn new() -> Result<Self, SimError> {
        let sim = MjSim::load(Builtin::Reacher3d.task(), MODEL)?;
        if sim.qpos().len() != JOINTS || sim.qvel().len() != JOINTS {
            return Err(SimError::ModelMismatch {
                task: Builtin::Reacher3d,
                detail: format!("expected {JOINTS} hinges, found nq = {}", sim.qpos().len()),
            });
        }
        Ok(Self {
            sim,
            goal: tip(&REST_POSE),
        })
    }
}

impl TaskSim for Reacher3d {
    #[cfg(feature = "render")]
    fn physics(&self) -> &MjSim {
        &self.sim
    }

    fn reset(&mut self, rng: &mut StdRng) {
        let normal = Normal::new(0.0, GOAL_STD).expect("a positive standard deviation");
        let start = tip(&REST_POSE);
        for (g, s) in self.goal.iter_mut().zip(start) {
            *g = s + normal.sample(rng);
        }
        self.sim
            .set_state(&REST_POSE.map(f64::from), &[0.0; JOINTS]);
    }

    fn step(&mut self, action: &[f32]) -> Result<(), Unstable> {
        self.sim.advance(action)
    }

    fn observe(&self, out: &mut [f32]) {
        for (o, &q) in out[..JOINTS].iter_mut().zip(self.sim.qpos()) {
            *o = q as f32;
        }
        out[GOAL..GOAL + 3].copy_from_slice(&self.goal);
        for (o, &v) in out[GOAL + 3..].iter_mut().zip(self.sim.qvel()) {
            *o = v as f32;
        }
    }

    fn set_state(&mut self, obs: &[f32]) -> Result<(), SimError> {
        let qpos: Vec<f64> = obs[..JOINTS].iter().map(|&v| f64::from(v)).collect();
        let qvel: Vec<f64> = obs[GOAL + 3..].iter().map(|&v| f64::from(v)).collect();
        self.goal.copy_from_slice(&obs[GOAL..GOAL + 3]);
        self.sim.set_state(&qpos, &qvel);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Env;
    use rand::{RngExt, SeedableRng};

    const OBS: usize = 17;

    fn random_action(rng: &mut StdRng) -> Vec<f32> {
        (0..JOINTS).map(|_| rng.random_range(-20.0..20.0)).collect()
    }

    /// The MJCF's `tip` site is where proto's forward kinematics put it, in any pose: the
    /// reward the planner computes from joint angles is about the simulated arm.
    #[test]
    fn model_tip_matches_proto_forward_kinematics() {
        let mut r = Reacher3d::new().unwrap();
        let mut rng = StdRng::seed_from_u64(1);
        let mut poses = vec![[0.0; JOINTS], REST_POSE];
        for _ in 0..50 {
            poses.push(std::array::from_fn(|_| rng.random_range(-1.5..1.5)));
        }
        for q in poses {
            let mut obs = [0.0; OBS];
            obs[..JOINTS].copy_from_slice(&q);
            r.set_state(&obs).unwrap();
            let site = r.sim.site_position("tip").unwrap();
            let fk = tip(&q);
            for (s, f) in site.iter().zip(fk) {
                assert!((*s as f32 - f).abs() < 1e-5, "{q:?}: {site:?} vs {fk:?}");
            }
        }
    }

    #[test]
    fn dimensions_and_goal_sampling() {
        let mut env = Env::new(Builtin::Reacher3d).unwrap();
        assert_eq!((env.spec().obs_dim, env.spec().act_dim), (OBS, 7));
        let start = tip(&REST_POSE);
        let mut offsets = Vec::new();
        for seed in 0..300 {
            let obs = env.reset(seed).to_vec();
            assert_eq!(obs.len(), OBS);
            assert_eq!(&obs[..JOINTS], &REST_POSE, "the arm starts at rest");
            assert!(obs[GOAL + 3..].iter().all(|&v| v == 0.0));
            offsets.extend(obs[GOAL..GOAL + 3].iter().zip(start).map(|(g, s)| g - s));
        }
        let n = offsets.len() as f32;
        let mean = offsets.iter().sum::<f32>() / n;
        let std = (offsets.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / n).sqrt();
        assert!(mean.abs() < 0.015, "mean {mean}");
        assert!((std - GOAL_STD).abs() < 0.01, "std {std}");
    }

    #[test]
    fn a_random_episode_runs_its_full_length() {
        let mut env = Env::new(Builtin::Reacher3d).unwrap();
        let spec = env.spec();
        env.reset(2);
        let goal = env.observation()[GOAL..GOAL + 3].to_vec();
        let mut rng = StdRng::seed_from_u64(2);
        let mut prev = env.observation().to_vec();
        for step in 1..=spec.episode_len {
            let act = random_action(&mut rng);
            let out = env.step(&act).unwrap();
            assert!(out.obs.iter().all(|v| v.is_finite()), "step {step}");
            assert_eq!(&out.obs[GOAL..GOAL + 3], &goal[..], "the goal holds still");
            assert_eq!(out.reward, spec.reward(&prev, &act, &out.obs));
            assert!(!out.terminated);
            assert_eq!(out.truncated, step == spec.episode_len);
            prev = out.obs;
        }
    }

    /// The reward is highest with the tip on the goal and falls off with the distance; a torque
    /// on the shoulder moves the tip (the arm is actuated as the FK says).
    #[test]
    fn reward_peaks_at_the_goal() {
        let mut env = Env::new(Builtin::Reacher3d).unwrap();
        let mut obs = [0.0; OBS];
        obs[..JOINTS].copy_from_slice(&REST_POSE);
        obs[GOAL..GOAL + 3].copy_from_slice(&tip(&REST_POSE));
        let mut rewards = Vec::new();
        for dx in [0.0f32, 0.05, 0.1, 0.2, 0.4] {
            let mut o = obs;
            o[GOAL] += dx;
            env.set_state(&o).unwrap();
            rewards.push(env.step(&[0.0; JOINTS]).unwrap().reward);
        }
        assert!(rewards[0] > -1e-6, "at the goal: {}", rewards[0]);
        assert!(rewards.windows(2).all(|w| w[0] > w[1]), "{rewards:?}");

        env.set_state(&obs).unwrap();
        let mut last = env.observation().to_vec();
        for _ in 0..5 {
            last = env.step(&[5.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]).unwrap().obs;
        }
        let moved = tip(&last);
        assert!(last[0] > 0.05, "the pan joint turned: {last:?}");
        assert!(moved[1] > tip(&REST_POSE)[1] + 0.02, "the tip swung left");
    }
}
