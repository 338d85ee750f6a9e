//! A restart opens only what a running daemon may hold: at most `max_runs` stored runs, the
//! newest first, and only while the open runs' replay is below `[storage]
//! max_total_replay_bytes`. The other stored runs stay on disk untouched, `status` lists them
//! as dormant with the budget that kept them closed, and an attach to one is refused with
//! that budget's name while the open runs keep serving.

use ebmpc_e2e::client::{Client, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{Builtin, RunSpec, TrainMode};
use std::path::Path;
use std::time::{Duration, SystemTime};

const PLANNER: &str = "dormant";
const RUNS: [&str; 3] = ["r0", "r1", "r2"];

fn config(max_runs: usize, max_total_replay_bytes: Option<u64>) -> String {
    let mut config =
        PlannerConfig::new(PLANNER, Sizes::TINY).line(format!("max_runs = {max_runs}"));
    if let Some(bytes) = max_total_replay_bytes {
        config = config.line(format!("[storage]\nmax_total_replay_bytes = {bytes}"));
    }
    config.toml()
}

fn spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: Some("cem".into()),
        overrides: Default::default(),
        mode: TrainMode::Async,
        seed: 1,
        task_spec: None,
    }
}

/// Makes the runs' replay logs last written in `newest_first` order (a minute apart), so
/// that which runs a restart opens does not depend on what the last daemon wrote when.
fn set_last_written(data_dir: &Path, newest_first: &[&str]) {
    let now = SystemTime::now();
    for (age, run) in newest_first.iter().enumerate() {
        let log = ebmpc_e2e::newest_replay_segment(data_dir, run);
        let file = std::fs::File::options().write(true).open(&log).unwrap();
        file.set_modified(now - Duration::from_secs(60 * age as u64))
            .unwrap();
    }
}

/// Names of the open runs and of the dormant ones (with their budgets), from `status`.
async fn open_and_dormant(client: &Client) -> (Vec<String>, Vec<(String, String)>, u64) {
    let s = status(&client.session, PLANNER).await.unwrap();
    let open = s.runs.iter().map(|r| r.name.clone()).collect();
    let dormant = s
        .dormant_runs
        .iter()
        .map(|d| (d.name.clone(), d.budget.clone()))
        .collect();
    assert_eq!(s.budgets.runs.used, s.runs.len() as u64);
    (open, dormant, s.dormant_run_count)
}

#[test]
fn a_restart_opens_stored_runs_only_within_max_runs_and_the_replay_budget() {
    let dir = TempDir::new("dormant-runs");

    // Three runs stored by a daemon that may host them all.
    let mut planner = Planner::start(dir.path(), &config(3, None)).expect("planner starts");
    runtime().block_on(async {
        for run in RUNS {
            let client = Client::connect(&planner.endpoint, run, "a").await.unwrap();
            client.attach(&spec()).await.unwrap();
        }
    });
    planner.stop().unwrap();

    // Restarted with max_runs = 2: the two newest open, the oldest stays dormant.
    set_last_written(&planner.data_dir, &["r0", "r1", "r2"]);
    let mut planner = Planner::start(dir.path(), &config(2, None)).expect("planner restarts");
    runtime().block_on(async {
        let r0 = Client::connect(&planner.endpoint, "r0", "a").await.unwrap();
        r0.attach(&spec()).await.expect("an open run is served");
        let (open, dormant, count) = open_and_dormant(&r0).await;
        assert_eq!(
            open,
            ["r0", "r1"],
            "the newest runs open, no more than max_runs"
        );
        assert_eq!(count, 1);
        assert_eq!(dormant.len(), 1);
        assert_eq!(dormant[0].0, "r2");
        assert!(dormant[0].1.contains("max_runs"), "{dormant:?}");

        let r2 = Client::connect(&planner.endpoint, "r2", "a").await.unwrap();
        let refused = r2
            .attach(&spec())
            .await
            .expect_err("a dormant run is refused");
        let message = refused.to_string();
        assert!(
            message.contains("stored here but not open") && message.contains("max_runs"),
            "{message}"
        );
        let (open, _, count) = open_and_dormant(&r0).await;
        assert_eq!((open.len(), count), (2, 1), "the refusal opened nothing");
    });
    planner.stop().unwrap();
    let data_dir = planner.data_dir.clone();
    let stored = |run: &str| planner_service::persist::RunDir::new(&data_dir, run).has_replay();
    assert!(stored("r2"), "the dormant run stays on disk");

    // Restarted with room for every run but a replay budget of one byte: the newest run opens
    // (the budget is not reached before it), then the budget is, and the others stay closed.
    set_last_written(&data_dir, &["r1", "r2", "r0"]);
    let mut planner = Planner::start(dir.path(), &config(3, Some(1))).expect("planner restarts");
    runtime().block_on(async {
        let r1 = Client::connect(&planner.endpoint, "r1", "a").await.unwrap();
        r1.attach(&spec()).await.expect("the open run is served");
        let (open, dormant, count) = open_and_dormant(&r1).await;
        assert_eq!(open, ["r1"]);
        assert_eq!(count, 2);
        let names: Vec<&str> = dormant.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["r0", "r2"]);
        assert!(
            dormant
                .iter()
                .all(|(_, budget)| budget.contains("max_total_replay_bytes")),
            "{dormant:?}"
        );
        let r0 = Client::connect(&planner.endpoint, "r0", "a").await.unwrap();
        let message = r0.attach(&spec()).await.unwrap_err().to_string();
        assert!(message.contains("max_total_replay_bytes"), "{message}");
    });
    planner.stop().unwrap();
    for run in RUNS {
        assert!(stored(run), "run {run} is kept on disk");
    }
}

/// A stored run whose opening fails on an I/O error that may pass (here its replay log is
/// briefly a directory) is not set aside: `status` lists it as retrying, and once the error
/// passes the daemon opens it by itself, with nothing lost.
#[test]
fn a_transient_open_error_is_retried_until_the_run_opens() {
    let dir = TempDir::new("transient-open");
    let mut planner = Planner::start(dir.path(), &config(3, None)).expect("planner starts");
    runtime().block_on(async {
        let client = Client::connect(&planner.endpoint, "t", "a").await.unwrap();
        client.attach(&spec()).await.unwrap();
    });
    planner.stop().unwrap();
    let log = ebmpc_e2e::newest_replay_segment(&planner.data_dir, "t");
    let aside = log.with_extension("aside");
    let bytes = std::fs::metadata(&log).unwrap().len();
    std::fs::rename(&log, &aside).unwrap();
    std::fs::create_dir(&log).unwrap();

    let mut planner = Planner::start(dir.path(), &config(3, None)).expect("planner restarts");
    runtime().block_on(async {
        let client = Client::connect(&planner.endpoint, "other", "a")
            .await
            .unwrap();
        client
            .attach(&spec())
            .await
            .expect("the daemon serves others");
        let deadline = std::time::Instant::now() + Duration::from_secs(30);
        let retrying = loop {
            let s = status(&client.session, PLANNER).await.unwrap();
            if let Some(r) = s.retrying_runs.iter().find(|r| r.name == "t") {
                break r.clone();
            }
            assert!(
                std::time::Instant::now() < deadline,
                "never retrying: {s:?}"
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        };
        assert!(retrying.attempts >= 1, "{retrying:?}");
        let s = status(&client.session, PLANNER).await.unwrap();
        assert!(
            s.failed_runs.iter().all(|f| f.name != "t"),
            "set aside: {s:?}"
        );

        // The error passes: the next try opens the run.
        std::fs::remove_dir(&log).unwrap();
        std::fs::rename(&aside, &log).unwrap();
        let deadline = std::time::Instant::now() + Duration::from_secs(60);
        loop {
            let s = status(&client.session, PLANNER).await.unwrap();
            if s.runs.iter().any(|r| r.name == "t") {
                assert!(s.retrying_runs.is_empty(), "{s:?}");
                break;
            }
            assert!(std::time::Instant::now() < deadline, "never opened: {s:?}");
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        let t = Client::connect(&planner.endpoint, "t", "a").await.unwrap();
        t.attach(&spec()).await.expect("the reopened run is served");
    });
    planner.stop().unwrap();
    assert!(std::fs::metadata(&log).unwrap().len() >= bytes);
}
