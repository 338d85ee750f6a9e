//! Messages no one can read never reach a run, and never stop the agent whose name they use:
//! while an honest agent plays an episode, a hostile process sends observations over
//! `[limits] max_payload_bytes` (under its own name, and under the honest agent's name with the
//! honest agent's session token) and undecodable bytes on the honest agent's key. Each is
//! refused on the key's error key with an error that names the limit (or says what is
//! malformed) and carries no session ([`NO_SESSION`]); the honest agent, which treats any
//! report about its session as fatal, steps on undisturbed, its episode is stored, nothing of
//! the hostile messages is, and a message far over the limit (dropped by the transport) leaves
//! the daemon serving.

use ebmpc_e2e::client::{Client, ToySystem, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{Builtin, Encoding, EpisodeEnd, ErrorCode, NO_SESSION, Observation, RunSpec};
use std::time::Duration;

const PLANNER: &str = "hostile-payload";
const RUN: &str = "honest";
const STEPS: u32 = 9;
/// `[limits] max_payload_bytes` by default.
const LIMIT: usize = 64 << 10;

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

/// A well-formed observation of `floats` values in session `token`, postcard-encoded.
fn observation_of(floats: usize, token: u64) -> Vec<u8> {
    let obs = Observation::new(0, 1, vec![0.5; floats], Some(1.0), None).in_session(token);
    proto::encode(&obs, Encoding::Postcard).unwrap()
}

#[test]
fn oversized_and_undecodable_messages_are_refused_and_never_disturb_the_honest_agent() {
    let dir = TempDir::new("hostile-payload");
    let config = PlannerConfig::new(PLANNER, Sizes::TINY)
        .exploration_episodes(5)
        .toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    let sent = runtime().block_on(async {
        let honest = Client::connect(&planner.endpoint, RUN, "g").await.unwrap();
        honest.attach(&spec()).await.unwrap();
        let token = honest.session_token();
        // The hostile process: under a name of its own, and posing as the honest agent (it
        // hears that name's error key). It never attaches.
        let own = Client::connect(&planner.endpoint, RUN, "h").await.unwrap();
        let posing = Client::connect(&planner.endpoint, RUN, "g").await.unwrap();
        // Just over the limit: it arrives (Zenoh's own bound has headroom) and is refused.
        let oversized = observation_of(20_000, token);
        assert!(oversized.len() > LIMIT && oversized.len() < 2 * LIMIT);
        let mime = Encoding::Postcard.mime();

        let mut system = ToySystem::new(3);
        let mut sent = vec![system.state[0]];
        let first = Observation::new(0, 0, system.state.to_vec(), None, None);
        let mut action = honest.step(&first).await.unwrap().action;
        for step in 1..=STEPS {
            let (sender, bytes, code) = match step % 3 {
                0 => (&own, oversized.clone(), ErrorCode::Refused),
                1 => (&posing, oversized.clone(), ErrorCode::Refused),
                _ => (&posing, vec![0xff; 40], ErrorCode::Malformed),
            };
            sender.send_raw(RUN, bytes, mime).await.unwrap();
            let report = sender.next_error_any().await.unwrap();
            assert_eq!(report.code, code, "step {step}: {report}");
            assert_eq!(report.session, Some(NO_SESSION), "step {step}: {report}");
            if code == ErrorCode::Refused {
                let limit = format!("limit of {LIMIT} bytes ([limits] max_payload_bytes)");
                assert!(report.message.contains(&limit), "{report}");
                let size = format!("a message of {} bytes", oversized.len());
                assert!(report.message.contains(&size), "{report}");
            }
            // The honest agent's step is answered as if nothing happened (a report reaching
            // it would fail the step).
            let reward = system.step(&action);
            sent.push(system.state[0]);
            let end = (step == STEPS).then_some(EpisodeEnd::TimeLimit);
            let msg = Observation::new(0, step, system.state.to_vec(), Some(reward), end);
            if end.is_some() {
                honest.send(&msg).await.unwrap();
            } else {
                action = honest.step(&msg).await.unwrap().action;
            }
        }
        // Far over the limit: the transport drops it; the daemon serves on.
        own.send_raw(RUN, observation_of(1 << 20, token), mime)
            .await
            .unwrap();
        let next = Observation::new(1, 0, ToySystem::new(4).state.to_vec(), None, None);
        honest.step(&next).await.unwrap();
        for _ in 0..300 {
            if status(&honest.session, PLANNER).await.unwrap().runs[0].episodes == 1 {
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        for client in [honest, own, posing] {
            client.close().await.unwrap();
        }
        sent
    });
    planner.stop().unwrap();

    // The honest agent's episode is stored whole, and nothing else is.
    let replay = planner.replay(RUN, Builtin::Cartpole).unwrap();
    let stored: Vec<f32> = (0..replay.len())
        .map(|i| replay.transitions().row(i).2[0])
        .collect();
    assert_eq!(
        stored,
        sent[1..],
        "the stored next states are the honest agent's"
    );
    let episodes: Vec<_> = replay
        .episodes()
        .iter()
        .map(|e| (e.episode, e.steps, e.end))
        .collect();
    // Episode 1 was left after its first step when the agent closed.
    let finished = (0, STEPS, EpisodeEnd::TimeLimit);
    assert_eq!(episodes, [finished, (1, 0, EpisodeEnd::Interrupted)]);
    let runs: Vec<_> = std::fs::read_dir(planner.data_dir.join("runs"))
        .unwrap()
        .map(|entry| entry.unwrap().file_name())
        .collect();
    assert_eq!(runs, [RUN], "no run of the hostile messages");
}
