//! One daemon serves a fleet: four agents on two runs at once (one run sync, one async), every
//! step answered; the async run keeps answering while its trainer works; the config's limits
//! refuse extra runs and agents at attach with a clear message; an agent that vanishes is
//! dropped and its open episode recorded as interrupted.

use ebmpc_e2e::client::{Client, ToySystem, open_session, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{Builtin, EpisodeEnd, Observation, PlannerOverrides, RunEventKind, RunSpec, TrainMode};
use std::time::{Duration, Instant};

fn config() -> String {
    PlannerConfig::new("fleet", Sizes::TINY)
        .line("max_runs = 2")
        .line("max_agents_per_run = 3")
        .exploration_episodes(1)
        .toml()
}

const EPISODES: u32 = 3;
const STEPS: u32 = 40;

fn spec(mode: TrainMode) -> RunSpec {
    let overrides = match mode {
        TrainMode::Sync => PlannerOverrides::default(),
        // The async run's energy network has the paper's size and many epochs, so that its
        // trainer works for seconds while its agents keep stepping.
        TrainMode::Async => PlannerOverrides {
            energy_hidden_layers: Some(5),
            energy_hidden_size: Some(500),
            energy_epochs: Some(100),
            ..Default::default()
        },
    };
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: Some("cem+deen".into()),
        overrides,
        mode,
        seed: 2,
        task_spec: None,
    }
}

/// When one agent received each action, and when it saw each run event.
#[derive(Default)]
struct Timeline {
    actions: Vec<Instant>,
    events: Vec<(Instant, RunEventKind)>,
}

/// Plays `EPISODES` episodes of `STEPS` steps; every step must be answered.
async fn play(client: Client, seed: u32) -> (Client, Timeline) {
    let mut timeline = Timeline::default();
    let mut system = ToySystem::new(seed);
    for episode in 0..EPISODES {
        let mut action = client
            .step(&Observation::new(
                episode,
                0,
                system.state.to_vec(),
                None,
                None,
            ))
            .await
            .unwrap_or_else(|e| panic!("{}: {e}", client.agent));
        timeline.actions.push(Instant::now());
        for step in 1..=STEPS {
            let reward = system.step(&action.action);
            let end = (step == STEPS).then_some(EpisodeEnd::TimeLimit);
            let msg = Observation::new(episode, step, system.state.to_vec(), Some(reward), end);
            if end.is_some() {
                client.send(&msg).await.unwrap();
            } else {
                action = client
                    .step(&msg)
                    .await
                    .unwrap_or_else(|e| panic!("{}: {e}", client.agent));
                timeline.actions.push(Instant::now());
            }
            let now = Instant::now();
            for event in client.drain_events().unwrap() {
                timeline.events.push((now, event.kind));
            }
        }
    }
    (client, timeline)
}

#[test]
fn four_agents_on_two_runs_are_served_at_once() {
    let dir = TempDir::new("fleet");
    let mut planner = Planner::start(dir.path(), &config()).expect("planner starts");
    let endpoint = planner.endpoint.clone();
    let runtime = runtime();
    runtime.block_on(async {
        let mut agents = Vec::new();
        for (run, mode) in [("sync", TrainMode::Sync), ("async", TrainMode::Async)] {
            for agent in ["a", "b"] {
                let client = Client::connect(&endpoint, run, agent).await.unwrap();
                client.attach(&spec(mode)).await.unwrap();
                agents.push(client);
            }
        }

        // Limits: a third run and a fourth agent on a run are refused, saying why.
        let third = Client::connect(&endpoint, "third", "a").await.unwrap();
        let err = third.attach(&spec(TrainMode::Sync)).await.unwrap_err();
        assert!(err.to_string().contains("limit of 2 runs"), "{err}");
        third.close().await.unwrap();

        // A third agent attaches to the sync run, starts an episode and vanishes.
        let ghost = Client::connect(&endpoint, "sync", "ghost").await.unwrap();
        ghost.attach(&spec(TrainMode::Sync)).await.unwrap();
        let extra = Client::connect(&endpoint, "sync", "extra").await.unwrap();
        let err = extra.attach(&spec(TrainMode::Sync)).await.unwrap_err();
        assert!(err.to_string().contains("limit of 3 agents"), "{err}");
        extra.close().await.unwrap();
        let mut ghost_system = ToySystem::new(9);
        let first = ghost
            .step(&Observation::new(
                0,
                0,
                ghost_system.state.to_vec(),
                None,
                None,
            ))
            .await
            .unwrap();
        let reward = ghost_system.step(&first.action);
        ghost
            .step(&Observation::new(
                0,
                1,
                ghost_system.state.to_vec(),
                Some(reward),
                None,
            ))
            .await
            .unwrap();
        ghost.close().await.unwrap();

        // The four agents play concurrently.
        let tasks: Vec<_> = agents
            .into_iter()
            .enumerate()
            .map(|(i, client)| tokio::spawn(play(client, i as u32)))
            .collect();
        let mut timelines = Vec::new();
        for task in tasks {
            let (client, timeline) = task.await.expect("an agent was not served");
            assert_eq!(timeline.actions.len() as u32, EPISODES * STEPS);
            timelines.push((client.run.clone(), timeline));
            client.close().await.unwrap();
        }

        // The async run answered while its trainer was working: actions arrived after an
        // agent saw `TrainingStarted` and before it saw the `ModelsUpdated` that ended it (or
        // before the agent was done, if training outlasted its episodes).
        let mut answered_while_training = 0;
        for (_, timeline) in timelines.iter().filter(|(run, _)| run == "async") {
            let started = timeline
                .events
                .iter()
                .find(|(_, k)| matches!(k, RunEventKind::TrainingStarted { .. }))
                .map(|(at, _)| *at);
            let Some(started) = started else { continue };
            let updated = timeline
                .events
                .iter()
                .find(|(at, k)| *at > started && matches!(k, RunEventKind::ModelsUpdated { .. }))
                .map(|(at, _)| *at);
            answered_while_training += timeline
                .actions
                .iter()
                .filter(|t| **t > started && updated.is_none_or(|u| **t < u))
                .count();
        }
        assert!(
            answered_while_training > 0,
            "no async action arrived while training ran"
        );

        // Status: both runs with all their episodes; the vanished agent is gone.
        let session = open_session(&endpoint).await.unwrap();
        // ... and the async run's trainer does finish and swap its models in.
        let started = Instant::now();
        let report = loop {
            let report = status(&session, "fleet").await.unwrap();
            let sync = report.runs.iter().find(|r| r.name == "sync").unwrap();
            let asynch = report.runs.iter().find(|r| r.name == "async").unwrap();
            let ghost_gone = !sync.agents.iter().any(|a| a == "ghost");
            if ghost_gone && asynch.models_version >= 1 {
                break report;
            }
            assert!(
                started.elapsed() < Duration::from_secs(180),
                "after 180 s: ghost gone {ghost_gone} (agents {:?}), async models version {}",
                sync.agents,
                asynch.models_version
            );
            tokio::time::sleep(Duration::from_millis(200)).await;
        };
        for run in &report.runs {
            assert_eq!(run.episodes, 2 * EPISODES, "{}", run.name);
            assert!(
                run.transitions >= (2 * EPISODES * STEPS) as usize,
                "{}",
                run.name
            );
        }
        // The sync run planned (its agents waited for models); the async run may have been
        // served random actions throughout, its trainer being slower than its agents.
        let sync = report.runs.iter().find(|r| r.name == "sync").unwrap();
        assert!(sync.planning_latency.is_some());
        session.close().await.unwrap();
    });

    planner.stop().unwrap();
    let sync = planner.replay("sync", Builtin::Cartpole).unwrap();
    let ghost = sync
        .episodes()
        .iter()
        .find(|e| e.agent == "ghost")
        .expect("the vanished agent's episode is recorded");
    assert_eq!((ghost.episode, ghost.end), (0, EpisodeEnd::Interrupted));
    assert_eq!(sync.len(), (2 * EPISODES * STEPS) as usize + 1);
}
