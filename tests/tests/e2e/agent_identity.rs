//! No one can take a live agent's place: attach hands out a session token that every
//! observation must carry. Someone else attaching under a live agent's name is refused (the
//! refusal names the agent), observations with a wrong, missing or hostile token are refused
//! with `ErrorCode::Session` and never touch the live agent's episode, the live agent reconnects
//! with its own token, an agent whose attach answer was lost asks again and is let in (on its
//! first attach too), and a vanished agent's name can be attached again.

use ebmpc_e2e::client::{Client, ToySystem, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{
    AttachOutcome, AttachRequest, Builtin, Encoding, EpisodeEnd, ErrorCode, Observation,
    PROTOCOL_VERSION, RunSpec,
};
use std::time::Duration;

const RUN: &str = "identity";
const AGENT: &str = "a";
const STEPS: u32 = 12;

fn spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: None,
        overrides: Default::default(),
        mode: Default::default(),
        seed: 11,
        task_spec: None,
    }
}

fn start(dir: &TempDir) -> Planner {
    let config = PlannerConfig::new(RUN, Sizes::TINY).toml();
    Planner::start(dir.path(), &config).expect("planner starts")
}

/// An attach request under `AGENT` presenting `session`, postcard-encoded.
fn attach_request(session: Option<u64>) -> Vec<u8> {
    let request = AttachRequest {
        version: PROTOCOL_VERSION,
        agent: AGENT.into(),
        spec: spec(),
        session,
    };
    proto::encode(&request, Encoding::Postcard).unwrap()
}

#[test]
fn an_impostor_is_refused_and_the_live_agent_steps_on_undisturbed() {
    let dir = TempDir::new("identity-impostor");
    let mut planner = start(&dir);
    runtime().block_on(async {
        let live = Client::connect(&planner.endpoint, RUN, AGENT).await.unwrap();
        let accepted = live.attach(&spec()).await.unwrap();
        let token = accepted.session;
        assert_ne!(token, 0, "a session token is never 0");
        let episode = accepted.next_episode;
        let mut system = ToySystem::new(1);
        let first = Observation::new(episode, 0, system.state.to_vec(), None, None);
        let mut action = live.step(&first).await.unwrap();

        // Another process under the same name (it even holds a liveliness token for it).
        let impostor = Client::connect(&planner.endpoint, RUN, AGENT).await.unwrap();
        let refused = impostor.attach(&spec()).await.unwrap_err().to_string();
        assert!(
            refused.contains("agent `a` is attached to run `identity` and live"),
            "{refused}"
        );
        // Guessed tokens do not make it the agent either.
        for guess in [0, 1, u64::MAX, token ^ 0x5a5a_5a5a, rand::random()] {
            let reply = impostor
                .attach_raw(RUN, attach_request(Some(guess)), Encoding::Postcard.mime())
                .await
                .unwrap();
            assert!(
                matches!(&reply.outcome, AttachOutcome::Rejected(r) if r.message.contains("and live")),
                "token {guess}: {reply:?}"
            );
        }

        for step in 1..=STEPS {
            let reward = system.step(&action.action);
            let end = (step == STEPS).then_some(EpisodeEnd::TimeLimit);
            let msg = Observation::new(episode, step, system.state.to_vec(), Some(reward), end);
            // Before every step of the live agent, the impostor sends that very step with a
            // hostile token: 0 (none), u64::MAX, a random one, one next to the real token.
            let guess = match step % 4 {
                0 => 0,
                1 => u64::MAX,
                2 => rand::random::<u64>() | 1,
                _ => token.wrapping_add(1),
            };
            let forged = msg.clone().in_session(guess);
            impostor
                .send_raw(
                    RUN,
                    proto::encode(&forged, Encoding::Postcard).unwrap(),
                    Encoding::Postcard.mime(),
                )
                .await
                .unwrap();
            let report = impostor.next_error_any().await.unwrap();
            assert_eq!(report.code, ErrorCode::Session, "{report}");
            assert_eq!(report.session, Some(guess));
            assert_eq!((report.episode, report.step), (Some(episode), Some(step)));
            if end.is_some() {
                live.send(&msg).await.unwrap();
            } else {
                // The live agent's step is answered as if nothing happened: it was not taken
                // as a duplicate, and no report about the impostor reached the live agent.
                action = live.step(&msg).await.unwrap();
            }
        }
        // A JSON observation without any token is refused the same way.
        let json = format!(
            r#"{{"version":{PROTOCOL_VERSION},"episode":{},"step":0,"obs":[0,0,0,0]}}"#,
            episode + 1
        );
        impostor
            .send_raw(RUN, json.into_bytes(), Encoding::Json.mime())
            .await
            .unwrap();
        let report = impostor.next_error_any().await.unwrap();
        assert_eq!((report.code, report.session), (ErrorCode::Session, Some(0)));

        // Every step of the live agent's episode is stored: it finished with all its steps.
        let mut stored = 0;
        for _ in 0..100 {
            let report = status(&live.session, RUN).await.unwrap();
            stored = report.runs[0].transitions;
            if stored == STEPS as usize {
                break;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        assert_eq!(stored, STEPS as usize);
        let report = status(&live.session, RUN).await.unwrap();
        assert_eq!(report.runs[0].episodes, 1);
        assert_eq!(report.runs[0].agents, [AGENT]);

        // The live agent reconnects with its token: a new session, and the old token is dead.
        let again = live.attach(&spec()).await.unwrap();
        assert_ne!(again.session, token);
        let stale = Observation::new(again.next_episode, 0, vec![0.0; 4], None, None)
            .in_session(token);
        live.send_raw(
            RUN,
            proto::encode(&stale, Encoding::Postcard).unwrap(),
            Encoding::Postcard.mime(),
        )
        .await
        .unwrap();
        // The name's error key carries the impostor's refusals too: skip to the one about
        // the old token.
        let report = loop {
            let report = live.next_error_any().await.unwrap();
            if report.session == Some(token) {
                break report;
            }
            assert_eq!(report.code, ErrorCode::Session, "{report}");
        };
        assert_eq!(report.code, ErrorCode::Session, "{report}");
        let first = Observation::new(again.next_episode, 0, vec![0.0; 4], None, None);
        live.step(&first).await.unwrap();
        impostor.close().await.unwrap();
        live.close().await.unwrap();
    });
    planner.stop().unwrap();
}

#[test]
fn a_vanished_agents_name_can_be_attached_again() {
    let dir = TempDir::new("identity-vanished");
    let mut planner = start(&dir);
    runtime().block_on(async {
        let first = Client::connect(&planner.endpoint, RUN, AGENT)
            .await
            .unwrap();
        let accepted = first.attach(&spec()).await.unwrap();
        let state = ToySystem::new(2).state.to_vec();
        let obs = Observation::new(accepted.next_episode, 0, state.clone(), None, None);
        first.step(&obs).await.unwrap();
        // The process dies: its liveliness token goes with its session.
        first.close().await.unwrap();

        let successor = Client::connect(&planner.endpoint, RUN, AGENT)
            .await
            .unwrap();
        let mut attached = None;
        for _ in 0..100 {
            match successor.attach(&spec()).await {
                Ok(accepted) => {
                    attached = Some(accepted);
                    break;
                }
                // Until the token's deletion reaches the planner, the name is live.
                Err(e) => {
                    assert!(e.to_string().contains("and live"), "{e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                }
            }
        }
        let attached = attached.expect("the vanished agent's name was never freed");
        assert_ne!(attached.session, accepted.session);
        let obs = Observation::new(attached.next_episode, 0, state, None, None);
        successor.step(&obs).await.unwrap();
        successor.close().await.unwrap();
    });
    planner.stop().unwrap();
}

#[test]
fn an_agent_whose_attach_answer_was_lost_asks_again_with_its_old_token() {
    let dir = TempDir::new("identity-lost-answer");
    let mut planner = start(&dir);
    runtime().block_on(async {
        let agent = Client::connect(&planner.endpoint, RUN, AGENT)
            .await
            .unwrap();
        let old = agent.attach(&spec()).await.unwrap().session;
        let accepted = |reply: proto::AttachReply| match reply.outcome {
            AttachOutcome::Accepted(accepted) => accepted.session,
            AttachOutcome::Rejected(report) => panic!("refused: {report}"),
        };
        // The agent reconnects with its token, but the answer (a new session) never reaches
        // it: its query timed out while the planner was still taking the run over, say.
        let lost = accepted(
            agent
                .attach_raw(RUN, attach_request(Some(old)), Encoding::Postcard.mime())
                .await
                .unwrap(),
        );
        assert_ne!(lost, old);
        // It asks again with the token it has: that is the agent, let in again.
        let again = agent.attach(&spec()).await.unwrap();
        assert!(again.session != old && again.session != lost);
        // The lost session's token is dead, and it is no key to the name either.
        let reply = agent
            .attach_raw(RUN, attach_request(Some(lost)), Encoding::Postcard.mime())
            .await
            .unwrap();
        assert!(
            matches!(&reply.outcome, AttachOutcome::Rejected(r) if r.message.contains("and live")),
            "{reply:?}"
        );
        let obs = Observation::new(
            again.next_episode,
            0,
            ToySystem::new(3).state.to_vec(),
            None,
            None,
        );
        agent.step(&obs).await.unwrap();
        agent.close().await.unwrap();
    });
    planner.stop().unwrap();
}

#[test]
fn a_new_agent_whose_first_attach_answer_was_lost_asks_again_and_is_let_in() {
    let dir = TempDir::new("identity-lost-first-answer");
    let mut planner = start(&dir);
    runtime().block_on(async {
        let agent = Client::connect(&planner.endpoint, RUN, AGENT)
            .await
            .unwrap();
        // Its first attach is accepted, but the answer never reaches it (the query timed out
        // while the planner was still opening the run, say): the planner holds a live session
        // under its name whose token the agent does not know.
        let first = agent.attach_request(&spec());
        assert!(
            first.session.is_some_and(|t| t != 0),
            "a first attach presents a drawn token: {first:?}"
        );
        let payload = proto::encode(&first, Encoding::Postcard).unwrap();
        let reply = agent
            .attach_raw(RUN, payload, Encoding::Postcard.mime())
            .await
            .unwrap();
        let lost = match reply.outcome {
            AttachOutcome::Accepted(accepted) => accepted.session,
            AttachOutcome::Rejected(report) => panic!("refused: {report}"),
        };
        // Without a token nothing tells the agent from an impostor: refused.
        let reply = agent
            .attach_raw(RUN, attach_request(None), Encoding::Postcard.mime())
            .await
            .unwrap();
        assert!(
            matches!(&reply.outcome, AttachOutcome::Rejected(r) if r.message.contains("and live")),
            "{reply:?}"
        );
        // Another process under the name draws a token of its own: refused.
        let impostor = Client::connect(&planner.endpoint, RUN, AGENT).await.unwrap();
        let refused = impostor.attach(&spec()).await.unwrap_err().to_string();
        assert!(refused.contains("and live"), "{refused}");
        // The agent asks again as it asked the first time: that is the agent, let in.
        let again = agent.attach(&spec()).await.unwrap();
        assert_ne!(again.session, lost);
        let obs = Observation::new(
            again.next_episode,
            0,
            ToySystem::new(4).state.to_vec(),
            None,
            None,
        );
        agent.step(&obs).await.unwrap();

        // The no-session token 0 is no claim (anyone can present it): a careless client that
        // attached with it is not taken over by the next one that does.
        let zero = AttachRequest {
            agent: "careless".into(),
            session: Some(proto::NO_SESSION),
            ..first
        };
        let zero = proto::encode(&zero, Encoding::Postcard).unwrap();
        let careless = Client::connect(&planner.endpoint, RUN, "careless")
            .await
            .unwrap();
        let replies = [
            careless
                .attach_raw(RUN, zero.clone(), Encoding::Postcard.mime())
                .await
                .unwrap(),
            impostor
                .attach_raw(RUN, zero, Encoding::Postcard.mime())
                .await
                .unwrap(),
        ];
        assert!(
            matches!(&replies[0].outcome, AttachOutcome::Accepted(_)),
            "{replies:?}"
        );
        assert!(
            matches!(&replies[1].outcome, AttachOutcome::Rejected(r) if r.message.contains("and live")),
            "{replies:?}"
        );
        careless.close().await.unwrap();
        agent.close().await.unwrap();
        impostor.close().await.unwrap();
    });
    planner.stop().unwrap();
}
