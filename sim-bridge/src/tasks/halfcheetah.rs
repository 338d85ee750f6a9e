//! Half-cheetah: a planar 9-link runner with 6 actuated joints, rewarded for running forward.
//!
//! The model is `assets/halfcheetah.xml`, our own MJCF of gym's HalfCheetah (the environment
//! PETS and the paper used), written from its published facts: the links' capsules (radius
//! 0.046 m, published centres, pitches and lengths), 14 kg spread by volume, per-joint ranges,
//! springs and dampers, armature 0.1, soft contacts and joint limits, friction 0.4, six motors
//! with ctrlrange ±1 and gears 120 / 90 / 60 (back thigh, shin, foot) and 120 / 60 / 30 (front),
//! the root free to slide in x and z and to pitch; 0.01 s Euler steps, five per 0.05 s control
//! step. `experiments/probes/halfcheetah_vs_gymnasium.py` finds the compiled model equal to
//! Gymnasium's HalfCheetah-v5 (masses within 1e-6 kg, capsule ends within 1e-7 m) and the two in
//! lockstep (1e-8 m apart after a control step, drifting as fast as v5 does from a 1e-8 m nudge
//! of itself).
//!
//! The observation (proto's [`proto::task::halfcheetah`] layout) is
//! `[Δx/dt, qpos[1..9], qvel[0..9]]`: the root's forward displacement over the last control step
//! divided by the control dt (0 right after a reset, as in PETS), then root height, root pitch,
//! the six joint angles, then all nine velocities. The root x itself is not observed: the task
//! is invariant to it. Initial state: the built pose plus N(0, 0.001) noise on every qpos and
//! qvel number (tasks.md).

use super::TaskSim;
use crate::error::SimError;
use crate::mujoco::{MjSim, ModelConfig, Unstable};
use mujoco_rs::prelude::MjtIntegrator;
use proto::Builtin;
use rand::rngs::StdRng;
use rand_distr::{Distribution, Normal};

const MODEL: ModelConfig = ModelConfig {
    xml: include_str!("../../assets/halfcheetah.xml"),
    substeps: 5,
    integrator: MjtIntegrator::mjINT_EULER,
};

/// Generalised coordinates (and velocities): root x, root z, root pitch, six joints.
const NQ: usize = 9;

/// Standard deviation of the reset noise on every qpos and qvel number.
const RESET_STD: f64 = 0.001;

/// The half-cheetah's physics.
#[derive(Debug)]
pub(crate) struct HalfCheetah {
    sim: MjSim,
    /// `Δx/dt` of the root over the last control step: the observation's first number.
    forward_velocity: f64,
    control_dt: f64,
}

impl HalfCheetah {
    pub fn new() -> Result<Self, SimError> {
        let spec = Builtin::HalfCheetah.task();
        let sim = MjSim::load(spec, MODEL)?;
        if sim.qpos().len() != NQ || sim.qvel().len() != NQ {
            return Err(SimError::ModelMismatch {
                task: Builtin::HalfCheetah,
                detail: format!(
                    "expected nq = nv = {NQ} (root x, z, pitch and six joints), found nq = {}, nv = {}",
                    sim.qpos().len(),
                    sim.qvel().len()
                ),
            });
        }
        Ok(Self {
            sim,
            forward_velocity: 0.0,
            control_dt: spec.control_dt,
        })
    }
}

impl TaskSim for HalfCheetah {
    #[cfg(feature = "render")]
    fn physics(&self) -> &MjSim {
        &self.sim
    }

    fn reset(&mut self, rng: &mut StdRng) {
        let normal = Normal::new(0.0, RESET_STD).expect("a positive standard deviation");
        let mut qpos = [0.0; NQ];
        let mut qvel = [0.0; NQ];
        for v in qpos.iter_mut().chain(qvel.iter_mut()) {
            *v = normal.sample(rng);
        }
        self.sim.set_state(&qpos, &qvel);
        self.forward_velocity = 0.0;
    }

    fn step(&mut self, action: &[f32]) -> Result<(), Unstable> {
        let x_before = self.sim.qpos()[0];
        let result = self.sim.advance(action);
        self.forward_velocity = (self.sim.qpos()[0] - x_before) / self.control_dt;
        result
    }

    fn observe(&self, out: &mut [f32]) {
        let (qpos, qvel) = (self.sim.qpos(), self.sim.qvel());
        out[0] = self.forward_velocity as f32;
        for (o, &q) in out[1..NQ].iter_mut().zip(&qpos[1..]) {
            *o = q as f32;
        }
        for (o, &v) in out[NQ..].iter_mut().zip(qvel) {
            *o = v as f32;
        }
    }

    /// The root is placed at x = 0; `obs[0]` is kept as the last step's forward velocity.
    fn set_state(&mut self, obs: &[f32]) -> Result<(), SimError> {
        let mut qpos = [0.0; NQ];
        for (q, &o) in qpos[1..].iter_mut().zip(&obs[1..NQ]) {
            *q = f64::from(o);
        }
        let mut qvel = [0.0; NQ];
        for (v, &o) in qvel.iter_mut().zip(&obs[NQ..]) {
            *v = f64::from(o);
        }
        self.sim.set_state(&qpos, &qvel);
        self.forward_velocity = f64::from(obs[0]);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Env;
    use rand::{RngExt, SeedableRng};

    const OBS: usize = 18;

    fn observe(c: &HalfCheetah) -> [f32; OBS] {
        let mut obs = [0.0; OBS];
        c.observe(&mut obs);
        obs
    }

    #[test]
    fn dimensions_follow_the_catalog() {
        let mut env = Env::new(Builtin::HalfCheetah).unwrap();
        let spec = env.spec();
        assert_eq!((spec.obs_dim, spec.act_dim), (OBS, 6));
        assert_eq!(env.reset(1).len(), OBS);
        assert_eq!(env.step(&[0.3; 6]).unwrap().obs.len(), OBS);
    }

    /// The first number is the root's displacement over the control step divided by its
    /// duration, not MuJoCo's instantaneous velocity.
    #[test]
    fn first_number_is_the_root_displacement_over_the_step() {
        let mut c = HalfCheetah::new().unwrap();
        c.reset(&mut StdRng::seed_from_u64(3));
        assert_eq!(observe(&c)[0], 0.0, "no displacement yet after a reset");
        let mut rng = StdRng::seed_from_u64(4);
        for _ in 0..20 {
            let x = c.sim.qpos()[0];
            let act: Vec<f32> = (0..6).map(|_| rng.random_range(-1.0..1.0)).collect();
            c.step(&act).unwrap();
            let expected = (c.sim.qpos()[0] - x) / 0.05;
            assert!((f64::from(observe(&c)[0]) - expected).abs() < 1e-5);
        }
    }

    #[test]
    fn reset_noise_is_small_and_seeded() {
        let mut c = HalfCheetah::new().unwrap();
        let mut all = Vec::new();
        for seed in 0..100 {
            c.reset(&mut StdRng::seed_from_u64(seed));
            all.extend(c.sim.qpos().iter().chain(c.sim.qvel()).copied());
        }
        let n = all.len() as f64;
        let mean = all.iter().sum::<f64>() / n;
        let std = (all.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
        assert!(mean.abs() < 2e-4, "mean {mean}");
        assert!((std - RESET_STD).abs() < 1e-4, "std {std}");
    }

    /// gym's cheetah weighs 14 kg, spread over its links by volume: the torso with its head
    /// 6.2502 kg, the back thigh 1.5435 kg, the front foot 0.8845 kg.
    #[test]
    fn bodies_weigh_what_gyms_do() {
        let cheetah = HalfCheetah::new().unwrap();
        let masses = cheetah.sim.body_masses();
        assert_eq!(masses.len(), 8, "world, torso and three bodies per leg");
        let total: f64 = masses.iter().sum();
        assert!((total - 14.0).abs() < 1e-4, "total {total}");
        for (body, want) in [(1, 6.25021), (2, 1.54351), (7, 0.88452)] {
            assert!(
                (masses[body] - want).abs() < 1e-4,
                "body {body}: {}",
                masses[body]
            );
        }
    }

    #[test]
    fn it_stands_on_its_feet_without_control() {
        let mut env = Env::new(Builtin::HalfCheetah).unwrap();
        env.reset(0);
        let mut last = Vec::new();
        for _ in 0..60 {
            last = env.step(&[0.0; 6]).unwrap().obs;
        }
        // Settled on its legs: the torso neither fell through the floor nor flipped, and it
        // has come to rest.
        let (z, pitch) = (last[1], last[2]);
        assert!((-0.2..0.1).contains(&z), "root height offset {z}");
        assert!(pitch.abs() < 0.5, "pitch {pitch}");
        assert!(
            last[9..].iter().all(|v| v.abs() < 0.1),
            "still moving: {last:?}"
        );
    }

    #[test]
    fn a_random_episode_runs_its_full_length() {
        let mut env = Env::new(Builtin::HalfCheetah).unwrap();
        let spec = env.spec();
        env.reset(5);
        let mut rng = StdRng::seed_from_u64(5);
        let mut prev = env.observation().to_vec();
        for step in 1..=spec.episode_len {
            let act: Vec<f32> = (0..6).map(|_| rng.random_range(-1.0..1.0)).collect();
            let out = env.step(&act).unwrap();
            assert!(out.obs.iter().all(|v| v.is_finite()), "step {step}");
            assert_eq!(out.reward, spec.reward(&prev, &act, &out.obs));
            assert!(!out.terminated);
            assert_eq!(out.truncated, step == spec.episode_len);
            prev = out.obs;
        }
    }

    /// A cheetah moving forward earns more than one standing still, and the reported reward is
    /// the forward displacement per second minus the control cost.
    #[test]
    fn moving_forward_pays_more_than_standing_still() {
        let mut env = Env::new(Builtin::HalfCheetah).unwrap();
        env.reset(0);
        for _ in 0..40 {
            env.step(&[0.0; 6]).unwrap();
        }
        let rest = env.observation().to_vec();

        env.set_state(&rest).unwrap();
        let still = env.step(&[0.0; 6]).unwrap();
        let mut pushed = rest.clone();
        pushed[9] = 3.0; // root x velocity
        env.set_state(&pushed).unwrap();
        let moving = env.step(&[0.0; 6]).unwrap();
        let mut backwards = rest.clone();
        backwards[9] = -3.0;
        env.set_state(&backwards).unwrap();
        let reversing = env.step(&[0.0; 6]).unwrap();

        assert!(
            still.reward.abs() < 0.05,
            "standing still: {}",
            still.reward
        );
        assert!(moving.reward > 1.0, "moving forward: {}", moving.reward);
        assert!(reversing.reward < -1.0, "moving back: {}", reversing.reward);
        // Full effort costs 0.1 × 6 = 0.6 on top of the forward velocity it produces.
        env.set_state(&rest).unwrap();
        let effort = env.step(&[1.0, -1.0, 1.0, -1.0, 1.0, -1.0]).unwrap();
        let cost = effort.obs[0] - effort.reward;
        assert!((cost - 0.6).abs() < 1e-5, "control cost {cost}");
    }

    /// A fixed open-loop gait (3 Hz sines, the front leg's phase a quarter period ahead of the
    /// back leg's, each shin 3/8 of a period and each foot a quarter period ahead of its thigh)
    /// runs forward at over 0.5 m/s with a positive return: the model can run, so a planner
    /// that does not make it run has failed, not the model.
    #[test]
    fn an_open_loop_gait_runs_forward() {
        use std::f32::consts::{FRAC_PI_2, FRAC_PI_4, PI};
        let mut env = Env::new(Builtin::HalfCheetah).unwrap();
        env.reset(2);
        let (mut distance, mut total) = (0.0, 0.0);
        let (shin, foot) = (3.0 * FRAC_PI_4, FRAC_PI_2);
        for step in 0..200 {
            let phase = 2.0 * PI * 3.0 * step as f32 * 0.05;
            let (back, front) = (phase, phase + FRAC_PI_2);
            let act = [
                back.sin(),
                (back + shin).sin(),
                (back + foot).sin(),
                front.sin(),
                (front + shin).sin(),
                (front + foot).sin(),
            ];
            let out = env.step(&act).unwrap();
            distance += out.obs[0] * 0.05;
            total += out.reward;
        }
        assert!(distance > 5.0, "ran {distance} m in 10 s");
        assert!(total > 0.0, "return over 200 steps {total}");
        eprintln!("open-loop gait: {distance} m in 10 s, return {total} over 200 steps");
    }
}
