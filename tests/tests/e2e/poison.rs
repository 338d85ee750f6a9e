//! Data cannot poison a run: observations and rewards beyond the task's magnitude bound
//! (±3.4e38 is finite, but its differences overflow) are refused with their own error code,
//! and a run fed the largest values the bound allows keeps finite models and keeps planning.

use ebmpc_e2e::client::{Answer, Client, runtime};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{
    ActionSource, Builtin, EpisodeEnd, ErrorCode, Observation, PlannerOverrides, RunEventKind,
    RunSpec,
};
use std::time::Duration;

const STEPS: u32 = 30;

fn spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: None,
        overrides: PlannerOverrides::default(),
        mode: Default::default(),
        seed: 4,
        task_spec: None,
    }
}

/// An observation at the task's magnitude bound, its signs changing with the step.
fn extreme(bound: f32, step: u32) -> Vec<f32> {
    let s = if step.is_multiple_of(2) { 1.0 } else { -1.0 };
    vec![s * bound, -s * bound, bound, -bound]
}

#[test]
fn extreme_values_are_refused_and_large_ones_train_finite_models() {
    let dir = TempDir::new("poison");
    let config = PlannerConfig::new("poison", Sizes::TINY)
        .exploration_episodes(1)
        .toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    let bound = Builtin::Cartpole.task().magnitudes;
    runtime().block_on(async {
        let client = Client::connect(&planner.endpoint, "poison", "p")
            .await
            .unwrap();
        client.attach(&spec()).await.unwrap();
        let refused = |what: String, answer: Answer| match answer {
            Answer::Error(report) => {
                assert_eq!(report.code, ErrorCode::OutOfRange, "{what}: {report}");
                assert!(report.message.contains("bound"), "{what}: {report}");
            }
            Answer::Action(action) => panic!("{what} was answered: {action:?}"),
        };
        for values in [
            vec![3.4e38, 0.0, 0.0, 0.0],
            vec![0.0, -3.4e38, 0.0, 0.0],
            vec![0.0, 0.0, f32::MAX, f32::MIN],
            vec![bound.observation * 1.5, 0.0, 0.0, 0.0],
        ] {
            client
                .send(&Observation::new(0, 0, values.clone(), None, None))
                .await
                .unwrap();
            refused(
                format!("{values:?}"),
                client.answer(Duration::from_secs(60)).await.unwrap(),
            );
        }
        // Episode 0 (random exploration) at the bound, with one reward beyond it refused on
        // the way: the episode goes on from where it was.
        let action = client
            .step(&Observation::new(
                0,
                0,
                extreme(bound.observation, 0),
                None,
                None,
            ))
            .await
            .unwrap();
        assert!(action.action.iter().all(|a| a.is_finite()));
        for step in 1..=STEPS {
            let obs = extreme(bound.observation, step);
            let reward = if step.is_multiple_of(2) {
                bound.reward
            } else {
                -bound.reward
            };
            if step == 5 {
                let over = Observation::new(0, step, obs.clone(), Some(-3.4e38), None);
                client.send(&over).await.unwrap();
                refused(
                    "reward -3.4e38".into(),
                    client.answer(Duration::from_secs(60)).await.unwrap(),
                );
            }
            let end = (step == STEPS).then_some(EpisodeEnd::TimeLimit);
            let msg = Observation::new(0, step, obs, Some(reward), end);
            if end.is_some() {
                client.send(&msg).await.unwrap();
            } else {
                let action = client.step(&msg).await.unwrap();
                assert!(action.action.iter().all(|a| a.is_finite()));
            }
        }
        // Episode 1 waits for the models trained on episode 0 (sync mode), then plans.
        let mut planned = 0;
        let mut state = vec![0.5, -0.5, 0.1, 0.0];
        let mut action = client
            .step(&Observation::new(1, 0, state.clone(), None, None))
            .await
            .unwrap();
        for step in 1..=STEPS {
            assert!(
                action.action.iter().all(|a| a.is_finite())
                    && action.stats.predicted_return.is_finite(),
                "{action:?}"
            );
            if action.stats.source == ActionSource::Planned {
                planned += 1;
                assert!(action.stats.models_version >= 1, "{action:?}");
            }
            state[0] += 0.01 * action.action[0];
            let end = (step == STEPS).then_some(EpisodeEnd::TimeLimit);
            let msg = Observation::new(1, step, state.clone(), Some(0.0), end);
            if end.is_some() {
                client.send(&msg).await.unwrap();
            } else {
                action = client.step(&msg).await.unwrap();
            }
        }
        assert_eq!(planned, STEPS, "every step of episode 1 was planned");
        let events = client.drain_events().unwrap();
        let mut updated = 0;
        for event in &events {
            match &event.kind {
                RunEventKind::ModelsUpdated {
                    dynamics_loss,
                    energy_loss,
                    ..
                } => {
                    assert!(
                        dynamics_loss.is_finite() && energy_loss.is_finite(),
                        "{event:?}"
                    );
                    updated += 1;
                }
                RunEventKind::TrainingFailed { message } => panic!("training failed: {message}"),
                _ => {}
            }
        }
        assert!(updated >= 1, "{events:?}");
        client.close().await.unwrap();
    });
    planner.stop().unwrap();
}
