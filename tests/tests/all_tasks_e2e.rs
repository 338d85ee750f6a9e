//! Every task of the catalog end to end: a real planner daemon and a real MuJoCo sim-bridge run
//! one random exploration episode, retrain, then one episode planned by MPC with the trained
//! models, over Zenoh on loopback. This is the plumbing of each task (dimensions, bounds,
//! rewards, termination, model transforms, presets) through both processes, not learning:
//! the networks are tiny, the population small, and episodes are capped at [`STEPS`] steps by
//! the bridge (`--max-steps`) so the five tasks take a few minutes on a loaded 2-core machine.

use ebmpc_e2e::{Planner, TempDir, read_csv, run_bridge};
use planner_service::replay::ReplayBuffer;
use proto::TaskId;
use std::sync::Mutex;
use std::time::Duration;

/// Steps per episode (every task's own episode is longer).
const STEPS: u32 = 50;

/// Tiny networks, a small population and one exploration episode for every task (the
/// half-cheetah preset explores for three).
const SMALL: &str = r#"
planner_id = "e2e-all-tasks"
[overrides]
dynamics_hidden_layers = 2
dynamics_hidden_size = 32
dynamics_epochs = 5
energy_hidden_layers = 2
energy_hidden_size = 32
energy_epochs = 5
population = 40
elites = 5
horizon = 8
cem_iterations = 2
exploration_episodes = 1
"#;

/// The tests share two cores: one planner–bridge pair at a time keeps each within its
/// timeouts however many test threads cargo starts.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

/// Runs two capped episodes of `task` through a fresh planner and checks that the first was
/// random, the second planned with trained models, and that the planner stored both.
fn random_then_planned(task: TaskId) {
    let _turn = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let spec = task.spec();
    let dir = TempDir::new(task.name());
    let mut planner = Planner::start(dir.path(), SMALL).expect("planner starts");
    let csv = dir.path().join("episodes.csv");
    let steps = STEPS.to_string();
    let args = [
        "--task",
        task.name(),
        "--run",
        task.name(),
        "--agent",
        "bridge-0",
        "--episodes",
        "2",
        "--seed",
        "5",
        "--max-steps",
        &steps,
        "--out",
        csv.to_str().unwrap(),
    ];
    let (status, log) = run_bridge(
        dir.path(),
        &planner.endpoint,
        &args,
        Duration::from_secs(300),
    )
    .unwrap();
    assert!(
        status.success(),
        "{task}: sim-bridge failed: {status}\n{log}\nplanner:\n{}",
        planner.process.log()
    );

    let rows = read_csv(&csv).unwrap();
    assert_eq!(rows.len(), 2, "{task}: {rows:?}");
    let mut stored = 0;
    for (episode, row) in rows.iter().enumerate() {
        let steps: u32 = row["steps"].parse().unwrap();
        // Only the ant can end early: by falling.
        if task == TaskId::Ant {
            assert!((1..=STEPS).contains(&steps), "{task}: {row:?}");
        } else {
            assert_eq!(steps, STEPS, "{task}: {row:?}");
        }
        stored += steps as usize;
        let ret: f32 = row["return"].parse().unwrap();
        assert!(ret.is_finite(), "{task}: {row:?}");
        let planned: u32 = row["planned_steps"].parse().unwrap();
        let plan_ms: f64 = row["plan_ms_mean"].parse().unwrap();
        if episode == 0 {
            assert_eq!(planned, 0, "{task}: exploration is random: {row:?}");
        } else {
            assert_eq!(planned, steps, "{task}: every action planned: {row:?}");
            assert!(
                plan_ms > 0.0,
                "{task}: the planner timed its plans: {row:?}"
            );
        }
    }

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

    let status = planner.process.terminate(Duration::from_secs(30)).unwrap();
    assert!(status.success(), "{task}: planner exit: {status}");
    let path = planner
        .data_dir
        .join(format!("runs/{}/replay.log", task.name()));
    let buffer = ReplayBuffer::open(&path, spec).unwrap();
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
            .zip(spec.action_low.iter().zip(spec.action_high))
            .all(|(v, (lo, hi))| (lo..=hi).contains(&v));
        assert!(within, "{task}: transition {i} action out of bounds: {a:?}");
    }
}

#[test]
fn cartpole() {
    random_then_planned(TaskId::Cartpole);
}

#[test]
fn reacher3d() {
    random_then_planned(TaskId::Reacher3d);
}

#[test]
fn pusher() {
    random_then_planned(TaskId::Pusher);
}

#[test]
fn halfcheetah() {
    random_then_planned(TaskId::HalfCheetah);
}

#[test]
fn ant() {
    random_then_planned(TaskId::Ant);
}
