//! A run's deadline bounds its plans: with a 5 ms deadline and a search far too large for it,
//! every planned action comes back cut short (fewer iterations than configured, `cut` set),
//! and the status report counts the same cut plans and misses the agent saw. The same search
//! with the deadline turned off (`deadline_ms = 0`, as sim-bridge sends) runs every iteration
//! of every plan and never reports a cut or a miss.

use ebmpc_e2e::client::{Client, ToySystem, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{Action, ActionSource, Builtin, EpisodeEnd, Observation, PlannerOverrides, RunSpec};

const PLANNER: &str = "deadlines";
/// Configured iterations: far more than fit in 5 ms at this population and horizon.
const ITERATIONS: u32 = 50;
const EXPLORED_STEPS: u32 = 20;
const PLANNED_STEPS: u32 = 8;

fn spec(deadline_ms: u32) -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: None,
        overrides: PlannerOverrides {
            population: Some(400),
            elites: Some(40),
            horizon: Some(30),
            cem_iterations: Some(ITERATIONS),
            // No early stop on a narrow distribution: only the deadline ends a plan early.
            cem_min_variance: Some(0.0),
            deadline_ms: Some(deadline_ms),
            ..PlannerOverrides::default()
        },
        mode: Default::default(),
        seed: 5,
        task_spec: None,
    }
}

/// One explored episode, then the planned actions of the next one's first steps.
async fn planned_actions(client: &Client) -> Vec<Action> {
    let mut system = ToySystem::new(1);
    let mut action = client
        .step(&Observation::new(0, 0, system.state.to_vec(), None, None))
        .await
        .unwrap();
    for step in 1..=EXPLORED_STEPS {
        let reward = system.step(&action.action);
        let end = (step == EXPLORED_STEPS).then_some(EpisodeEnd::TimeLimit);
        let obs = Observation::new(0, step, system.state.to_vec(), Some(reward), end);
        if end.is_some() {
            client.send(&obs).await.unwrap();
        } else {
            action = client.step(&obs).await.unwrap();
        }
    }
    // Sync mode: the first action of episode 1 comes once the models are trained.
    let mut system = ToySystem::new(2);
    let mut planned = Vec::new();
    let mut reward = None;
    for step in 0..PLANNED_STEPS {
        let obs = Observation::new(1, step, system.state.to_vec(), reward, None);
        let action = client.step(&obs).await.unwrap();
        assert_eq!(action.stats.source, ActionSource::Planned, "{action:?}");
        reward = Some(system.step(&action.action));
        planned.push(action);
    }
    planned
}

#[test]
fn a_tight_deadline_cuts_every_plan_and_none_without_it() {
    let dir = TempDir::new("deadlines");
    let config = PlannerConfig::new(PLANNER, Sizes::TINY)
        .exploration_episodes(1)
        .toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    runtime().block_on(async {
        let tight = Client::connect(&planner.endpoint, "tight", "a")
            .await
            .unwrap();
        tight.attach(&spec(5)).await.unwrap();
        let actions = planned_actions(&tight).await;
        for action in &actions {
            let stats = &action.stats;
            assert!(stats.cut, "a 5 ms deadline cut every plan: {stats:?}");
            assert!(stats.iterations < ITERATIONS, "{stats:?}");
            // No iteration at all is a miss, answered with the previous plan's next action.
            assert!(stats.iterations > 0 || stats.missed, "{stats:?}");
        }

        let free = Client::connect(&planner.endpoint, "free", "a")
            .await
            .unwrap();
        free.attach(&spec(0)).await.unwrap();
        for action in planned_actions(&free).await {
            let stats = &action.stats;
            assert_eq!(
                (stats.iterations, stats.cut, stats.missed),
                (ITERATIONS, false, false)
            );
        }

        let report = status(&tight.session, PLANNER).await.unwrap();
        let run = |name: &str| report.runs.iter().find(|r| r.name == name).unwrap();
        let (tight_run, free_run) = (run("tight"), run("free"));
        assert_eq!(tight_run.deadline_ms, Some(5));
        assert_eq!(free_run.deadline_ms, None);
        let misses = actions.iter().filter(|a| a.stats.missed).count() as u64;
        let iterations: u64 = actions.iter().map(|a| u64::from(a.stats.iterations)).sum();
        let t = tight_run.plan_tally;
        assert_eq!(
            (t.plans, t.cut, t.deadline_misses, t.iterations),
            (
                PLANNED_STEPS as u64,
                PLANNED_STEPS as u64,
                misses,
                iterations
            )
        );
        let f = free_run.plan_tally;
        assert_eq!(
            (f.plans, f.cut, f.deadline_misses, f.iterations),
            (
                PLANNED_STEPS as u64,
                0,
                0,
                u64::from(PLANNED_STEPS * ITERATIONS)
            )
        );
        tight.close().await.unwrap();
        free.close().await.unwrap();
    });
    planner.stop().unwrap();
}
