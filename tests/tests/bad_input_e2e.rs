//! Bad input never harms the daemon: every malformed, mis-sized, non-finite, mis-versioned,
//! misaddressed or out-of-order observation gets a clear error on the sender's error key, none
//! reaches the replay buffer, and a well-behaved agent is served throughout.

use ebmpc_e2e::{Planner, TempDir, read_csv, run_bridge};
use planner_service::replay::ReplayBuffer;
use proto::{
    AttachOutcome, AttachReply, AttachRequest, Encoding, ErrorCode, ErrorReport, Keys, Observation,
    PROTOCOL_VERSION, RunSpec, TaskId,
};
use std::time::Duration;

const SMALL: &str = r#"
planner_id = "bad-input"
[overrides]
dynamics_hidden_layers = 2
dynamics_hidden_size = 16
dynamics_epochs = 2
energy_hidden_layers = 2
energy_hidden_size = 16
energy_epochs = 2
population = 20
elites = 4
horizon = 5
cem_iterations = 2
"#;

struct Client {
    session: zenoh::Session,
    keys: Keys,
    errors: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    actions: zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    run: String,
    agent: String,
}

impl Client {
    async fn connect(endpoint: &str, run: &str, agent: &str) -> Client {
        let endpoints = proto::session::Endpoints {
            listen: vec![],
            connect: vec![endpoint.to_string()],
        };
        let session = zenoh::open(proto::session::zenoh_config(&endpoints, None).unwrap())
            .await
            .unwrap();
        let keys = Keys::default();
        let errors = session
            .declare_subscriber(keys.error(run, agent))
            .await
            .unwrap();
        let actions = session
            .declare_subscriber(keys.act(run, agent))
            .await
            .unwrap();
        Client {
            session,
            keys,
            errors,
            actions,
            run: run.into(),
            agent: agent.into(),
        }
    }

    async fn attach(&self) {
        let request = AttachRequest {
            version: PROTOCOL_VERSION,
            agent: self.agent.clone(),
            spec: RunSpec {
                task: TaskId::Cartpole,
                preset: None,
                overrides: Default::default(),
                mode: Default::default(),
                seed: 1,
            },
        };
        let payload = proto::encode(&request, Encoding::Postcard).unwrap();
        for _ in 0..100 {
            let replies = self
                .session
                .get(self.keys.attach(&self.run))
                .payload(payload.clone())
                .await
                .unwrap();
            if let Ok(reply) = replies.recv_async().await {
                let bytes = reply
                    .result()
                    .expect("attach reply")
                    .payload()
                    .to_bytes()
                    .into_owned();
                let reply: AttachReply = proto::decode(&bytes, Encoding::Postcard).unwrap();
                assert!(
                    matches!(reply.outcome, AttachOutcome::Accepted(_)),
                    "{reply:?}"
                );
                // Give the planner's subscriber a moment to be matched by our publisher.
                tokio::time::sleep(Duration::from_millis(300)).await;
                return;
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        panic!("attach got no reply");
    }

    async fn send_raw(&self, run: &str, bytes: Vec<u8>, encoding: &str) {
        let key = self.keys.obs(run, &self.agent);
        self.session
            .put(key, bytes)
            .encoding(zenoh::bytes::Encoding::from(encoding))
            .await
            .unwrap();
    }

    async fn send(&self, obs: &Observation) {
        self.send_raw(
            &self.run.clone(),
            proto::encode(obs, Encoding::Postcard).unwrap(),
            Encoding::Postcard.mime(),
        )
        .await;
    }

    async fn next_error(&self) -> ErrorReport {
        let sample = tokio::time::timeout(Duration::from_secs(20), self.errors.recv_async())
            .await
            .expect("an error report")
            .unwrap();
        let encoding = Encoding::from_mime(&sample.encoding().to_string());
        proto::decode(&sample.payload().to_bytes(), encoding).unwrap()
    }
}

fn obs(episode: u32, step: u32, values: Vec<f32>, reward: Option<f32>) -> Observation {
    Observation {
        version: PROTOCOL_VERSION,
        episode,
        step,
        obs: values,
        reward,
        end: None,
    }
}

#[test]
fn bad_input_is_reported_and_never_stored() {
    let dir = TempDir::new("bad-input");
    let mut planner = Planner::start(dir.path(), SMALL).expect("planner starts");
    let endpoint = planner.endpoint.clone();

    // A well-behaved agent runs one full episode on its own run while the bad input flows.
    let good_dir = dir.path().to_path_buf();
    let good_endpoint = endpoint.clone();
    let good = std::thread::spawn(move || {
        let csv = good_dir.join("good.csv");
        let args = [
            "--task",
            "cartpole",
            "--run",
            "good",
            "--agent",
            "g",
            "--episodes",
            "1",
            "--out",
            csv.to_str().unwrap(),
        ];
        let (status, log) =
            run_bridge(&good_dir, &good_endpoint, &args, Duration::from_secs(240)).unwrap();
        (status, log, csv)
    });

    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    runtime.block_on(async {
        let client = Client::connect(&endpoint, "bad", "b").await;
        client.attach().await;
        let cases: Vec<(Vec<u8>, &str, ErrorCode)> = vec![
            (
                vec![0xde, 0xad, 0xbe, 0xef, 0x01],
                Encoding::Postcard.mime(),
                ErrorCode::Malformed,
            ),
            (Vec::new(), Encoding::Postcard.mime(), ErrorCode::Malformed),
            (
                b"{\"version\":1,\"episode\":0".to_vec(),
                "application/json",
                ErrorCode::Malformed,
            ),
            (
                proto::encode(&obs(0, 0, vec![0.0; 4], None), Encoding::Postcard).unwrap()[..6]
                    .to_vec(),
                Encoding::Postcard.mime(),
                ErrorCode::Malformed,
            ),
            (
                proto::encode(
                    &Observation {
                        version: 99,
                        ..obs(0, 0, vec![0.0; 4], None)
                    },
                    Encoding::Postcard,
                )
                .unwrap(),
                Encoding::Postcard.mime(),
                ErrorCode::ProtocolVersion,
            ),
            (
                proto::encode(&obs(0, 0, vec![0.0; 3], None), Encoding::Postcard).unwrap(),
                Encoding::Postcard.mime(),
                ErrorCode::Dimension,
            ),
            (
                proto::encode(
                    &obs(0, 0, vec![0.0, f32::NAN, 0.0, 0.0], None),
                    Encoding::Postcard,
                )
                .unwrap(),
                Encoding::Postcard.mime(),
                ErrorCode::NonFinite,
            ),
            (
                proto::encode(
                    &obs(0, 0, vec![f32::INFINITY, 0.0, 0.0, 0.0], None),
                    Encoding::Postcard,
                )
                .unwrap(),
                Encoding::Postcard.mime(),
                ErrorCode::NonFinite,
            ),
            (
                proto::encode(&obs(0, 5, vec![0.0; 4], Some(1.0)), Encoding::Postcard).unwrap(),
                Encoding::Postcard.mime(),
                ErrorCode::OutOfOrder,
            ),
        ];
        for (bytes, mime, code) in cases {
            client.send_raw("bad", bytes.clone(), mime).await;
            let report = client.next_error().await;
            assert_eq!(report.code, code, "{bytes:?} → {report}");
            assert!(!report.message.is_empty());
        }

        // An unknown run is named as such.
        let unknown = Client::connect(&endpoint, "nobody-here", "b").await;
        unknown.send(&obs(0, 0, vec![0.0; 4], None)).await;
        assert_eq!(unknown.next_error().await.code, ErrorCode::UnknownRun);

        // After all that, a proper step is still answered, and a JSON client gets JSON back.
        client.send(&obs(0, 0, vec![0.0; 4], None)).await;
        let action = tokio::time::timeout(Duration::from_secs(20), client.actions.recv_async())
            .await
            .expect("an action")
            .unwrap();
        let act: proto::Action =
            proto::decode(&action.payload().to_bytes(), Encoding::Postcard).unwrap();
        assert_eq!((act.episode, act.step, act.action.len()), (0, 0, 1));
        // Step 1 in JSON with a NaN-free but mis-sized observation: a JSON error comes back.
        client
            .send_raw(
                "bad",
                br#"{"version":1,"episode":0,"step":1,"obs":[1,2],"reward":0.5}"#.to_vec(),
                "application/json",
            )
            .await;
        let sample = client.errors.recv_async().await.unwrap();
        assert_eq!(sample.encoding().to_string(), "application/json");
        let report: ErrorReport = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
        assert_eq!(report.code, ErrorCode::Dimension);
        client.session.close().await.unwrap();
        unknown.session.close().await.unwrap();
    });

    let (status, log, csv) = good.join().unwrap();
    assert!(
        status.success(),
        "the good agent failed: {log}\nplanner:\n{}",
        planner.process.log()
    );
    assert_eq!(read_csv(&csv).unwrap()[0]["steps"], "200");
    let planner_log = planner.process.log();
    assert!(
        planner_log.contains("rejected"),
        "errors are logged:\n{planner_log}"
    );

    assert!(
        planner
            .process
            .terminate(Duration::from_secs(30))
            .unwrap()
            .success()
    );
    let bad = ReplayBuffer::open(
        &planner.data_dir.join("runs/bad/replay.log"),
        TaskId::Cartpole.spec(),
    )
    .unwrap();
    assert_eq!(bad.len(), 0, "no bad observation was stored");
    let good = ReplayBuffer::open(
        &planner.data_dir.join("runs/good/replay.log"),
        TaskId::Cartpole.spec(),
    )
    .unwrap();
    assert_eq!(good.len(), 200);
}
