//! A daemon killed with SIGKILL in the middle of an episode and started again loses nothing it
//! acknowledged: every transition whose next action the agent received is in the replay log,
//! the run is back (listed before any agent returns) with the models of its newest checkpoint,
//! the broken episode is recorded as interrupted, and the agent carries on with planned actions.

use ebmpc_e2e::client::{Answer, Client, ToySystem, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir, free_endpoint};
use proto::{Action, ActionSource, Builtin, EpisodeEnd, Observation, RunSpec, TrainMode};
use std::time::{Duration, Instant};

fn config() -> String {
    PlannerConfig::new("durable", Sizes::TINY)
        .exploration_episodes(1)
        .toml()
}

const STEPS: u32 = 20;

/// A transition the daemon acknowledged: the agent got the action for its `next_obs`.
type Acked = (Vec<f32>, Vec<f32>, Vec<f32>);

fn spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: Some("cem+deen".into()),
        overrides: Default::default(),
        mode: TrainMode::Sync,
        seed: 5,
        task_spec: None,
    }
}

/// Plays `steps` steps of `episode` (ending it with a time limit if `finish`), recording every
/// acknowledged transition. Returns the last action received.
async fn play(
    client: &Client,
    system: &mut ToySystem,
    episode: u32,
    steps: u32,
    finish: bool,
    acked: &mut Vec<Acked>,
) -> Action {
    let mut obs = system.state.to_vec();
    let mut action = client
        .step(&Observation::new(episode, 0, obs.clone(), None, None))
        .await
        .expect("step 0 answered");
    for step in 1..=steps {
        let reward = system.step(&action.action);
        let next = system.state.to_vec();
        let end = (finish && step == steps).then_some(EpisodeEnd::TimeLimit);
        let msg = Observation::new(episode, step, next.clone(), Some(reward), end);
        if end.is_some() {
            client.send(&msg).await.unwrap();
            // The episode end gets no action; the next episode's first action acknowledges it.
            return action;
        }
        let answer = client.step(&msg).await.expect("step answered");
        acked.push((obs, action.action.clone(), next.clone()));
        obs = next;
        action = answer;
    }
    action
}

#[test]
fn sigkill_mid_episode_loses_no_acknowledged_transition() {
    let dir = TempDir::new("durability");
    let endpoint = free_endpoint();
    let mut planner = Planner::start_on(dir.path(), &config(), &endpoint).expect("planner starts");
    let runtime = runtime();
    let mut acked: Vec<Acked> = Vec::new();
    let mut system = ToySystem::new(1);

    let (client, version_before, in_flight) = runtime.block_on(async {
        let client = Client::connect(&endpoint, "durable", "a").await.unwrap();
        let accepted = client.attach(&spec()).await.unwrap();
        assert_eq!(accepted.next_episode, 0);
        play(&client, &mut system, 0, STEPS, true, &mut acked).await;
        play(&client, &mut system, 1, STEPS, true, &mut acked).await;
        // The last ended episode was acknowledged by episode 2's first action (sync mode: it
        // waited for models trained on both episodes, which were checkpointed before use).
        let last = play(&client, &mut system, 2, STEPS / 2, false, &mut acked).await;
        assert_eq!(last.stats.source, ActionSource::Planned);
        let version = last.stats.models_version;
        assert!(version >= 1, "models were trained before the kill");
        // The next observation is in flight when the daemon dies.
        let obs = system.state.to_vec();
        let reward = system.step(&last.action);
        let next = system.state.to_vec();
        let msg = Observation::new(2, STEPS / 2 + 1, next.clone(), Some(reward), None);
        client.send(&msg).await.unwrap();
        (client, version, (obs, last.action, next))
    });
    planner.process.signal("KILL").unwrap();
    assert!(
        !planner
            .process
            .wait(Duration::from_secs(30))
            .unwrap()
            .success()
    );
    let killed_log = planner.process.log();
    drop(planner);

    let mut planner =
        Planner::start_on(dir.path(), &config(), &endpoint).expect("planner restarts");
    runtime.block_on(async {
        // The run is back before its agent returns, with the checkpointed models.
        let started = Instant::now();
        let report = loop {
            match status(&client.session, "durable").await {
                Ok(report) if !report.runs.is_empty() => break report,
                _ if started.elapsed() < Duration::from_secs(60) => {
                    tokio::time::sleep(Duration::from_millis(200)).await;
                }
                other => panic!("no status with the resumed run: {other:?}"),
            }
        };
        let run = &report.runs[0];
        assert_eq!(run.name, "durable");
        assert_eq!(run.episodes, 2, "two finished episodes");
        assert!(
            run.transitions >= acked.len(),
            "{} < {}",
            run.transitions,
            acked.len()
        );
        assert_eq!(
            run.models_version, version_before,
            "newest checkpoint loaded"
        );
        assert!(!run.exploring);

        // The observation in flight may have been answered before the kill; that answer is
        // stale now (and the transition it acknowledged is checked with the others).
        for answer in client.take_pending().unwrap() {
            match answer {
                Answer::Action(a) if (a.episode, a.step) == (2, STEPS / 2 + 1) => {
                    acked.push(in_flight.clone());
                }
                other => panic!("unexpected answer before re-attaching: {other:?}"),
            }
        }
        // The agent re-attaches: episode 2 was interrupted, so it continues with episode 3,
        // planned by the restored models.
        let accepted = client.attach(&spec()).await.unwrap();
        assert_eq!(accepted.next_episode, 3);
        assert_eq!(accepted.models_version, version_before);
        let mut more = Vec::new();
        let last = play(&client, &mut system, 3, 3, false, &mut more).await;
        assert_eq!(
            (last.stats.source, last.stats.models_version),
            (ActionSource::Planned, version_before)
        );
        client.close().await.unwrap();
    });
    planner
        .stop()
        .unwrap_or_else(|e| panic!("SIGTERM shuts down cleanly: {e:?}"));

    let buffer = planner.replay("durable", Builtin::Cartpole).unwrap();
    let stored = buffer.transitions();
    for (i, (obs, act, next)) in acked.iter().enumerate() {
        let found = (0..stored.len()).any(|r| {
            let (o, a, n) = stored.row(r);
            o == obs.as_slice() && a == act.as_slice() && n == next.as_slice()
        });
        assert!(
            found,
            "acknowledged transition {i} is missing after the kill\nkilled daemon's log:\n{killed_log}"
        );
    }
    let interrupted = buffer
        .episodes()
        .iter()
        .find(|e| e.agent == "a" && e.episode == 2)
        .expect("episode 2 recorded");
    assert_eq!(interrupted.end, EpisodeEnd::Interrupted);
    assert!(interrupted.steps >= STEPS / 2);
    let log = planner.process.log();
    assert!(log.contains("recorded as interrupted"), "{log}");
}
