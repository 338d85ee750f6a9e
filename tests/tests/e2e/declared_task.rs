//! A run of a task the operator declared (`[tasks.NAME]`) stores the spec it runs in its
//! `run.json`, as a client's spec is: with the declaration removed the run still resumes with
//! its stored spec, and with the declaration changed the stored run is set aside with a clear
//! reason instead of resuming with a task it was not trained on.

use ebmpc_e2e::client::{Client, runtime};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir, free_endpoint};
use proto::{RunSpec, TrainMode};

const TASK: &str = "declared-toy";

/// A planner configuration declaring the task with `episode_len` steps (`None`: not declared).
fn config(episode_len: Option<u32>) -> String {
    let mut config = PlannerConfig::new("declared", Sizes::TINY);
    if let Some(len) = episode_len {
        for line in [
            format!("[tasks.{TASK}]"),
            "obs_dim = 4".into(),
            "act_dim = 1".into(),
            "action_low = [-3.0]".into(),
            "action_high = [3.0]".into(),
            format!("episode_len = {len}"),
            "control_dt = 0.04".into(),
            "reward = \"learned\"".into(),
        ] {
            config = config.line(line);
        }
    }
    config.toml()
}

/// The run's spec, naming the task only.
fn by_name() -> RunSpec {
    RunSpec {
        task: TASK.into(),
        preset: Some("cem".into()),
        overrides: Default::default(),
        mode: TrainMode::Sync,
        seed: 1,
        task_spec: None,
    }
}

/// Starts a planner with `config`, attaches agent `agent` to the run by task name and stops
/// the planner; returns the attach's outcome (`Err`: the refusal's text).
fn attach_once(dir: &TempDir, endpoint: &str, config: &str, agent: &str) -> Result<(), String> {
    let mut planner = Planner::start_on(dir.path(), config, endpoint).expect("planner starts");
    let outcome = runtime().block_on(async {
        let client = Client::connect(endpoint, "declared", agent).await.unwrap();
        let outcome = client.attach(&by_name()).await.map(|_| ());
        client.close().await.unwrap();
        outcome.map_err(|e| e.to_string())
    });
    planner.stop().unwrap();
    outcome
}

#[test]
fn a_declared_task_is_stored_with_its_run_and_a_changed_declaration_is_refused() {
    let dir = TempDir::new("declared-task");
    let endpoint = free_endpoint();
    attach_once(&dir, &endpoint, &config(Some(20)), "a").expect("attached by name");
    let stored: serde_json::Value = serde_json::from_slice(
        &std::fs::read(dir.path().join("data/runs/declared/run.json")).unwrap(),
    )
    .unwrap();
    let spec = &stored["task_spec"];
    assert_eq!(spec["name"], TASK, "{stored}");
    assert_eq!(spec["episode_len"], 20, "{stored}");
    assert_eq!(spec["reward"], "learned", "{stored}");

    // The declaration removed: the run resumes with the spec stored with it.
    attach_once(&dir, &endpoint, &config(None), "b").expect("resumed with its stored spec");

    // The declaration changed: the stored run is set aside, and an agent is told why.
    let err = attach_once(&dir, &endpoint, &config(Some(30)), "c").unwrap_err();
    assert!(
        err.contains("declares task `declared-toy` with another spec than the one stored"),
        "{err}"
    );
}
