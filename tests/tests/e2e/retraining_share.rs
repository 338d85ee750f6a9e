//! A sync run's retraining finishes in bounded time beside a run that plans without pause.
//!
//! Two agents of a half-cheetah run plan back to back with a large search and no deadline, so
//! one of their plans always holds or waits for the cores and the daemon never idles. A
//! cartpole agent in `sync` mode ends an episode and waits for its models: its retraining runs
//! at `SCHED_IDLE`, below every plan, and got no core at all while plans never stopped. With
//! its guaranteed share it takes a slice from the plans every few minibatches: it finishes
//! within [`RETRAINING_BOUND`], the agent's next episode starts, and `status` shows that the
//! retraining was starving and how many slices it took.

use ebmpc_e2e::client::{Client, ToySystem, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{
    ActionSource, Builtin, EpisodeEnd, Observation, PlannerOverrides, RunEventKind, RunSpec,
    TrainMode,
};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

const PLANNER: &str = "share";

/// The stated bound on the cartpole retraining beside continuous planning. Alone it takes a
/// few seconds here; with the default share (0.2) about five times that.
const RETRAINING_BOUND: Duration = Duration::from_secs(150);

/// A half-cheetah run that plans a large search without a deadline, after one short explored
/// episode (ended by its agent) has trained its first models.
fn cheetah() -> RunSpec {
    RunSpec {
        task: Builtin::HalfCheetah.name().into(),
        preset: Some("cem".into()),
        overrides: PlannerOverrides {
            population: Some(400),
            elites: Some(40),
            horizon: Some(25),
            cem_iterations: Some(5),
            cem_min_variance: Some(0.0),
            dynamics_hidden_size: Some(200),
            dynamics_epochs: Some(1),
            exploration_episodes: Some(1),
            deadline_ms: Some(0),
            ..PlannerOverrides::default()
        },
        mode: TrainMode::Async,
        seed: 2,
        task_spec: None,
    }
}

/// A cartpole run in sync mode whose retraining takes seconds alone.
fn cartpole() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: Some("cem".into()),
        overrides: PlannerOverrides {
            dynamics_hidden_layers: Some(3),
            dynamics_hidden_size: Some(200),
            dynamics_epochs: Some(25),
            exploration_episodes: Some(1),
            ..PlannerOverrides::default()
        },
        mode: TrainMode::Sync,
        seed: 1,
        task_spec: None,
    }
}

/// Observation `t` of a made-up half-cheetah trajectory (18 numbers, the task's observation).
fn cheetah_obs(t: u32) -> Vec<f32> {
    (0..18)
        .map(|i| ((t + i) as f32 * 0.1).sin() * 0.5)
        .collect()
}

/// One half-cheetah agent: a short explored episode (ended as terminated), then planned steps
/// back to back until `stop`; counts its planned actions.
async fn plan_without_pause(client: Client, stop: Arc<AtomicBool>, planned: Arc<AtomicU64>) {
    let token = client.session_token();
    let obs = |episode, step, end| {
        let reward = (step > 0).then_some(0.1);
        Observation::new(episode, step, cheetah_obs(step), reward, end).in_session(token)
    };
    for step in 0..3 {
        client.step(&obs(0, step, None)).await.unwrap();
    }
    client
        .send(&obs(0, 3, Some(EpisodeEnd::Terminated)))
        .await
        .unwrap();
    // The async run plans once its first models are in; until then its actions are random.
    let mut step = 0;
    let mut episode = 1;
    while !stop.load(Ordering::SeqCst) {
        let action = client.step(&obs(episode, step, None)).await.unwrap();
        if action.stats.source == ActionSource::Planned {
            planned.fetch_add(1, Ordering::SeqCst);
        }
        step += 1;
        if step == 900 {
            client
                .send(&obs(episode, step, Some(EpisodeEnd::Terminated)))
                .await
                .unwrap();
            (episode, step) = (episode + 1, 0);
        }
    }
}

#[test]
fn a_sync_runs_retraining_finishes_beside_continuous_planning() {
    let dir = TempDir::new("retraining-share");
    let config = PlannerConfig::new(PLANNER, Sizes::TINY).toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    let endpoint = planner.endpoint.clone();
    runtime().block_on(async {
        let stop = Arc::new(AtomicBool::new(false));
        let planned = Arc::new(AtomicU64::new(0));
        let mut heavy = Vec::new();
        for agent in ["h1", "h2"] {
            let client = Client::connect(&endpoint, "cheetah", agent).await.unwrap();
            client.attach(&cheetah()).await.unwrap();
            heavy.push(tokio::spawn(plan_without_pause(
                client,
                stop.clone(),
                planned.clone(),
            )));
        }
        // Wait until the cheetah plans without pause.
        let started = Instant::now();
        while planned.load(Ordering::SeqCst) < 4 {
            assert!(
                started.elapsed() < Duration::from_secs(300),
                "the half-cheetah run never planned"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }

        let agent = Client::connect(&endpoint, "cart", "c").await.unwrap();
        agent.attach(&cartpole()).await.unwrap();
        let token = agent.session_token();
        let mut system = ToySystem::new(1);
        let mut reward = None;
        for step in 0..200 {
            let obs = Observation::new(0, step, system.state.to_vec(), reward, None)
                .in_session(token);
            let action = agent.step(&obs).await.unwrap();
            reward = Some(system.step(&action.action));
        }
        let last = Observation::new(0, 200, system.state.to_vec(), reward, None)
            .in_session(token);
        agent
            .send(&Observation {
                end: Some(EpisodeEnd::TimeLimit),
                ..last
            })
            .await
            .unwrap();
        let ended = Instant::now();
        // The retraining finishes within the bound, while the cheetah keeps planning.
        let planned_before = planned.load(Ordering::SeqCst);
        let mut seconds = None;
        while seconds.is_none() {
            for event in agent.drain_events().unwrap() {
                if let RunEventKind::ModelsUpdated { seconds: s, .. } = event.kind {
                    seconds = Some(s);
                }
            }
            assert!(
                ended.elapsed() < RETRAINING_BOUND,
                "the retraining did not finish within {RETRAINING_BOUND:?} beside continuous planning"
            );
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let report = status(&agent.session, PLANNER).await.unwrap();
        eprintln!(
            "retraining took {:.1} s beside continuous planning; {:?}",
            seconds.unwrap(),
            report.retraining
        );
        assert!(
            report.retraining.slices > 0,
            "plans left no idle time, so the retraining took slices: {:?}",
            report.retraining
        );
        assert!(
            planned.load(Ordering::SeqCst) > planned_before,
            "the cheetah kept planning meanwhile"
        );
        // The sync agent's next episode starts.
        let next = Observation::new(1, 0, system.state.to_vec(), None, None).in_session(token);
        agent.step(&next).await.expect("the next episode starts");
        stop.store(true, Ordering::SeqCst);
        for h in heavy {
            tokio::time::timeout(Duration::from_secs(120), h)
                .await
                .expect("the cheetah agents stop")
                .unwrap();
        }
    });
    planner.stop().unwrap();
}
