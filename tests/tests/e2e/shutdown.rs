//! Shutdown within 10 s whatever is running: SIGTERM while a run trains for minutes ends the
//! daemon cleanly within the contract of 10 s (a bound on the daemon's promise, not a
//! speed target), because training is cancelled between minibatches.

use ebmpc_e2e::client::{Client, ToySystem, runtime};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{Builtin, EpisodeEnd, Observation, PlannerOverrides, RunEventKind, RunSpec};
use std::time::{Duration, Instant};

/// The daemon's promise: it exits within this long after SIGTERM.
const STOP_CONTRACT: Duration = Duration::from_secs(10);

/// Training that takes far longer than the test: one-transition minibatches for the
/// largest epochs the default limits allow.
fn long_training() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: Some("cem+deen".into()),
        overrides: PlannerOverrides {
            dynamics_epochs: Some(5_000),
            dynamics_batch_size: Some(1),
            dynamics_hidden_size: Some(256),
            energy_epochs: Some(5_000),
            energy_batch_size: Some(1),
            ..Default::default()
        },
        mode: Default::default(),
        seed: 5,
        task_spec: None,
    }
}

#[test]
fn sigterm_during_training_stops_the_daemon_within_ten_seconds() {
    let dir = TempDir::new("shutdown");
    let config = PlannerConfig::new("shutdown", Sizes::TINY)
        .exploration_episodes(1)
        .toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    runtime().block_on(async {
        let client = Client::connect(&planner.endpoint, "long", "l")
            .await
            .unwrap();
        client.attach(&long_training()).await.unwrap();
        let mut system = ToySystem::new(1);
        let mut action = client
            .step(&Observation::new(0, 0, system.state.to_vec(), None, None))
            .await
            .unwrap();
        for step in 1..=20 {
            let reward = system.step(&action.action);
            let end = (step == 20).then_some(EpisodeEnd::TimeLimit);
            let msg = Observation::new(0, step, system.state.to_vec(), Some(reward), end);
            if end.is_some() {
                client.send(&msg).await.unwrap();
            } else {
                action = client.step(&msg).await.unwrap();
            }
        }
        // Wait until the trainer is at work.
        let started = tokio::time::timeout(Duration::from_secs(60), async {
            loop {
                let sample = client.events.recv_async().await.unwrap();
                let event: proto::RunEvent =
                    proto::decode(&sample.payload().to_bytes(), proto::Encoding::Postcard).unwrap();
                if matches!(event.kind, RunEventKind::TrainingStarted { .. }) {
                    return;
                }
            }
        })
        .await;
        assert!(started.is_ok(), "training never started");
        // The agent waits for the next episode's first action, as a sync agent does.
        client
            .send(&Observation::new(1, 0, system.state.to_vec(), None, None))
            .await
            .unwrap();
        tokio::time::sleep(Duration::from_millis(500)).await;
        client.close().await.unwrap();
    });
    let sent = Instant::now();
    let status = planner
        .process
        .terminate(STOP_CONTRACT)
        .unwrap_or_else(|e| panic!("the daemon outlived its stop contract: {e}"));
    let took = sent.elapsed();
    assert!(
        status.success(),
        "exit {status}:\n{}",
        planner.process.log()
    );
    assert!(took <= STOP_CONTRACT, "{took:?}");
    assert!(
        !planner.process.log().contains("models updated"),
        "the training finished before the stop: the test needs longer training"
    );
}
