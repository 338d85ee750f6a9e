//! Prints how fast each simulated task steps (control steps per second, one thread), e.g.
//! `cargo run --release -p sim-bridge --example step_rate`.

use sim_bridge::{Env, SIMULATED};
use std::time::Instant;

fn main() -> Result<(), sim_bridge::SimError> {
    for &task in SIMULATED {
        let mut env = Env::new(task)?;
        let spec = env.spec();
        let episodes = 50;
        let mut steps = 0u64;
        let started = Instant::now();
        for episode in 0..episodes {
            env.reset(episode);
            loop {
                // A deterministic action sweep across the bounds.
                let phase = (steps as f32 * 0.1).sin();
                let action: Vec<f32> = spec
                    .action_low
                    .iter()
                    .zip(spec.action_high)
                    .map(|(lo, hi)| lo + (hi - lo) * 0.5 * (phase + 1.0))
                    .collect();
                steps += 1;
                if env.step(&action)?.done() {
                    break;
                }
            }
        }
        let seconds = started.elapsed().as_secs_f64();
        println!(
            "{task}: {steps} control steps in {seconds:.3} s = {:.0} steps/s ({:.1} µs/step, {:.0}× real time)",
            steps as f64 / seconds,
            1e6 * seconds / steps as f64,
            steps as f64 * spec.control_dt / seconds
        );
    }
    Ok(())
}
