//! The walking skeleton end to end: a real planner daemon and a real MuJoCo sim-bridge learn
//! cartpole over Zenoh on loopback — one random exploration episode, a retraining, then one
//! planned episode — and every step is answered, stored, and trained on.

use ebmpc_e2e::{Planner, TempDir, read_csv, run_bridge};
use planner_service::replay::ReplayBuffer;
use proto::TaskId;
use std::time::Duration;

/// Tiny networks and a small population: this test checks the plumbing, not the learning.
const SMALL: &str = r#"
planner_id = "e2e"
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
"#;

/// `(planned, random, models version)` of every "N planned, M random actions; models vK" line
/// the bridge logs, one per episode.
fn action_sources(log: &str) -> Vec<(u32, u32, u64)> {
    log.lines()
        .filter_map(|line| {
            let (before, after) = line.split_once(" planned, ")?;
            let planned = before
                .rsplit(|c: char| !c.is_ascii_digit())
                .next()?
                .parse()
                .ok()?;
            let (random, rest) = after.split_once(" random actions; models v")?;
            let version = rest
                .split(|c: char| !c.is_ascii_digit())
                .next()?
                .parse()
                .ok()?;
            Some((planned, random.trim().parse().ok()?, version))
        })
        .collect()
}

#[test]
fn two_cartpole_episodes_random_then_planned() {
    let dir = TempDir::new("cartpole");
    let mut planner = Planner::start(dir.path(), SMALL).expect("planner starts");
    let csv = dir.path().join("episodes.csv");
    let args = [
        "--task",
        "cartpole",
        "--run",
        "skeleton",
        "--agent",
        "bridge-0",
        "--episodes",
        "2",
        "--seed",
        "3",
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
        "sim-bridge failed: {status}\n{log}\nplanner:\n{}",
        planner.process.log()
    );

    // Every step of both episodes was answered: the bridge only counts a step once its action came.
    let rows = read_csv(&csv).unwrap();
    assert_eq!(rows.len(), 2, "{rows:?}");
    for row in &rows {
        assert_eq!(row["steps"], "200", "{row:?}");
        let ret: f32 = row["return"].parse().unwrap();
        assert!(ret.is_finite() && (-20.0..=200.0).contains(&ret), "{row:?}");
    }

    // Training ran between the episodes and the second episode was planned with its models.
    let planner_log = planner.process.log();
    assert!(
        planner_log.contains("models updated"),
        "no training in:\n{planner_log}"
    );
    let episodes = action_sources(&log);
    assert_eq!(episodes.len(), 2, "per-episode action summaries in:\n{log}");
    assert_eq!(
        episodes[0],
        (0, 200, 0),
        "exploration episode is all random:\n{log}"
    );
    assert_eq!(
        episodes[1].0, 200,
        "every step of the second episode is planned:\n{log}"
    );
    assert!(
        episodes[1].2 >= 1,
        "the second episode is planned with trained models:\n{log}"
    );

    // A clean shutdown, then the replay buffer holds every transition of both episodes.
    let status = planner.process.terminate(Duration::from_secs(30)).unwrap();
    assert!(
        status.success(),
        "planner exit: {status}\n{}",
        planner.process.log()
    );
    let buffer = ReplayBuffer::open(
        &planner.data_dir.join("runs/skeleton/replay.log"),
        TaskId::Cartpole.spec(),
    )
    .unwrap();
    assert_eq!(buffer.len(), 400);
    assert_eq!(buffer.episodes().len(), 2);
    for (i, transition) in (0..buffer.len())
        .map(|i| buffer.transitions().row(i))
        .enumerate()
    {
        let (s, a, s2) = transition;
        assert!(
            s.iter().chain(a).chain(s2).all(|v| v.is_finite()),
            "transition {i}"
        );
        assert!(
            a[0].abs() <= 3.0,
            "transition {i} action out of bounds: {a:?}"
        );
    }
}

/// An agent whose planner is killed mid-run waits for it, attaches again when it is back, and
/// finishes all its episodes; the restarted planner resumed the run from disk.
#[test]
fn the_bridge_rides_out_a_planner_killed_and_restarted() {
    let dir = TempDir::new("cartpole-restart");
    let endpoint = ebmpc_e2e::free_endpoint();
    let mut planner = Planner::start_on(dir.path(), SMALL, &endpoint).expect("planner starts");
    let csv = dir.path().join("episodes.csv");
    let mut cmd = std::process::Command::new(&ebmpc_e2e::binaries().bridge);
    cmd.args([
        "run", "--task", "cartpole", "--run", "restart", "--agent", "b0",
    ])
    .args(["--episodes", "3", "--max-steps", "40", "--seed", "1"])
    .args(["--connect", &endpoint, "--out"])
    .arg(&csv)
    .env("RUST_LOG", "info,zenoh=warn");
    let mut bridge =
        ebmpc_e2e::Guarded::spawn("sim-bridge", cmd, dir.path().join("bridge.log")).unwrap();
    bridge
        .wait_for_log("episode 1/3 done", Duration::from_secs(180))
        .unwrap();
    planner.process.signal("KILL").unwrap();
    let _ = planner.process.wait(Duration::from_secs(30));
    drop(planner);
    std::thread::sleep(Duration::from_millis(500));
    let mut planner = Planner::start_on(dir.path(), SMALL, &endpoint).expect("planner restarts");
    assert!(
        planner.process.log().contains("run opened"),
        "the run was resumed from disk:\n{}",
        planner.process.log()
    );

    let status = bridge.wait(Duration::from_secs(300)).unwrap();
    let log = bridge.log();
    assert!(
        status.success(),
        "sim-bridge failed: {status}\n{log}\nplanner:\n{}",
        planner.process.log()
    );
    let rows = read_csv(&csv).unwrap();
    assert_eq!(rows.len(), 3, "{rows:?}");
    assert!(rows.iter().all(|r| r["steps"] == "40"), "{rows:?}");
    assert!(
        log.contains("attaching again") || log.contains("went away"),
        "the bridge noticed the planner leave:\n{log}"
    );
    assert!(
        planner
            .process
            .terminate(Duration::from_secs(30))
            .unwrap()
            .success()
    );
    let buffer = ReplayBuffer::open(
        &planner.data_dir.join("runs/restart/replay.log"),
        TaskId::Cartpole.spec(),
    )
    .unwrap();
    let finished = buffer
        .episodes()
        .iter()
        .filter(|e| e.end != proto::EpisodeEnd::Interrupted)
        .count();
    assert_eq!(finished, 3, "{:?}", buffer.episodes());
}
