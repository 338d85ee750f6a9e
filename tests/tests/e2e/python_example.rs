//! A controller in another language: `examples/python_controller.py` (the `eclipse-zenoh`
//! package, JSON encoding) attaches to a real planner daemon, plays short episodes of its own
//! toy cart-pole, and the planner stores every transition of them; `planner-service status`
//! shows the run, as a table and as JSON.
//!
//! The interpreter is `$EBMPC_PYTHON`, or `.venv/bin/python` in the workspace (see
//! [`ebmpc_e2e::python`]). Without it these tests fail: they never skip.

use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::python::run_controller;
use ebmpc_e2e::{Planner, TempDir, free_endpoint, status_cli};
use std::time::Duration;

/// Tiny networks and a small population: these tests check the interop, not the learning.
fn config() -> String {
    PlannerConfig::new("py-e2e", Sizes::SMALL).toml()
}

const EPISODES: u32 = 3;
const STEPS: u32 = 25;

/// One "episode N: return R over S steps (P planned, Q random actions; models vK)" line.
#[derive(Debug, PartialEq)]
struct EpisodeLine {
    episode: u32,
    ret: f32,
    steps: u32,
    planned: u32,
    random: u32,
    models: u64,
}

fn episode_lines(log: &str) -> Vec<EpisodeLine> {
    log.lines()
        .filter_map(|line| {
            let rest = line.strip_prefix("episode ")?;
            let (episode, rest) = rest.split_once(": return ")?;
            let (ret, rest) = rest.split_once(" over ")?;
            let (steps, rest) = rest.split_once(" steps (")?;
            let (planned, rest) = rest.split_once(" planned, ")?;
            let (random, rest) = rest.split_once(" random actions; models v")?;
            let models = rest.strip_suffix(')')?;
            Some(EpisodeLine {
                episode: episode.parse().ok()?,
                ret: ret.parse().ok()?,
                steps: steps.parse().ok()?,
                planned: planned.parse().ok()?,
                random: random.parse().ok()?,
                models: models.parse().ok()?,
            })
        })
        .collect()
}

#[test]
fn python_controller_plays_episodes_that_the_planner_stores() {
    let dir = TempDir::new("python");
    let mut planner = Planner::start(dir.path(), &config()).expect("planner starts");
    let (steps, episodes) = (STEPS.to_string(), EPISODES.to_string());
    let args = [
        "--connect",
        &planner.endpoint,
        "--run",
        "py-run",
        "--agent",
        "py-0",
        "--episodes",
        &episodes,
        "--steps",
        &steps,
        "--seed",
        "2",
        // Sent in the attach request's JSON: one random episode, then planning.
        "--override",
        "exploration_episodes=1",
    ];
    let (status, log) = run_controller(dir.path(), &args, Duration::from_secs(300)).unwrap();
    assert!(
        status.success(),
        "python controller failed: {status}\n{log}\nplanner:\n{}",
        planner.process.log()
    );

    // Every step was answered in JSON: one random exploration episode, then planned ones with
    // retrained models (sync mode: each episode waits for the models of the last).
    let lines = episode_lines(&log);
    assert_eq!(lines.len(), EPISODES as usize, "{log}");
    for (i, line) in lines.iter().enumerate() {
        assert_eq!(line.episode, i as u32, "{log}");
        assert_eq!(line.steps, STEPS, "{log}");
        assert!(
            line.ret.is_finite() && line.ret.abs() <= STEPS as f32,
            "{log}"
        );
        if i == 0 {
            assert_eq!(
                (line.planned, line.random, line.models),
                (0, STEPS, 0),
                "{log}"
            );
        } else {
            assert_eq!((line.planned, line.random), (STEPS, 0), "{log}");
            assert!(
                line.models >= i as u64,
                "episode {i} planned with stale models: {log}"
            );
        }
    }
    assert!(log.contains("stored: run `py-run`"), "{log}");

    // The planner's status, through the CLI: the run holds every transition, and the returns
    // it computed from the rewards the controller sent are the controller's.
    let (ok, json, err) = status_cli(&planner.endpoint, &["--json"]).unwrap();
    assert!(ok.success(), "status --json failed: {err}");
    let reports: serde_json::Value = serde_json::from_str(&json).expect("status --json is JSON");
    let reports = reports.as_array().expect("an array of planner reports");
    assert_eq!(reports.len(), 1, "{json}");
    assert_eq!(reports[0]["planner_id"], "py-e2e", "{json}");
    let runs = reports[0]["runs"].as_array().expect("runs");
    let run = runs
        .iter()
        .find(|r| r["name"] == "py-run")
        .unwrap_or_else(|| panic!("run py-run missing: {json}"));
    assert_eq!(run["task"], "cartpole", "{json}");
    assert_eq!(run["episodes"], EPISODES, "{json}");
    assert_eq!(run["transitions"], EPISODES * STEPS, "{json}");
    let returns = run["last_returns"].as_array().expect("last_returns");
    assert_eq!(returns.len(), EPISODES as usize, "{json}");
    for (stored, line) in returns.iter().zip(&lines) {
        assert_eq!(stored[0], "py-0", "{json}");
        assert_eq!(stored[1], line.episode, "{json}");
        let ret = stored[2].as_f64().expect("a return") as f32;
        assert!(
            (ret - line.ret).abs() <= 1.5e-3,
            "planner return {ret} vs controller {}",
            line.ret
        );
    }
    assert!(
        run["planning_latency"]["samples"].as_u64().unwrap() >= u64::from(2 * STEPS),
        "planned actions are timed: {json}"
    );

    // The table names the run with its task and counts.
    let (ok, table, err) = status_cli(&planner.endpoint, &["--planner", "py-e2e"]).unwrap();
    assert!(ok.success(), "status failed: {err}");
    assert!(table.starts_with("planner py-e2e "), "{table}");
    let row = table
        .lines()
        .find(|l| l.starts_with("py-run "))
        .unwrap_or_else(|| panic!("no row for py-run:\n{table}"));
    let cells: Vec<&str> = row.split_whitespace().collect();
    assert_eq!(
        &cells[..6],
        &[
            "py-run",
            "cartpole",
            "cem+deen",
            "sync",
            &EPISODES.to_string(),
            &(EPISODES * STEPS).to_string()
        ],
        "{table}"
    );

    planner.stop().unwrap();
}

#[test]
fn python_controller_fails_on_errors() {
    let dir = TempDir::new("python-errors");

    // Nobody listens: the controller gives up with an error, not a hang or a zero exit.
    let nowhere = free_endpoint();
    let (status, log) = run_controller(
        dir.path(),
        &["--connect", &nowhere, "--attach-timeout", "2"],
        Duration::from_secs(60),
    )
    .unwrap();
    assert_eq!(status.code(), Some(1), "{log}");
    assert!(log.contains("error: no planner answered"), "{log}");

    // The planner's error report (an invalid run configuration) ends the controller with it.
    let planner = Planner::start(dir.path(), &config()).expect("planner starts");
    let (status, log) = run_controller(
        dir.path(),
        &[
            "--connect",
            &planner.endpoint,
            "--run",
            "bad",
            "--override",
            "population=0",
        ],
        Duration::from_secs(60),
    )
    .unwrap();
    assert_eq!(status.code(), Some(1), "{log}");
    assert!(log.contains("error: attach refused: refused:"), "{log}");

    // ... and `status` of a planner that is not there fails too.
    let (ok, _, err) = status_cli(
        &planner.endpoint,
        &["--planner", "absent", "--timeout", "1"],
    )
    .unwrap();
    assert!(!ok.success());
    assert!(err.contains("no planner answered"), "{err}");
}
