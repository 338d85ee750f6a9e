//! A system whose reward is only observed: a run of a task spec with `reward = "learned"`
//! attaches, explores with random actions, trains its reward model on the rewards the agent
//! sends (together with the dynamics), plans with it, and after a restart resumes with the
//! checkpointed reward model, planning from its first step.

use ebmpc_e2e::client::{Client, ToySystem, runtime};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir, free_endpoint};
use proto::task::{DeclaredTransforms, ModelTransforms, RewardKind};
use proto::{
    Action, ActionSource, Builtin, EpisodeEnd, Observation, RunEventKind, RunSpec, TaskSpec,
    TrainMode,
};

const STEPS: u32 = 20;
const TASK: &str = "toy-learned";

/// The toy system as a custom task: its reward is whatever the agent reports.
fn task_spec() -> TaskSpec {
    TaskSpec {
        name: TASK.into(),
        obs_dim: 4,
        act_dim: 1,
        action_low: vec![-3.0],
        action_high: vec![3.0],
        episode_len: STEPS,
        control_dt: 0.04,
        observation_bounds: None,
        magnitudes: proto::task::Magnitudes::GENEROUS,
        model: ModelTransforms::Declared(DeclaredTransforms {
            angles: vec![1],
            absolute: vec![],
        }),
        termination: Default::default(),
        reward: RewardKind::Learned,
        base_preset: Builtin::Cartpole,
    }
}

fn run_spec(task_spec: Option<TaskSpec>) -> RunSpec {
    RunSpec {
        task: TASK.into(),
        preset: Some("cem".into()),
        overrides: Default::default(),
        mode: TrainMode::Sync,
        seed: 3,
        task_spec,
    }
}

/// Plays one whole episode; returns every action received.
async fn play(client: &Client, system: &mut ToySystem, episode: u32) -> Vec<Action> {
    let mut actions = vec![
        client
            .step(&Observation::new(
                episode,
                0,
                system.state.to_vec(),
                None,
                None,
            ))
            .await
            .expect("step 0 answered"),
    ];
    for step in 1..=STEPS {
        let reward = system.step(&actions.last().unwrap().action);
        let end = (step == STEPS).then_some(EpisodeEnd::TimeLimit);
        let msg = Observation::new(episode, step, system.state.to_vec(), Some(reward), end);
        if end.is_some() {
            client.send(&msg).await.unwrap();
        } else {
            actions.push(client.step(&msg).await.expect("step answered"));
        }
    }
    actions
}

#[test]
fn a_learned_reward_run_explores_trains_plans_and_resumes() {
    let dir = TempDir::new("learned-reward");
    let endpoint = free_endpoint();
    let config = PlannerConfig::new("learned", Sizes::TINY)
        .exploration_episodes(1)
        .toml();
    let mut planner = Planner::start_on(dir.path(), &config, &endpoint).expect("planner starts");
    let runtime = runtime();
    let mut system = ToySystem::new(2);
    runtime.block_on(async {
        let client = Client::connect(&endpoint, "learned", "a").await.unwrap();
        let accepted = client.attach(&run_spec(Some(task_spec()))).await.unwrap();
        assert_eq!((accepted.task.as_str(), accepted.models_version), (TASK, 0));
        // Episode 0: random play, before any model (the reward model included) is trained.
        let random = play(&client, &mut system, 0).await;
        assert!(
            random
                .iter()
                .all(|a| a.stats.source == ActionSource::Random),
            "{random:?}"
        );
        // Episode 1 waits for models trained on episode 0 (sync mode), then plans with them.
        let planned = play(&client, &mut system, 1).await;
        for action in &planned {
            assert_eq!(action.stats.source, ActionSource::Planned, "{action:?}");
            assert!(action.stats.models_version >= 1, "{action:?}");
            assert!(action.stats.predicted_return.is_finite(), "{action:?}");
            assert!((-3.0..=3.0).contains(&action.action[0]), "{action:?}");
        }
        let events = client.drain_events().unwrap();
        let reward_losses: Vec<f32> = events
            .iter()
            .filter_map(|e| match &e.kind {
                RunEventKind::ModelsUpdated { reward_loss, .. } => {
                    Some(reward_loss.expect("a learned reward reports its model's loss"))
                }
                RunEventKind::TrainingFailed { message } => panic!("training failed: {message}"),
                _ => None,
            })
            .collect();
        assert!(!reward_losses.is_empty(), "{events:?}");
        assert!(
            reward_losses.iter().all(|l| l.is_finite()),
            "{reward_losses:?}"
        );
        client.close().await.unwrap();
    });
    planner.stop().unwrap();

    // Restarted, the run resumes with its checkpointed models, reward model included: an agent
    // naming the task only plans from its very first step.
    let mut planner = Planner::start_on(dir.path(), &config, &endpoint).expect("planner restarts");
    runtime.block_on(async {
        let client = Client::connect(&endpoint, "learned", "b").await.unwrap();
        let accepted = client.attach(&run_spec(None)).await.unwrap();
        assert!(accepted.models_version >= 1, "{accepted:?}");
        let resumed = play(&client, &mut system, accepted.next_episode).await;
        assert_eq!(
            resumed[0].stats.source,
            ActionSource::Planned,
            "{resumed:?}"
        );
        assert!(resumed[0].stats.predicted_return.is_finite());
        client.close().await.unwrap();
    });
    let log = planner.process.log();
    planner.stop().unwrap();
    assert!(
        !log.contains("skipping a checkpoint") && !log.contains("damaged checkpoint"),
        "{log}"
    );
}
