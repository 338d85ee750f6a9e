//! A pumping agent cannot grow a daemon's replay without bound: each run's log stops at
//! `[storage] max_run_replay_bytes` and all runs' logs together at `max_total_replay_bytes`;
//! at a budget the agent is refused with an error naming the setting, `status` says how close
//! each budget is, and the restarted daemon opens the runs inside the same budgets (and keeps
//! refusing beyond them).

use ebmpc_e2e::client::{Answer, Client, ToySystem, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{Builtin, EpisodeEnd, ErrorCode, ErrorReport, Observation, RunSpec, TrainMode};
use std::time::Duration;

const PLANNER: &str = "budget";
const PER_RUN: u64 = 50_000;
const TOTAL: u64 = 80_000;
/// What one observation may add beyond a budget: the check is made before each store, and
/// one store writes at most a transition and an episode's end.
const ONE_STORE: u64 = 1_000;

fn config() -> String {
    PlannerConfig::new(PLANNER, Sizes::TINY)
        .exploration_episodes(1_000)
        .line(format!(
            "[storage]\nmax_run_replay_bytes = {PER_RUN}\nmax_total_replay_bytes = {TOTAL}"
        ))
        .toml()
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

/// Plays cartpole episodes of random actions back to back until the planner refuses a step;
/// returns the refusal and the number of steps that were answered or stored.
async fn pump(client: &Client) -> (ErrorReport, u32) {
    let token = client.session_token();
    let mut system = ToySystem::new(1);
    let mut stored = 0;
    for episode in 0..1_000 {
        let mut reward = None;
        for step in 0..=200 {
            let end = (step == 200).then_some(EpisodeEnd::TimeLimit);
            let obs = Observation::new(episode, step, system.state.to_vec(), reward, end)
                .in_session(token);
            client.send(&obs).await.unwrap();
            if end.is_some() {
                stored += 1;
                break;
            }
            match client.answer(Duration::from_secs(60)).await.unwrap() {
                Answer::Action(action) => reward = Some(system.step(&action.action)),
                Answer::Error(report) => return (report, stored),
            }
            stored += 1;
        }
    }
    panic!("a thousand episodes were stored under a budget of {PER_RUN} bytes");
}

#[test]
fn a_pumping_agent_is_refused_at_the_replay_budgets_and_the_restart_stays_inside() {
    let dir = TempDir::new("replay-budget");
    let mut planner = Planner::start(dir.path(), &config()).expect("planner starts");
    let endpoint = planner.endpoint.clone();
    runtime().block_on(async {
        let a = Client::connect(&endpoint, "pump-a", "a").await.unwrap();
        a.attach(&spec()).await.unwrap();
        let (report, stored) = pump(&a).await;
        assert_eq!(report.code, ErrorCode::Refused, "{report}");
        assert!(report.message.contains("max_run_replay_bytes"), "{report}");
        assert!(stored > 200, "a few episodes fit the budget: {stored}");
        let s = status(&a.session, PLANNER).await.unwrap();
        let run = s.runs.iter().find(|r| r.name == "pump-a").unwrap();
        assert!(
            run.replay_bytes >= PER_RUN && run.replay_bytes <= PER_RUN + ONE_STORE,
            "{} bytes",
            run.replay_bytes
        );
        assert_eq!(s.budgets.fullest_run_replay_bytes.limit, Some(PER_RUN));
        assert_eq!(s.budgets.replay_bytes.limit, Some(TOTAL));
        assert_eq!(s.budgets.replay_bytes.used, run.replay_bytes);

        // A second run fills what is left of the total budget.
        let b = Client::connect(&endpoint, "pump-b", "b").await.unwrap();
        b.attach(&spec()).await.unwrap();
        let (report, _) = pump(&b).await;
        assert_eq!(report.code, ErrorCode::Refused, "{report}");
        assert!(
            report.message.contains("max_total_replay_bytes"),
            "{report}"
        );
        let s = status(&b.session, PLANNER).await.unwrap();
        assert!(
            s.budgets.replay_bytes.used >= TOTAL
                && s.budgets.replay_bytes.used <= TOTAL + ONE_STORE,
            "{:?}",
            s.budgets
        );
    });
    planner.stop().unwrap();

    // On disk: each log inside its budget, all of them inside the total.
    let log_bytes =
        |run: &str| planner_service::persist::RunDir::new(&planner.data_dir, run).replay_bytes();
    let (a, b) = (log_bytes("pump-a"), log_bytes("pump-b"));
    assert!(a <= PER_RUN + ONE_STORE, "{a} bytes");
    assert!(a + b <= TOTAL + 2 * ONE_STORE, "{a} + {b} bytes");

    // Restarted, the daemon opens both runs inside the budgets and refuses beyond them.
    let mut planner = Planner::start(dir.path(), &config()).expect("planner restarts");
    runtime().block_on(async {
        let a = Client::connect(&planner.endpoint, "pump-a", "a")
            .await
            .unwrap();
        let accepted = a.attach(&spec()).await.unwrap();
        let s = status(&a.session, PLANNER).await.unwrap();
        assert_eq!(s.runs.len(), 2, "both runs are open");
        assert!(
            s.budgets.replay_bytes.used <= TOTAL + 2 * ONE_STORE,
            "{:?}",
            s.budgets
        );
        let token = a.session_token();
        let episode = accepted.next_episode;
        a.send(&Observation::new(episode, 0, vec![0.0; 4], None, None).in_session(token))
            .await
            .unwrap();
        // Step 0 stores nothing and is answered; step 1 would store a transition.
        let Answer::Action(action) = a.answer(Duration::from_secs(60)).await.unwrap() else {
            panic!("step 0 stores nothing and is answered");
        };
        let mut system = ToySystem::new(2);
        let reward = system.step(&action.action);
        a.send(
            &Observation::new(episode, 1, system.state.to_vec(), Some(reward), None)
                .in_session(token),
        )
        .await
        .unwrap();
        let Answer::Error(report) = a.answer(Duration::from_secs(60)).await.unwrap() else {
            panic!("a step beyond the budget was stored after the restart");
        };
        assert_eq!(report.code, ErrorCode::Refused, "{report}");
    });
    planner.stop().unwrap();
}
