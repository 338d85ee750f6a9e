//! The Gymnasium driver (`python -m ebmpc.gym`) against this build's planner daemon: a planner
//! that knows nothing of an environment but what the driver derives from its spaces learns it.
//!
//! - `InvertedPendulum-v5` (MuJoCo, through the PyPI `mujoco` wheel): Gymnasium's alive bonus
//!   (`1` per step) and its termination rule as formulas; the pole balances for the whole
//!   1,000-step episode within 5 episodes.
//!
//! Sizes are the `cartpole` base preset's with documented overrides that keep a run within a
//! few minutes on a loaded 2-core machine (fixed seeds, not tuned per seed). The interpreter is
//! `$EBMPC_PYTHON`, or `.venv/bin/python` (see [`ebmpc_e2e::python`]); `make test` installs
//! Gymnasium and MuJoCo into it (the package's `gym` extra). Without them these tests fail:
//! they never skip.

use ebmpc_e2e::python::run_gym_driver;
use ebmpc_e2e::{Planner, TempDir};
use std::time::Duration;

/// A planner with no task of its own: the driver's attach carries the whole task spec.
const PLANNER_CONFIG: &str = "planner_id = \"gym-e2e\"\n";

/// One `episode N: return R, steps S, end E, M ms per action (first F ms; P planned, models vK)`
/// line of the driver.
#[derive(Debug, PartialEq)]
struct Episode {
    episode: u32,
    ret: f64,
    steps: u32,
    end: String,
    planned: u32,
    models: u64,
}

fn episodes(log: &str) -> Vec<Episode> {
    log.lines()
        .filter_map(|line| {
            let rest = line.strip_prefix("episode ")?;
            let (episode, rest) = rest.split_once(": return ")?;
            let (ret, rest) = rest.split_once(", steps ")?;
            let (steps, rest) = rest.split_once(", end ")?;
            let (end, rest) = rest.split_once(", ")?;
            let (_, rest) = rest.split_once("; ")?;
            let (planned, rest) = rest.split_once(" planned, models v")?;
            let models = rest.strip_suffix(')')?;
            Some(Episode {
                episode: episode.parse().ok()?,
                ret: ret.parse().ok()?,
                steps: steps.parse().ok()?,
                end: end.to_string(),
                planned: planned.parse().ok()?,
                models: models.parse().ok()?,
            })
        })
        .collect()
}

/// Runs the driver against a fresh planner; its episodes, and the log of both for failures.
fn drive(name: &str, args: &[&str], timeout: Duration) -> (Vec<Episode>, String) {
    let dir = TempDir::new(name);
    let mut planner = Planner::start(dir.path(), PLANNER_CONFIG).expect("planner starts");
    let mut all = vec!["--connect", &planner.endpoint];
    all.extend_from_slice(args);
    let (status, log) = run_gym_driver(dir.path(), &all, timeout).unwrap();
    let both = format!("driver:\n{log}\nplanner:\n{}", planner.process.log());
    assert!(status.success(), "the driver failed ({status}):\n{both}");
    planner.stop().unwrap();
    (episodes(&log), both)
}

#[test]
fn inverted_pendulum_balances_its_whole_episode_within_five_episodes() {
    let (episodes, log) = drive(
        "gym-inverted-pendulum",
        &[
            "--env",
            "InvertedPendulum-v5",
            "--run",
            "inverted-pendulum",
            "--episodes",
            "5",
            "--seed",
            "0",
            // Gymnasium's own reward and termination (its InvertedPendulumEnv.step): 1 per step
            // alive; the episode ends once the pole leaves ±0.2 rad or a number is not finite.
            "--reward-expression",
            "1",
            "--termination-expression",
            "!(abs(s_next[1]) <= 0.2 && norm1(s_next) < 1e30)",
            "--preset",
            "cem+deen",
            "--base-preset",
            "cartpole",
            // The cartpole sizes (paper Table 2) cut to what a 2-core CI machine trains and plans
            // with in minutes: narrower, shallower networks, a capped retraining, a smaller
            // search, and every CEM iteration run (no deadline: the simulator waits).
            "--override",
            "dynamics_hidden_layers=2",
            "--override",
            "dynamics_hidden_size=64",
            "--override",
            "energy_hidden_layers=2",
            "--override",
            "energy_hidden_size=64",
            "--override",
            "max_gradient_steps=2000",
            "--override",
            "population=100",
            "--override",
            "elites=10",
            "--override",
            "horizon=15",
            "--override",
            "cem_iterations=3",
            "--override",
            "deadline_ms=0",
        ],
        Duration::from_secs(900),
    );
    assert_eq!(episodes.len(), 5, "{log}");
    for (i, e) in episodes.iter().enumerate() {
        assert_eq!(e.episode, i as u32, "{log}");
        // A terminated episode ends where the pole fell; only the limit ends a full one.
        let expected_end = if e.steps == 1000 { "time_limit" } else { "terminated" };
        assert_eq!(e.end, expected_end, "{log}");
        // Gymnasium pays 1 for every step but the one that fell.
        let alive = e.steps - u32::from(e.end == "terminated");
        assert_eq!(e.ret, f64::from(alive), "1 per step alive: {log}");
    }
    let last = episodes.last().unwrap();
    assert_eq!(last.steps, 1000, "the last episode balances to the limit: {log}");
    assert_eq!(last.planned, 1000, "every action of it planned: {log}");
    assert!(last.models >= 1, "planned with trained models: {log}");
}
