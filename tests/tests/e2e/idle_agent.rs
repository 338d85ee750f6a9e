//! An agent that went silent without a liveliness token (its deletion never reached the
//! planner) does not keep its slot for ever: after `[limits] agent_idle_seconds` its session is
//! closed and another agent can take the run's last slot.

use ebmpc_e2e::client::{Client, runtime};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{AttachOutcome, AttachRequest, Builtin, Encoding, PROTOCOL_VERSION, RunSpec};
use std::time::Duration;

fn spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: None,
        overrides: Default::default(),
        mode: Default::default(),
        seed: 6,
        task_spec: None,
    }
}

#[test]
fn an_idle_agent_without_a_token_frees_its_slot() {
    let dir = TempDir::new("idle-agent");
    let config = PlannerConfig::new("idle", Sizes::TINY)
        .line("max_agents_per_run = 1")
        .toml()
        + "[limits]\nagent_idle_seconds = 2\n";
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    runtime().block_on(async {
        // "ghost" attaches from a session whose liveliness token names another agent: the
        // planner never sees a token for it, as after a crash whose deletion was lost.
        let carrier = Client::connect(&planner.endpoint, "idle", "carrier")
            .await
            .unwrap();
        let request = AttachRequest {
            version: PROTOCOL_VERSION,
            agent: "ghost".into(),
            spec: spec(),
            session: None,
        };
        let bytes = proto::encode(&request, Encoding::Postcard).unwrap();
        let reply = carrier
            .attach_raw("idle", bytes, Encoding::Postcard.mime())
            .await
            .unwrap();
        assert!(
            matches!(reply.outcome, AttachOutcome::Accepted(_)),
            "{reply:?}"
        );
        // The run's only slot is taken until the ghost's session is closed.
        let real = Client::connect(&planner.endpoint, "idle", "real")
            .await
            .unwrap();
        let mut attached = None;
        for _ in 0..60 {
            match real.attach(&spec()).await {
                Ok(accepted) => {
                    attached = Some(accepted);
                    break;
                }
                Err(e) => {
                    assert!(e.to_string().contains("limit of 1 agents"), "{e}");
                    tokio::time::sleep(Duration::from_millis(500)).await;
                }
            }
        }
        assert!(attached.is_some(), "the ghost kept the slot");
        real.close().await.unwrap();
        carrier.close().await.unwrap();
    });
    assert!(
        planner
            .process
            .log()
            .contains("agent idle without a liveliness token"),
        "{}",
        planner.process.log()
    );
    planner.stop().unwrap();
}
