//! Observations and attaches put on wildcard key expressions are dropped unanswered: an answer
//! could only go to the key the sender chose, which matches every agent under it, so each of
//! them would receive an `unknown_run` / `not_attached` report it did not cause. Two bystander
//! agents (one on another run) receive nothing from them, the drops are counted in the status
//! report, and both bystanders are served as before.

use ebmpc_e2e::client::{Client, open_session, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{AttachRequest, Builtin, Encoding, Observation, PROTOCOL_VERSION, RunSpec};
use std::time::Duration;

const PLANNER: &str = "wildcards";

fn spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: None,
        overrides: Default::default(),
        mode: Default::default(),
        seed: 4,
        task_spec: None,
    }
}

/// Observation keys with wildcards, each of which matches the bystanders' own keys.
const WILD_OBS: [&str; 5] = [
    "ebmpc/runs/*/agents/*/obs",
    "ebmpc/runs/legit/agents/*/obs",
    "ebmpc/runs/*/agents/b/obs",
    "ebmpc/runs/legit/agents/**/obs",
    "ebmpc/runs/leg$*/agents/b/obs",
];

/// Attach query keys with wildcards, each of which reaches the planner's attach queryable.
const WILD_ATTACH: [&str; 3] = [
    "ebmpc/runs/*/attach",
    "ebmpc/**/attach",
    "ebmpc/runs/l$*/attach",
];

#[test]
fn wildcard_keys_reach_no_bystander() {
    let dir = TempDir::new("wildcard-keys");
    let config = PlannerConfig::new(PLANNER, Sizes::TINY)
        .exploration_episodes(1)
        .toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    runtime().block_on(async {
        let bystander = Client::connect(&planner.endpoint, "legit", "b")
            .await
            .unwrap();
        bystander.attach(&spec()).await.unwrap();
        let other = Client::connect(&planner.endpoint, "other", "b")
            .await
            .unwrap();
        other.attach(&spec()).await.unwrap();
        let first = Observation::new(0, 0, vec![0.0; 4], None, None);
        bystander.step(&first).await.unwrap();
        other.step(&first).await.unwrap();

        let hostile = open_session(&planner.endpoint).await.unwrap();
        // Give the planner's subscriber a moment to match the new session's publications.
        tokio::time::sleep(Duration::from_millis(300)).await;
        let observation = Observation::new(0, 1, vec![0.0; 4], Some(0.0), None);
        for (key, encoding) in WILD_OBS
            .iter()
            .flat_map(|k| [(k, Encoding::Postcard), (k, Encoding::Json)])
        {
            hostile
                .put(*key, proto::encode(&observation, encoding).unwrap())
                .encoding(zenoh::bytes::Encoding::from(encoding.mime()))
                .await
                .unwrap();
        }
        let request = AttachRequest {
            version: PROTOCOL_VERSION,
            agent: "b".into(),
            spec: spec(),
            session: None,
        };
        for key in WILD_ATTACH {
            let replies = hostile
                .get(key)
                .payload(proto::encode(&request, Encoding::Postcard).unwrap())
                .timeout(Duration::from_secs(10))
                .await
                .unwrap();
            assert!(
                replies.recv_async().await.is_err(),
                "an attach on `{key}` was answered"
            );
        }

        // Once the planner has counted every drop, nothing has reached either bystander.
        let expected = (2 * WILD_OBS.len() + WILD_ATTACH.len()) as u64;
        let mut dropped = 0;
        for _ in 0..120 {
            dropped = status(&hostile, PLANNER).await.unwrap().wildcards_dropped;
            if dropped >= expected {
                break;
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
        assert_eq!(
            dropped, expected,
            "every wildcard message is counted as dropped"
        );
        tokio::time::sleep(Duration::from_secs(1)).await;
        for client in [&bystander, &other] {
            let pending = client.take_pending().unwrap();
            assert!(
                pending.is_empty(),
                "{}/{} received answers it did not cause: {pending:?}",
                client.run,
                client.agent
            );
        }
        // Neither bystander's episode moved: its own step 1 is answered with an action.
        for client in [&bystander, &other] {
            let action = client.step(&observation).await.unwrap();
            assert_eq!((action.episode, action.step), (0, 1));
        }
        // Nothing was stored from the hostile session: one transition each (step 0 → 1).
        let status = status(&hostile, PLANNER).await.unwrap();
        for run in &status.runs {
            assert_eq!(run.transitions, 1, "{}: {run:?}", run.name);
        }
        hostile.close().await.unwrap();
        bystander.close().await.unwrap();
        other.close().await.unwrap();
    });
    let log = planner.process.log();
    assert!(log.contains("wildcard key"), "drops are logged:\n{log}");
    planner.stop().unwrap();
}
