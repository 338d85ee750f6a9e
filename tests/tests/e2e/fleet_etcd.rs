//! A fleet whose ownership lives in a real etcd: three planner processes behind a Zenoh router
//! (in this process, multicast scouting off, free ports), one etcd (started here on free
//! loopback ports, killed when the test ends, also on failure), one shared data directory.
//!
//! - the owner SIGKILLed mid-episode, again and again across the three planners: no
//!   acknowledged transition is lost, every episode is accounted for, and no planner ever
//!   acknowledged a step after a newer owner had (checked from the actions the agent received);
//! - a planner cut off from etcd stops acknowledging within its lease TTL and its run moves;
//! - a planner cut off from the router takes no run, and nothing acknowledged is lost;
//! - forged planner and lease tokens (10,000 names, huge epochs) move no run and keep the
//!   planner's view and memory bounded;
//! - stale owners appending to their own old replay segments after a takeover add nothing to
//!   the run;
//! - a planner given SIGTERM in the middle of a stuck takeover exits within 10 s and the run
//!   moves;
//! - with `replay_capacity`, owners killed round after round compact the run across the
//!   segments of earlier terms: nothing of the newest episodes is lost, the replay stays
//!   bounded, superseded segments are removed;
//! - on a shared disk that fills up (a small tmpfs), a stale owner's failed writes delete
//!   nothing of the new owner's: its segment, checkpoints and acknowledged transitions.

use ebmpc_e2e::Guarded;
use ebmpc_e2e::client::{Answer, Client, ToySystem, open_session, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::fleet::Fleet;
use ebmpc_e2e::proxy::Proxy;
use ebmpc_e2e::transitions::{TransitionKey, stored_keys, transition_key};
use planner_service::config::Preset;
use planner_service::models::Models;
use planner_service::persist::{CheckpointId, PersistError, RunDir};
use planner_service::replay::segments::SegmentId;
use planner_service::replay::{
    ActionOrigin, EpisodeEndRecord, LogFile, Record, ReplayBuffer, ReplayLog, TransitionRecord,
};
use proto::{Builtin, EpisodeEnd, Observation, RunSpec, TrainMode};
use std::collections::{BTreeMap, HashSet};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

/// The planners' lease: short, so that a dead owner's runs move within seconds.
const TTL_SECONDS: u64 = 3;
const STEPS: u32 = 10;

fn spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: Some("cem".into()),
        overrides: Default::default(),
        mode: TrainMode::Async,
        seed: 5,
        task_spec: None,
    }
}

/// The lease of the router-cut test's planners: long enough that no owner's lease lapses
/// under a loaded CI machine while the test holds the partition (a lapsed lease would let the
/// cut-off planner take that run legitimately, and its agent, behind the router, would go
/// unserved). The test is about etcd naming the owners, not about how fast runs move.
const PARTITION_TTL_SECONDS: u64 = 10;

/// A fleet planner's configuration: connects to `router` only, owns through `etcd`.
fn config(id: &str, router: &str, etcd: &str) -> String {
    leased_config(id, router, etcd, TTL_SECONDS)
}

/// [`config`] with a lease of `ttl_seconds`.
fn leased_config(id: &str, router: &str, etcd: &str, ttl_seconds: u64) -> String {
    PlannerConfig::new(id, Sizes::TINY)
        .exploration_episodes(2)
        .line(format!("connect = [\"{router}\"]"))
        .in_fleet(etcd, ttl_seconds)
        .toml()
}

/// Starts fleet planner `id`, connected to the fleet's router and etcd.
fn start(fleet: &Fleet, id: &str) -> Guarded {
    fleet.planner(id, &config(id, &fleet.endpoint, &fleet.etcd.endpoint))
}

fn run_path(data: &Path, run: &str) -> PathBuf {
    data.join("runs").join(run)
}

/// What an agent was told, to check the replay and the fencing against.
#[derive(Default)]
struct Ledger {
    acknowledged: HashSet<TransitionKey>,
    /// The acknowledged transitions of each episode.
    by_episode: BTreeMap<u32, HashSet<TransitionKey>>,
    /// Episodes started; `true` once their end was acknowledged.
    episodes: BTreeMap<u32, bool>,
    /// Every action received, with its fencing token, in the order received.
    tokens: Vec<u64>,
    /// When the last action came.
    last_action: Option<Instant>,
}

impl Ledger {
    /// The tokens of the actions received never go back: once a newer owner answered, no
    /// older one did (actions are published by each owner in order, and an owner that lost
    /// the run sends nothing after its lease's margin).
    fn check_one_owner_at_a_time(&self) {
        for pair in self.tokens.windows(2) {
            assert!(
                pair[0] <= pair[1],
                "an action of token {} came after one of token {}: two planners acknowledged at once",
                pair[1],
                pair[0]
            );
        }
    }

    /// Checks the stored replay of `run` against the ledger: every acknowledged transition is
    /// there, every episode is finished or interrupted. Returns the number acknowledged.
    fn check_replay(&self, data: &Path, run: &str, agent: &str) -> usize {
        let buffer = ReplayBuffer::read(&run_path(data, run), Builtin::Cartpole.task())
            .expect("the replay reads");
        let stored = stored_keys(&buffer);
        let lost = self
            .acknowledged
            .iter()
            .filter(|t| !stored.contains(*t))
            .count();
        assert_eq!(
            lost,
            0,
            "{lost} of {} acknowledged transitions lost",
            self.acknowledged.len()
        );
        for (&episode, &ended) in &self.episodes {
            let records: Vec<_> = buffer
                .episodes()
                .iter()
                .filter(|e| e.agent == agent && e.episode == episode)
                .collect();
            let accounted = match records.as_slice() {
                [one] => {
                    one.end == EpisodeEnd::TimeLimit
                        || (!ended && one.end == EpisodeEnd::Interrupted)
                }
                _ => false,
            };
            assert!(
                accounted,
                "episode {episode} (ended: {ended}) is recorded as {records:?}"
            );
        }
        self.acknowledged.len()
    }
}

/// One agent stepping a toy system.
struct Agent {
    client: Client,
    system: ToySystem,
    episode: u32,
    /// The episode whose end was sent and its last transition, acknowledged by the next
    /// episode's first action.
    ending: Option<(u32, TransitionKey)>,
}

impl Agent {
    async fn new(
        endpoint: &str,
        run: &str,
        episode: u32,
        seed: u32,
    ) -> (Self, proto::AttachAccepted) {
        let client = Client::connect(endpoint, run, "a").await.unwrap();
        let accepted = client.attach(&spec()).await.unwrap();
        let agent = Agent {
            client,
            system: ToySystem::new(seed),
            episode: episode.max(accepted.next_episode),
            ending: None,
        };
        (agent, accepted)
    }

    /// Attaches again (to whichever planner owns the run now) and starts a new episode; an
    /// episode end still unacknowledged is left unconfirmed (the new owner's first action
    /// says nothing about what the old one stored).
    async fn reattach(&mut self) -> proto::AttachAccepted {
        let accepted = self.client.attach(&spec()).await.unwrap();
        self.ending = None;
        self.episode = (self.episode + 1).max(accepted.next_episode);
        accepted
    }

    /// Sends `msg` and waits up to `wait` for its action, recording every action's token.
    /// `None`: no action came (an error report, or silence).
    async fn exchange(
        &self,
        msg: &Observation,
        wait: Duration,
        ledger: &mut Ledger,
    ) -> Option<Vec<f32>> {
        self.client.send(msg).await.unwrap();
        let deadline = Instant::now() + wait;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return None;
            }
            match self.client.answer(left).await {
                Ok(Answer::Action(a)) => {
                    ledger.tokens.push(a.epoch);
                    ledger.last_action = Some(Instant::now());
                    if (a.episode, a.step) == (msg.episode, msg.step) {
                        return Some(a.action);
                    }
                }
                Ok(Answer::Error(_)) | Err(_) => return None,
            }
        }
    }

    /// Plays whole episodes until `stop()` says so or an answer does not come within `wait`;
    /// returns the number of actions received.
    async fn play(
        &mut self,
        ledger: &mut Ledger,
        wait: Duration,
        stop: impl Fn(usize) -> bool,
    ) -> usize {
        let mut actions = 0;
        loop {
            let mut obs = self.system.state.to_vec();
            let first = Observation::new(self.episode, 0, obs.clone(), None, None);
            let Some(mut action) = self.exchange(&first, wait, ledger).await else {
                return actions;
            };
            actions += 1;
            if let Some((ended, last)) = self.ending.take() {
                ledger.acknowledged.insert(last.clone());
                ledger.by_episode.entry(ended).or_default().insert(last);
                ledger.episodes.insert(ended, true);
            }
            for step in 1..=STEPS {
                let reward = self.system.step(&action);
                let next = self.system.state.to_vec();
                if step == STEPS {
                    let end = Some(EpisodeEnd::TimeLimit);
                    let msg = Observation::new(self.episode, step, next.clone(), Some(reward), end);
                    self.client.send(&msg).await.unwrap();
                    self.ending = Some((self.episode, transition_key(&obs, &action, &next)));
                    break;
                }
                let msg = Observation::new(self.episode, step, next.clone(), Some(reward), None);
                let Some(next_action) = self.exchange(&msg, wait, ledger).await else {
                    // The episode is left unfinished: the next play starts a new one.
                    self.episode += 1;
                    return actions;
                };
                actions += 1;
                let key = transition_key(&obs, &action, &next);
                ledger.acknowledged.insert(key.clone());
                ledger
                    .by_episode
                    .entry(self.episode)
                    .or_default()
                    .insert(key);
                ledger.episodes.entry(self.episode).or_insert(false);
                obs = next;
                action = next_action;
                if stop(actions) {
                    self.episode += 1;
                    return actions;
                }
            }
            self.episode += 1;
            if stop(actions) {
                return actions;
            }
        }
    }
}

/// The run names each live planner's status lists.
async fn hosted(session: &zenoh::Session, planners: &[&str]) -> BTreeMap<String, Vec<String>> {
    let mut owners: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for planner in planners {
        if let Ok(report) = status(session, planner).await {
            for run in report.runs {
                owners
                    .entry(run.name)
                    .or_default()
                    .push(planner.to_string());
            }
        }
    }
    owners
}

/// The owner is SIGKILLed mid-episode, round after round, across three planners.
#[test]
fn the_owner_killed_mid_episode_again_and_again_loses_nothing_acknowledged() {
    let kills: usize = std::env::var("EBMPC_FLEET_KILLS")
        .ok()
        .and_then(|k| k.parse().ok())
        .unwrap_or(20);
    let fleet = Fleet::start("fleet-kill");
    let (data, endpoint, rt) = (&fleet.data, &fleet.endpoint, &fleet.rt);
    let ids = ["pa", "pb", "pc"];
    let mut planners: BTreeMap<&str, Guarded> =
        ids.iter().map(|id| (*id, start(&fleet, id))).collect();
    let run = "killed";
    let mut ledger = Ledger::default();
    let mut episode = 0;
    let mut last_token = 0;
    let mut owners_seen = BTreeMap::new();
    let started = Instant::now();
    // The last planner killed: restarted once another planner took the run over, so the run
    // moves between planners rather than back to the one it prefers.
    let mut dead: Option<&str> = None;
    for round in 0..kills {
        let (owner, token) = rt.block_on(async {
            let (mut agent, accepted) = Agent::new(endpoint, run, episode, round as u32).await;
            if let Some(id) = dead.take() {
                planners.insert(id, start(&fleet, id));
            }
            assert!(
                accepted.epoch > last_token,
                "round {round}: token {} after {last_token}",
                accepted.epoch
            );
            // Play a random number of steps (past an episode end now and then), then kill
            // the owner while the agent keeps stepping.
            let steps = 3 + (round * 7) % 17;
            agent
                .play(&mut ledger, Duration::from_secs(20), |n| n >= steps)
                .await;
            planners
                .get_mut(accepted.planner_id.as_str())
                .unwrap()
                .signal("KILL")
                .unwrap();
            agent
                .play(&mut ledger, Duration::from_secs(2), |_| false)
                .await;
            episode = agent.episode + 1;
            (accepted.planner_id, accepted.epoch)
        });
        last_token = token;
        *owners_seen.entry(owner.clone()).or_insert(0) += 1;
        let victim = planners.get_mut(owner.as_str()).unwrap();
        victim.wait(Duration::from_secs(10)).unwrap();
        dead = ids.iter().find(|p| **p == owner).copied();
    }
    if let Some(id) = dead {
        planners.insert(id, start(&fleet, id));
    }
    eprintln!(
        "{kills} kills in {:.0} s, owners {owners_seen:?}, {} actions",
        started.elapsed().as_secs_f64(),
        ledger.tokens.len()
    );
    assert!(
        owners_seen.len() >= 2,
        "the run moved between planners: {owners_seen:?}"
    );
    ledger.check_one_owner_at_a_time();
    for (_, planner) in planners.iter_mut() {
        planner.terminate(Duration::from_secs(20)).unwrap();
    }
    let acknowledged = ledger.check_replay(data, run, "a");
    assert!(acknowledged > kills, "{acknowledged} acknowledged");
}

/// A planner cut off from etcd stops acknowledging within its lease's TTL, and its run moves
/// to a planner that can reach etcd; nothing acknowledged is lost, and after the link heals
/// the cut-off planner takes nothing back.
#[test]
fn a_planner_cut_off_from_etcd_stops_acknowledging_and_its_run_moves() {
    let fleet = Fleet::start("fleet-etcd-cut");
    let (data, etcd, endpoint, rt) = (&fleet.data, &fleet.etcd, &fleet.endpoint, &fleet.rt);
    let upstream = etcd.endpoint.trim_start_matches("http://").parse().unwrap();
    let link = Proxy::start(upstream).unwrap();
    let through = format!("http://127.0.0.1:{}", link.port);
    // pa alone first, so the run is created there.
    let mut pa = fleet.planner("pa", &config("pa", endpoint, &through));
    let run = "cut";
    let mut ledger = Ledger::default();
    let mut others = Vec::new();
    let new_owner = rt.block_on(async {
        let (mut agent, accepted) = Agent::new(endpoint, run, 0, 1).await;
        assert_eq!(accepted.planner_id, "pa");
        let token = accepted.epoch;
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| n >= 2 * STEPS as usize)
            .await;
        for id in ["pb", "pc"] {
            others.push(start(&fleet, id));
        }
        let again = agent.reattach().await;
        assert_eq!(
            (again.planner_id.as_str(), again.epoch),
            ("pa", token),
            "a held run stays with its holder"
        );
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| n >= 5)
            .await;
        link.cut();
        let cut_at = Instant::now();
        // The agent keeps stepping: pa answers until its lease's margin, then no more.
        agent
            .play(&mut ledger, Duration::from_secs(2 * TTL_SECONDS), |_| false)
            .await;
        let last_ack = ledger.last_action.unwrap().saturating_duration_since(cut_at);
        assert!(
            last_ack < Duration::from_secs(TTL_SECONDS),
            "pa kept acknowledging {last_ack:?} after its etcd link was cut (lease TTL {TTL_SECONDS} s)"
        );
        // Another planner takes the run at a newer token once pa's lease expired.
        let moved = agent.reattach().await;
        assert_ne!(moved.planner_id, "pa");
        assert!(moved.epoch > token);
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| n >= STEPS as usize + 2)
            .await;
        // Heal: pa gets a new lease and takes nothing back.
        link.heal();
        tokio::time::sleep(Duration::from_secs(TTL_SECONDS + 2)).await;
        let owners = hosted(&agent.client.session, &["pa", "pb", "pc"]).await;
        assert_eq!(owners.get(run), Some(&vec![moved.planner_id.clone()]), "{owners:?}");
        let pa_status = status(&agent.client.session, "pa").await.unwrap();
        assert!(
            pa_status.fleet.lease.is_some_and(|l| l.valid_for_seconds > 0.0),
            "pa renewed its lease"
        );
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| n >= 3)
            .await;
        moved.planner_id
    });
    eprintln!("the run moved to {new_owner}");
    ledger.check_one_owner_at_a_time();
    pa.terminate(Duration::from_secs(20)).unwrap();
    for planner in &mut others {
        planner.terminate(Duration::from_secs(20)).unwrap();
    }
    ledger.check_replay(data, run, "a");
}

/// A planner whose router link is cut sees no other planner and prefers every run, but etcd
/// names their owners: it takes none, before or after the link heals, and the agents of the
/// runs (served by the other planners) lose nothing.
#[test]
fn a_planner_cut_off_from_the_router_takes_no_run() {
    let fleet = Fleet::start("fleet-router-cut");
    let (data, etcd, endpoint, rt) = (&fleet.data, &fleet.etcd, &fleet.endpoint, &fleet.rt);
    let planner = |id: &str, router: &str| {
        fleet.planner(
            id,
            &leased_config(id, router, &etcd.endpoint, PARTITION_TTL_SECONDS),
        )
    };
    let mut planners: Vec<Guarded> = vec![planner("pa", endpoint), planner("pb", endpoint)];
    let runs = ["r0", "r1", "r2", "r3"];
    let upstream = endpoint.trim_start_matches("tcp/").parse().unwrap();
    let link = Proxy::start(upstream).unwrap();
    let mut ledgers: Vec<Ledger> = runs.iter().map(|_| Ledger::default()).collect();
    rt.block_on(async {
        let mut agents = Vec::new();
        for (i, run) in runs.iter().enumerate() {
            let (mut agent, _) = Agent::new(endpoint, run, 0, i as u32).await;
            agent
                .play(&mut ledgers[i], Duration::from_secs(20), |n| n >= 3)
                .await;
            agents.push(agent);
        }
        let session = open_session(endpoint).await.unwrap();
        let before = hosted(&session, &["pa", "pb"]).await;
        assert_eq!(before.len(), runs.len(), "{before:?}");
        // pc joins through the link, then the link is cut while every agent keeps stepping.
        let through = format!("tcp/127.0.0.1:{}", link.port);
        planners.push(planner("pc", &through));
        tokio::time::sleep(Duration::from_secs(1)).await;
        link.cut();
        let partition = Instant::now();
        let mut rounds = 0;
        // As long as three of the other tests' leases: time for pc to try many times.
        while partition.elapsed() < Duration::from_secs(3 * TTL_SECONDS) {
            for (agent, ledger) in agents.iter_mut().zip(&mut ledgers) {
                four_steps_served(agent, ledger, "during the partition", &planners).await;
            }
            rounds += 1;
        }
        assert!(rounds > 0);
        link.heal();
        tokio::time::sleep(Duration::from_secs(TTL_SECONDS)).await;
        for (agent, ledger) in agents.iter_mut().zip(&mut ledgers) {
            four_steps_served(agent, ledger, "after the partition", &planners).await;
        }
        let after = hosted(&session, &["pa", "pb", "pc"]).await;
        assert_eq!(before, after, "runs moved: {before:?} -> {after:?}");
        session.close().await.unwrap();
    });
    let pc_log = planners[2].log();
    assert!(
        !pc_log.contains("took the run"),
        "pc took a run while cut off from the router:\n{pc_log}"
    );
    for planner in &mut planners {
        planner.terminate(Duration::from_secs(20)).unwrap();
    }
    for (run, ledger) in runs.iter().zip(&ledgers) {
        ledger.check_one_owner_at_a_time();
        ledger.check_replay(data, run, "a");
    }
}

/// Plays four steps of `agent`'s run and fails, naming `when` and every planner's ownership
/// log, if they are not all answered within 20 s.
async fn four_steps_served(
    agent: &mut Agent,
    ledger: &mut Ledger,
    when: &str,
    planners: &[Guarded],
) {
    let served = agent
        .play(ledger, Duration::from_secs(20), |n| n >= 4)
        .await;
    assert!(
        served >= 4,
        "{}: not served {when}\n{}",
        agent.client.run,
        ownership_lines(planners)
    );
}

/// The lines of each planner's log that speak of ownership (runs taken, stepped down, the
/// lease), for a failure message: what tells a run taken from its holder from a lease that
/// lapsed.
fn ownership_lines(planners: &[Guarded]) -> String {
    planners
        .iter()
        .enumerate()
        .map(|(i, planner)| {
            let log = planner.log();
            let lines: Vec<&str> = log
                .lines()
                .filter(|l| {
                    ["took the run", "stepped down", "lease"]
                        .iter()
                        .any(|needle| l.contains(needle))
                })
                .collect();
            format!("planner {i}:\n{}", lines.join("\n"))
        })
        .collect::<Vec<_>>()
        .join("\n")
}

/// The resident memory of process `pid`, in KiB.
fn rss_kib(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap()
}

/// A client declares 10,000 planner tokens and lease tokens with huge epochs for a run the
/// fleet holds: the run stays with its owner, which keeps answering its attach and other
/// sessions' status queries, and the planner's view of the fleet (and its memory) stays bounded.
#[test]
fn forged_planner_and_lease_tokens_move_no_run() {
    let fleet = Fleet::start("fleet-forged");
    let (data, endpoint, rt) = (&fleet.data, &fleet.endpoint, &fleet.rt);
    let mut pa = start(&fleet, "pa");
    let run = "target";
    let mut ledger = Ledger::default();
    rt.block_on(async {
        let (mut agent, accepted) = Agent::new(endpoint, run, 0, 7).await;
        assert_eq!(accepted.planner_id, "pa");
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| n >= 5)
            .await;
        let rss_before = rss_kib(pa.pid());
        let forger = open_session(endpoint).await.unwrap();
        // The planner is asked from a session of its own: the forger's own query queues behind
        // its 20,000 declarations at the router (18 s on 2 cores busy with other work too),
        // which delays only the forger; a second session was answered within a second.
        let bystander = open_session(endpoint).await.unwrap();
        let mut tokens = Vec::new();
        for i in 0..10_000 {
            for key in [
                format!("ebmpc/alive/planners/forged-{i}"),
                format!("ebmpc/alive/leases/{run}/18446744073709551615/forged-{i}"),
            ] {
                tokens.push(forger.liveliness().declare_token(key).await.unwrap());
            }
        }
        tokio::time::sleep(Duration::from_secs(TTL_SECONDS)).await;
        let report = status(&bystander, "pa").await.unwrap();
        assert!(
            report.fleet.planners.len() <= planner_service::fleet::view::MAX_PLANNERS,
            "{} planners in the view",
            report.fleet.planners.len()
        );
        assert_eq!(
            report
                .runs
                .iter()
                .map(|r| r.name.as_str())
                .collect::<Vec<_>>(),
            [run],
            "the run stays with pa"
        );
        // The agent keeps being served, and a re-attach is answered by pa at the same token.
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| n >= 5)
            .await;
        let again = agent.client.attach(&spec()).await.unwrap();
        assert_eq!(
            (again.planner_id.as_str(), again.epoch),
            ("pa", accepted.epoch)
        );
        let rss_after = rss_kib(pa.pid());
        assert!(
            rss_after < rss_before + 64 * 1024,
            "pa grew from {rss_before} KiB to {rss_after} KiB under forged tokens"
        );
        drop(tokens);
        forger.close().await.unwrap();
        bystander.close().await.unwrap();
    });
    ledger.check_one_owner_at_a_time();
    pa.terminate(Duration::from_secs(20)).unwrap();
    ledger.check_replay(data, run, "a");
}

/// What a stale owner writes: transitions and an episode end under its old token, marked by
/// an observation no agent sends, appended to its own (old) replay segment.
fn stale_records(token: u64) -> Vec<Record> {
    let mut records: Vec<Record> = (0..3)
        .map(|step| {
            Record::Transition(TransitionRecord {
                epoch: token,
                agent: "a".into(),
                episode: STALE_EPISODE,
                step,
                obs: vec![STALE_MARK; 4],
                act: vec![0.0],
                origin: ActionOrigin::Planned,
                next_obs: vec![STALE_MARK; 4],
                reward: 1.0,
            })
        })
        .collect();
    records.push(Record::EpisodeEnd(EpisodeEndRecord {
        epoch: token,
        agent: "a".into(),
        episode: STALE_EPISODE,
        steps: 3,
        episode_return: 3.0,
        end: EpisodeEnd::TimeLimit,
    }));
    records
}

const STALE_MARK: f32 = 4242.5;
const STALE_EPISODE: u32 = 999_999;

/// The bytes a stale owner appends for `records`: framed by the replay log's own codec (a
/// scratch log in `scratch` holding them, less its file header).
fn framed(scratch: &Path, records: &[Record]) -> Vec<u8> {
    let path = scratch.join("stale-frames.log");
    let _ = std::fs::remove_file(&path);
    let mut log = ReplayLog::create_with(&path, &[], |file| -> Box<dyn LogFile> { Box::new(file) })
        .expect("a scratch log is created");
    let header = log.len_bytes() as usize;
    log.append(records).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    std::fs::remove_file(&path).unwrap();
    bytes[header..].to_vec()
}

/// Appends `frames` to `segment` as its old owner would if it had lost its lease without
/// noticing (its process paused, its clock slow): the file is its own, so it appends to its
/// end like any owner does (a writer's handle is in append mode).
fn append_as_stale_owner(segment: &Path, frames: &[u8]) -> std::io::Result<()> {
    let mut file = std::fs::OpenOptions::new().append(true).open(segment)?;
    file.write_all(frames)?;
    file.sync_data()
}

/// Appends `stale_records(token)` to `segment` as its stale owner, and checks they are in it.
fn write_as_stale_owner(scratch: &Path, segment: &Path, token: u64) {
    append_as_stale_owner(segment, &framed(scratch, &stale_records(token)))
        .expect("the stale owner appends");
    let read = ReplayLog::read(segment).unwrap();
    assert!(
        read.records
            .iter()
            .any(|r| matches!(r, Record::Transition(TransitionRecord { obs, .. }) if obs[0] == STALE_MARK)),
        "the stale records are in the old segment"
    );
}

/// Two stale owners (each a term that a newer one took over) append to their own old
/// segments after the takeover: none of it reaches the run, as read by the owners that open
/// it later and by a reader, and nothing acknowledged is lost.
#[test]
fn a_stale_writers_late_appends_never_reach_the_run() {
    let fleet = Fleet::start("fleet-stale-writer");
    let (data, endpoint, rt) = (&fleet.data, &fleet.endpoint, &fleet.rt);
    let run = "stale";
    let mut ledger = Ledger::default();
    let mut pa = start(&fleet, "pa");
    let mut pb = None;
    let mut pc = None;
    rt.block_on(async {
        let (mut agent, first) = Agent::new(endpoint, run, 0, 3).await;
        assert_eq!(first.planner_id, "pa");
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= 2 * STEPS as usize + 3
            })
            .await;
        let pa_segment = ebmpc_e2e::newest_replay_segment(data, run);
        // pa loses the run: its process stops (as if paused) and pb takes over at a newer
        // token once pa's lease expired.
        pa.signal("KILL").unwrap();
        pa.wait(Duration::from_secs(10)).unwrap();
        pb = Some(start(&fleet, "pb"));
        let second = agent.reattach().await;
        assert_eq!(second.planner_id, "pb");
        assert!(second.epoch > first.epoch);
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= STEPS as usize + 4
            })
            .await;
        // pa, stale, writes on to its segment after pb read it.
        write_as_stale_owner(fleet.dir.path(), &pa_segment, first.epoch);
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= STEPS as usize
            })
            .await;
        let pb_segment = ebmpc_e2e::newest_replay_segment(data, run);
        assert_ne!(pb_segment, pa_segment, "each term writes its own segment");
        // pb loses the run too; pc takes it over, reading both older segments.
        pb.as_mut().unwrap().signal("KILL").unwrap();
        pb.as_mut().unwrap().wait(Duration::from_secs(10)).unwrap();
        pc = Some(start(&fleet, "pc"));
        let third = agent.reattach().await;
        assert_eq!(third.planner_id, "pc");
        assert!(third.epoch > second.epoch);
        // Both stale owners write on after pc read their segments.
        write_as_stale_owner(fleet.dir.path(), &pa_segment, first.epoch);
        write_as_stale_owner(fleet.dir.path(), &pb_segment, second.epoch);
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= 2 * STEPS as usize
            })
            .await;
    });
    // pc is stopped and pa opens the run once more (a fourth term, reading all three).
    pc.as_mut()
        .unwrap()
        .terminate(Duration::from_secs(20))
        .unwrap();
    let mut pa = start(&fleet, "pa");
    rt.block_on(async {
        let (mut agent, fourth) = Agent::new(endpoint, run, 1000, 4).await;
        assert_eq!(fourth.planner_id, "pa");
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= STEPS as usize
            })
            .await;
    });
    pa.terminate(Duration::from_secs(20)).unwrap();
    let stored = check_nothing_stale_reached(&ledger, data, run, 4);
    assert!(
        stored.episodes().iter().all(|e| e.episode != STALE_EPISODE),
        "a stale owner's episode reached the run"
    );
    let segments = planner_service::replay::segments::list(&run_path(data, run)).unwrap();
    assert!(segments.len() >= 4, "one segment per term: {segments:?}");
}

/// The end of a stale-writer test: one owner at a time, more than `rounds × STEPS`
/// transitions acknowledged and every one stored, and none of the stale owner's (marked
/// `STALE_MARK`) in the run. Returns the run's stored replay.
fn check_nothing_stale_reached(
    ledger: &Ledger,
    data: &Path,
    run: &str,
    rounds: usize,
) -> ReplayBuffer {
    ledger.check_one_owner_at_a_time();
    let acknowledged = ledger.check_replay(data, run, "a");
    assert!(
        acknowledged > rounds * STEPS as usize,
        "{acknowledged} acknowledged"
    );
    let stored = ReplayBuffer::read(&run_path(data, run), Builtin::Cartpole.task()).unwrap();
    assert!(
        (0..stored.len()).all(|i| stored.transitions().row(i).0[0] != STALE_MARK),
        "a stale owner's transitions reached the run"
    );
    stored
}

/// SIGTERM to `planner` once it logged that it took a run over (and then stuck in opening
/// it): it must exit cleanly within 10 s. Returns how long it took.
fn terminate_mid_takeover(planner: &mut Guarded, name: &str) -> Duration {
    planner
        .wait_for_log("took the run", Duration::from_secs(30))
        .unwrap_or_else(|e| panic!("{name} starts taking the run over: {e}"));
    std::thread::sleep(Duration::from_millis(300));
    assert!(
        !planner.log().contains("run opened"),
        "{name}'s takeover was still under way at SIGTERM:\n{}",
        planner.log()
    );
    let term = Instant::now();
    planner.signal("TERM").unwrap();
    let status = planner
        .wait(Duration::from_secs(10))
        .unwrap_or_else(|e| panic!("{name} exits within 10 s of SIGTERM: {e}"));
    let took = term.elapsed();
    assert!(status.success(), "{name} exit: {status}\n{}", planner.log());
    assert!(took < Duration::from_secs(10), "{name} took {took:?}");
    took
}

/// A planner given SIGTERM in the middle of a takeover (its opening of the run stuck in a
/// read of the run's replay, as on a stalled mount: the newest segment is swapped for a FIFO
/// nobody writes) exits within 10 s and releases the run with its lease; both as a serving
/// planner whose steward takes a dead owner's run over, and as a planner resuming stored runs
/// at its start. Once the replay is readable again another planner owns and serves the run
/// at a newer token with nothing acknowledged lost.
#[test]
fn sigterm_in_the_middle_of_a_takeover_exits_in_time_and_the_run_moves() {
    let fleet = Fleet::start("fleet-sigterm-takeover");
    let (data, etcd, endpoint, rt) = (&fleet.data, &fleet.etcd, &fleet.endpoint, &fleet.rt);
    let run = "stuck";
    let mut ledger = Ledger::default();
    let mut pa = start(&fleet, "pa");
    let (first, episode) = rt.block_on(async {
        let (mut agent, first) = Agent::new(endpoint, run, 0, 9).await;
        assert_eq!(first.planner_id, "pa");
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= 2 * STEPS as usize + 5
            })
            .await;
        (first, agent.episode)
    });
    let mut pb = start(&fleet, "pb");
    // The owner dies, and the run's replay stalls before pb takes it over (after the TTL):
    // reading its newest segment blocks until a writer comes, which none does.
    pa.signal("KILL").unwrap();
    pa.wait(Duration::from_secs(10)).unwrap();
    let segment = ebmpc_e2e::newest_replay_segment(data, run);
    let aside = segment.with_extension("aside");
    std::fs::rename(&segment, &aside).unwrap();
    let made = std::process::Command::new("mkfifo")
        .arg(&segment)
        .status()
        .unwrap();
    assert!(made.success(), "mkfifo");
    let by_steward = terminate_mid_takeover(&mut pb, "pb (serving)");
    // A planner starting while the replay still stalls resumes the run at its start: stuck
    // the same way, and stopped the same way.
    let mut pc = ebmpc_e2e::spawn_planner(
        &fleet.dir.path().join("pc"),
        data,
        &config("pc", endpoint, &etcd.endpoint),
        None,
    )
    .unwrap();
    let at_start = terminate_mid_takeover(&mut pc, "pc (starting)");
    eprintln!(
        "SIGTERM in the middle of a takeover: exited after {by_steward:?} (serving), {at_start:?} (starting)"
    );
    // The mount recovers; another planner takes the run at once (the leases were revoked).
    std::fs::remove_file(&segment).unwrap();
    std::fs::rename(&aside, &segment).unwrap();
    let mut pd = start(&fleet, "pd");
    rt.block_on(async {
        let (mut agent, moved) = Agent::new(endpoint, run, episode + 1, 10).await;
        assert_eq!(moved.planner_id, "pd");
        assert!(moved.epoch > first.epoch);
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= STEPS as usize + 3
            })
            .await;
    });
    pd.terminate(Duration::from_secs(20)).unwrap();
    ledger.check_one_owner_at_a_time();
    ledger.check_replay(data, run, "a");
}

/// Owners SIGKILLed round after round while `[storage] replay_capacity` makes each of them
/// evict and compact the run's replay across the segments of earlier terms: every episode
/// stays accounted for, the newest episodes' acknowledged transitions are all kept, the
/// replay on disk stays bounded, and superseded segments are removed.
#[test]
fn compaction_across_takeovers_keeps_the_newest_episodes_and_bounds_the_replay() {
    const CAPACITY: usize = 40;
    let fleet = Fleet::start("fleet-compaction");
    let (data, etcd, endpoint, rt) = (&fleet.data, &fleet.etcd, &fleet.endpoint, &fleet.rt);
    let bounded = |id: &str| {
        format!(
            "{}\n[storage]\nreplay_capacity = {CAPACITY}\n",
            config(id, endpoint, &etcd.endpoint)
        )
    };
    let ids = ["pa", "pb", "pc"];
    let mut planners: BTreeMap<&str, Guarded> = ids
        .iter()
        .map(|id| (*id, fleet.planner(id, &bounded(id))))
        .collect();
    let run = "bounded";
    let mut ledger = Ledger::default();
    let mut episode = 0;
    let rounds = 5;
    for round in 0..rounds {
        let owner = rt.block_on(async {
            let (mut agent, accepted) = Agent::new(endpoint, run, episode, round).await;
            // Past the capacity every round, so each owner evicts and compacts.
            agent
                .play(&mut ledger, Duration::from_secs(20), |n| {
                    n >= 6 * STEPS as usize + 3
                })
                .await;
            planners[accepted.planner_id.as_str()]
                .signal("KILL")
                .unwrap();
            agent
                .play(&mut ledger, Duration::from_secs(2), |_| false)
                .await;
            episode = agent.episode + 1;
            accepted.planner_id
        });
        let id = ids.iter().find(|p| **p == owner).copied().unwrap();
        planners
            .get_mut(id)
            .unwrap()
            .wait(Duration::from_secs(10))
            .unwrap();
        planners.insert(id, fleet.planner(id, &bounded(id)));
    }
    // The last owner plays on: at least two whole episodes, the newest of the run.
    rt.block_on(async {
        let (mut agent, _) = Agent::new(endpoint, run, episode, 99).await;
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= 3 * STEPS as usize + 3
            })
            .await;
    });
    for planner in planners.values_mut() {
        planner.terminate(Duration::from_secs(20)).unwrap();
    }
    ledger.check_one_owner_at_a_time();
    let root = run_path(data, run);
    let stored = ReplayBuffer::read(&root, Builtin::Cartpole.task()).unwrap();
    let held = stored_keys(&stored);
    for (&episode, &ended) in &ledger.episodes {
        let records: Vec<_> = stored
            .episodes()
            .iter()
            .filter(|e| e.episode == episode)
            .collect();
        let accounted = match records.as_slice() {
            [one] => {
                one.end == EpisodeEnd::TimeLimit || (!ended && one.end == EpisodeEnd::Interrupted)
            }
            _ => false,
        };
        assert!(
            accounted,
            "episode {episode} (ended: {ended}) is recorded as {records:?}"
        );
    }
    let finished: Vec<u32> = ledger
        .episodes
        .iter()
        .filter(|(_, ended)| **ended)
        .map(|(e, _)| *e)
        .collect();
    for episode in finished.iter().rev().take(2) {
        let missing = ledger.by_episode[episode]
            .iter()
            .filter(|t| !held.contains(*t))
            .count();
        assert_eq!(
            missing, 0,
            "episode {episode}: {missing} acknowledged transitions lost"
        );
    }
    assert!(
        ledger.acknowledged.len() > 3 * CAPACITY,
        "{} acknowledged",
        ledger.acknowledged.len()
    );
    assert!(
        stored.len() <= 2 * CAPACITY + STEPS as usize,
        "{} transitions on disk: the replay was not compacted",
        stored.len()
    );
    let segments = planner_service::replay::segments::list(&root).unwrap();
    assert!(
        segments.len() < rounds as usize + 1,
        "superseded segments removed: {segments:?}"
    );
    // Every planner's log, the killed ones' too: compactions ran and removed segments.
    let mut logs = String::new();
    for id in ids {
        for entry in std::fs::read_dir(fleet.dir.path().join(id)).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "log") {
                logs.push_str(&std::fs::read_to_string(&path).unwrap());
            }
        }
    }
    let compactions = logs.matches("compacted the replay log").count();
    let removed = logs.matches("removed a superseded replay segment").count();
    eprintln!("{compactions} compactions, {removed} superseded segments removed");
    assert!(
        compactions >= 2 && removed >= 2,
        "{compactions} compactions, {removed} removed"
    );
}

/// A small tmpfs mounted over a directory for the life of the test (unmounted when dropped,
/// also on failure), so that the disk really fills up.
struct SmallDisk {
    path: PathBuf,
}

impl SmallDisk {
    /// Mounts a tmpfs of `mib` MiB at `path`. The process must be root (of the machine, or of
    /// a user namespace of its own: see [`SmallDisk::rerun_unless_root`]).
    fn mount(path: &Path, mib: u32) -> Self {
        std::fs::create_dir_all(path).unwrap();
        let mounted = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mib}m"), "ebmpc-test"])
            .arg(path)
            .status()
            .expect("`mount` runs");
        assert!(
            mounted.success(),
            "cannot mount a tmpfs at {} ({mounted}): this test fills a disk of its own and \
             needs to run as root",
            path.display()
        );
        Self {
            path: path.to_path_buf(),
        }
    }

    /// Where this process is not root, runs the test `name` (a function of this module) again
    /// as root of a user and mount namespace of its own (`unshare --user --map-root-user
    /// --mount`, open to unprivileged users on current Linux) and returns `true` once that run
    /// passed: there it may mount the tmpfs, the processes it starts see the mount, and the
    /// network is the machine's. Returns `false` where this process is root already and the
    /// test goes on here.
    fn rerun_unless_root(name: &str) -> bool {
        let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
        let effective_uid = status
            .lines()
            .find_map(|l| l.strip_prefix("Uid:"))
            .and_then(|ids| ids.split_whitespace().nth(1))
            .expect("an effective user id");
        if effective_uid == "0" {
            return false;
        }
        // libtest names a test by its path below the crate: `fleet_etcd::name`.
        let module = module_path!()
            .split_once("::")
            .map_or(module_path!(), |(_, below_crate)| below_crate);
        let test = format!("{module}::{name}");
        let rerun = std::process::Command::new("unshare")
            .args(["--user", "--map-root-user", "--mount", "--"])
            .arg(std::env::current_exe().expect("the test binary"))
            .args([test.as_str(), "--exact", "--nocapture", "--test-threads=1"])
            .output()
            .expect("`unshare` (util-linux) runs");
        let printed = format!(
            "{}{}",
            String::from_utf8_lossy(&rerun.stdout),
            String::from_utf8_lossy(&rerun.stderr)
        );
        assert!(
            rerun.status.success(),
            "{test} in a user and mount namespace of its own ({}):\n{printed}",
            rerun.status
        );
        // A filter that matched nothing passes too: the rerun must have run this very test.
        assert!(
            printed.contains("test result: ok. 1 passed"),
            "the rerun ran {test} once:\n{printed}"
        );
        true
    }

    /// Fills the disk: `filler` grows until no byte more fits. Files that end inside a
    /// page still have that page's slack to write into, as on any file system.
    fn fill(&self, filler: &Path) {
        let mut file = std::fs::File::create(filler).unwrap();
        for chunk in [1 << 20, 4096, 1] {
            let bytes = vec![0u8; chunk];
            while file.write_all(&bytes).is_ok() {}
        }
        assert!(
            std::fs::File::create(self.path.join("one-more")).is_ok_and(|mut f| f
                .write_all(&[0; 8192])
                .and_then(|()| f.sync_data())
                .is_err()),
            "the disk is full"
        );
        let _ = std::fs::remove_file(self.path.join("one-more"));
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        // Lazily: a planner killed a moment ago may still hold a file open.
        let _ = std::process::Command::new("umount")
            .arg("-l")
            .arg(&self.path)
            .status();
    }
}

/// The checkpoints of term `token` in the run's directory, with their bytes.
fn checkpoints_of(root: &Path, token: u64) -> BTreeMap<u64, Vec<u8>> {
    std::fs::read_dir(root)
        .unwrap()
        .filter_map(|entry| {
            let entry = entry.ok()?;
            let id = CheckpointId::parse(entry.file_name().to_str()?)?;
            (id.token == token).then(|| (id.version, std::fs::read(entry.path()).unwrap()))
        })
        .collect()
}

/// Waits until `planner` holds `run` with a checkpoint of its term on disk and is not
/// training (so it writes nothing of its own meanwhile); returns its models version.
async fn settled_with_a_checkpoint(
    session: &zenoh::Session,
    planner: &str,
    run: &str,
    root: &Path,
) -> u64 {
    let deadline = Instant::now() + Duration::from_secs(120);
    let mut last = None;
    loop {
        assert!(
            Instant::now() < deadline,
            "{planner} wrote no checkpoint of {run}"
        );
        tokio::time::sleep(Duration::from_millis(500)).await;
        let Ok(report) = status(session, planner).await else {
            continue;
        };
        let Some(held) = report.runs.into_iter().find(|r| r.name == run) else {
            continue;
        };
        let on_disk = checkpoints_of(root, held.epoch);
        let now = (held.models_version, held.training);
        if !held.training && on_disk.contains_key(&held.models_version) && last == Some(now) {
            return held.models_version;
        }
        last = Some(now);
    }
}

/// The shared data directory is a small disk of its own that fills up while a stale owner
/// (a term a newer owner took over, which has not noticed) keeps writing: its appends to
/// its own replay segment fail part-way, its checkpoint save and its attempt at a new
/// segment fail. None of that deletes or changes anything of the new owner's: its segment,
/// its checkpoints, and every transition it acknowledged, before the disk filled, while it
/// was full (a step is acknowledged only once stored) and after, survive into the next
/// term; the next owner resumes from the new owner's newest checkpoint.
#[test]
fn a_stale_owners_failed_writes_on_a_full_disk_delete_nothing_of_the_new_owners() {
    if SmallDisk::rerun_unless_root(
        "a_stale_owners_failed_writes_on_a_full_disk_delete_nothing_of_the_new_owners",
    ) {
        return;
    }
    let fleet = Fleet::start("fleet-full-disk");
    let (data, endpoint, rt) = (&fleet.data, &fleet.endpoint, &fleet.rt);
    let disk = SmallDisk::mount(data, 24);
    let run = "full";
    let root = run_path(data, run);
    let mut ledger = Ledger::default();
    let mut pa = start(&fleet, "pa");
    let mut pb = None;
    let (stale_token, new_token, saved_version) = rt.block_on(async {
        let (mut agent, first) = Agent::new(endpoint, run, 0, 7).await;
        assert_eq!(first.planner_id, "pa");
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= 3 * STEPS as usize + 2
            })
            .await;
        // pa loses the run (as if paused); pb takes it over at a newer token.
        pa.signal("KILL").unwrap();
        pa.wait(Duration::from_secs(10)).unwrap();
        pb = Some(start(&fleet, "pb"));
        let second = agent.reattach().await;
        assert_eq!(second.planner_id, "pb");
        assert!(second.epoch > first.epoch);
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= 3 * STEPS as usize + 2
            })
            .await;
        let session = &agent.client.session;
        let version = settled_with_a_checkpoint(session, "pb", run, &root).await;
        let pa_segment = planner_service::replay::segments::list(&root)
            .unwrap()
            .into_iter()
            .find(|id| matches!(id, SegmentId::Term { token, .. } if *token == first.epoch))
            .map(|id| root.join(id.name()))
            .expect("pa's segment");
        let pb_segment = ebmpc_e2e::newest_replay_segment(data, run);

        // The disk fills up. Everything of pb's as it is now:
        disk.fill(&data.join("filler"));
        let pb_checkpoints = checkpoints_of(&root, second.epoch);
        let pb_bytes = std::fs::read(&pb_segment).unwrap();
        assert!(pb_checkpoints.contains_key(&version));

        // pa, stale, writes on: more than its segment's last page holds, so the append
        // fails part-way (a full disk's partial write, left where it lands).
        let frames: Vec<u8> = framed(fleet.dir.path(), &stale_records(first.epoch)).repeat(40);
        let appended = append_as_stale_owner(&pa_segment, &frames);
        assert!(appended.is_err(), "the disk is full: {appended:?}");
        // Its trainer's checkpoint, many versions ahead: refused.
        let preset = Preset::new(Builtin::Cartpole.task(), Some("cem")).unwrap();
        let mut models = Models::untrained(Builtin::Cartpole.task(), &preset, 1);
        models.version = version + 100;
        let saved = RunDir::at(&root).save_models(first.epoch, &models, Builtin::Cartpole.task());
        assert!(
            matches!(saved, Err(PersistError::NewerTerm { .. })),
            "a stale checkpoint was written: {saved:?}"
        );
        // A compaction's new segment of its term: it cannot be created.
        let late = root.join(
            SegmentId::Term {
                token: first.epoch,
                seq: 1_000,
            }
            .name(),
        );
        let created = ReplayLog::create_with(
            &late,
            &stale_records(first.epoch),
            |file| -> Box<dyn LogFile> { Box::new(file) },
        );
        assert!(created.is_err(), "the disk is full");
        assert!(!late.exists());

        // pb keeps serving: it acknowledges what still fits in its segment's last page,
        // then refuses the step it cannot store (no action comes).
        let before = ledger.acknowledged.len();
        let answered = agent
            .play(&mut ledger, Duration::from_secs(5), |n| {
                n >= 20 * STEPS as usize
            })
            .await;
        assert!(
            answered < 20 * STEPS as usize,
            "pb acknowledged {answered} steps on a full disk"
        );
        eprintln!(
            "on the full disk pb acknowledged {} transitions, then refused a step",
            ledger.acknowledged.len() - before
        );
        assert_eq!(
            checkpoints_of(&root, second.epoch),
            pb_checkpoints,
            "pb's checkpoints are untouched"
        );
        let now = std::fs::read(&pb_segment).unwrap();
        assert_eq!(
            &now[..pb_bytes.len()],
            pb_bytes.as_slice(),
            "pb's segment is unchanged up to where it was"
        );

        // Space returns; the agent attaches again (its refused step left the episode open)
        // and pb acknowledges again.
        std::fs::remove_file(data.join("filler")).unwrap();
        let again = agent.reattach().await;
        assert_eq!(
            (again.planner_id.as_str(), again.epoch),
            ("pb", second.epoch)
        );
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= 2 * STEPS as usize
            })
            .await;
        (first.epoch, second.epoch, version)
    });
    // pb stops; pc opens the run, from pb's checkpoints and everything pb acknowledged.
    pb.as_mut()
        .unwrap()
        .terminate(Duration::from_secs(20))
        .unwrap();
    let newest_of_pb = *checkpoints_of(&root, new_token)
        .keys()
        .max()
        .expect("pb's checkpoints survive");
    assert!(newest_of_pb >= saved_version);
    let stale_save = CheckpointId {
        token: stale_token,
        version: saved_version + 100,
    };
    assert!(!root.join(stale_save.file_name()).exists());
    let mut pc = start(&fleet, "pc");
    rt.block_on(async {
        let (mut agent, third) = Agent::new(endpoint, run, 1000, 8).await;
        assert_eq!(third.planner_id, "pc");
        assert!(third.epoch > new_token);
        let report = status(&agent.client.session, "pc").await.unwrap();
        let held = report.runs.iter().find(|r| r.name == run).unwrap();
        // pc opened the run at pb's newest version; it may have retrained once since, on the
        // transitions pb stored after that checkpoint (a fresh start would be at 0 or 1).
        assert!(
            (newest_of_pb..=newest_of_pb + 1).contains(&held.models_version),
            "pc resumed from pb's newest checkpoint {newest_of_pb}: at {}",
            held.models_version
        );
        agent
            .play(&mut ledger, Duration::from_secs(20), |n| {
                n >= STEPS as usize
            })
            .await;
    });
    pc.terminate(Duration::from_secs(20)).unwrap();
    check_nothing_stale_reached(&ledger, data, run, 6);
}
