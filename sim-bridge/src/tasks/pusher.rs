//! Pusher: a 7-joint arm without gravity pushes a cylinder across a table to a fixed goal.
//!
//! The model is `assets/pusher.xml` (our own MJCF): 0.01 s Euler steps, four per 0.04 s control
//! step, no gravity, seven torque motors (gear 1, ±2 N·m) on a PR2-like joint sequence and
//! PR2's joint limits. Deviations from PETS/gym, whose arm is the PR2's with its meshes, link
//! offsets and a claw-like tip:
//! - the arm is a plain serial chain (upper arm 0.4 m, forearm 0.321 m, wrist to tip 0.2 m,
//!   no offsets) ending in a fingertip sphere, the reacher3d arm's layout with a longer hand so
//!   that the tip reaches behind the object;
//! - only the hand and the fingertip collide (with the object and the table); the upper arm and
//!   the forearm pass through everything, which keeps contacts few and simple;
//! - the object is a 0.1 kg cylinder sliding on two damped slide joints (gym: a nearly massless
//!   one, so its motion is set by the damping alone). The goal is a site, not a body with slide
//!   joints of its own as in gym, because it never moves;
//! - the goal is at the object's centre height, so a perfect push costs zero (gym's goal body
//!   sits lower than the object, which puts a constant into the L1 distance).
//!
//! The observation is proto's layout: `[q (7), q̇ (7), tip (3), object (3)]`, both positions
//! read from the model's sites after the kinematics are brought up to date with the last
//! substep. Each episode starts as PETS's does: the arm straight out at its zero pose, joint
//! velocities uniform in ±0.005, the object at rest 0.25 m before and 0.15 m beside the goal
//! plus N(0, 0.025) per axis (tasks.md).

use super::TaskSim;
use crate::error::SimError;
use crate::mujoco::{MjSim, ModelConfig, Unstable};
use mujoco_rs::prelude::MjtIntegrator;
use proto::Builtin;
use proto::task::pusher::{JOINTS, OBJECT, QVEL, TIP};
use rand::RngExt;
use rand::rngs::StdRng;
use rand_distr::{Distribution, Normal};

const MODEL: ModelConfig = ModelConfig {
    xml: include_str!("../../assets/pusher.xml"),
    substeps: 4,
    integrator: MjtIntegrator::mjINT_EULER,
};

/// Generalised coordinates: the arm's joints, then the object's x and y slides.
const NQ: usize = JOINTS + 2;
/// The object's start, as offsets of its slide joints from the goal, before noise.
const OBJECT_START: [f64; 2] = [-0.25, 0.15];
/// Standard deviation of the object's start per axis.
const OBJECT_STD: f64 = 0.025;
/// Range of the uniform noise on the arm's initial joint velocities.
const ARM_VEL_NOISE: f64 = 0.005;

/// The arm, the object, and where to read them.
#[derive(Debug)]
pub(crate) struct Pusher {
    sim: MjSim,
    /// Site ids of the fingertip and the object's centre.
    tip: usize,
    object: usize,
    /// The object's centre with its slide joints at 0 (the goal), the origin of those joints.
    home: [f64; 3],
}

impl Pusher {
    pub fn new() -> Result<Self, SimError> {
        let mut sim = MjSim::load(Builtin::Pusher.task(), MODEL)?;
        let mismatch = |detail: String| SimError::ModelMismatch {
            task: Builtin::Pusher,
            detail,
        };
        if sim.qpos().len() != NQ || sim.qvel().len() != NQ {
            return Err(mismatch(format!(
                "expected {JOINTS} hinges and 2 slides (nq = nv = {NQ}), found nq = {}, nv = {}",
                sim.qpos().len(),
                sim.qvel().len()
            )));
        }
        let site = |name: &str| {
            sim.site_id(name)
                .ok_or_else(|| mismatch(format!("no `{name}` site")))
        };
        let (tip, object) = (site("tip")?, site("object")?);
        sim.set_state(&[0.0; NQ], &[0.0; NQ]);
        let home = sim.site_xpos(object);
        Ok(Self {
            sim,
            tip,
            object,
            home,
        })
    }
}

impl TaskSim for Pusher {
    #[cfg(feature = "render")]
    fn physics(&self) -> &MjSim {
        &self.sim
    }

    fn reset(&mut self, rng: &mut StdRng) {
        let normal = Normal::new(0.0, OBJECT_STD).expect("a positive standard deviation");
        let mut qpos = [0.0; NQ];
        for (q, start) in qpos[JOINTS..].iter_mut().zip(OBJECT_START) {
            *q = start + normal.sample(rng);
        }
        let mut qvel = [0.0; NQ];
        for v in &mut qvel[..JOINTS] {
            *v = rng.random_range(-ARM_VEL_NOISE..ARM_VEL_NOISE);
        }
        self.sim.set_state(&qpos, &qvel);
    }

    fn step(&mut self, action: &[f32]) -> Result<(), Unstable> {
        let stepped = self.sim.advance(action);
        self.sim.update_kinematics();
        stepped
    }

    fn observe(&self, out: &mut [f32]) {
        let (qpos, qvel) = (self.sim.qpos(), self.sim.qvel());
        for (o, &q) in out[..JOINTS].iter_mut().zip(qpos) {
            *o = q as f32;
        }
        for (o, &v) in out[QVEL..QVEL + JOINTS].iter_mut().zip(qvel) {
            *o = v as f32;
        }
        for (start, site) in [(TIP, self.tip), (OBJECT, self.object)] {
            for (o, &p) in out[start..start + 3]
                .iter_mut()
                .zip(&self.sim.site_xpos(site))
            {
                *o = p as f32;
            }
        }
    }

    /// Joint angles and velocities from the observation, the object where it is observed (its
    /// height is fixed, so only x and y count) and at rest: the observation does not carry the
    /// object's velocity. The observed tip is ignored; it follows from the joint angles.
    fn set_state(&mut self, obs: &[f32]) -> Result<(), SimError> {
        let mut qpos = [0.0; NQ];
        let mut qvel = [0.0; NQ];
        for (q, &o) in qpos[..JOINTS].iter_mut().zip(&obs[..JOINTS]) {
            *q = f64::from(o);
        }
        for (v, &o) in qvel[..JOINTS].iter_mut().zip(&obs[QVEL..QVEL + JOINTS]) {
            *v = f64::from(o);
        }
        for (i, q) in qpos[JOINTS..].iter_mut().enumerate() {
            *q = f64::from(obs[OBJECT + i]) - self.home[i];
        }
        self.sim.set_state(&qpos, &qvel);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Env;
    use proto::task::pusher::GOAL;
    use rand::SeedableRng;

    const OBS: usize = 20;
    /// The shoulder joint's position in the world (the `upper_arm` body).
    const SHOULDER: [f32; 3] = [0.0, -0.6, 0.0];
    /// Height of the table top.
    const TABLE_TOP: f32 = -0.3;

    fn random_action(rng: &mut StdRng) -> Vec<f32> {
        (0..JOINTS).map(|_| rng.random_range(-2.0..2.0)).collect()
    }

    fn close(a: &[f32], b: &[f32], tolerance: f32) -> bool {
        a.iter().zip(b).all(|(x, y)| (x - y).abs() < tolerance)
    }

    /// An observation of the arm at `q` (at rest) and the object at `object`.
    fn state(q: [f32; JOINTS], object: [f32; 3]) -> [f32; OBS] {
        let mut obs = [0.0; OBS];
        obs[..JOINTS].copy_from_slice(&q);
        obs[OBJECT..OBJECT + 3].copy_from_slice(&object);
        obs
    }

    /// The model's goal marker and the object's home are proto's goal, and the arm is as long
    /// as its doc says: the reward the planner computes is about this model.
    #[test]
    fn model_geometry_matches_the_catalog() {
        let mut p = Pusher::new().unwrap();
        let goal = p.sim.site_position("goal").unwrap().map(|v| v as f32);
        assert!(close(&goal, &GOAL, 1e-6), "{goal:?}");
        assert!(close(&p.home.map(|v| v as f32), &GOAL, 1e-6));

        let mut env = Env::new(Builtin::Pusher).unwrap();
        let obs = env.set_state(&state([0.0; JOINTS], GOAL)).unwrap();
        let reach = 0.4 + 0.321 + 0.2;
        let tip = [SHOULDER[0] + reach, SHOULDER[1], SHOULDER[2]];
        assert!(close(&obs[TIP..TIP + 3], &tip, 1e-5), "{obs:?}");
        assert!(close(&obs[OBJECT..OBJECT + 3], &GOAL, 1e-6));

        // Setting a state reproduces the observed object position and joint angles exactly.
        let q = [0.5, 0.3, -0.2, -1.0, 0.4, -0.5, 0.1];
        let object = [0.1, 0.2, GOAL[2]];
        let obs = env.set_state(&state(q, object)).unwrap().to_vec();
        assert!(close(&obs[..JOINTS], &q, 1e-6));
        assert!(close(&obs[OBJECT..OBJECT + 3], &object, 1e-6));
        p.set_state(&obs).unwrap();
        let mut again = [0.0; OBS];
        p.observe(&mut again);
        assert_eq!(&again[..], &obs[..]);
    }

    #[test]
    fn dimensions_and_start_distribution() {
        let mut env = Env::new(Builtin::Pusher).unwrap();
        assert_eq!((env.spec().obs_dim, env.spec().act_dim), (OBS, JOINTS));
        let mut offsets = [Vec::new(), Vec::new()];
        for seed in 0..400 {
            let obs = env.reset(seed).to_vec();
            assert_eq!(obs.len(), OBS);
            assert_eq!(&obs[..JOINTS], &[0.0; JOINTS], "the arm starts straight");
            assert!(
                obs[QVEL..QVEL + JOINTS]
                    .iter()
                    .all(|v| v.abs() <= ARM_VEL_NOISE as f32),
                "{obs:?}"
            );
            assert!(obs[QVEL..QVEL + JOINTS].iter().any(|&v| v != 0.0));
            assert!((obs[OBJECT + 2] - GOAL[2]).abs() < 1e-6, "on the table");
            for (axis, offset) in offsets.iter_mut().enumerate() {
                offset.push(obs[OBJECT + axis] - GOAL[axis]);
            }
        }
        for (axis, values) in offsets.iter().enumerate() {
            let n = values.len() as f32;
            let mean = values.iter().sum::<f32>() / n;
            let std = (values.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / n).sqrt();
            let expected = OBJECT_START[axis] as f32;
            assert!((mean - expected).abs() < 0.005, "axis {axis}: mean {mean}");
            assert!(
                (std - OBJECT_STD as f32).abs() < 0.004,
                "axis {axis}: std {std}"
            );
        }
    }

    #[test]
    fn a_random_episode_runs_its_full_length() {
        let mut env = Env::new(Builtin::Pusher).unwrap();
        let spec = env.spec();
        env.reset(2);
        let mut rng = StdRng::seed_from_u64(2);
        let mut prev = env.observation().to_vec();
        for step in 1..=spec.episode_len {
            let act = random_action(&mut rng);
            let out = env.step(&act).unwrap();
            assert!(out.obs.iter().all(|v| v.is_finite()), "step {step}");
            assert_eq!(out.reward, spec.reward(&prev, &act, &out.obs));
            assert!(
                out.reward < 0.0 && out.reward > -5.0,
                "step {step}: {out:?}"
            );
            assert!(!out.terminated);
            assert_eq!(out.truncated, step == spec.episode_len);
            // The fingertip (radius 0.03) stays on or above the table top.
            assert!(out.obs[TIP + 2] > TABLE_TOP + 0.02, "step {step}: {out:?}");
            prev = out.obs;
        }
    }

    /// The observed tip is where the arm is after the step, not one substep before it.
    #[test]
    fn the_tip_is_observed_after_the_step() {
        let mut env = Env::new(Builtin::Pusher).unwrap();
        let mut p = Pusher::new().unwrap();
        env.reset(3);
        let mut rng = StdRng::seed_from_u64(3);
        for _ in 0..20 {
            let out = env.step(&random_action(&mut rng)).unwrap();
            p.set_state(&out.obs).unwrap();
            let tip = p.sim.site_position("tip").unwrap().map(|v| v as f32);
            assert!(close(&out.obs[TIP..TIP + 3], &tip, 1e-5), "{out:?}");
        }
    }

    /// With the tip touching the object on the side away from the goal and the arm at rest, the
    /// reward rises as the object is placed nearer the goal.
    #[test]
    fn reward_rises_as_the_object_nears_the_goal() {
        let mut env = Env::new(Builtin::Pusher).unwrap();
        let q = [1.0, 0.6, 0.0, -1.0, 0.0, -0.4, 0.0];
        let mut rewards = Vec::new();
        for d in [0.4f32, 0.3, 0.2, 0.1, 0.0] {
            env.set_state(&state(q, [GOAL[0] - d, GOAL[1] + 0.6 * d, GOAL[2]]))
                .unwrap();
            rewards.push(env.step(&[0.0; JOINTS]).unwrap().reward);
        }
        assert!(rewards.windows(2).all(|w| w[0] < w[1]), "{rewards:?}");
    }

    /// A pose with the fingertip just above the table, found by lowering the shoulder.
    fn pose_at_object_height(env: &mut Env) -> ([f32; JOINTS], [f32; 3]) {
        let mut best = None;
        for i in 0..=60 {
            let lift = -0.5 + 1.9 * i as f32 / 60.0;
            let q = [1.0, lift, 0.0, -0.6, 0.0, -0.3, 0.0];
            let obs = env.set_state(&state(q, [1.5, 1.5, GOAL[2]])).unwrap();
            let tip = [obs[TIP], obs[TIP + 1], obs[TIP + 2]];
            let miss = (tip[2] - GOAL[2]).abs();
            if best.as_ref().is_none_or(|(m, _, _)| miss < *m) {
                best = Some((miss, q, tip));
            }
        }
        let (miss, q, tip) = best.unwrap();
        assert!(miss < 0.02, "no pose reaches the object's height: {miss}");
        (q, tip)
    }

    /// The arm moves the object only by touching it: swinging the fingertip into the object
    /// pushes it along, swinging away leaves it where it is; and the table stops the hand.
    #[test]
    fn the_fingertip_pushes_the_object_and_the_table_holds_the_hand() {
        let mut env = Env::new(Builtin::Pusher).unwrap();
        let (q, tip) = pose_at_object_height(&mut env);
        // A positive pan torque swings the tip about the shoulder's vertical axis.
        let radial = [tip[0] - SHOULDER[0], tip[1] - SHOULDER[1]];
        let norm = (radial[0] * radial[0] + radial[1] * radial[1]).sqrt();
        let ahead = [-radial[1] / norm, radial[0] / norm];
        let gap = 0.03 + 0.05 + 0.01;
        let object = [tip[0] + gap * ahead[0], tip[1] + gap * ahead[1], GOAL[2]];
        let pan = |torque: f32| [torque, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];

        env.set_state(&state(q, object)).unwrap();
        let mut obs = env.observation().to_vec();
        for _ in 0..10 {
            obs = env.step(&pan(2.0)).unwrap().obs;
        }
        let moved = [obs[OBJECT] - object[0], obs[OBJECT + 1] - object[1]];
        let along = moved[0] * ahead[0] + moved[1] * ahead[1];
        assert!(along > 0.03, "pushed {along} m: {obs:?}");
        assert!(
            (obs[OBJECT + 2] - GOAL[2]).abs() < 1e-6,
            "the object stays on the table"
        );

        env.set_state(&state(q, object)).unwrap();
        for _ in 0..10 {
            obs = env.step(&pan(-2.0)).unwrap().obs;
        }
        assert!(obs[0] < q[0] - 0.05, "the arm swung away: {obs:?}");
        assert!(close(&obs[OBJECT..OBJECT + 3], &object, 1e-6), "{obs:?}");

        // Full torque down on the shoulder and the wrist presses the hand onto the table.
        env.set_state(&state(q, [1.5, 1.5, GOAL[2]])).unwrap();
        for _ in 0..25 {
            obs = env.step(&[0.0, 2.0, 0.0, 2.0, 0.0, 2.0, 0.0]).unwrap().obs;
            assert!(obs[TIP + 2] > TABLE_TOP + 0.02, "{obs:?}");
        }
    }
}
