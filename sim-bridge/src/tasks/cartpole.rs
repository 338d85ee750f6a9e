//! Cartpole swing-up: a cart on an unlimited rail with a 0.6 m pole, θ = 0 hanging down.
//!
//! The model is `assets/cartpole.xml` (our own MJCF, written from the PETS task's published
//! facts): 0.02 s RK4 steps, two per 0.04 s control step, a motor on the cart whose force in
//! newtons is the action (±3). Deviation from PETS, whose gear-100 motor drives a ~10 kg cart
//! and a ~5 kg pole: with force = action the masses are scaled down (0.1 kg cart, 0.05 kg pole)
//! to keep PETS's control authority and mass ratio, so the swing-up takes about a second as
//! there; the rail has no end stops. See the MJCF's header for the numbers.
//!
//! The observation is `[x, θ, ẋ, θ̇]`, the slider and hinge coordinates as they are, with the
//! hinge about +y so that the pole's tip is at `(x − 0.6 sin θ, −0.6 cos θ)`: proto's
//! [`proto::task::cartpole`] convention (θ = π is upright). θ is not wrapped; the planner's
//! features put it on the circle. Initial state: all four numbers ~ N(0, 0.1).

use super::TaskSim;
use crate::error::SimError;
use crate::mujoco::{MjSim, ModelConfig, Unstable};
use mujoco_rs::prelude::MjtIntegrator;
use proto::Builtin;
use rand::rngs::StdRng;
use rand_distr::{Distribution, Normal};

const MODEL: ModelConfig = ModelConfig {
    xml: include_str!("../../assets/cartpole.xml"),
    substeps: 2,
    integrator: MjtIntegrator::mjINT_RK4,
};

/// Standard deviation of every initial state number.
const RESET_STD: f64 = 0.1;

/// The cartpole's physics.
#[derive(Debug)]
pub(crate) struct Cartpole {
    sim: MjSim,
}

impl Cartpole {
    pub fn new() -> Result<Self, SimError> {
        let sim = MjSim::load(Builtin::Cartpole.task(), MODEL)?;
        if sim.qpos().len() != 2 || sim.qvel().len() != 2 {
            return Err(SimError::ModelMismatch {
                task: Builtin::Cartpole,
                detail: format!(
                    "expected a slider and a hinge, found nq = {}",
                    sim.qpos().len()
                ),
            });
        }
        Ok(Self { sim })
    }
}

impl TaskSim for Cartpole {
    #[cfg(feature = "render")]
    fn physics(&self) -> &MjSim {
        &self.sim
    }

    fn reset(&mut self, rng: &mut StdRng) {
        let normal = Normal::new(0.0, RESET_STD).expect("a positive standard deviation");
        let mut draw = || normal.sample(rng);
        let qpos = [draw(), draw()];
        let qvel = [draw(), draw()];
        self.sim.set_state(&qpos, &qvel);
    }

    fn step(&mut self, action: &[f32]) -> Result<(), Unstable> {
        self.sim.advance(action)
    }

    fn observe(&self, out: &mut [f32]) {
        let (qpos, qvel) = (self.sim.qpos(), self.sim.qvel());
        out[0] = qpos[0] as f32;
        out[1] = qpos[1] as f32;
        out[2] = qvel[0] as f32;
        out[3] = qvel[1] as f32;
    }

    fn set_state(&mut self, obs: &[f32]) -> Result<(), SimError> {
        let qpos = [f64::from(obs[0]), f64::from(obs[1])];
        let qvel = [f64::from(obs[2]), f64::from(obs[3])];
        self.sim.set_state(&qpos, &qvel);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proto::task::cartpole::{POLE_LENGTH, tip};
    use rand::SeedableRng;
    use std::f32::consts::PI;

    fn observe(c: &Cartpole) -> [f32; 4] {
        let mut obs = [0.0; 4];
        c.observe(&mut obs);
        obs
    }

    /// The MJCF's pole tip (a site) is where proto's reward thinks it is, for any state:
    /// the sign convention of θ and the pole length agree between simulator and planner.
    #[test]
    fn model_tip_matches_the_catalog_tip() {
        let mut c = Cartpole::new().unwrap();
        for &(x, theta) in &[(0.0, 0.0), (0.0, PI), (0.3, 0.5), (-1.0, -2.0), (0.7, 4.0)] {
            c.set_state(&[x, theta, 0.0, 0.0]).unwrap();
            let site = c.sim.site_position("tip").unwrap();
            let (tx, tz) = tip(&[x, theta, 0.0, 0.0]);
            assert!(
                (site[0] as f32 - tx).abs() < 1e-5,
                "x={x} θ={theta}: {site:?} vs {tx}"
            );
            assert!(
                site[1].abs() < 1e-9,
                "the pole stays in the x–z plane: {site:?}"
            );
            assert!(
                (site[2] as f32 - tz).abs() < 1e-5,
                "x={x} θ={theta}: {site:?} vs {tz}"
            );
        }
        c.set_state(&[0.0, 0.0, 0.0, 0.0]).unwrap();
        let hanging = c.sim.site_position("tip").unwrap();
        assert!(
            (hanging[2] as f32 + POLE_LENGTH).abs() < 1e-6,
            "θ = 0 hangs down: {hanging:?}"
        );
    }

    #[test]
    fn pushing_right_moves_the_cart_right() {
        let mut c = Cartpole::new().unwrap();
        c.set_state(&[0.0; 4]).unwrap();
        for _ in 0..10 {
            c.step(&[3.0]).unwrap();
        }
        let pushed = observe(&c);
        assert!(pushed[0] > 0.1 && pushed[2] > 0.5, "{pushed:?}");
        // Accelerating the pivot to the right leaves the pole behind: its tip swings to the
        // left of the cart, which is θ > 0 in this convention.
        assert!(pushed[1] > 0.0, "{pushed:?}");

        c.set_state(&[0.0; 4]).unwrap();
        for _ in 0..10 {
            c.step(&[-3.0]).unwrap();
        }
        let left = observe(&c);
        assert!(
            left[0] < -0.1 && left[2] < -0.5 && left[1] < 0.0,
            "{left:?}"
        );
    }

    #[test]
    fn the_pole_swings_under_gravity() {
        let mut c = Cartpole::new().unwrap();
        // Released from horizontal at rest, the pole falls towards hanging down (θ → 0).
        c.set_state(&[0.0, PI / 2.0, 0.0, 0.0]).unwrap();
        c.step(&[0.0]).unwrap();
        let after = observe(&c);
        assert!(after[1] < PI / 2.0 && after[3] < 0.0, "{after:?}");
        // It swings through the bottom well up the other side, but not as high as it started:
        // damping only takes energy out, ...
        let mut min_theta = f32::MAX;
        for _ in 0..40 {
            c.step(&[0.0]).unwrap();
            min_theta = min_theta.min(observe(&c)[1]);
        }
        assert!(
            (-PI / 2.0..-0.5).contains(&min_theta),
            "swung to {min_theta}"
        );
        // ... and the upright position is an unstable equilibrium: a nudge makes it fall.
        c.set_state(&[0.0, PI - 0.01, 0.0, 0.0]).unwrap();
        for _ in 0..50 {
            c.step(&[0.0]).unwrap();
        }
        let fallen = observe(&c);
        assert!((fallen[1] - PI).abs() > 1.0, "{fallen:?}");
    }

    #[test]
    fn reset_samples_small_states_from_the_seed() {
        let mut c = Cartpole::new().unwrap();
        let mut all = Vec::new();
        for seed in 0..200 {
            c.reset(&mut StdRng::seed_from_u64(seed));
            all.extend(observe(&c));
        }
        let n = all.len() as f32;
        let mean = all.iter().sum::<f32>() / n;
        let std = (all.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / n).sqrt();
        assert!(mean.abs() < 0.02, "mean {mean}");
        assert!((std - 0.1).abs() < 0.01, "std {std}");
    }

    /// The task can be solved within its limits: a textbook energy-pumping controller with a
    /// linear balancing law near the top, using only ±3 N, brings the pole up within about a
    /// second, brings the cart back to the origin and balances there (PETS's behaviour).
    /// Without this, a planner failing to swing up would say nothing about the planner.
    #[test]
    fn a_hand_written_controller_swings_up_within_the_episode() {
        let spec = Builtin::Cartpole.task();
        let mut c = Cartpole::new().unwrap();
        c.set_state(&[0.0, 0.05, 0.0, 0.0]).unwrap();
        let mut total = 0.0;
        let mut last_50 = 0.0;
        for step in 0..spec.episode_len {
            let obs = observe(&c);
            let mut act = [swing_up_controller(&obs)];
            spec.clamp_action(&mut act);
            c.step(&act).unwrap();
            let r = spec.reward(&obs, &act, &observe(&c));
            total += r;
            if step >= spec.episode_len - 50 {
                last_50 += r;
            }
        }
        let end = observe(&c);
        let phi = from_upright(end[1]);
        assert!(phi.abs() < 0.05 && end[0].abs() < 0.1, "ends at {end:?}");
        assert!(
            last_50 > 0.95 * 50.0,
            "last 50 steps earned {last_50} (return {total})"
        );
        assert!(total > 100.0, "return {total}");
        eprintln!("hand-written swing-up return: {total}");
    }

    /// The angle from upright, wrapped to [−π, π); φ > 0 puts the tip right of the cart.
    fn from_upright(theta: f32) -> f32 {
        theta.rem_euclid(2.0 * PI) - PI
    }

    /// Energy pumping away from the top, a linear balancing law near it.
    fn swing_up_controller(obs: &[f32]) -> f32 {
        let [x, theta, xd, thetad] = [obs[0], obs[1], obs[2], obs[3]];
        let phi = from_upright(theta);
        if phi.abs() < CATCH {
            // Push under the pole; the small positive cart terms lean the pole towards x = 0.
            K_PHI * phi + K_PHID * thetad + (K_X * x + K_XD * xd).clamp(-0.6, 0.6)
        } else {
            // θ̈ = (3 / 2L)(ẍ cos θ − g sin θ), so the pole's energy relative to upright,
            // E = ½θ̇² − ω²(1 + cos θ) with ω² = 3g / 2L, changes at dE/dt ∝ ẍ θ̇ cos θ:
            // accelerate the cart with that sign while E < 0, against it when E > 0.
            let omega2 = 3.0 * 9.81 / (2.0 * POLE_LENGTH);
            let energy = 0.5 * thetad * thetad - omega2 * (1.0 + theta.cos());
            K_PUMP * -energy * thetad * theta.cos() - K_X * x
        }
    }

    const CATCH: f32 = 0.5;
    const K_PHI: f32 = 6.0;
    const K_PHID: f32 = 1.2;
    const K_X: f32 = 1.0;
    const K_XD: f32 = 1.0;
    const K_PUMP: f32 = 1.0;
}
