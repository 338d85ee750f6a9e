//! The bridge loop against a scripted planner over real Zenoh sessions on loopback.
//!
//! The fake planner speaks proto's protocol the way planner-service does (attach queryable,
//! observation subscriber, actions on the agent's act key, errors on its error key, events on
//! the run's events key) and can be told to misbehave, so the bridge's error paths are exercised
//! with the same transport as production.

use proto::session::{Endpoints, zenoh_config};
use proto::{
    Action, ActionSource, AttachAccepted, AttachOutcome, AttachReply, AttachRequest, Builtin,
    Encoding, EpisodeEnd, ErrorCode, ErrorReport, Keys, Observation, PROTOCOL_VERSION, PlanStats,
    RunEvent, RunEventKind, RunSpec, TrainMode,
};
use sim_bridge::{BridgeConfig, BridgeError, Env, EpisodeDeadline};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant, SystemTime};
use zenoh::bytes::Encoding as ZEncoding;

/// How the scripted planner behaves.
#[derive(Clone, Default)]
struct Script {
    /// Refuse every attach with this message.
    reject: Option<String>,
    /// Never answer this step (of every episode).
    silent_at: Option<u32>,
    /// Answer this step with an error report instead of an action.
    error_at: Option<u32>,
    /// Refuse this step (step, times) with a storage error the first `times` times it comes.
    storage_full_at: Option<(u32, usize)>,
    /// Hold the first action of every episode after the first this long (a sync planner
    /// retraining on the episodes before it).
    first_action_delay: Duration,
    /// Announce the models retrained on an episode this long after it ends.
    models_delay: Duration,
    /// Publish an undecodable action as each episode ends (a stray or hostile publisher).
    garbage_after_episode: bool,
}

/// What the scripted planner saw.
#[derive(Default)]
struct Seen {
    attach: Vec<AttachRequest>,
    observations: Vec<Observation>,
    /// When each models update was announced.
    models_announced: Vec<Instant>,
}

fn free_endpoint() -> String {
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    format!("tcp/127.0.0.1:{}", listener.local_addr().unwrap().port())
}

/// The run's ownership epoch the scripted planner attaches agents at.
const EPOCH: u64 = 4;

/// The session token the scripted planner hands out.
const SESSION: u64 = 0x5eed_f00d_ba5e;

/// The step at which an action of an older epoch arrives before the real one (the bridge must
/// ignore it: the replay check below would see its effect otherwise).
const STALE_AT: u32 = 7;

/// The deterministic "policy" of the scripted planner: a slow sine of the step.
fn scripted_action(step: u32) -> Vec<f32> {
    vec![3.0 * (step as f32 * 0.3).sin()]
}

fn publish_bytes<T: serde::Serialize>(msg: &T) -> Vec<u8> {
    proto::encode(msg, Encoding::Postcard).unwrap()
}

/// Starts the scripted planner listening on `endpoint`; returns what it sees as it runs.
async fn start_planner(endpoint: &str, script: Script) -> (zenoh::Session, Arc<Mutex<Seen>>) {
    let endpoints = Endpoints {
        listen: vec![endpoint.to_string()],
        connect: vec![],
    };
    let session = zenoh::open(zenoh_config(&endpoints, None).unwrap())
        .await
        .unwrap();
    let keys = Keys::default();
    let seen = Arc::new(Mutex::new(Seen::default()));
    let token = session
        .liveliness()
        .declare_token(keys.planner_alive("fake"))
        .await
        .unwrap();
    let attach = session.declare_queryable(keys.all_attach()).await.unwrap();
    let observations = session.declare_subscriber(keys.all_obs()).await.unwrap();

    let (s, k, seen2) = (session.clone(), keys.clone(), seen.clone());
    tokio::spawn(async move {
        let _token = token;
        loop {
            tokio::select! {
                Ok(query) = attach.recv_async() => {
                    let bytes = query.payload().unwrap().to_bytes().into_owned();
                    let request: AttachRequest = proto::decode(&bytes, Encoding::Postcard).unwrap();
                    let outcome = match &script.reject {
                        Some(why) => AttachOutcome::Rejected(ErrorReport::new(ErrorCode::Refused, why.clone())),
                        None => AttachOutcome::Accepted(AttachAccepted {
                            planner_id: "fake".into(),
                            task: request.spec.task.clone(),
                            mode: request.spec.mode,
                            episodes_done: 5,
                            models_version: 0,
                            next_episode: 5,
                            epoch: EPOCH,
                            session: SESSION,
                        }),
                    };
                    seen2.lock().unwrap().attach.push(request);
                    let reply = AttachReply { version: PROTOCOL_VERSION, outcome };
                    let key = query.key_expr().as_str().to_string();
                    query.reply(key, publish_bytes(&reply)).encoding(ZEncoding::from(Encoding::Postcard.mime())).await.unwrap();
                }
                Ok(sample) = observations.recv_async() => {
                    let (run, agent) = {
                        let (r, a) = k.parse_agent_key(sample.key_expr().as_str(), proto::AgentChannel::Obs).unwrap();
                        (r.to_string(), a.to_string())
                    };
                    let obs: Observation = proto::decode(&sample.payload().to_bytes(), Encoding::Postcard).unwrap();
                    seen2.lock().unwrap().observations.push(obs.clone());
                    if let Some(end) = obs.end {
                        let events = [
                            RunEventKind::EpisodeFinished { agent: agent.clone(), episode: obs.episode, episode_return: 0.0, steps: obs.step, end },
                            RunEventKind::TrainingStarted { transitions: u64::from(obs.step) },
                        ];
                        for kind in events {
                            let event = RunEvent { version: PROTOCOL_VERSION, run: run.clone(), kind };
                            s.put(k.events(&run, Encoding::Postcard), publish_bytes(&event)).await.unwrap();
                        }
                        if script.garbage_after_episode {
                            s.put(k.act(&run, &agent), vec![0xff_u8; 7]).await.unwrap();
                        }
                        let (s, k, seen) = (s.clone(), k.clone(), seen2.clone());
                        let delay = script.models_delay;
                        tokio::spawn(async move {
                            tokio::time::sleep(delay).await;
                            let kind = RunEventKind::ModelsUpdated { models_version: 1, dynamics_loss: 0.1, energy_loss: 0.2, reward_loss: None, seconds: 0.01, termination_accuracy: None };
                            let event = RunEvent { version: PROTOCOL_VERSION, run: run.clone(), kind };
                            s.put(k.events(&run, Encoding::Postcard), publish_bytes(&event)).await.unwrap();
                            seen.lock().unwrap().models_announced.push(Instant::now());
                        });
                        continue;
                    }
                    if obs.step == 0 && obs.episode > 5 {
                        tokio::time::sleep(script.first_action_delay).await;
                    }
                    if script.silent_at == Some(obs.step) {
                        continue;
                    }
                    if let Some((step, times)) = script.storage_full_at {
                        let refused = seen2.lock().unwrap().observations.iter().filter(|o| o.step == step).count() <= times;
                        if obs.step == step && refused {
                            let report = ErrorReport::new(ErrorCode::Storage, "disk full: scripted").at(obs.episode, obs.step);
                            s.put(k.error(&run, &agent), publish_bytes(&report)).await.unwrap();
                            continue;
                        }
                    }
                    if script.error_at == Some(obs.step) {
                        let report = ErrorReport::new(ErrorCode::Internal, "planning failed: scripted").at(obs.episode, obs.step);
                        s.put(k.error(&run, &agent), publish_bytes(&report)).await.unwrap();
                        continue;
                    }
                    let action = Action {
                        version: PROTOCOL_VERSION,
                        episode: obs.episode,
                        step: obs.step,
                        action: scripted_action(obs.step),
                        stats: PlanStats {
                            source: if obs.episode == 5 { ActionSource::Random } else { ActionSource::Planned },
                            planning_ms: 1.0,
                            predicted_return: 0.0,
                            mean_energy: 0.0,
                            iterations: 1,
                            models_version: 0,
                            cut: false,
                            missed: false,
                        },
                        epoch: EPOCH,
                    };
                    if obs.step == STALE_AT {
                        // Someone else using the agent's name had an observation refused: the
                        // report names their session, and the bridge must not take it as its own.
                        let alien = ErrorReport::new(ErrorCode::Session, "not your session: scripted")
                            .at(obs.episode, obs.step)
                            .for_session(SESSION + 1);
                        s.put(k.error(&run, &agent), publish_bytes(&alien)).await.unwrap();
                        // A planner that lost the run answers first, with another action.
                        let stale = Action { epoch: EPOCH - 1, action: vec![-2.5], ..action.clone() };
                        s.put(k.act(&run, &agent), publish_bytes(&stale)).await.unwrap();
                    }
                    s.put(k.act(&run, &agent), publish_bytes(&action)).await.unwrap();
                }
                else => break,
            }
        }
    });
    (session, seen)
}

fn config(endpoint: &str, episodes: u32) -> BridgeConfig {
    BridgeConfig {
        prefix: "ebmpc".into(),
        endpoints: Endpoints {
            listen: vec![],
            connect: vec![endpoint.to_string()],
        },
        zenoh_config: None,
        run: "test-run".into(),
        agent: "bridge-0".into(),
        spec: RunSpec {
            task: Builtin::Cartpole.name().into(),
            preset: Some("cem+deen".into()),
            overrides: Default::default(),
            mode: TrainMode::Sync,
            seed: 9,
            task_spec: None,
        },
        episodes,
        timesteps: None,
        deadline: None,
        seed: 100,
        attach_timeout: Duration::from_secs(20),
        action_timeout: Duration::from_secs(20),
        train_timeout: Duration::from_secs(20),
        max_steps: None,
        #[cfg(feature = "render")]
        render: None,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn episodes_run_step_by_step_and_report_the_simulators_rewards() {
    let endpoint = free_endpoint();
    let (_planner, seen) = start_planner(&endpoint, Script::default()).await;
    let config = config(&endpoint, 2);
    let mut streamed = Vec::new();
    let records = sim_bridge::bridge::run(&config, |r| streamed.push(r.clone()))
        .await
        .unwrap();
    assert_eq!(
        records, streamed,
        "each record is handed out as its episode ends"
    );

    let seen = seen.lock().unwrap();
    assert_eq!(seen.attach.len(), 1);
    assert_eq!(seen.attach[0].agent, "bridge-0");
    assert_eq!(seen.attach[0].spec, config.spec);

    // Episodes continue the run's numbering; each is the full time limit.
    assert_eq!(
        records.iter().map(|r| r.episode).collect::<Vec<_>>(),
        [5, 6]
    );
    assert_eq!(seen.observations.len(), 2 * 201);
    assert!(
        seen.observations.iter().all(|o| o.session == SESSION),
        "every observation carries the session token of the attach"
    );
    for record in &records {
        assert_eq!((record.steps, record.end), (200, EpisodeEnd::TimeLimit));
        let (planned, random) = if record.episode == 5 {
            (0, 200)
        } else {
            (200, 0)
        };
        assert_eq!(
            (record.actions.planned, record.actions.random),
            (planned, random)
        );
    }

    // Replaying the same seeds and actions locally gives exactly what was sent, and the
    // returns are the sums of the sent rewards.
    let mut env = Env::new(Builtin::Cartpole).unwrap();
    for (record, sent) in records.iter().zip(seen.observations.chunks(201)) {
        let start = env.reset(config.seed + u64::from(record.episode)).to_vec();
        assert_eq!(sent[0].obs, start);
        assert_eq!(
            (sent[0].episode, sent[0].step, sent[0].reward, sent[0].end),
            (record.episode, 0, None, None)
        );
        let mut total = 0.0;
        for (step, msg) in sent.iter().enumerate().skip(1) {
            let outcome = env.step(&scripted_action(step as u32 - 1)).unwrap();
            assert_eq!((msg.episode, msg.step), (record.episode, step as u32));
            assert_eq!(
                msg.obs, outcome.obs,
                "episode {} step {step}",
                record.episode
            );
            assert_eq!(msg.reward, Some(outcome.reward));
            assert_eq!(
                msg.applied.as_ref(),
                Some(&outcome.applied),
                "the applied action is sent"
            );
            assert_eq!(msg.end, (step == 200).then_some(EpisodeEnd::TimeLimit));
            total += outcome.reward;
        }
        assert_eq!(record.episode_return, total);
    }
}

/// A deadline stops the run between episodes, before the simulator resets: the planner never
/// sees the first observation of an episode that would end after it (it would record that
/// episode as interrupted and spend its number). After random exploration the planned-episode
/// estimate decides; after a planned episode, that episode's own wall time; an episode with no
/// estimate starts.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_deadline_stops_between_episodes_before_the_next_reset() {
    let endpoint = free_endpoint();
    let (_planner, seen) = start_planner(&endpoint, Script::default()).await;
    let mut config = config(&endpoint, 4);
    // Episode 5 is random; a planned one would take two hours, the deadline is one away.
    config.deadline = Some(EpisodeDeadline {
        at: SystemTime::now() + Duration::from_secs(3_600),
        planned_episode: Some(Duration::from_secs(7_200)),
    });
    let records = sim_bridge::bridge::run(&config, |_| {}).await.unwrap();
    assert_eq!(records.iter().map(|r| r.episode).collect::<Vec<_>>(), [5]);
    assert_eq!(
        seen.lock().unwrap().observations.len(),
        201,
        "no observation of episode 6"
    );
    assert!(
        seen.lock()
            .unwrap()
            .observations
            .iter()
            .all(|o| o.episode == 5)
    );

    // A deadline already past, no planned estimate: the episode after the random one starts
    // (nothing predicts it), and the planned episode's own wall time then stops the run.
    let (_planner, seen) = start_planner(&free_endpoint_for(&mut config), Script::default()).await;
    config.deadline = Some(EpisodeDeadline {
        at: SystemTime::now(),
        planned_episode: None,
    });
    let records = sim_bridge::bridge::run(&config, |_| {}).await.unwrap();
    assert_eq!(
        records.iter().map(|r| r.episode).collect::<Vec<_>>(),
        [5, 6]
    );
    assert_eq!(records[1].actions.planned, 200);
    assert_eq!(seen.lock().unwrap().observations.len(), 2 * 201);
}

/// A run stopped at its deadline after a planned episode waits for the planner's retraining on
/// that episode (announced only once its models are checkpointed), so that the resumed run need
/// not redo it; but never past the deadline.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_stopped_at_its_deadline_waits_for_the_retraining_until_the_deadline() {
    // Episode 5 is random and fast; episode 6 plans and takes over 6 s (its first action is
    // held 6 s), so with the deadline 11 s away episode 7 (as long as 6) does not fit.
    // An undecodable action meanwhile (published as each episode ends: episode 5's arrives
    // while the bridge waits for episode 6's first action) ends neither the run nor the wait.
    let script = |models_delay, garbage_after_episode| Script {
        first_action_delay: Duration::from_secs(6),
        models_delay,
        garbage_after_episode,
        ..Script::default()
    };
    for (models_delay, garbage, waits_for_models) in [
        (500, false, true),
        (500, true, true),
        (60_000, false, false),
    ] {
        let endpoint = free_endpoint();
        let (_planner, seen) = start_planner(
            &endpoint,
            script(Duration::from_millis(models_delay), garbage),
        )
        .await;
        let mut config = config(&endpoint, 4);
        config.train_timeout = Duration::from_secs(60);
        let at = SystemTime::now() + Duration::from_secs(11);
        config.deadline = Some(EpisodeDeadline {
            at,
            planned_episode: None,
        });
        let records = sim_bridge::bridge::run(&config, |_| {}).await.unwrap();
        let returned = Instant::now();
        assert_eq!(
            records.iter().map(|r| r.episode).collect::<Vec<_>>(),
            [5, 6]
        );
        assert_eq!(seen.lock().unwrap().observations.len(), 2 * 201);
        let announced = seen.lock().unwrap().models_announced.clone();
        if waits_for_models {
            // The second announcement is the retraining on episode 6.
            assert_eq!(
                announced.len(),
                2,
                "the bridge stopped before the retraining ended"
            );
            assert!(returned >= announced[1]);
        } else {
            assert!(announced.is_empty());
            let early = at.duration_since(SystemTime::now()).unwrap_or_default();
            assert!(
                early < Duration::from_millis(500),
                "stopped {early:?} before the deadline"
            );
            let late = SystemTime::now().duration_since(at).unwrap_or_default();
            assert!(
                late < Duration::from_secs(10),
                "stopped {late:?} after the deadline"
            );
        }
    }
}

/// Points `config` at a new free endpoint and returns it (a second scripted planner).
fn free_endpoint_for(config: &mut BridgeConfig) -> String {
    let endpoint = free_endpoint();
    config.endpoints.connect = vec![endpoint.clone()];
    endpoint
}

/// A step budget ends the run after the episode that reaches it: 250 steps of cartpole's
/// 200-step episodes are two whole episodes, though five were allowed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_step_budget_stops_after_the_episode_that_reaches_it() {
    let endpoint = free_endpoint();
    let (_planner, seen) = start_planner(&endpoint, Script::default()).await;
    let mut config = config(&endpoint, 5);
    config.timesteps = Some(250);
    let records = sim_bridge::bridge::run(&config, |_| {}).await.unwrap();
    assert_eq!(records.len(), 2);
    assert!(records.iter().all(|r| r.steps == 200));
    assert_eq!(seen.lock().unwrap().observations.len(), 2 * 201);
    // A budget met exactly by an episode's end stops there too.
    config.timesteps = Some(200);
    let records = sim_bridge::bridge::run(&config, |_| {}).await.unwrap();
    assert_eq!(records.len(), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_refused_attach_is_reported_with_the_planners_reason() {
    let endpoint = free_endpoint();
    let script = Script {
        reject: Some("run `test-run` learns ant, not cartpole".into()),
        ..Script::default()
    };
    let (_planner, _) = start_planner(&endpoint, script).await;
    let err = sim_bridge::bridge::run(&config(&endpoint, 1), |_| {})
        .await
        .unwrap_err();
    assert!(matches!(err, BridgeError::AttachRejected { .. }), "{err}");
    assert!(
        err.to_string().contains("learns ant, not cartpole"),
        "{err}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_missing_action_times_out_naming_the_step() {
    let endpoint = free_endpoint();
    let script = Script {
        silent_at: Some(3),
        ..Script::default()
    };
    let (_planner, seen) = start_planner(&endpoint, script).await;
    let mut config = config(&endpoint, 1);
    config.action_timeout = Duration::from_millis(500);
    let err = sim_bridge::bridge::run(&config, |_| {}).await.unwrap_err();
    match &err {
        BridgeError::ActionTimeout {
            episode: 5,
            step: 3,
            waited,
            while_training: false,
        } => {
            assert!(*waited >= Duration::from_millis(500), "{waited:?}");
        }
        other => panic!("{other}"),
    }
    assert!(err.to_string().contains("episode 5 step 3"), "{err}");
    assert_eq!(
        seen.lock().unwrap().observations.len(),
        4,
        "steps 0..=3 were sent"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_error_for_the_pending_step_stops_the_bridge() {
    let endpoint = free_endpoint();
    let script = Script {
        error_at: Some(7),
        ..Script::default()
    };
    let (_planner, _) = start_planner(&endpoint, script).await;
    let err = sim_bridge::bridge::run(&config(&endpoint, 1), |_| {})
        .await
        .unwrap_err();
    match &err {
        BridgeError::Planner {
            episode: 5,
            step: 7,
            report,
        } => assert_eq!(report.code, ErrorCode::Internal),
        other => panic!("{other}"),
    }
    assert!(err.to_string().contains("scripted"), "{err}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_step_the_planner_could_not_store_is_sent_again_until_it_is() {
    let endpoint = free_endpoint();
    let script = Script {
        storage_full_at: Some((3, 2)),
        ..Script::default()
    };
    let (_planner, seen) = start_planner(&endpoint, script).await;
    let records = sim_bridge::bridge::run(&config(&endpoint, 1), |_| {})
        .await
        .expect("the episode finishes once the step is stored");
    assert_eq!(records.len(), 1);
    let seen = seen.lock().unwrap();
    let step3: Vec<&Observation> = seen.observations.iter().filter(|o| o.step == 3).collect();
    assert_eq!(step3.len(), 3, "refused twice, then stored");
    assert!(
        step3.iter().all(|o| o == &step3[0]),
        "the same observation each time"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_planner_is_a_clear_error() {
    let endpoint = free_endpoint();
    // Something to connect to, but nothing serves the attach key.
    let endpoints = Endpoints {
        listen: vec![endpoint.clone()],
        connect: vec![],
    };
    let _peer = zenoh::open(zenoh_config(&endpoints, None).unwrap())
        .await
        .unwrap();
    let mut config = config(&endpoint, 1);
    config.attach_timeout = Duration::from_secs(1);
    let err = sim_bridge::bridge::run(&config, |_| {}).await.unwrap_err();
    assert!(matches!(err, BridgeError::NoPlanner { .. }), "{err}");
    assert!(
        err.to_string().contains("is planner-service running"),
        "{err}"
    );
}

#[tokio::test]
async fn invalid_names_are_refused_before_connecting() {
    let mut config = config("tcp/127.0.0.1:9", 1);
    config.agent = "a/b".into();
    let err = sim_bridge::bridge::run(&config, |_| {}).await.unwrap_err();
    assert!(
        matches!(
            err,
            BridgeError::InvalidName {
                what: "agent name",
                ..
            }
        ),
        "{err}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restarted_planner_is_attached_again_and_the_episode_starts_over() {
    let endpoint = free_endpoint();
    let script = Script {
        silent_at: Some(3),
        ..Script::default()
    };
    let (first, seen_by_first) = start_planner(&endpoint, script).await;
    let config = config(&endpoint, 1);
    let bridge = tokio::spawn({
        let config = config.clone();
        async move { sim_bridge::bridge::run(&config, |_| {}).await }
    });

    // The first planner stalls at step 3 of episode 5; then it is stopped and replaced.
    let stalled = tokio::time::Instant::now() + Duration::from_secs(20);
    while seen_by_first.lock().unwrap().observations.len() < 4 {
        assert!(
            tokio::time::Instant::now() < stalled,
            "the bridge never reached step 3"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    first.close().await.unwrap();
    let (_second, seen_by_second) = start_planner(&endpoint, Script::default()).await;

    let records = bridge.await.unwrap().unwrap();
    assert_eq!(records.len(), 1);
    // The abandoned episode's number is not reused.
    assert_eq!((records[0].episode, records[0].steps), (6, 200));
    let seen = seen_by_second.lock().unwrap();
    assert_eq!(seen.attach.len(), 1, "attached again");
    assert_eq!(seen.observations.len(), 201);
    assert!(seen.observations.iter().all(|o| o.episode == 6));
}
