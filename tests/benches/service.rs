//! `cargo bench -p ebmpc-e2e --bench service`: the cost of the Zenoh control loop itself.
//!
//! Starts the real `planner-service` binary with planning taken out of the loop (every run
//! stays in its exploration phase, so each action is a uniform random draw, a few hundred
//! nanoseconds), then drives it with concurrent scripted agents, each on its own Zenoh session
//! and run. Every step is a full round trip: observation published → decoded, validated,
//! stored in the run's replay log → action published → received.
//!
//! Two set-ups, each printing the round-trip p50/p99 and the total steps per second:
//! - *direct*: one planner on a loopback port, agents connected to it, 1, 2, 4 and 8 agents,
//!   twice side by side: the log synced at episode ends (a single daemon's default), and every
//!   step synced before it is acknowledged (`[storage] sync_every_step`, group commit; a
//!   fleet's default): the difference is the group commit's cost per step;
//! - *fleet*: a Zenoh router (in this process), 1..N planners sharing one data directory, and
//!   the same number of agents each time, spread over the planners by etcd (started here) and
//!   the fleet's placement; steps synced at episode ends, as in the direct set-up's first row.
//!   The difference between the direct and the one-planner fleet p50 at equal agent count is
//!   the router's overhead per step (one more hop each way).
//!
//! Flags (after `--`): `--steps N` per agent (default 2000), `--agents 1,2,4,8` (direct),
//! `--planners 1,2,3` (fleet), `--fleet-agents N` (default 12).

use anyhow::{Context, Result};
use ebmpc_e2e::client::{Client, ToySystem, open_session, runtime, status};
use ebmpc_e2e::etcd::Etcd;
use ebmpc_e2e::{Guarded, Planner, TempDir, free_endpoint, router, serve_data};
use proto::{Builtin, EpisodeEnd, Observation, RunSpec, TrainMode};
use std::path::Path;
use std::time::{Duration, Instant};

/// No planning: exploration outlasts the bench (the most episodes `[limits]` allows, far more
/// than a round plays), so every action is random. (`{top}` takes the planner id and, in a
/// fleet, the router to connect to.)
const CONFIG: &str = r#"
max_agents_per_run = 64
[overrides]
exploration_episodes = 1000
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
    planners: Vec<usize>,
    fleet_agents: usize,
}

/// A planner's configuration: its id and top-level lines, then the common settings.
fn config(id: &str, top: &str) -> String {
    format!("planner_id = \"{id}\"\n{top}\n{CONFIG}")
}

fn list(text: Option<String>, what: &str) -> Result<Vec<usize>> {
    Ok(text
        .with_context(|| format!("{what} 1,2,4"))?
        .split(',')
        .map(str::parse)
        .collect::<Result<_, _>>()?)
}

fn parse_args() -> Result<Args> {
    let mut args = Args {
        steps: 2000,
        agents: vec![1, 2, 4, 8],
        planners: vec![1, 2, 3],
        fleet_agents: 12,
    };
    let mut it = std::env::args().skip(1);
    while let Some(arg) = it.next() {
        match arg.as_str() {
            "--steps" => args.steps = it.next().context("--steps N")?.parse()?,
            "--agents" => args.agents = list(it.next(), "--agents")?,
            "--planners" => args.planners = list(it.next(), "--planners")?,
            "--fleet-agents" => {
                args.fleet_agents = it.next().context("--fleet-agents N")?.parse()?;
            }
            // cargo bench passes `--bench`; anything else is a mistake worth saying.
            "--bench" => {}
            other => anyhow::bail!(
                "unknown flag `{other}` (known: --steps N, --agents 1,2,4, --planners 1,2,3, --fleet-agents N)"
            ),
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

/// Connects and attaches one agent per run (`{prefix}-{i}`) at `endpoint`, plays `steps` steps
/// with each at once; every round trip and the wall time.
async fn round(
    endpoint: &str,
    prefix: &str,
    agents: usize,
    steps: u32,
) -> Result<(Vec<Duration>, Duration)> {
    let mut clients = Vec::new();
    for i in 0..agents {
        let client = Client::connect(endpoint, &format!("{prefix}-{i}"), "a").await?;
        let spec = RunSpec {
            task: Builtin::Cartpole.name().into(),
            preset: Some("cem".into()),
            overrides: Default::default(),
            mode: TrainMode::Async,
            seed: 0,
            task_spec: None,
        };
        client.attach(&spec).await?;
        clients.push(client);
    }
    let started = Instant::now();
    let tasks: Vec<_> = clients
        .into_iter()
        .enumerate()
        .map(|(i, c)| tokio::spawn(drive(c, steps, i as u32)))
        .collect();
    let mut all = Vec::new();
    for task in tasks {
        all.extend(task.await??);
    }
    Ok((all, started.elapsed()))
}

/// The p50 and p99 in ms and the steps per second of a round, printed after `label`.
fn report(label: &str, round_trips: Vec<Duration>, wall: Duration) -> f64 {
    let mut sorted = round_trips;
    sorted.sort();
    let p50 = percentile(&sorted, 0.5);
    println!(
        "{label}  {p50:>6.3}  {:>6.3}  {:>7.0}",
        percentile(&sorted, 0.99),
        sorted.len() as f64 / wall.as_secs_f64()
    );
    p50
}

/// Starts etcd, a router and `n` planners sharing one data directory, waits until each sees
/// all. (The planners come before etcd in the result, so they stop first.)
fn fleet(
    dir: &Path,
    n: usize,
    runtime: &tokio::runtime::Runtime,
) -> Result<(zenoh::Session, String, Vec<Guarded>, Etcd)> {
    let etcd = Etcd::start(dir)?;
    let endpoint = free_endpoint();
    let router = runtime.block_on(router(&endpoint))?;
    let data = dir.join("data");
    let top = format!("connect = [\"{endpoint}\"]");
    let mut planners = Vec::new();
    for i in 0..n {
        let id = format!("p{i}");
        let config = format!(
            "{}\n[storage]\nsync_every_step = false\n{}",
            config(&id, &top),
            etcd.fleet_toml(10)
        );
        planners.push(serve_data(&dir.join(&id), &data, &config, None)?);
    }
    runtime.block_on(async {
        let session = open_session(&endpoint).await?;
        for i in 0..n {
            let started = Instant::now();
            while status(&session, &format!("p{i}"))
                .await?
                .fleet
                .planners
                .len()
                < n
            {
                anyhow::ensure!(
                    started.elapsed() < Duration::from_secs(60),
                    "planners never saw each other"
                );
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
        session
            .close()
            .await
            .map_err(|e| anyhow::anyhow!("close: {e}"))
    })?;
    Ok((router, endpoint, planners, etcd))
}

fn main() -> Result<()> {
    let args = parse_args()?;
    let dir = TempDir::new("bench-service");
    let runtime = runtime();
    println!(
        "service round trip (loopback, planning replaced by a random action), {} steps per agent",
        args.steps
    );
    let mut direct_p50 = std::collections::BTreeMap::new();
    if !args.agents.is_empty() {
        let planner = Planner::start(&dir.path().join("direct"), &config("bench", ""))?;
        let durable = Planner::start(
            &dir.path().join("direct-sync"),
            &format!(
                "{}\n[storage]\nsync_every_step = true\n",
                config("bench-sync", "")
            ),
        )?;
        println!(
            "direct to one planner (sync: at episode ends | every step, group commit)\nagents  sync   p50 ms  p99 ms  steps/s  (total)"
        );
        for (i, &agents) in args.agents.iter().enumerate() {
            let (round_trips, wall) = runtime.block_on(round(
                &planner.endpoint,
                &format!("d{i}"),
                agents,
                args.steps,
            ))?;
            let p50 = report(&format!("{agents:>6}  ends "), round_trips, wall);
            direct_p50.insert(agents, p50);
            let (round_trips, wall) = runtime.block_on(round(
                &durable.endpoint,
                &format!("s{i}"),
                agents,
                args.steps,
            ))?;
            let synced = report(&format!("{agents:>6}  steps"), round_trips, wall);
            println!(
                "        group commit per step at {agents} agents: {:+.3} ms p50 ({:.2}x)",
                synced - p50,
                synced / p50
            );
        }
    }
    if !args.planners.is_empty() {
        println!(
            "through a router, {} agents (one run each) over the planners\nplanners  p50 ms  p99 ms  steps/s  (total)",
            args.fleet_agents
        );
        for &n in &args.planners {
            let fleet_dir = dir.path().join(format!("fleet-{n}"));
            let (router, endpoint, mut planners, _etcd) = fleet(&fleet_dir, n, &runtime)?;
            let (round_trips, wall) = runtime.block_on(round(
                &endpoint,
                &format!("f{n}"),
                args.fleet_agents,
                args.steps,
            ))?;
            let p50 = report(&format!("{n:>8}"), round_trips, wall);
            if n == 1
                && let Some(direct) = direct_p50.get(&args.fleet_agents)
            {
                println!(
                    "router overhead per step at {} agents: {:.3} ms (p50 through the router {p50:.3} − direct {direct:.3})",
                    args.fleet_agents,
                    p50 - direct
                );
            }
            for planner in &mut planners {
                planner.terminate(Duration::from_secs(30))?;
            }
            runtime
                .block_on(async { router.close().await })
                .map_err(|e| anyhow::anyhow!("router: {e}"))?;
        }
    }
    Ok(())
}
