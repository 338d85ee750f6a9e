//! A light run's actions keep their deadline while a heavy run plans and a third retrains.
//!
//! Every plan spreads over all of the daemon's cores. The heavy run plans without a deadline
//! (as a simulator does) with a large population, so each of its iterations takes a good
//! share of a second; the light run plans a tiny search of many iterations under a generous
//! deadline; the third run explores and retrains in `async` mode all the while. The planner
//! gives the cores to the plan with a deadline, and the heavy plan steps back between two of its
//! imagined steps, so a light plan waits at most one heavy step and then runs alone: none of
//! its plans is cut or missed, and the heavy run's tally counts its step-backs. Sharing the
//! cores first come, first served (every plan on the pool at once, as before the scheduler:
//! checked by making `Scheduler::turn` return at once), nothing steps back and the test fails
//! on that count; the light run's deadlines then often hold anyway on two cores, because a
//! rayon worker waiting in one of the heavy plan's joins picks up the light plan's jobs.
//!
//! Checked on the daemon's own counters (the status report's plan tally), not on wall-clock
//! figures measured by the test.

use ebmpc_e2e::client::{Client, ToySystem, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{ActionSource, Builtin, EpisodeEnd, Observation, PlannerOverrides, RunSpec, TrainMode};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

const PLANNER: &str = "fair-share";
const EXPLORED_STEPS: u32 = 15;
/// The light run's planned steps checked against their deadline.
const LIGHT_STEPS: u32 = 12;
/// The light run's iterations: each one waited behind a heavy iteration on a shared pool.
const LIGHT_ITERATIONS: u32 = 40;
/// Far more than the light search needs alone (a few milliseconds) and several heavy
/// iterations long, so that a loaded machine does not cut it; far less than the light plan
/// took behind the heavy one on a shared pool.
const LIGHT_DEADLINE_MS: u32 = 1_500;

fn spec(overrides: PlannerOverrides, mode: TrainMode, seed: u64) -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: None,
        overrides,
        mode,
        seed,
        task_spec: None,
    }
}

fn light() -> RunSpec {
    spec(
        PlannerOverrides {
            population: Some(20),
            elites: Some(4),
            horizon: Some(5),
            cem_iterations: Some(LIGHT_ITERATIONS),
            // No early stop on a narrow distribution: every iteration runs unless cut.
            cem_min_variance: Some(0.0),
            deadline_ms: Some(LIGHT_DEADLINE_MS),
            ..PlannerOverrides::default()
        },
        TrainMode::Sync,
        1,
    )
}

fn heavy() -> RunSpec {
    spec(
        PlannerOverrides {
            population: Some(5_000),
            elites: Some(50),
            horizon: Some(60),
            particles: Some(4),
            cem_iterations: Some(10),
            cem_min_variance: Some(0.0),
            deadline_ms: Some(0),
            ..PlannerOverrides::default()
        },
        TrainMode::Sync,
        2,
    )
}

/// Explores for ever (never plans) and retrains after every episode, in the background.
fn retraining() -> RunSpec {
    spec(
        PlannerOverrides {
            exploration_episodes: Some(1_000),
            dynamics_epochs: Some(200),
            energy_epochs: Some(200),
            ..PlannerOverrides::default()
        },
        TrainMode::Async,
        3,
    )
}

/// One episode of `EXPLORED_STEPS` steps from `seed`, ended by the time limit.
async fn episode(client: &Client, episode: u32, seed: u32) {
    let mut system = ToySystem::new(seed);
    let mut reward = None;
    for step in 0..EXPLORED_STEPS {
        let obs = Observation::new(episode, step, system.state.to_vec(), reward, None);
        let action = client.step(&obs).await.unwrap();
        reward = Some(system.step(&action.action));
    }
    let end = Observation::new(
        episode,
        EXPLORED_STEPS,
        system.state.to_vec(),
        reward,
        Some(EpisodeEnd::TimeLimit),
    );
    client.send(&end).await.unwrap();
}

/// Planned steps of episode 1 until `stop` is raised (at least one), after the explored
/// episode 0; raises `planning` at the first planned action.
async fn plan_until(client: &Client, planning: &AtomicBool, stop: &AtomicBool) -> u32 {
    episode(client, 0, 20).await;
    let mut system = ToySystem::new(21);
    let mut reward = None;
    let mut step = 0;
    while step == 0 || (!stop.load(Ordering::SeqCst) && step < EXPLORED_STEPS) {
        let obs = Observation::new(1, step, system.state.to_vec(), reward, None);
        let action = client.step(&obs).await.unwrap();
        assert_eq!(action.stats.source, ActionSource::Planned, "{action:?}");
        planning.store(true, Ordering::SeqCst);
        reward = Some(system.step(&action.action));
        step += 1;
    }
    step
}

#[test]
fn a_light_run_keeps_its_deadline_while_a_heavy_run_plans_and_a_third_retrains() {
    let dir = TempDir::new("fair-share");
    let config = PlannerConfig::new(PLANNER, Sizes::TINY)
        .exploration_episodes(1)
        .toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    runtime().block_on(async {
        let endpoint = &planner.endpoint;
        let light_agent = Client::connect(endpoint, "light", "a").await.unwrap();
        let heavy_agent = Client::connect(endpoint, "heavy", "a").await.unwrap();
        let trainer_agent = Client::connect(endpoint, "retraining", "a").await.unwrap();
        light_agent.attach(&light()).await.unwrap();
        heavy_agent.attach(&heavy()).await.unwrap();
        trainer_agent.attach(&retraining()).await.unwrap();

        let heavy_planning = Arc::new(AtomicBool::new(false));
        let done = Arc::new(AtomicBool::new(false));
        let heavy_steps = plan_until(&heavy_agent, &heavy_planning, &done);
        let retrain = async {
            let mut episodes = 0;
            while episodes == 0 || !done.load(Ordering::SeqCst) {
                episode(&trainer_agent, episodes, 100 + episodes).await;
                episodes += 1;
                // Each retraining covers the whole buffer for many epochs: a few episodes keep
                // it busy, and a paced agent keeps the transport's queues short.
                tokio::time::sleep(std::time::Duration::from_millis(100)).await;
            }
            episodes
        };
        let light_steps = async {
            episode(&light_agent, 0, 10).await;
            while !heavy_planning.load(Ordering::SeqCst) {
                tokio::time::sleep(std::time::Duration::from_millis(10)).await;
            }
            let mut system = ToySystem::new(11);
            let mut reward = None;
            let mut light_actions = vec![];
            for step in 0..LIGHT_STEPS {
                let obs = Observation::new(1, step, system.state.to_vec(), reward, None);
                let action = light_agent.step(&obs).await.unwrap();
                assert_eq!(action.stats.source, ActionSource::Planned, "{action:?}");
                reward = Some(system.step(&action.action));
                light_actions.push(action);
            }
            done.store(true, Ordering::SeqCst);
            light_actions
        };
        let (heavy_steps, retrained_episodes, light_actions) =
            tokio::join!(heavy_steps, retrain, light_steps);

        let report = status(&light_agent.session, PLANNER).await.unwrap();
        let run = |name: &str| report.runs.iter().find(|r| r.name == name).unwrap();
        let (light_run, heavy_run, trainer_run) = (run("light"), run("heavy"), run("retraining"));
        eprintln!(
            "light {:?} {:?}\nheavy {:?} {:?}\nretraining: {} episodes, models version {}",
            light_run.plan_tally,
            light_run.planning_latency,
            heavy_run.plan_tally,
            heavy_run.planning_latency,
            retrained_episodes,
            trainer_run.models_version
        );
        // The load was there: the heavy run planned throughout, and the third run was retraining
        // (still at it, or done at least once: on a fast machine the light run may finish
        // before the first retraining does).
        assert_eq!(heavy_run.plan_tally.plans, u64::from(heavy_steps));
        assert!(
            trainer_run.training || trainer_run.models_version >= 1,
            "{trainer_run:?}"
        );
        // The scheduler made way for the light run: the heavy run's plans stepped back for it
        // (without a scheduler, every plan on the pool at once, they never do; rayon's joins
        // then often let a light plan through anyway, so the light run's tally alone does not
        // tell the two apart on every machine).
        assert!(heavy_run.plan_tally.stepped_back >= 1, "{heavy_run:?}");
        // The light run may step back too, but only for a retraining's guaranteed slice
        // (`retraining_share`: a retraining that plans leave no idle time runs a minibatch while
        // every plan waits), never past its deadline, which the tally below checks.
        // The light run kept every deadline: no plan cut, none missed, every iteration ran.
        let l = light_run.plan_tally;
        assert_eq!(
            (l.plans, l.cut, l.deadline_misses, l.iterations),
            (
                u64::from(LIGHT_STEPS),
                0,
                0,
                u64::from(LIGHT_STEPS * LIGHT_ITERATIONS)
            ),
            "{light_run:?}"
        );
        // The agent saw the same: every action planned with every iteration, none cut or late.
        for action in &light_actions {
            let stats = &action.stats;
            assert_eq!(
                (stats.iterations, stats.cut, stats.missed),
                (LIGHT_ITERATIONS, false, false),
                "{stats:?}"
            );
        }
        for agent in [light_agent, heavy_agent, trainer_agent] {
            agent.close().await.unwrap();
        }
    });
    planner.stop().unwrap();
}
