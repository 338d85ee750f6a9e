//! Bad input never harms the daemon: every malformed, mis-sized, non-finite, mis-versioned,
//! misaddressed or out-of-order observation gets a clear error on the sender's error key (bytes
//! that do not decode with no session, [`NO_SESSION`]), none reaches the replay buffer, and a
//! well-behaved agent is served throughout.

use ebmpc_e2e::bridge::run_episodes;
use ebmpc_e2e::client::{Answer, Client, runtime};
use ebmpc_e2e::config::{PlannerConfig, Sizes};
use ebmpc_e2e::{Planner, TempDir};
use proto::{
    Builtin, Encoding, ErrorCode, ErrorReport, NO_SESSION, Observation, PROTOCOL_VERSION, RunSpec,
};
use std::time::Duration;

fn config() -> String {
    PlannerConfig::new(
        "bad-input",
        Sizes {
            epochs: 2,
            ..Sizes::TINY
        },
    )
    .toml()
}

fn cartpole_spec() -> RunSpec {
    RunSpec {
        task: Builtin::Cartpole.name().into(),
        preset: None,
        overrides: Default::default(),
        mode: Default::default(),
        seed: 1,
        task_spec: None,
    }
}

fn obs(episode: u32, step: u32, values: Vec<f32>, reward: Option<f32>) -> Observation {
    Observation::new(episode, step, values, reward, None)
}

#[test]
fn bad_input_is_reported_and_never_stored() {
    let dir = TempDir::new("bad-input");
    let mut planner = Planner::start(dir.path(), &config()).expect("planner starts");
    let endpoint = planner.endpoint.clone();

    let good = std::thread::scope(|scope| {
        // A well-behaved agent runs one full episode on its own run while the bad input flows.
        let good = scope.spawn(|| {
            let args = ["--task", "cartpole", "--run", "good", "--agent", "g"];
            run_episodes(dir.path(), &planner, &args, 1, Duration::from_secs(240))
        });
        bad_input_is_refused(&endpoint);
        good.join().expect("the good agent's thread")
    });
    let good = good.unwrap_or_else(|e| panic!("the good agent failed: {e:?}"));
    assert_eq!(good.episodes[0].steps, 200);
    let planner_log = planner.process.log();
    assert!(
        planner_log.contains("rejected"),
        "errors are logged:\n{planner_log}"
    );

    planner.stop().unwrap();
    let bad = planner.replay("bad", Builtin::Cartpole).unwrap();
    assert_eq!(bad.len(), 0, "no bad observation was stored");
    let good = planner.replay("good", Builtin::Cartpole).unwrap();
    assert_eq!(good.len(), 200);
}

/// Sends every kind of bad input to a run of its own at `endpoint` and checks each report.
fn bad_input_is_refused(endpoint: &str) {
    runtime().block_on(async {
        let client = Client::connect(endpoint, "bad", "b").await.unwrap();
        client.attach(&cartpole_spec()).await.unwrap();
        // This client's observations, in its session (else they are refused for the token).
        let token = client.session_token();
        let obs = |episode, step, values, reward| obs(episode, step, values, reward).in_session(token);
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
            (
                proto::encode(
                    &obs(0, 0, vec![0.0; 4], None).with_applied(vec![0.0]),
                    Encoding::Postcard,
                )
                .unwrap(),
                Encoding::Postcard.mime(),
                ErrorCode::OutOfOrder,
            ),
        ];
        for (bytes, mime, code) in cases {
            client.send_raw("bad", bytes.clone(), mime).await.unwrap();
            let report = client.next_error_any().await.unwrap();
            assert_eq!(report.code, code, "{bytes:?} → {report}");
            assert!(!report.message.is_empty());
            // Bytes that do not decode name no session (anyone may have sent them under this
            // name); the rest are reported to the session they carried.
            let unreadable = matches!(code, ErrorCode::Malformed | ErrorCode::ProtocolVersion);
            let session = if unreadable { NO_SESSION } else { token };
            assert_eq!(report.session, Some(session), "{bytes:?} → {report}");
        }

        // An unknown run is named as such.
        let unknown = Client::connect(endpoint, "nobody-here", "b").await.unwrap();
        unknown.send(&obs(0, 0, vec![0.0; 4], None)).await.unwrap();
        assert_eq!(
            unknown.next_error().await.unwrap().code,
            ErrorCode::UnknownRun
        );

        // After all that, a proper step is still answered, and a JSON client gets JSON back.
        let act = client.step(&obs(0, 0, vec![0.0; 4], None)).await.unwrap();
        assert_eq!((act.episode, act.step, act.action.len()), (0, 0, 1));
        // Step 1 in JSON with a NaN-free but mis-sized observation: a JSON error comes back.
        client
            .send_raw(
                "bad",
                format!(r#"{{"version":{PROTOCOL_VERSION},"episode":0,"step":1,"obs":[1,2],"reward":0.5,"session":{token}}}"#).into_bytes(),
                "application/json",
            )
            .await
            .unwrap();
        let sample = client.errors.recv_async().await.unwrap();
        assert_eq!(sample.encoding().to_string(), "application/json");
        let report: ErrorReport = serde_json::from_slice(&sample.payload().to_bytes()).unwrap();
        assert_eq!(report.code, ErrorCode::Dimension);
        // A hostile applied action (cartpole's bounds are ±3): refused, the episode stays put.
        for (applied, code) in [
            (vec![3.5], ErrorCode::OutOfRange),
            (vec![-1e38], ErrorCode::OutOfRange),
            (vec![f32::NAN], ErrorCode::NonFinite),
            (vec![0.0, 0.0], ErrorCode::Dimension),
            (vec![], ErrorCode::Dimension),
        ] {
            let msg = obs(0, 1, vec![0.0; 4], Some(0.5)).with_applied(applied.clone());
            client.send(&msg).await.unwrap();
            let report = client.next_error().await.unwrap();
            assert_eq!(report.code, code, "{applied:?} → {report}");
        }
        // Steps out of order after a good one: the episode is not advanced by them.
        client.send(&obs(0, 0, vec![0.0; 4], None)).await.unwrap();
        match client.answer(Duration::from_secs(20)).await.unwrap() {
            Answer::Error(report) => assert_eq!(report.code, ErrorCode::OutOfOrder),
            Answer::Action(a) => panic!("a repeated step 0 was answered: {a:?}"),
        }
        client.close().await.unwrap();
        unknown.close().await.unwrap();
    });
}
