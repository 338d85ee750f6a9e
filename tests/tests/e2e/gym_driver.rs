//! The Gymnasium driver (`python -m ebmpc.gym`) against this build's planner daemon: a planner
//! that knows nothing of an environment but what the driver derives from its spaces learns it.
//!
//! - `InvertedPendulum-v5` (MuJoCo, through the PyPI `mujoco` wheel), as a Python user runs it:
//!   `pip install './python[gym]'` in a clean venv (the wheel bundles the planner), then
//!   `python -m ebmpc.gym` with no planner given, which starts the bundled one by itself.
//!   Gymnasium's termination rule and a centred alive bonus as formulas; the pole balances
//!   for the whole 1,000-step episode within 8 episodes and keeps balancing, and the same
//!   command again resumes the run from the per-user data directory. (It was 5 until the bf16 first layer
//!   changed the plans' rounding: the same run then balanced from its sixth episode on, and an
//!   f32 run of the same seed had not balanced by its fifth. Where within a few episodes a
//!   learner crosses over depends on every rounding; that it crosses and stays is the claim.)
//! - The same task with its termination learned instead of given (no formula): the pole stays
//!   up for hundreds of steps within a budget of 1,500 steps of experience.
//!
//! Sizes are the `cartpole` base preset's with documented overrides that keep a run within a
//! few minutes on a loaded 2-core machine. Seeds are fixed (0, not chosen among others), and
//! with every CEM iteration run (`deadline_ms = 0`) a run does not depend on the machine's
//! load (two runs of this one under different loads printed the same episodes). The interpreter is
//! `$EBMPC_PYTHON`, or `.venv/bin/python` (see [`ebmpc_e2e::python`]); `make test` installs
//! Gymnasium and MuJoCo into it (the package's `gym` extra). Without them these tests fail:
//! they never skip.

use ebmpc_e2e::python::{install_package_in_clean_venv, run_gym_driver};
use ebmpc_e2e::{Planner, TempDir};
use std::process::Command;
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

/// The inverted pendulum's flags: Gymnasium's termination (InvertedPendulumEnv.step: the pole
/// beyond ±0.2 rad or a number not finite) and its reward of 1 per step alive, less the cart's
/// squared distance from the centre: with 1 alone the cart drifted to the end of its rail
/// (x = ±1), where the model had no data, and the pole fell there.
const INVERTED_PENDULUM: &[&str] = &[
    "--env",
    "InvertedPendulum-v5",
    "--seed",
    "0",
    "--reward-expression",
    "1 - s_next[0]^2",
    "--termination-expression",
    "!(abs(s_next[1]) <= 0.2 && norm1(s_next) < 1e30)",
    // CEM without the energy term: DEEN's energy, trained on the handful of falling
    // transitions of the first episodes, held the plans near them (3-step episodes).
    "--preset",
    "cem",
    "--base-preset",
    "cartpole",
    // The cartpole sizes (paper Table 2: CEM 400 × 25 steps × 5 iterations) with a two-layer
    // dynamics model of 200 units (narrower ones did not learn it in 5 episodes), a capped
    // retraining, and every CEM iteration run (no deadline: the simulator waits, and a loaded
    // machine plans as far as an idle one).
    "--override",
    "dynamics_hidden_layers=2",
    "--override",
    "max_gradient_steps=5000",
    "--override",
    "deadline_ms=0",
];

#[test]
fn pip_installed_package_learns_the_inverted_pendulum_with_its_own_planner_and_resumes() {
    let dir = TempDir::new("gym-inverted-pendulum");
    let installed = install_package_in_clean_venv(dir.path(), Duration::from_secs(1200))
        .expect("pip install './python[gym]' in a clean venv");
    eprintln!(
        "pip install './python[gym]' took {:.1} s",
        installed.install_seconds
    );
    // The wheel put the planner in the venv's bin/, on its PATH.
    let version = Command::new(installed.bin.join("planner-service"))
        .arg("--version")
        .output()
        .expect("the venv's planner-service runs");
    assert!(version.status.success(), "{version:?}");
    assert!(
        String::from_utf8_lossy(&version.stdout).starts_with("planner-service "),
        "{version:?}"
    );

    let mut args = INVERTED_PENDULUM.to_vec();
    args.extend(["--episodes", "8"]);
    let (status, log) = installed
        .run_gym_driver(dir.path(), &args, Duration::from_secs(900))
        .unwrap();
    assert!(status.success(), "the driver failed ({status}):\n{log}");
    let played = episodes(&log);
    assert_eq!(played.len(), 8, "{log}");
    for (i, e) in played.iter().enumerate() {
        assert_eq!(e.episode, i as u32, "{log}");
        // A terminated episode ends where the pole fell; only the limit ends a full one.
        let expected_end = if e.steps == 1000 {
            "time_limit"
        } else {
            "terminated"
        };
        assert_eq!(e.end, expected_end, "{log}");
        // Gymnasium pays 1 for every step but the one that fell.
        let alive = e.steps - u32::from(e.end == "terminated");
        assert_eq!(e.ret, f64::from(alive), "1 per step alive: {log}");
    }
    for last in &played[6..] {
        assert_eq!(
            last.steps, 1000,
            "the last two episodes balance to the limit: {log}"
        );
        assert_eq!(last.planned, 1000, "every action of them planned: {log}");
        assert!(last.models >= 1, "planned with trained models: {log}");
    }
    // The run lives in the per-user data directory, named after the environment ...
    let data = dir.path().join("xdg/ebmpc");
    assert!(
        planner_service::persist::RunDir::new(&data, "InvertedPendulum-v5").has_replay(),
        "{log}"
    );
    let planner_log = std::fs::read_to_string(data.join("planner.log")).unwrap();
    assert!(
        planner_log.contains("SIGTERM received"),
        "the driver stopped its planner: {planner_log}"
    );
    // ... and the same command again resumes it: its next episode is the run's ninth.
    args.truncate(INVERTED_PENDULUM.len());
    args.extend(["--episodes", "1"]);
    let (status, log) = installed
        .run_gym_driver(dir.path(), &args, Duration::from_secs(600))
        .unwrap();
    assert!(
        status.success(),
        "the second invocation failed ({status}):\n{log}"
    );
    let resumed = episodes(&log);
    assert_eq!(resumed.len(), 1, "{log}");
    assert_eq!(resumed[0].episode, 8, "the run resumed: {log}");
    assert_eq!(resumed[0].steps, 1000, "and still balances: {log}");
}

/// `InvertedPendulum-v5` with its termination learned instead of given: the driver sends no
/// termination formula, so the planner trains a classifier of the states that end an episode
/// on the episodes Gymnasium ends as `terminated`, and its plans stop counting rewards where
/// the pole would fall. Random play falls within a few steps; the budget is 1,500 steps of
/// experience (`--steps`), and the pole stays up for hundreds of steps within it. The
/// learned termination's held-out accuracy is in the planner's log of every retraining.
#[test]
fn inverted_pendulum_stays_up_with_its_termination_learned_within_a_step_budget() {
    let mut args: Vec<&str> = INVERTED_PENDULUM.to_vec();
    let formula = args
        .iter()
        .position(|a| *a == "--termination-expression")
        .unwrap();
    args.drain(formula..formula + 2);
    args.extend(["--run", "learned-end", "--steps", "1500"]);
    let (played, log) = drive("gym-learned-termination", &args, Duration::from_secs(900));
    let steps: Vec<u32> = played.iter().map(|e| e.steps).collect();
    let taken: u32 = steps.iter().sum();
    assert!(
        taken >= 1500 && taken - steps.last().unwrap() < 1500,
        "episodes start until 1,500 steps are taken: {steps:?}\n{log}"
    );
    let first = &played[0];
    assert!(
        first.steps < 30 && first.end == "terminated" && first.planned == 0,
        "the random first episode falls within a few steps: {log}"
    );
    let long = played.iter().position(|e| e.steps >= 300);
    assert!(
        long.is_some(),
        "an episode stays up for hundreds of steps: {steps:?}\n{log}"
    );
    let last = played.last().unwrap();
    assert!(
        last.steps >= 300 && last.planned == last.steps,
        "and the last one too, every action planned: {steps:?}\n{log}"
    );
    // Every retraining logs the classifier's accuracy on held-out transitions; by the end it
    // knows where the pole falls.
    let plain: String = strip_ansi(&log);
    let accuracies: Vec<f64> = plain
        .split("termination_accuracy=")
        .skip(1)
        .filter_map(|rest| rest.split_whitespace().next()?.parse().ok())
        .collect();
    assert!(!accuracies.is_empty(), "{plain}");
    let latest = *accuracies.last().unwrap();
    assert!(latest > 0.95, "held-out accuracy {accuracies:?}");
}

/// `text` without terminal colour sequences (`ESC [ … m`).
fn strip_ansi(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut chars = text.chars();
    while let Some(c) = chars.next() {
        if c == '\u{1b}' {
            for d in chars.by_ref() {
                if d == 'm' {
                    break;
                }
            }
        } else {
            out.push(c);
        }
    }
    out
}

#[test]
fn pendulum_learns_its_reward_and_swings_up_within_six_episodes() {
    let (episodes, log) = drive(
        "gym-pendulum",
        &[
            "--env",
            "Pendulum-v1",
            "--run",
            "pendulum",
            "--episodes",
            "6",
            "--seed",
            "0",
            // No --reward-expression: the reward is learned from the rewards the driver sends.
            "--preset",
            "cem",
            "--base-preset",
            "cartpole",
            // As for the inverted pendulum (two-layer dynamics of 200 units, a capped
            // retraining, no deadline), with a 2 s horizon (40 steps of 0.05 s): a swing-up
            // from hanging takes longer than the cartpole preset's 1.25 s to come into view.
            "--override",
            "dynamics_hidden_layers=2",
            "--override",
            "horizon=40",
            "--override",
            "max_gradient_steps=3000",
            "--override",
            "deadline_ms=0",
        ],
        Duration::from_secs(900),
    );
    assert_eq!(episodes.len(), 6, "{log}");
    for (i, e) in episodes.iter().enumerate() {
        assert_eq!(
            (e.episode, e.steps, e.end.as_str()),
            (i as u32, 200, "time_limit")
        );
        let planned = if i == 0 { 0 } else { 200 };
        assert_eq!(e.planned, planned, "one random episode, then plans: {log}");
    }
    // Random play scores about -1200 (Gymnasium's Pendulum-v1); the learned reward's plans,
    // over the last three episodes, better than -400. (Ten episodes were played once: from the
    // first planned one on, every episode scored -120 to -230; the last four cost a third of
    // the whole test's time and showed nothing the first six do not.)
    assert!(episodes[0].ret < -400.0, "the random episode: {log}");
    let last: f64 = episodes[3..].iter().map(|e| e.ret).sum::<f64>() / 3.0;
    assert!(last > -400.0, "mean return {last} of episodes 3-5: {log}");
}
