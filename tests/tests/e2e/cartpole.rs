//! The walking skeleton end to end: a real planner daemon and a real MuJoCo sim-bridge learn
//! cartpole over Zenoh on loopback — one random exploration episode, a retraining, then one
//! planned episode — and every step is answered, stored, and trained on.

use ebmpc_e2e::bridge::{check_random_then_planned, read_episodes, run_episodes, spawn_bridge};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir, free_endpoint};
use proto::{Builtin, EpisodeEnd};
use std::time::Duration;

/// Tiny networks and a small population: this test checks the plumbing, not the learning.
fn config() -> String {
    PlannerConfig::new("e2e", Sizes::SMALL).toml()
}

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
    let mut planner = Planner::start(dir.path(), &config()).expect("planner starts");
    let args = [
        "--task", "cartpole", "--run", "skeleton", "--agent", "bridge-0", "--seed", "3",
    ];
    let bridge = run_episodes(dir.path(), &planner, &args, 2, Duration::from_secs(300)).unwrap();
    let log = &bridge.log;

    // Every step of both episodes was answered: the bridge only counts a step once its action
    // came. The first episode explored, the second was planned.
    for row in &bridge.episodes {
        assert_eq!(row.steps, 200, "{row:?}");
        assert!((-20.0..=200.0).contains(&row.ret), "{row:?}");
    }
    check_random_then_planned(&bridge.episodes).unwrap();

    // Training ran between the episodes and the second episode was planned with its models.
    let planner_log = planner.process.log();
    assert!(
        planner_log.contains("models updated"),
        "no training in:\n{planner_log}"
    );
    let episodes = action_sources(log);
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
    planner.stop().unwrap();
    let buffer = planner.replay("skeleton", Builtin::Cartpole).unwrap();
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

/// Starts a bridge for 3 cartpole episodes of 40 steps of `run` (episodes into `csv`, `extra`
/// flags appended) and returns once its first episode is done: the moment the tests below do
/// something to the planner.
fn bridge_past_its_first_of_three_episodes(
    dir: &TempDir,
    endpoint: &str,
    run: &str,
    csv: &std::path::Path,
    extra: &[&str],
) -> ebmpc_e2e::Guarded {
    let csv = csv.to_str().unwrap();
    let args = [
        "--task",
        "cartpole",
        "--run",
        run,
        "--agent",
        "b0",
        "--episodes",
        "3",
        "--max-steps",
        "40",
        "--seed",
        "1",
        "--out",
        csv,
    ];
    let mut bridge = spawn_bridge(dir.path(), endpoint, &[&args[..], extra].concat()).unwrap();
    bridge
        .wait_for_log("episode 1/3 done", Duration::from_secs(180))
        .unwrap();
    bridge
}

/// The log of `bridge` once it has exited successfully (within 5 minutes).
fn finished_log(bridge: &mut ebmpc_e2e::Guarded, planner: &Planner) -> String {
    let status = bridge.wait(Duration::from_secs(300)).unwrap();
    let log = bridge.log();
    assert!(
        status.success(),
        "sim-bridge failed: {status}\n{log}\nplanner:\n{}",
        planner.process.log()
    );
    log
}

/// An agent whose planner is killed mid-run waits for it, attaches again when it is back, and
/// finishes all its episodes; the restarted planner resumed the run from disk.
#[test]
fn the_bridge_rides_out_a_planner_killed_and_restarted() {
    let dir = TempDir::new("cartpole-restart");
    let endpoint = free_endpoint();
    // Retraining must outlast the harness's log polling (50 ms), or the bridge can finish all
    // its episodes between "episode 1/3 done" and the kill: small networks train for long.
    let config = PlannerConfig::new(
        "e2e",
        Sizes {
            hidden_size: 128,
            epochs: 3000,
            ..Sizes::SMALL
        },
    )
    .toml();
    let mut planner = Planner::start_on(dir.path(), &config, &endpoint).expect("planner starts");
    let csv = dir.path().join("episodes.csv");
    let mut bridge = bridge_past_its_first_of_three_episodes(&dir, &endpoint, "restart", &csv, &[]);
    planner.process.signal("KILL").unwrap();
    let _ = planner.process.wait(Duration::from_secs(30));
    drop(planner);
    std::thread::sleep(Duration::from_millis(500));
    let mut planner = Planner::start_on(dir.path(), &config, &endpoint).expect("planner restarts");
    assert!(
        planner.process.log().contains("run opened"),
        "the run was resumed from disk:\n{}",
        planner.process.log()
    );

    let log = finished_log(&mut bridge, &planner);
    let rows = read_episodes(&csv, 3).unwrap();
    assert!(rows.iter().all(|r| r.steps == 40), "{rows:?}");
    assert!(
        log.contains("attaching again") || log.contains("went away"),
        "the bridge noticed the planner leave:\n{log}"
    );
    planner.stop().unwrap();
    let buffer = planner.replay("restart", Builtin::Cartpole).unwrap();
    let finished = buffer
        .episodes()
        .iter()
        .filter(|e| e.end != EpisodeEnd::Interrupted)
        .count();
    assert_eq!(finished, 3, "{:?}", buffer.episodes());
}

/// A planner that gets no CPU for longer than Zenoh's default link lease (10 s; here it is
/// stopped for 13 s, as an idle-priority daemon beside a build can be) is not taken for gone
/// when the planner and the bridge start from a Zenoh file with a longer lease (the experiment
/// launcher writes one): the bridge waits, the episode under way goes on, and the run's buffer
/// holds no interrupted episode. With the default lease the bridge would start that episode
/// over.
#[test]
fn a_long_link_lease_rides_out_a_starved_planner() {
    let dir = TempDir::new("cartpole-starved");
    let zenoh = dir.path().join("zenoh.json5");
    std::fs::write(&zenoh, "{ transport: { link: { tx: { lease: 120000 } } } }").unwrap();
    let config = format!(
        "zenoh_config = {:?}\n{}",
        zenoh.display().to_string(),
        config()
    );
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    let csv = dir.path().join("episodes.csv");
    let waits = [
        "--action-timeout",
        "120",
        "--train-timeout",
        "120",
        "--zenoh-config",
    ];
    let extra = [&waits[..], &[zenoh.to_str().unwrap()]].concat();
    let mut bridge =
        bridge_past_its_first_of_three_episodes(&dir, &planner.endpoint, "starved", &csv, &extra);
    planner.process.signal("STOP").unwrap();
    std::thread::sleep(Duration::from_secs(13));
    planner.process.signal("CONT").unwrap();

    let log = finished_log(&mut bridge, &planner);
    assert!(
        !log.contains("went away") && !log.contains("attaching again"),
        "the bridge took the stopped planner for gone:\n{log}"
    );
    let rows = read_episodes(&csv, 3).unwrap();
    assert_eq!(
        rows.iter().map(|r| r.episode).collect::<Vec<_>>(),
        [0, 1, 2],
        "no episode started over: {rows:?}"
    );
    assert!(rows.iter().all(|r| r.steps == 40), "{rows:?}");
    planner.stop().unwrap();
    let buffer = planner.replay("starved", Builtin::Cartpole).unwrap();
    assert!(
        buffer
            .episodes()
            .iter()
            .all(|e| e.end != EpisodeEnd::Interrupted),
        "{:?}",
        buffer.episodes()
    );
    assert_eq!(buffer.episodes().len(), 3, "{:?}", buffer.episodes());
}

/// The gradient-based baseline through the service: a run created with the `adam+dae` preset
/// explores one episode, trains its model and DAE, and plans every step of the next episode
/// with Adam (40 candidates, two Adam steps: plumbing, not learning), within the bounds.
#[test]
fn adam_dae_plans_a_cartpole_episode_through_the_service() {
    let dir = TempDir::new("cartpole-adam");
    let mut planner = Planner::start(dir.path(), &config()).expect("planner starts");
    let args = [
        "--task",
        "cartpole",
        "--run",
        "adam",
        "--agent",
        "bridge-0",
        "--seed",
        "4",
        "--preset",
        "adam+dae",
        "--max-steps",
        "30",
    ];
    let bridge = run_episodes(dir.path(), &planner, &args, 2, Duration::from_secs(300)).unwrap();
    for row in &bridge.episodes {
        assert_eq!(row.steps, 30, "{row:?}");
        assert!(row.ret.is_finite(), "{row:?}");
    }
    check_random_then_planned(&bridge.episodes).unwrap();
    let episodes = action_sources(&bridge.log);
    assert_eq!(
        episodes.len(),
        2,
        "per-episode summaries in:\n{}",
        bridge.log
    );
    assert_eq!(episodes[1].0, 30, "every step planned:\n{}", bridge.log);
    assert!(episodes[1].2 >= 1, "planned with trained models");
    planner.stop().unwrap();
    // The run was stored with Adam and the DAE, and its actions stayed in bounds.
    let spec = std::fs::read_to_string(planner.data_dir.join("runs/adam/run.json")).unwrap();
    assert!(spec.contains("\"adam+dae\""), "{spec}");
    let buffer = planner.replay("adam", Builtin::Cartpole).unwrap();
    assert_eq!(buffer.len(), 60);
    for i in 0..buffer.len() {
        let (s, a, s2) = buffer.transitions().row(i);
        assert!(s.iter().chain(s2).all(|v| v.is_finite()), "transition {i}");
        assert!(a[0].abs() <= 3.0, "transition {i}: {a:?}");
    }
}
