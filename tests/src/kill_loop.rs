//! The kill loop: a daemon SIGKILLed at random moments while a scripted agent steps, restarted
//! each time on the same data directory and endpoint, and checked at the end against what the
//! agent was told: every transition whose next action the agent received must be in the
//! replay log, and every episode must be recorded as finished or interrupted.
//!
//! `tests/tests/e2e/kill_loop.rs` runs it in CI (10 kills); `EBMPC_KILLS=100 cargo test -p
//! ebmpc-e2e --test e2e kill_loop:: -- --nocapture` runs it by hand and prints the figures.

use crate::client::{Answer, Client, ToySystem};
use crate::config::{PlannerConfig, Sizes};
use crate::transitions::{TransitionKey, stored_keys, transition_key};
use crate::{Planner, free_endpoint};
use anyhow::{Context, Result, bail};
use proto::{Builtin, EpisodeEnd, Observation, RunSpec, TrainMode};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::collections::{BTreeMap, HashSet};
use std::path::Path;
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

const RUN: &str = "killed";
const AGENT: &str = "a";
/// Steps per episode: short, so that kills land on episode ends and training too.
const EPISODE_STEPS: u32 = 12;
/// The longest a kill waits after the agent attached.
const MAX_KILL_DELAY_MS: u64 = 600;

/// What a kill loop found.
#[derive(Debug)]
pub struct KillLoopReport {
    pub kills: usize,
    /// Transitions whose next action the agent received.
    pub acknowledged: usize,
    /// Acknowledged transitions missing from the replay log after the last restart.
    pub lost: usize,
    /// Transitions in the replay log (acknowledged or not: a transition may be stored and the
    /// daemon killed before its action reached the agent).
    pub stored: usize,
    /// Episodes the agent started.
    pub episodes_started: usize,
    pub episodes_finished: usize,
    pub episodes_interrupted: usize,
    /// Started episodes with no record in the log (neither finished nor interrupted).
    pub episodes_unaccounted: usize,
    pub seconds: f64,
}

fn spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: Some("cem".into()),
        overrides: Default::default(),
        mode: TrainMode::Async,
        seed: 11,
        task_spec: None,
    }
}

fn config() -> String {
    PlannerConfig::new("killloop", Sizes::TINY)
        .exploration_episodes(2)
        .toml()
}

/// What the agent knows.
#[derive(Default)]
struct Ledger {
    acknowledged: HashSet<TransitionKey>,
    /// Episodes started; `true` once their end was sent and the next episode's first action
    /// acknowledged it.
    episodes: BTreeMap<u32, bool>,
}

/// Runs `kills` kill-and-restart rounds in `dir` and checks the log.
pub fn kill_loop(dir: &Path, kills: usize, seed: u64) -> Result<KillLoopReport> {
    let started = Instant::now();
    let endpoint = free_endpoint();
    let runtime = crate::client::runtime();
    let mut rng = StdRng::seed_from_u64(seed);
    let mut system = ToySystem::new(3);
    let mut ledger = Ledger::default();
    for round in 0..kills {
        let planner = Planner::start_on(dir, &config(), &endpoint)
            .with_context(|| format!("planner start before kill {round}"))?;
        let pid = planner.process.pid();
        let delay = Duration::from_millis(rng.random_range(0..=MAX_KILL_DELAY_MS));
        let killed = Arc::new(AtomicBool::new(false));
        runtime
            .block_on(async {
                // A fresh session per daemon: the agent's process is not what is under test,
                // and a Zenoh session that saw its peer SIGKILLed takes a while to settle.
                let client = Client::connect(&endpoint, RUN, AGENT).await?;
                let accepted = attach(&client).await?;
                let fired = killed.clone();
                let killer = std::thread::spawn(move || {
                    std::thread::sleep(delay);
                    let status = Command::new("kill")
                        .args(["-KILL", &pid.to_string()])
                        .status();
                    fired.store(true, Ordering::SeqCst);
                    status
                });
                play_until_killed(
                    &client,
                    &mut system,
                    accepted.next_episode,
                    &killed,
                    &mut ledger,
                )
                .await?;
                let status = killer.join().expect("killer thread")?;
                if !status.success() {
                    bail!("kill -KILL {pid} failed");
                }
                drop(client);
                Ok(())
            })
            .with_context(|| format!("kill {round}"))?;
        let mut planner = planner;
        planner.process.wait(Duration::from_secs(30))?;
    }
    // The last restart: the daemon recovers the log, then stops cleanly.
    let mut planner = Planner::start_on(dir, &config(), &endpoint)?;
    planner.stop()?;
    let buffer = planner.replay(RUN, Builtin::Cartpole)?;
    let in_log = stored_keys(&buffer);
    let lost = ledger
        .acknowledged
        .iter()
        .filter(|t| !in_log.contains(*t))
        .count();
    let mut finished = 0;
    let mut interrupted = 0;
    let mut unaccounted = 0;
    for (&episode, &ended) in &ledger.episodes {
        let records: Vec<_> = buffer
            .episodes()
            .iter()
            .filter(|e| e.agent == AGENT && e.episode == episode)
            .collect();
        match records.as_slice() {
            [one] if one.end == EpisodeEnd::Interrupted && !ended => interrupted += 1,
            [one] if one.end == EpisodeEnd::TimeLimit => finished += 1,
            _ => unaccounted += 1,
        }
    }
    Ok(KillLoopReport {
        kills,
        acknowledged: ledger.acknowledged.len(),
        lost,
        stored: buffer.len(),
        episodes_started: ledger.episodes.len(),
        episodes_finished: finished,
        episodes_interrupted: interrupted,
        episodes_unaccounted: unaccounted,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// Attaches, trying again if the query itself fails (the daemon is still starting).
async fn attach(client: &Client) -> Result<proto::AttachAccepted> {
    let mut tries = 0;
    loop {
        match client.attach(&spec()).await {
            Ok(accepted) => return Ok(accepted),
            Err(e) if tries < 10 => {
                tries += 1;
                eprintln!("attach failed, trying again: {e}");
                tokio::time::sleep(Duration::from_millis(500)).await;
            }
            Err(e) => return Err(e),
        }
    }
}

/// Plays episodes from `episode` on until the daemon is gone (the kill fired and an answer
/// did not come). An episode enters the ledger with its first acknowledged transition.
async fn play_until_killed(
    client: &Client,
    system: &mut ToySystem,
    mut episode: u32,
    killed: &AtomicBool,
    ledger: &mut Ledger,
) -> Result<()> {
    // The episode whose end was sent, with its last transition: both are acknowledged by the
    // next episode's first action (one worker per agent stores them before taking that step).
    let mut ending: Option<(u32, TransitionKey)> = None;
    loop {
        let mut obs = system.state.to_vec();
        let Some(mut action) = answer(
            client,
            &Observation::new(episode, 0, obs.clone(), None, None),
            killed,
        )
        .await?
        else {
            return Ok(());
        };
        if let Some((ended, last)) = ending.take() {
            ledger.acknowledged.insert(last);
            ledger.episodes.insert(ended, true);
        }
        for step in 1..=EPISODE_STEPS {
            let reward = system.step(&action);
            let next = system.state.to_vec();
            if step == EPISODE_STEPS {
                let end = Some(EpisodeEnd::TimeLimit);
                client
                    .send(&Observation::new(
                        episode,
                        step,
                        next.clone(),
                        Some(reward),
                        end,
                    ))
                    .await?;
                ending = Some((episode, transition_key(&obs, &action, &next)));
                break;
            }
            let msg = Observation::new(episode, step, next.clone(), Some(reward), None);
            let Some(next_action) = answer(client, &msg, killed).await? else {
                return Ok(());
            };
            ledger
                .acknowledged
                .insert(transition_key(&obs, &action, &next));
            ledger.episodes.entry(episode).or_insert(false);
            obs = next;
            action = next_action;
        }
        episode += 1;
    }
}

/// Sends `msg` and waits for its action: `None` once the kill has fired and no answer comes.
async fn answer(
    client: &Client,
    msg: &Observation,
    killed: &AtomicBool,
) -> Result<Option<Vec<f32>>> {
    client.send(msg).await?;
    loop {
        match client.answer(Duration::from_secs(2)).await {
            Ok(Answer::Action(a)) if (a.episode, a.step) == (msg.episode, msg.step) => {
                return Ok(Some(a.action));
            }
            Ok(Answer::Action(_stale)) => {}
            Ok(Answer::Error(report)) => {
                bail!(
                    "episode {} step {} refused: {report}",
                    msg.episode,
                    msg.step
                )
            }
            Err(_) if killed.load(Ordering::SeqCst) => return Ok(None),
            // Not killed yet: the daemon is only slow (a loaded machine); keep waiting.
            Err(_) => {}
        }
    }
}
