//! Ant: a quadruped with 8 actuated joints, rewarded for walking forward and for staying up.
//!
//! The model is `assets/ant.xml`, our own MJCF of gym's Ant (the environment MBPO and the paper
//! used) written from its published facts: a spherical torso of radius 0.25 m starting 0.75 m up;
//! four legs of capsules (radius 0.08 m) at 45° to the axes, each a 0.283 m hip stub, a 0.283 m
//! thigh on a vertical hip hinge (±30°) and a 0.566 m shin on an ankle hinge bent 30°–70°
//! downwards; density 5 (the published masses: torso 327.25 g, 145.91 g per leg), armature and
//! damping 1 on the joints, friction (1, 0.5, 0.5) and a 0.01 m contact margin on the geoms;
//! eight motors with ctrlrange ±1 and gear 150 in gym's action order (the +x−y leg first, see
//! the MJCF); 0.01 s RK4 steps, five per 0.05 s control step. Its random-action episodes match
//! Gymnasium's `Ant-v5` in length and return within noise
//! (`experiments/probes/ant_vs_gymnasium.py`, results in docs/results.md): under random
//! torques the light ant is kicked off the floor, and most episodes end with the torso above
//! 1 m within a few hundred steps, in Gymnasium's ant as in this one.
//!
//! Deviations from gym: the reward is the paper's (MBPO's) `forward velocity − 0.5 ‖a‖² + 1` in
//! proto, a function of the observation: the forward velocity is the torso's x velocity after
//! the step (gym: its displacement over the step divided by 0.05 s), there is no contact cost
//! (the truncated observation has no contact forces, and the mujoco-py of MBPO's time reported
//! them as zero), and the survive bonus is paid on the terminating step too. The floor is an
//! infinite plane. The termination band [0.2, 1.0] comes from proto: an ant on its back rests
//! at about 0.27 m, inside the band, and keeps collecting the bonus there, as in gym.
//!
//! The torso starts at 0.75 m and settles at about 0.5 m on its legs (0.54 m from the built
//! pose, 0.48 m from seed 0's noisy start).
//!
//! The observation (proto's [`proto::task::ant`] layout, MBPO's truncated one without contact
//! forces) is `[qpos[2..15], qvel[0..14]]`: torso height, orientation quaternion (w, x, y, z),
//! the eight joint angles, then the torso's linear velocity in the world frame (so `obs[13]` is
//! the forward velocity), its angular velocity in its own frame and the eight joint velocities.
//! Initial state: the built pose (torso at 0.75 m, upright) plus uniform noise in ±0.1 on
//! positions (the quaternion is renormalised) and N(0, 0.1) on velocities, gym's distribution.

use super::TaskSim;
use crate::error::SimError;
use crate::mujoco::{MjSim, ModelConfig, Unstable};
use mujoco_rs::prelude::MjtIntegrator;
use proto::Builtin;
use rand::RngExt;
use rand::rngs::StdRng;
use rand_distr::{Distribution, Normal};

const MODEL: ModelConfig = ModelConfig {
    xml: include_str!("../../assets/ant.xml"),
    substeps: 5,
    integrator: MjtIntegrator::mjINT_RK4,
};

/// Generalised coordinates: torso position (3), quaternion (4), eight joints.
const NQ: usize = 15;
/// Generalised velocities: torso linear (3) and angular (3), eight joints.
const NV: usize = 14;
/// Observed coordinates: qpos without the torso's x and y.
const OBS_Q: usize = NQ - 2;
/// Range of the uniform noise on positions at reset.
const RESET_POS_NOISE: f64 = 0.1;
/// Standard deviation of the normal noise on velocities at reset.
const RESET_VEL_STD: f64 = 0.1;

/// The ant's physics.
#[derive(Debug)]
pub(crate) struct Ant {
    sim: MjSim,
    /// The model's built pose (torso at 0.75 m, upright, joints at 0), the mean of resets.
    rest_qpos: [f64; NQ],
}

impl Ant {
    pub fn new() -> Result<Self, SimError> {
        let sim = MjSim::load(Builtin::Ant.task(), MODEL)?;
        if sim.qpos().len() != NQ || sim.qvel().len() != NV {
            return Err(SimError::ModelMismatch {
                task: Builtin::Ant,
                detail: format!(
                    "expected a free torso and eight joints (nq = {NQ}, nv = {NV}), found nq = {}, nv = {}",
                    sim.qpos().len(),
                    sim.qvel().len()
                ),
            });
        }
        let mut rest_qpos = [0.0; NQ];
        rest_qpos.copy_from_slice(sim.qpos());
        Ok(Self { sim, rest_qpos })
    }
}

/// Scales the quaternion `q` (w, x, y, z) to unit length; a zero quaternion becomes upright.
fn normalize_quaternion(q: &mut [f64]) {
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if norm > 1e-12 {
        q.iter_mut().for_each(|v| *v /= norm);
    } else {
        q.copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
    }
}

impl TaskSim for Ant {
    #[cfg(feature = "render")]
    fn physics(&self) -> &MjSim {
        &self.sim
    }

    fn reset(&mut self, rng: &mut StdRng) {
        let normal = Normal::new(0.0, RESET_VEL_STD).expect("a positive standard deviation");
        let mut qpos = self.rest_qpos;
        for q in &mut qpos {
            *q += rng.random_range(-RESET_POS_NOISE..RESET_POS_NOISE);
        }
        normalize_quaternion(&mut qpos[3..7]);
        let mut qvel = [0.0; NV];
        for v in &mut qvel {
            *v = normal.sample(rng);
        }
        self.sim.set_state(&qpos, &qvel);
    }

    fn step(&mut self, action: &[f32]) -> Result<(), Unstable> {
        self.sim.advance(action)
    }

    fn observe(&self, out: &mut [f32]) {
        let (qpos, qvel) = (self.sim.qpos(), self.sim.qvel());
        for (o, &q) in out[..OBS_Q].iter_mut().zip(&qpos[2..]) {
            *o = q as f32;
        }
        for (o, &v) in out[OBS_Q..].iter_mut().zip(qvel) {
            *o = v as f32;
        }
    }

    /// The torso is placed at x = y = 0; the quaternion is renormalised.
    fn set_state(&mut self, obs: &[f32]) -> Result<(), SimError> {
        let mut qpos = [0.0; NQ];
        for (q, &o) in qpos[2..].iter_mut().zip(&obs[..OBS_Q]) {
            *q = f64::from(o);
        }
        normalize_quaternion(&mut qpos[3..7]);
        let mut qvel = [0.0; NV];
        for (v, &o) in qvel.iter_mut().zip(&obs[OBS_Q..]) {
            *v = f64::from(o);
        }
        self.sim.set_state(&qpos, &qvel);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Env, StepOutcome};
    use proto::task::ant::{FORWARD_VELOCITY, HEALTHY_HEIGHT, TORSO_HEIGHT};
    use rand::SeedableRng;

    const OBS: usize = 27;

    fn random_action(rng: &mut StdRng) -> Vec<f32> {
        (0..8).map(|_| rng.random_range(-1.0..1.0)).collect()
    }

    /// An observation of the ant standing still after settling from seed 0's start.
    fn settled(env: &mut Env) -> Vec<f32> {
        env.reset(0);
        for _ in 0..100 {
            env.step(&[0.0; 8]).unwrap();
        }
        let mut obs = env.observation().to_vec();
        obs[OBS_Q..].iter_mut().for_each(|v| *v = 0.0);
        obs
    }

    #[test]
    fn dimensions_follow_the_catalog() {
        let mut env = Env::new(Builtin::Ant).unwrap();
        let spec = env.spec();
        assert_eq!((spec.obs_dim, spec.act_dim), (OBS, 8));
        assert_eq!(env.reset(1).len(), OBS);
        assert_eq!(env.step(&[0.2; 8]).unwrap().obs.len(), OBS);
    }

    #[test]
    fn it_lands_on_its_legs_and_stands() {
        let mut env = Env::new(Builtin::Ant).unwrap();
        let start = env.reset(0).to_vec();
        assert!((start[TORSO_HEIGHT] - 0.75).abs() < 0.11, "{start:?}");
        for _ in 0..100 {
            let out = env.step(&[0.0; 8]).unwrap();
            assert!(!out.terminated, "fell: {:?}", out.obs);
        }
        let obs = env.observation();
        let z = obs[TORSO_HEIGHT];
        assert!((0.45..0.6).contains(&z), "torso at {z}");
        // Upright (w dominates the quaternion) and nearly at rest (legs that landed against a
        // joint limit still creep by a few cm/s).
        assert!(obs[1].abs() > 0.95, "orientation {:?}", &obs[1..5]);
        assert!(obs[OBS_Q..].iter().all(|v| v.abs() < 0.2), "{obs:?}");
    }

    /// The published masses of gym's ant follow from its geometry at density 5: the torso
    /// 327.25 g, each leg (stub, thigh, shin) 145.91 g, 910.88 g in all.
    #[test]
    fn bodies_weigh_what_gyms_do() {
        let ant = Ant::new().unwrap();
        let masses = ant.sim.body_masses();
        assert_eq!(masses.len(), 14, "world, torso and three bodies per leg");
        assert!((masses[1] - 0.32725).abs() < 1e-5, "torso {}", masses[1]);
        for leg in masses[2..].chunks(3) {
            let m: f64 = leg.iter().sum();
            assert!((m - 0.14591).abs() < 1e-5, "leg {m}");
        }
        let total: f64 = masses.iter().sum();
        assert!((total - 0.91088).abs() < 1e-4, "total {total}");
    }

    #[test]
    fn reset_noise_is_gyms() {
        let mut ant = Ant::new().unwrap();
        let (mut joints, mut vels) = (Vec::new(), Vec::new());
        for seed in 0..200 {
            ant.reset(&mut StdRng::seed_from_u64(seed));
            let q = ant.sim.qpos();
            let norm: f64 = q[3..7].iter().map(|v| v * v).sum();
            assert!((norm - 1.0).abs() < 1e-9, "a unit quaternion");
            joints.extend_from_slice(&q[7..]);
            vels.extend_from_slice(ant.sim.qvel());
        }
        assert!(joints.iter().all(|j| j.abs() <= RESET_POS_NOISE));
        let spread = joints.iter().map(|j| j * j).sum::<f64>() / joints.len() as f64;
        // Uniform in ±0.1 has variance 0.1² / 3.
        assert!((spread - 0.01 / 3.0).abs() < 5e-4, "variance {spread}");
        let var = vels.iter().map(|v| v * v).sum::<f64>() / vels.len() as f64;
        assert!(
            (var.sqrt() - RESET_VEL_STD).abs() < 0.01,
            "std {}",
            var.sqrt()
        );
    }

    /// Random actions for up to the episode's length: every step is finite, the reward is the
    /// catalog's, and the episode ends exactly when the catalog's termination holds or at the
    /// time limit.
    #[test]
    fn random_episodes_end_by_termination_or_time_limit() {
        let mut env = Env::new(Builtin::Ant).unwrap();
        let spec = env.spec();
        for seed in 0..3 {
            env.reset(seed);
            let mut rng = StdRng::seed_from_u64(seed);
            let mut prev = env.observation().to_vec();
            let mut steps = 0;
            loop {
                let act = random_action(&mut rng);
                let out = env.step(&act).unwrap();
                steps += 1;
                assert!(out.obs.iter().all(|v| v.is_finite()), "step {steps}");
                assert_eq!(out.reward, spec.reward(&prev, &act, &out.obs));
                assert_eq!(out.terminated, spec.is_terminal(&out.obs));
                assert_eq!(out.truncated, !out.terminated && steps == spec.episode_len);
                if out.done() {
                    break;
                }
                prev = out.obs;
            }
            assert!(steps <= spec.episode_len);
            assert!(env.step(&[0.0; 8]).is_err(), "the episode is over");
        }
    }

    /// Random torques kick the light ant off the floor: as in Gymnasium's `Ant-v5` (200
    /// episodes: median 66 steps, 185 ended above 1 m, 15 at the time limit, none on the floor;
    /// `experiments/probes/ant_vs_gymnasium.py`), episodes end by the torso rising above 1 m
    /// after tens to hundreds of steps, never by the ant lying on the floor.
    #[test]
    fn random_actions_end_episodes_like_gyms_ant() {
        let mut env = Env::new(Builtin::Ant).unwrap();
        let mut lengths = Vec::new();
        let (mut above, mut below) = (0, 0);
        for seed in 0..40 {
            env.reset(seed);
            let mut rng = StdRng::seed_from_u64(1000 + seed);
            let mut steps = 0;
            loop {
                let out = env.step(&random_action(&mut rng)).unwrap();
                steps += 1;
                if out.terminated {
                    if out.obs[TORSO_HEIGHT] > HEALTHY_HEIGHT.1 {
                        above += 1;
                    } else {
                        below += 1;
                    }
                }
                if out.done() {
                    break;
                }
            }
            lengths.push(steps);
        }
        lengths.sort_unstable();
        let median = lengths[lengths.len() / 2];
        assert!((30..=200).contains(&median), "median {median}: {lengths:?}");
        assert_eq!(below, 0, "episodes ended on the floor: {lengths:?}");
        assert!(above >= 30, "{above} of 40 ended above 1 m: {lengths:?}");
    }

    #[test]
    fn lying_on_its_back_is_healthy_and_flying_off_terminates() {
        let mut env = Env::new(Builtin::Ant).unwrap();
        let standing = settled(&mut env);
        env.set_state(&standing).unwrap();
        for _ in 0..20 {
            assert!(!env.step(&[0.0; 8]).unwrap().done(), "standing is healthy");
        }

        // Turned upside down half a metre up: it drops onto its back, where the torso rests on
        // the floor inside the healthy band (radius 0.25 m), and stays healthy there, as gym's.
        let mut flipped = standing.clone();
        flipped[TORSO_HEIGHT] = 0.5;
        flipped[1..5].copy_from_slice(&[0.0, 1.0, 0.0, 0.0]);
        env.set_state(&flipped).unwrap();
        for _ in 0..60 {
            assert!(!env.step(&[0.0; 8]).unwrap().done(), "lying on its back");
        }
        let z = env.observation()[TORSO_HEIGHT];
        assert!((HEALTHY_HEIGHT.0..0.3).contains(&z), "torso at {z}");

        // Launched upwards at 4 m/s: it rises through 1 m within a few steps and terminates.
        let mut launched = standing.clone();
        launched[OBS_Q + 2] = 4.0;
        let last = run_until_done(&mut env, &launched, 10);
        assert!(last.terminated && last.obs[TORSO_HEIGHT] > HEALTHY_HEIGHT.1);
    }

    /// Steps with zero action from `state` until the episode ends, within `limit` steps.
    fn run_until_done(env: &mut Env, state: &[f32], limit: u32) -> StepOutcome {
        env.set_state(state).unwrap();
        for _ in 0..limit {
            let out = env.step(&[0.0; 8]).unwrap();
            if out.done() {
                return out;
            }
        }
        panic!("still going after {limit} steps: {:?}", env.observation());
    }

    #[test]
    fn walking_forward_pays_more_than_standing_still() {
        let mut env = Env::new(Builtin::Ant).unwrap();
        let standing = settled(&mut env);
        env.set_state(&standing).unwrap();
        let still = env.step(&[0.0; 8]).unwrap();
        let mut sliding = standing.clone();
        sliding[FORWARD_VELOCITY] = 1.0;
        env.set_state(&sliding).unwrap();
        let moving = env.step(&[0.0; 8]).unwrap();
        // The survive bonus, nothing else, for standing still.
        assert!((still.reward - 1.0).abs() < 0.05, "{}", still.reward);
        assert!(moving.obs[FORWARD_VELOCITY] > 0.1, "{:?}", moving.obs);
        assert!(moving.reward > still.reward + 0.1, "{}", moving.reward);
    }
}
