//! `cargo bench -p ebmpc-e2e --bench mixed`: a light run's action latency and deadline
//! misses beside heavier neighbours (issue 17, item 6).
//!
//! Starts the real `planner-service` binary (release) on a loopback endpoint and drives it
//! with scripted postcard agents over real Zenoh, each on its own session and run:
//!
//! 1. *alone*: a cartpole `cem+deen` agent at the paper's sizes, with its default deadline
//!    (the 40 ms control period);
//! 2. *+ half-cheetah*: the same agent beside a half-cheetah `cem+deen` agent at the paper's
//!    sizes, with its default deadline (50 ms), planning all the while;
//! 3. *+ retraining*: the same agent beside a cartpole run that explores and retrains in
//!    `async` mode all the while (thousands of epochs per retraining, so it never idles).
//!
//! Each agent first explores one short episode and waits for its first models (`sync` mode;
//! a retraining capped at a few hundred gradient steps, since the bench is about planning,
//! not learning). In each mix the cartpole agent plays `--steps` planned steps of one episode
//! (never ended, so its own run does not retrain during the measure) while the neighbour
//! plays. Printed for each agent of each mix: its planned steps, the p50 and p99 of the round
//! trip (observation sent → action received, measured by the agent), and the plans the
//! deadline cut and the deadlines missed, from each action's stats. Planned steps are paced as
//! a controller paces them: one observation per control period of the agent's task (40 ms
//! cartpole, 50 ms half-cheetah), the next one at once after a late action.
//!
//! Flags (after `--`): `--steps N` planned cartpole steps per mix (default 200).

use anyhow::{Context, Result, bail};
use ebmpc_e2e::client::{Client, runtime, status};
use ebmpc_e2e::{Planner, TempDir};
use proto::{
    Action, ActionSource, Builtin, EpisodeEnd, Observation, PlannerOverrides, RunSpec, TrainMode,
};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

const PLANNER: &str = "mixed";

/// Steps of the exploration episode each agent starts with.
const EXPLORED_STEPS: u32 = 30;

/// The first models are trained for at most this many gradient steps per model: enough to
/// plan with, quick on a loaded machine. Planning cost does not depend on it.
const FIRST_TRAINING_STEPS: u64 = 300;

fn spec(task: Builtin, mode: TrainMode, seed: u64, overrides: PlannerOverrides) -> RunSpec {
    RunSpec {
        task: task.name().into(),
        preset: Some("cem+deen".into()),
        overrides,
        mode,
        seed,
        task_spec: None,
    }
}

/// A planning run at the paper's sizes, quick to get its first models.
fn planning(task: Builtin, seed: u64) -> RunSpec {
    spec(
        task,
        TrainMode::Sync,
        seed,
        PlannerOverrides {
            exploration_episodes: Some(1),
            max_gradient_steps: Some(FIRST_TRAINING_STEPS),
            ..PlannerOverrides::default()
        },
    )
}

/// Explores for ever and retrains after every episode, each retraining long.
fn retraining() -> RunSpec {
    spec(
        Builtin::Cartpole,
        TrainMode::Async,
        3,
        PlannerOverrides {
            exploration_episodes: Some(1_000),
            dynamics_epochs: Some(2_000),
            energy_epochs: Some(2_000),
            ..PlannerOverrides::default()
        },
    )
}

/// A stand-in system of any size: the planner's cost does not depend on the data, only on
/// the models' and the search's sizes. Bounded, deterministic, a little driven by the action.
struct Plant {
    state: Vec<f32>,
    t: f32,
}

impl Plant {
    fn new(obs_dim: usize) -> Self {
        Self {
            state: vec![0.0; obs_dim],
            t: 0.0,
        }
    }

    fn step(&mut self, action: &[f32]) -> f32 {
        self.t += 0.05;
        let push: f32 = action.iter().sum::<f32>() / action.len() as f32;
        for (i, x) in self.state.iter_mut().enumerate() {
            *x = 0.9 * *x + 0.1 * (self.t + i as f32).sin() + 0.05 * push;
        }
        push
    }
}

/// What one agent saw in one mix.
#[derive(Default)]
struct Seen {
    round_trips: Vec<Duration>,
    cut: u32,
    missed: u32,
}

impl Seen {
    fn record(&mut self, sent: Instant, action: &Action) {
        self.round_trips.push(sent.elapsed());
        self.cut += u32::from(action.stats.cut);
        self.missed += u32::from(action.stats.missed);
    }

    fn print(self, mix: &str, agent: &str) {
        let mut sorted = self.round_trips;
        sorted.sort();
        let at = |q: f64| {
            sorted
                .get(((sorted.len().max(1) - 1) as f64 * q).round() as usize)
                .map_or(f64::NAN, |d| d.as_secs_f64() * 1e3)
        };
        println!(
            "{mix:<16} {agent:<12} {:>6} {:>9.1} {:>9.1} {:>6} {:>7}",
            sorted.len(),
            at(0.5),
            at(0.99),
            self.cut,
            self.missed
        );
    }
}

/// An agent of one run, with its stand-in system and its episode.
struct Agent {
    client: Client,
    plant: Plant,
    episode: u32,
    /// The task's time limit: an episode's last step is `episode_len - 1`.
    episode_len: u32,
    /// The task's control period: a controller sends an observation once per period.
    period: Duration,
}

impl Agent {
    async fn attach(endpoint: &str, run: &str, spec: &RunSpec, task: Builtin) -> Result<Self> {
        let client = Client::connect(endpoint, run, "a").await?;
        client.attach(spec).await?;
        Ok(Self {
            client,
            plant: Plant::new(task.task().obs_dim),
            episode: 0,
            episode_len: task.task().episode_len,
            period: Duration::from_secs_f64(task.spec().control_dt),
        })
    }

    /// One explored episode of `steps` steps, ended by the time limit, one observation per
    /// control period like the planned steps (an explorer flooding the daemon with messages
    /// would measure the transport, not the retraining beside it).
    async fn explore(&mut self, steps: u32) -> Result<()> {
        let mut reward = None;
        let mut tick = tokio::time::interval(self.period);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        for step in 0..steps {
            tick.tick().await;
            let obs = Observation::new(self.episode, step, self.plant.state.clone(), reward, None);
            let action = self.client.step(&obs).await?;
            reward = Some(self.plant.step(&action.action));
        }
        let end = Observation::new(
            self.episode,
            steps,
            self.plant.state.clone(),
            reward,
            Some(EpisodeEnd::TimeLimit),
        );
        self.client.send(&end).await?;
        // The client keeps run events in a bounded channel; left full (256 events: a
        // retraining neighbour ends that many episodes in seconds) it would stall the client's
        // session, and with it the answers to this agent.
        self.client.drain_events()?;
        self.episode += 1;
        Ok(())
    }

    /// Plans `max` steps, or until `stop` is raised, from a new episode on, one observation per
    /// control period as a controller sends them (the next one as soon as a late action comes).
    /// Episodes are never ended (a new one abandons the last one), so the agent's own run does
    /// not retrain.
    async fn plan(&mut self, max: u32, stop: Option<&AtomicBool>) -> Result<Seen> {
        let mut seen = Seen::default();
        let (mut step, mut reward) = (0, None);
        let mut tick = tokio::time::interval(self.period);
        // A late action delays the next observation; it does not make the controller catch up.
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        for _ in 0..max {
            tick.tick().await;
            if stop.is_some_and(|s| s.load(Ordering::SeqCst)) {
                break;
            }
            if step == self.episode_len {
                (self.episode, step, reward) = (self.episode + 1, 0, None);
            }
            let obs = Observation::new(self.episode, step, self.plant.state.clone(), reward, None);
            let sent = Instant::now();
            let action = self.client.step(&obs).await?;
            if action.stats.source != ActionSource::Planned {
                bail!(
                    "{}: step {step} was not planned: {action:?}",
                    self.client.run
                );
            }
            seen.record(sent, &action);
            reward = Some(self.plant.step(&action.action));
            step += 1;
        }
        self.episode += 1;
        Ok(seen)
    }
}

/// The cartpole agent plays `steps` planned steps while `neighbour` plays planned steps;
/// prints both.
async fn beside(light: &mut Agent, neighbour: &mut Agent, steps: u32, mix: &str) -> Result<()> {
    let done = AtomicBool::new(false);
    let (light_seen, neighbour_seen) = tokio::join!(
        async {
            let seen = light.plan(steps, None).await;
            done.store(true, Ordering::SeqCst);
            seen
        },
        neighbour.plan(u32::MAX, Some(&done)),
    );
    light_seen?.print(mix, "cartpole");
    neighbour_seen?.print(mix, "halfcheetah");
    Ok(())
}

fn parse_args() -> Result<u32> {
    let mut steps = 200;
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        match arg.as_str() {
            "--steps" => steps = it.next().context("--steps N")?.parse()?,
            "--bench" => {}
            other => bail!("unknown flag `{other}` (known: --steps N)"),
        }
    }
    Ok(steps)
}

fn main() -> Result<()> {
    let steps = parse_args()?;
    let dir = TempDir::new("mixed-bench");
    let config = format!("planner_id = \"{PLANNER}\"\n");
    let mut planner = Planner::start(dir.path(), &config)?;
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    println!("mixed load, {steps} planned cartpole steps per mix, {cores} cores; round trip in ms");
    println!(
        "{:<16} {:<12} {:>6} {:>9} {:>9} {:>6} {:>7}",
        "mix", "agent", "steps", "p50 ms", "p99 ms", "cut", "missed"
    );
    let rt = runtime();
    let measured = rt.block_on(async {
        let endpoint = planner.endpoint.clone();
        let mut light = Agent::attach(
            &endpoint,
            "light",
            &planning(Builtin::Cartpole, 1),
            Builtin::Cartpole,
        )
        .await?;
        let mut heavy = Agent::attach(
            &endpoint,
            "halfcheetah",
            &planning(Builtin::HalfCheetah, 2),
            Builtin::HalfCheetah,
        )
        .await?;
        light.explore(EXPLORED_STEPS).await?;
        heavy.explore(EXPLORED_STEPS).await?;
        // Both runs' first models (the first planned step waits for them), before anything
        // is measured.
        light.plan(1, None).await?;
        heavy.plan(1, None).await?;

        light.plan(steps, None).await?.print("alone", "cartpole");
        beside(&mut light, &mut heavy, steps, "+ halfcheetah").await?;
        // The half-cheetah agent goes; a retraining run comes.
        heavy.client.close().await?;

        let mut trainer =
            Agent::attach(&endpoint, "retraining", &retraining(), Builtin::Cartpole).await?;
        let stop = Arc::new(AtomicBool::new(false));
        let feeding = {
            let stop = stop.clone();
            async move {
                // Episodes keep coming, so the run retrains all the while.
                while !stop.load(Ordering::SeqCst) {
                    trainer.explore(EXPLORED_STEPS).await?;
                }
                trainer.client.close().await?;
                anyhow::Ok(())
            }
        };
        let measured = async {
            // Measure only once the neighbour retrains.
            let session = &light.client.session;
            let started = Instant::now();
            loop {
                let report = status(session, PLANNER).await?;
                if report
                    .runs
                    .iter()
                    .any(|r| r.name == "retraining" && r.training)
                {
                    break;
                }
                if started.elapsed() > Duration::from_secs(120) {
                    bail!("the retraining run never started training");
                }
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            let seen = light.plan(steps, None).await;
            let report = status(&light.client.session, PLANNER).await?;
            let retrainings = report
                .runs
                .iter()
                .find(|r| r.name == "retraining")
                .map(|r| (r.training, r.retraining.count));
            stop.store(true, Ordering::SeqCst);
            seen?.print("+ retraining", "cartpole");
            println!(
                "(the neighbour was still retraining at the end: {:?}; retrainings done: {:?})",
                retrainings.map(|r| r.0),
                retrainings.map(|r| r.1)
            );
            anyhow::Ok(())
        };
        let (fed, measured) = tokio::join!(feeding, measured);
        fed?;
        measured?;
        light.client.close().await?;
        anyhow::Ok(())
    });
    if let Err(e) = measured {
        let log = planner.process.log();
        let tail: Vec<&str> = log.lines().rev().take(40).collect();
        eprintln!("the daemon's last log lines:");
        tail.iter().rev().for_each(|line| eprintln!("  {line}"));
        return Err(e);
    }
    planner.stop()
}
