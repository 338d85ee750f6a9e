//! `cargo bench -p ebmpc-e2e --bench service`: the cost of the Zenoh control loop itself.
//!
//! Starts the real `planner-service` binary on a loopback port with planning taken out of the
//! loop (every run stays in its exploration phase, so each action is a uniform random draw,
//! a few hundred nanoseconds), then drives it with 1, 2, 4 and 8 concurrent scripted agents,
//! each on its own Zenoh session. Every step is a full round trip: observation published →
//! decoded, validated, stored in the run's replay log → action published → received. It
//! prints the round-trip p50/p99 and the total steps per second for each agent count.
//!
//! Flags (after `--`): `--steps N` per agent (default 2000), `--agents 1,2,4,8`.

use anyhow::{Context, Result};
use ebmpc_e2e::client::{Client, ToySystem, runtime};
use ebmpc_e2e::{Planner, TempDir};
use proto::{EpisodeEnd, Observation, RunSpec, TaskId, TrainMode};
use std::time::{Duration, Instant};

/// No planning: exploration never ends, so every action is random.
const CONFIG: &str = r#"
planner_id = "bench"
max_agents_per_run = 64
[overrides]
exploration_episodes = 1000000
# The trainer still runs after every episode; keep it negligible.
dynamics_hidden_layers = 1
dynamics_hidden_size = 8
dynamics_epochs = 1
"#;

/// Steps per episode: episodes end now and then, as in real use (each end syncs the log).
const EPISODE_STEPS: u32 = 200;

struct Args {
    steps: u32,
    agents: Vec<usize>,
}

fn parse_args() -> Result<Args> {
    let mut args = Args {
        steps: 2000,
        agents: vec![1, 2, 4, 8],
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        match arg.as_str() {
            "--steps" => args.steps = it.next().context("--steps N")?.parse()?,
            "--agents" => {
                args.agents = it
                    .next()
                    .context("--agents 1,2,4")?
                    .split(',')
                    .map(str::parse)
                    .collect::<Result<_, _>>()?;
            }
            // cargo bench passes `--bench`; anything else is a mistake worth saying.
            "--bench" => {}
            other => anyhow::bail!("unknown flag `{other}` (known: --steps N, --agents 1,2,4)"),
        }
    }
    Ok(args)
}

/// Plays `steps` steps and returns the round trip of each.
async fn drive(client: Client, steps: u32, seed: u32) -> Result<Vec<Duration>> {
    let mut system = ToySystem::new(seed);
    let mut round_trips = Vec::with_capacity(steps as usize);
    let (mut episode, mut step) = (0, 0);
    let mut action = Vec::new();
    for _ in 0..steps {
        let msg = if step == 0 {
            Observation::new(episode, 0, system.state.to_vec(), None, None)
        } else {
            let reward = system.step(&action);
            Observation::new(episode, step, system.state.to_vec(), Some(reward), None)
        };
        let sent = Instant::now();
        action = client.step(&msg).await?.action;
        round_trips.push(sent.elapsed());
        step += 1;
        if step == EPISODE_STEPS {
            let reward = system.step(&action);
            let end = Some(EpisodeEnd::TimeLimit);
            client
                .send(&Observation::new(
                    episode,
                    step,
                    system.state.to_vec(),
                    Some(reward),
                    end,
                ))
                .await?;
            system = ToySystem::new(seed);
            (episode, step) = (episode + 1, 0);
        }
    }
    client.close().await?;
    Ok(round_trips)
}

fn percentile(sorted: &[Duration], p: f64) -> f64 {
    let i = ((sorted.len() - 1) as f64 * p).round() as usize;
    sorted[i].as_secs_f64() * 1e3
}

fn main() -> Result<()> {
    let args = parse_args()?;
    let dir = TempDir::new("bench-service");
    let planner = Planner::start(dir.path(), CONFIG)?;
    let runtime = runtime();
    println!(
        "service round trip (loopback, planning replaced by a random action), {} steps per agent",
        args.steps
    );
    println!("agents  p50 ms  p99 ms  steps/s  (total)");
    for (round, &agents) in args.agents.iter().enumerate() {
        let (round_trips, wall) = runtime.block_on(async {
            let mut clients = Vec::new();
            for i in 0..agents {
                let client =
                    Client::connect(&planner.endpoint, &format!("r{round}"), &format!("a{i}"))
                        .await?;
                let spec = RunSpec {
                    task: TaskId::Cartpole,
                    preset: Some("cem".into()),
                    overrides: Default::default(),
                    mode: TrainMode::Async,
                    seed: 0,
                };
                client.attach(&spec).await?;
                clients.push(client);
            }
            let started = Instant::now();
            let tasks: Vec<_> = clients
                .into_iter()
                .enumerate()
                .map(|(i, c)| tokio::spawn(drive(c, args.steps, i as u32)))
                .collect();
            let mut all = Vec::new();
            for task in tasks {
                all.extend(task.await??);
            }
            anyhow::Ok((all, started.elapsed()))
        })?;
        let mut sorted = round_trips;
        sorted.sort();
        println!(
            "{agents:>6}  {:>6.3}  {:>6.3}  {:>7.0}",
            percentile(&sorted, 0.5),
            percentile(&sorted, 0.99),
            sorted.len() as f64 / wall.as_secs_f64()
        );
    }
    Ok(())
}
