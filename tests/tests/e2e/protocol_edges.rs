//! The edges of the protocol a careless or hostile agent reaches: the last step of an episode
//! must end it (and the error says what to send), a field a message does not have is refused
//! by name in every message type, and refused attaches keep nothing (10,000 of them with
//! distinct task specs leave every task slot free).

use ebmpc_e2e::client::{Answer, Client, ToySystem, runtime, status};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{
    AttachOutcome, AttachRequest, Builtin, Encoding, EpisodeEnd, ErrorCode, Observation,
    PROTOCOL_VERSION, PlannerOverrides, RunEventKind, RunSpec, TaskSpec, TrainMode,
};
use std::sync::Arc;
use std::time::{Duration, Instant};

fn cartpole(mode: TrainMode) -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: Some("cem".into()),
        overrides: Default::default(),
        mode,
        seed: 1,
        task_spec: None,
    }
}

/// The next answer, which must be an error report; returns it.
async fn refused(client: &Client, obs: &Observation) -> proto::ErrorReport {
    client.send(obs).await.unwrap();
    match client.answer(Duration::from_secs(60)).await.unwrap() {
        Answer::Error(report) => report,
        Answer::Action(a) => panic!("step {} answered with an action: {a:?}", obs.step),
    }
}

/// Cartpole's 200 steps: steps 0–199, then step 200 without `end` is refused and says to send
/// it again with `end`; step 201 is refused and says the same; step 200 with `end` ends the
/// episode: it is published, counted by `status` with its 200 transitions, and the agent's
/// next episode starts once the sync run's models are in.
#[test]
fn the_last_step_must_end_the_episode_and_the_agent_is_told_what_to_send() {
    let dir = TempDir::new("episode-length");
    let config = PlannerConfig::new("edges", Sizes::TINY)
        .exploration_episodes(1)
        .toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    runtime().block_on(async {
        let client = Client::connect(&planner.endpoint, "len", "a")
            .await
            .unwrap();
        client.attach(&cartpole(TrainMode::Sync)).await.unwrap();
        let token = client.session_token();
        let obs = |step: u32, reward: Option<f32>, end: Option<EpisodeEnd>, x: &[f32; 4]| {
            Observation::new(0, step, x.to_vec(), reward, end).in_session(token)
        };
        let mut system = ToySystem::new(1);
        let mut reward = None;
        for step in 0..200 {
            let action = client
                .step(&obs(step, reward, None, &system.state))
                .await
                .unwrap();
            reward = Some(system.step(&action.action));
        }
        let state = system.state;
        let report = refused(&client, &obs(200, reward, None, &state)).await;
        assert_eq!(report.code, ErrorCode::OutOfOrder);
        assert_eq!((report.episode, report.step), (Some(0), Some(200)));
        assert!(
            report
                .message
                .contains("send step 200 of episode 0 again with `end` set"),
            "{report}"
        );
        for end in [None, Some(EpisodeEnd::TimeLimit)] {
            let report = refused(&client, &obs(201, reward, end, &state)).await;
            assert_eq!(report.code, ErrorCode::OutOfOrder);
            assert!(
                report
                    .message
                    .contains("beyond this task's episode length of 200")
                    && report
                        .message
                        .contains("send step 200 of episode 0 with `end` set"),
                "{report}"
            );
        }
        client
            .send(&obs(200, reward, Some(EpisodeEnd::TimeLimit), &state))
            .await
            .unwrap();
        let started = Instant::now();
        let finished = loop {
            let events = client.drain_events().unwrap();
            if let Some(steps) = events.iter().find_map(|e| match &e.kind {
                RunEventKind::EpisodeFinished { steps, end, .. } => {
                    assert_eq!(*end, EpisodeEnd::TimeLimit);
                    Some(*steps)
                }
                _ => None,
            }) {
                break steps;
            }
            assert!(
                started.elapsed() < Duration::from_secs(60),
                "no EpisodeFinished"
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        };
        assert_eq!(finished, 200);
        let report = status(&client.session, "edges").await.unwrap();
        let run = report.runs.iter().find(|r| r.name == "len").unwrap();
        assert_eq!((run.episodes, run.transitions), (1, 200));
        // The next episode starts (a sync run: once the models trained on episode 0 are in).
        let next = Observation::new(1, 0, vec![0.0; 4], None, None).in_session(token);
        client.step(&next).await.expect("the next episode starts");
    });
    planner.stop().unwrap();
}

/// Unknown fields are refused by name in every message an agent sends: the attach request,
/// its run spec (the reproduction: `"colour":"red"`), its overrides, and an observation.
#[test]
fn unknown_fields_are_refused_by_name_in_every_message() {
    let dir = TempDir::new("unknown-fields");
    let config = PlannerConfig::new("fields", Sizes::TINY).toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    runtime().block_on(async {
        let client = Client::connect(&planner.endpoint, "typo", "typo2").await.unwrap();
        let v = PROTOCOL_VERSION;
        let attach = |top: &str, spec: &str, overrides: &str| {
            format!(
                r#"{{"version":{v},"agent":"typo2","spec":{{"task":"cartpole","preset":"cem","overrides":{{"population":20,"elites":2{overrides}}},"mode":"sync","seed":1{spec}}}{top}}}"#
            )
        };
        for (json, field) in [
            (attach("", r#","colour":"red""#, ""), "colour"),
            (attach(r#","sesion":7"#, "", ""), "sesion"),
            (attach("", "", r#","populaton":5"#), "populaton"),
        ] {
            let reply = client
                .attach_raw("typo", json.into_bytes(), "application/json")
                .await
                .unwrap();
            let AttachOutcome::Rejected(report) = reply.outcome else {
                panic!("an attach with `{field}` was accepted");
            };
            assert_eq!(report.code, ErrorCode::Malformed, "{report}");
            assert!(
                report.message.contains(&format!("unknown field `{field}`")),
                "{report}"
            );
        }
        // Without the unknown field the same attach is accepted.
        let reply = client
            .attach_raw("typo", attach("", "", "").into_bytes(), "application/json")
            .await
            .unwrap();
        let AttachOutcome::Accepted(accepted) = reply.outcome else {
            panic!("the well-formed attach was refused: {reply:?}");
        };
        let obs = format!(
            r#"{{"version":{v},"episode":0,"step":0,"obs":[0,0,0,0],"session":{},"colour":"red"}}"#,
            accepted.session
        );
        client
            .send_raw("typo", obs.into_bytes(), "application/json")
            .await
            .unwrap();
        let report = client.next_error_any().await.unwrap();
        assert_eq!(report.code, ErrorCode::Malformed, "{report}");
        assert!(
            report.message.contains("unknown field `colour`"),
            "{report}"
        );
    });
    planner.stop().unwrap();
}

/// Attaches refused with a new task spec each (an override over the limits, checked after the
/// task): more of them than the process has task slots.
const REFUSED_ATTACHES: usize = 10_000;

/// Attaches in flight at once (the daemon handles 8 at a time and refuses more for a moment).
const IN_FLIGHT: usize = 4;

fn custom(name: &str) -> TaskSpec {
    let mut task = Builtin::Cartpole.spec();
    task.name = name.into();
    task.episode_len = 10;
    task.model = Default::default();
    task
}

fn custom_attach(name: &str, overrides: PlannerOverrides) -> Vec<u8> {
    let request = AttachRequest {
        version: PROTOCOL_VERSION,
        agent: "h".into(),
        spec: RunSpec {
            task: name.into(),
            task_spec: Some(custom(name)),
            overrides,
            ..cartpole(TrainMode::Async)
        },
        session: None,
    };
    proto::encode(&request, Encoding::Postcard).unwrap()
}

/// 10,000 refused attaches, each with a task spec of its own, keep nothing: every task slot
/// is still free, so a new task is accepted after them.
#[test]
fn refused_attaches_leave_every_task_slot_free() {
    let dir = TempDir::new("task-slots");
    let config = PlannerConfig::new("slots", Sizes::TINY).toml();
    let mut planner = Planner::start(dir.path(), &config).expect("planner starts");
    runtime().block_on(async {
        let client = Arc::new(Client::connect(&planner.endpoint, "x", "h").await.unwrap());
        let over = PlannerOverrides {
            population: Some(1_000_000_000),
            ..Default::default()
        };
        let mut next = 0;
        let mut in_flight = tokio::task::JoinSet::new();
        while next < REFUSED_ATTACHES || !in_flight.is_empty() {
            while next < REFUSED_ATTACHES && in_flight.len() < IN_FLIGHT {
                let (client, over) = (client.clone(), over.clone());
                let name = format!("slot-{next}");
                in_flight.spawn(async move {
                    let reply = client
                        .attach_raw(&name, custom_attach(&name, over), Encoding::Postcard.mime())
                        .await
                        .unwrap();
                    match reply.outcome {
                        AttachOutcome::Rejected(report) => report.message,
                        AttachOutcome::Accepted(a) => panic!("{name} accepted: {a:?}"),
                    }
                });
                next += 1;
            }
            let message = in_flight.join_next().await.unwrap().unwrap();
            assert!(message.contains("population"), "{message}");
        }
        let report = status(&client.session, "slots").await.unwrap();
        let slots = &report.budgets.task_slots;
        assert!(
            slots.used <= Builtin::ALL.len() as u64,
            "refused attaches took task slots: {slots:?}"
        );
        // Every slot is free: a new task is accepted.
        let reply = client
            .attach_raw(
                "fresh",
                custom_attach("fresh", Default::default()),
                Encoding::Postcard.mime(),
            )
            .await
            .unwrap();
        assert!(
            matches!(reply.outcome, AttachOutcome::Accepted(_)),
            "{reply:?}"
        );
    });
    planner.stop().unwrap();
}
