//! Every task of the catalog end to end: a real planner daemon and a real MuJoCo sim-bridge run
//! one random exploration episode, retrain, then one episode planned by MPC with the trained
//! models, over Zenoh on loopback. This is the plumbing of each task (dimensions, bounds,
//! rewards, termination, model transforms, presets) through both processes, not learning:
//! the networks are tiny, the population small, and episodes are capped at [`STEPS`] steps by
//! the bridge (`--max-steps`) so the five tasks take a few minutes on a loaded 2-core machine.

use ebmpc_e2e::bridge::{check_random_then_planned, run_episodes};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::Builtin;
use std::sync::Mutex;
use std::time::Duration;

/// Steps per episode (every task's own episode is longer).
const STEPS: u32 = 50;

/// Tiny networks, a small population and one exploration episode for every task (the
/// half-cheetah preset explores for three).
fn config() -> String {
    PlannerConfig::new("e2e-all-tasks", Sizes::SMALL)
        .exploration_episodes(1)
        .toml()
}

/// The tests share two cores: one planner–bridge pair at a time keeps each within its
/// timeouts however many test threads cargo starts.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

/// Runs two capped episodes of `task` through a fresh planner and checks that the first was
/// random, the second planned with trained models, and that the planner stored both.
fn random_then_planned(task: Builtin) {
    let _turn = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let spec = task.task();
    let dir = TempDir::new(task.name());
    let mut planner = Planner::start(dir.path(), &config()).expect("planner starts");
    let steps = STEPS.to_string();
    let args = [
        "--task",
        task.name(),
        "--run",
        task.name(),
        "--agent",
        "bridge-0",
        "--seed",
        "5",
        "--max-steps",
        &steps,
    ];
    let bridge = run_episodes(dir.path(), &planner, &args, 2, Duration::from_secs(300))
        .unwrap_or_else(|e| panic!("{task}: {e:?}"));
    let log = &bridge.log;

    let mut stored = 0;
    for row in &bridge.episodes {
        // Only the ant can end early: by falling.
        if task == Builtin::Ant {
            assert!((1..=STEPS).contains(&row.steps), "{task}: {row:?}");
        } else {
            assert_eq!(row.steps, STEPS, "{task}: {row:?}");
        }
        stored += row.steps as usize;
    }
    check_random_then_planned(&bridge.episodes).unwrap_or_else(|e| panic!("{task}: {e:?}"));

    // The planned episode used models trained on the exploration episode.
    let planner_log = planner.process.log();
    assert!(
        planner_log.contains("models updated"),
        "{task}: no training in:\n{planner_log}"
    );
    assert!(
        !log.contains("models v0; "),
        "{task}: a planned episode ran on untrained models:\n{log}"
    );

    planner.stop().unwrap_or_else(|e| panic!("{task}: {e:?}"));
    let buffer = planner.replay(task.name(), task).unwrap();
    assert_eq!(buffer.len(), stored, "{task}");
    assert_eq!(buffer.episodes().len(), 2, "{task}");
    for i in 0..buffer.len() {
        let (s, a, s2) = buffer.transitions().row(i);
        assert_eq!(
            (s.len(), a.len(), s2.len()),
            (spec.obs_dim, spec.act_dim, spec.obs_dim)
        );
        assert!(
            s.iter().chain(a).chain(s2).all(|v| v.is_finite()),
            "{task}: transition {i}"
        );
        let within = a
            .iter()
            .zip(spec.action_low.iter().zip(&spec.action_high))
            .all(|(v, (lo, hi))| (lo..=hi).contains(&v));
        assert!(within, "{task}: transition {i} action out of bounds: {a:?}");
    }
}

#[test]
fn cartpole() {
    random_then_planned(Builtin::Cartpole);
}

#[test]
fn reacher3d() {
    random_then_planned(Builtin::Reacher3d);
}

#[test]
fn pusher() {
    random_then_planned(Builtin::Pusher);
}

#[test]
fn halfcheetah() {
    random_then_planned(Builtin::HalfCheetah);
}

#[test]
fn ant() {
    random_then_planned(Builtin::Ant);
}
