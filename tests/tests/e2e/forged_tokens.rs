//! A planner alone (no `[fleet]` configured) never acts on liveliness tokens a client can
//! declare: a forged lease of run `forge` at the highest epoch under another planner's id, and
//! 2,000 forged planner tokens, change nothing. The agent stepping on `forge` keeps getting
//! every action, a new agent's attach to `forge` is accepted, a new run opens, and the daemon's
//! memory stays flat.

use ebmpc_e2e::client::{Client, ToySystem, open_session, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{Builtin, Keys, Observation, RunSpec};
use std::time::Duration;

/// Forged planner tokens: far more than any fleet has planners.
const FORGED_PLANNERS: usize = 2_000;

/// Steps the agent plays before and after the tokens appear (all exploration: cheap).
const STEPS: u32 = 20;

/// Most the daemon's resident memory may grow while the tokens are declared and the agents
/// keep stepping: room for allocator noise and one more run, far below what acting on 2,000
/// planners (a pins query each) or a handover would cost.
const RSS_SLACK_KIB: u64 = 48 * 1024;

fn spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: Some("cem".into()),
        overrides: Default::default(),
        mode: Default::default(),
        seed: 1,
        task_spec: None,
    }
}

/// Resident memory of process `pid`, in KiB.
fn rss_kib(pid: u32) -> u64 {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("/proc status");
    text.lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .expect("VmRSS")
}

/// Plays steps `from..from + STEPS` of episode 0 and returns how many were answered.
async fn play(client: &Client, system: &mut ToySystem, from: u32) -> u32 {
    let token = client.session_token();
    let mut answered = 0;
    // The reward of the transition into step `from` (any finite value: the toy system's own
    // was spent by the previous call).
    let mut reward = (from > 0).then_some(0.0);
    for step in from..from + STEPS {
        let obs = Observation::new(0, step, system.state.to_vec(), reward, None).in_session(token);
        match client.step(&obs).await {
            Ok(action) => {
                answered += 1;
                reward = Some(system.step(&action.action));
            }
            Err(e) => {
                eprintln!("step {step}: {e}");
                break;
            }
        }
    }
    answered
}

#[test]
fn forged_lease_and_planner_tokens_change_nothing_for_a_planner_alone() {
    let dir = TempDir::new("forged-tokens");
    let config = PlannerConfig::new("solo", Sizes::TINY).toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    let endpoint = planner.endpoint.clone();
    let pid = planner.process.pid();
    runtime().block_on(async {
        let agent = Client::connect(&endpoint, "forge", "a").await.unwrap();
        agent.attach(&spec()).await.unwrap();
        let mut system = ToySystem::new(1);
        assert_eq!(
            play(&agent, &mut system, 0).await,
            STEPS,
            "before the forgery"
        );
        let before = rss_kib(pid);

        // Another client declares what a planner would: a lease of `forge` at the highest
        // epoch under another planner's id, and thousands of planners.
        let intruder = open_session(&endpoint).await.unwrap();
        let keys = Keys::default();
        let mut tokens = vec![
            intruder
                .liveliness()
                .declare_token(keys.run_lease("forge", u64::MAX, "intruder"))
                .await
                .unwrap(),
        ];
        for i in 0..FORGED_PLANNERS {
            tokens.push(
                intruder
                    .liveliness()
                    .declare_token(keys.planner_alive(&format!("forged-{i}")))
                    .await
                    .unwrap(),
            );
        }
        // Give the tokens time to reach the daemon (and a fleet member time to act on them).
        tokio::time::sleep(Duration::from_secs(3)).await;

        assert_eq!(
            play(&agent, &mut system, STEPS).await,
            STEPS,
            "every observation is answered after the forgery"
        );
        let second = Client::connect(&endpoint, "forge", "b").await.unwrap();
        let accepted = second
            .attach(&spec())
            .await
            .expect("a new attach to `forge`");
        assert_eq!(accepted.planner_id, "solo");
        let other = Client::connect(&endpoint, "forge-2", "c").await.unwrap();
        other.attach(&spec()).await.expect("a new run opens");
        let mut second_system = ToySystem::new(2);
        assert_eq!(play(&second, &mut second_system, 0).await, STEPS);

        let report = status(&agent.session, "solo").await.unwrap();
        assert_eq!(
            report.fleet.planners,
            vec!["solo".to_string()],
            "a planner alone sees no other planner"
        );
        let forge = report.runs.iter().find(|r| r.name == "forge").unwrap();
        assert_eq!(forge.epoch, 1, "the run was never taken over");

        let after = rss_kib(pid);
        assert!(
            after <= before + RSS_SLACK_KIB,
            "resident memory grew from {before} KiB to {after} KiB"
        );
        drop(tokens);
        intruder.close().await.unwrap();
    });
    planner.stop().unwrap();
}
