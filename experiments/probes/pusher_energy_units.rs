//! Pusher: what DEEN's penalty charges for moving the object, with σ in standardised units (the
//! planner's default) and in the transitions' own units (the paper's "corrupting the
//! transitions in the replay buffer").
//!
//! Trains Table 2's pusher DEEN (3 × 200, σ = 0.1, batch 32, 100 epochs) on the transitions of
//! random-action episodes, the data the energy model has when planning starts, once per noise
//! unit. Then, on the transitions of a held-out random episode, it displaces the object along
//! +x (towards the goal) by δ, either in the next state only (the object moved during the step)
//! or in both states (an object that was pushed earlier and now rests there), and prints the
//! median energy increase times Table 2's α = 0.01: the penalty per imagined step, to set
//! against the reward such a displacement earns per step (1.25 δ from the goal term).
//!
//!     cargo run --release -p ebmpc-experiments --example pusher_energy_units [EPISODES]

use planner_service::energy::{Deen, EnergyConfig, NoiseUnits};
use proto::Builtin;
use proto::task::pusher::{GOAL_WEIGHT, OBJECT};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use sim_bridge::Env;

const ALPHA: f32 = 0.01;
const SIGMA: f32 = 0.1;

/// The transitions `[s, a, s']` of a random-action episode from seed `seed`.
fn random_episode(env: &mut Env, seed: u64) -> Vec<Vec<f32>> {
    let spec = env.spec().spec().clone();
    let mut rng = StdRng::seed_from_u64(seed);
    let mut obs = env.reset(seed).to_vec();
    let mut out = Vec::new();
    loop {
        let act: Vec<f32> = spec
            .action_low
            .iter()
            .zip(&spec.action_high)
            .map(|(&lo, &hi)| rng.random_range(lo..hi))
            .collect();
        let step = env.step(&act).expect("a stable step");
        let mut row = obs.clone();
        row.extend_from_slice(&act);
        row.extend_from_slice(&step.obs);
        out.push(row);
        if step.done() {
            return out;
        }
        obs = step.obs;
    }
}

fn median(mut v: Vec<f32>) -> f32 {
    v.sort_by(f32::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let episodes: u64 = std::env::args()
        .nth(1)
        .map_or(1, |a| a.parse().expect("a number of training episodes"));
    let mut env = Env::new(Builtin::Pusher).expect("the pusher simulator");
    let (obs_dim, act_dim) = (env.spec().spec().obs_dim, env.spec().spec().act_dim);
    let dim = 2 * obs_dim + act_dim;
    let train: Vec<f32> = (0..episodes)
        .flat_map(|s| random_episode(&mut env, s))
        .flatten()
        .collect();
    let held_out = random_episode(&mut env, 1000);
    let next_object = obs_dim + act_dim + OBJECT;

    let n = train.len() / dim;
    let std_of = |f: usize| {
        let mean = train.iter().skip(f).step_by(dim).sum::<f32>() / n as f32;
        (train
            .iter()
            .skip(f)
            .step_by(dim)
            .map(|v| (v - mean).powi(2))
            .sum::<f32>()
            / n as f32)
            .sqrt()
    };
    println!(
        "{episodes} random episode(s), {n} transitions; the object's x, y, z spread (std) in the next state: {:.2e}, {:.2e}, {:.2e} m",
        std_of(next_object),
        std_of(next_object + 1),
        std_of(next_object + 2)
    );
    println!("σ = {SIGMA}, α = {ALPHA}; penalty = α × median energy increase per imagined step");
    println!(
        "{:<13} {:>7} {:>12} {:>12} {:>10}",
        "units", "δ (cm)", "moved", "displaced", "reward"
    );
    for units in [NoiseUnits::Standardised, NoiseUnits::Raw] {
        let config = EnergyConfig {
            hidden_layers: 3,
            hidden_size: 200,
            epochs: 100,
            batch_size: 32,
            noise_sigma: SIGMA,
            noise_units: units,
            learning_rate: 1e-3,
        };
        let mut rng = StdRng::seed_from_u64(7);
        let mut deen = Deen::new(dim, &config, &mut rng);
        deen.fit(&train, config.epochs, &mut rng);
        let rows: Vec<f32> = held_out.iter().flatten().copied().collect();
        let base = deen.energy_rows(&rows);
        for delta in [0.005f32, 0.01, 0.02, 0.05] {
            let shifted = |both: bool| {
                let mut r = held_out.clone();
                for row in &mut r {
                    row[next_object] += delta;
                    if both {
                        row[OBJECT] += delta;
                    }
                }
                let e = deen.energy_rows(&r.into_iter().flatten().collect::<Vec<_>>());
                median(e.iter().zip(&base).map(|(e, b)| ALPHA * (e - b)).collect())
            };
            println!(
                "{:<13} {:>7.1} {:>12.3} {:>12.3} {:>10.4}",
                units.to_string(),
                delta * 100.0,
                shifted(false),
                shifted(true),
                GOAL_WEIGHT * delta
            );
        }
    }
}
