//! Fuzz target for the codec and validation: valid encodings of the messages a planner or an
//! agent receives, mutated (bits flipped, bytes inserted, removed, overwritten with extreme
//! values, cut short), and plain random bytes, decoded in both encodings as every message type
//! and validated against every task. No input may panic, and hostile length prefixes must be
//! refused without allocating what they claim.
//!
//! CI runs a fixed budget ([`DEFAULT_CASES`] per property, a few seconds). By hand, for as many
//! inputs as wanted: `EBMPC_FUZZ_CASES=10000000 cargo test --release -p ebmpc-proto --test
//! codec_fuzz -- --nocapture` (each property then runs that many cases).

use proptest::prelude::*;
use proto::task::TaskId;
use proto::validate::{validate_action, validate_observation};
use proto::{
    Action, ActionSource, AttachReply, AttachRequest, Encoding, EpisodeEnd, ErrorReport,
    Observation, PROTOCOL_VERSION, PlanStats, PlannerOverrides, RunEvent, RunSpec, TrainMode,
};

/// Cases per property in CI.
const DEFAULT_CASES: u32 = 3000;

fn cases() -> u32 {
    std::env::var("EBMPC_FUZZ_CASES")
        .ok()
        .and_then(|n| n.parse().ok())
        .unwrap_or(DEFAULT_CASES)
}

fn config() -> ProptestConfig {
    ProptestConfig {
        cases: cases(),
        // A failure is reported with its shrunk input; no regression file is written.
        failure_persistence: None,
        ..ProptestConfig::default()
    }
}

/// Floats including the extremes and non-finite values.
fn float() -> impl Strategy<Value = f32> {
    prop_oneof![
        any::<f32>(),
        Just(f32::MAX),
        Just(f32::MIN),
        Just(f32::NAN),
        Just(f32::INFINITY),
        -10.0f32..10.0,
    ]
}

fn observation() -> impl Strategy<Value = Observation> {
    (
        any::<u32>(),
        any::<u32>(),
        prop::collection::vec(float(), 0..40),
        prop::option::of(float()),
        prop::option::of(prop_oneof![
            Just(EpisodeEnd::Terminated),
            Just(EpisodeEnd::TimeLimit),
            Just(EpisodeEnd::Interrupted),
        ]),
    )
        .prop_map(|(episode, step, obs, reward, end)| {
            Observation::new(episode, step, obs, reward, end)
        })
}

fn name() -> impl Strategy<Value = String> {
    prop::collection::vec(any::<char>(), 0..20).prop_map(|c| c.into_iter().collect())
}

fn attach_request() -> impl Strategy<Value = AttachRequest> {
    (
        name(),
        prop::sample::select(TaskId::ALL.to_vec()),
        prop::option::of(name()),
        prop::option::of(any::<u32>()),
        prop::option::of(float()),
        any::<u64>(),
    )
        .prop_map(|(agent, task, preset, size, weight, seed)| AttachRequest {
            version: PROTOCOL_VERSION,
            agent,
            spec: RunSpec {
                task,
                preset,
                overrides: PlannerOverrides {
                    dynamics_hidden_size: size,
                    population: size,
                    energy_weight: weight,
                    ..PlannerOverrides::default()
                },
                mode: if seed % 2 == 0 {
                    TrainMode::Sync
                } else {
                    TrainMode::Async
                },
                seed,
            },
        })
}

fn action() -> impl Strategy<Value = Action> {
    (
        any::<u32>(),
        any::<u32>(),
        prop::collection::vec(float(), 0..12),
        float(),
        any::<u64>(),
    )
        .prop_map(|(episode, step, action, x, models_version)| Action {
            version: PROTOCOL_VERSION,
            episode,
            step,
            action,
            stats: PlanStats {
                source: ActionSource::Planned,
                planning_ms: x,
                predicted_return: x,
                mean_energy: x,
                iterations: step % 7,
                models_version,
            },
        })
}

/// One edit of an encoding.
#[derive(Clone, Debug)]
enum Mutation {
    FlipBit { at: usize, bit: u8 },
    Overwrite { at: usize, byte: u8 },
    Insert { at: usize, bytes: Vec<u8> },
    Remove { at: usize, len: usize },
    Truncate { at: usize },
}

fn mutation() -> impl Strategy<Value = Mutation> {
    // Bytes that make extreme varints, lengths and JSON tokens.
    let nasty = prop_oneof![
        Just(vec![0xff, 0xff, 0xff, 0xff, 0x0f]),
        Just(vec![0xff; 10]),
        Just(b"1e999".to_vec()),
        Just(b"[[[[[[[[[[[[[[[[".to_vec()),
        Just(b"\"\\u0000".to_vec()),
        prop::collection::vec(any::<u8>(), 1..8),
    ];
    prop_oneof![
        (any::<usize>(), 0u8..8).prop_map(|(at, bit)| Mutation::FlipBit { at, bit }),
        (any::<usize>(), any::<u8>()).prop_map(|(at, byte)| Mutation::Overwrite { at, byte }),
        (any::<usize>(), nasty).prop_map(|(at, bytes)| Mutation::Insert { at, bytes }),
        (any::<usize>(), 1usize..8).prop_map(|(at, len)| Mutation::Remove { at, len }),
        any::<usize>().prop_map(|at| Mutation::Truncate { at }),
    ]
}

fn mutate(mut bytes: Vec<u8>, mutations: &[Mutation]) -> Vec<u8> {
    for m in mutations {
        let n = bytes.len();
        match m {
            Mutation::FlipBit { at, bit } if n > 0 => bytes[at % n] ^= 1 << bit,
            Mutation::Overwrite { at, byte } if n > 0 => bytes[at % n] = *byte,
            Mutation::Insert { at, bytes: new } => {
                let at = at % (n + 1);
                bytes.splice(at..at, new.iter().copied());
            }
            Mutation::Remove { at, len } if n > 0 => {
                let at = at % n;
                bytes.drain(at..(at + len).min(n));
            }
            Mutation::Truncate { at } => bytes.truncate(at % (n + 1)),
            _ => {}
        }
    }
    bytes
}

/// Decodes `bytes` as every message type in `encoding`, validating what decodes. Must not
/// panic; the results are dropped (an error is the expected outcome of most inputs).
fn decode_everything(bytes: &[u8], encoding: Encoding) {
    if let Ok(obs) = proto::decode::<Observation>(bytes, encoding) {
        for task in TaskId::ALL {
            let _ = validate_observation(&obs, task.spec());
        }
    }
    if let Ok(action) = proto::decode::<Action>(bytes, encoding) {
        for task in TaskId::ALL {
            let _ = validate_action(&action, task.spec());
        }
    }
    let _ = proto::decode::<AttachRequest>(bytes, encoding);
    let _ = proto::decode::<AttachReply>(bytes, encoding);
    let _ = proto::decode::<ErrorReport>(bytes, encoding);
    let _ = proto::decode::<RunEvent>(bytes, encoding);
}

fn encodings_of<T: serde::Serialize>(msg: &T) -> [(Vec<u8>, Encoding); 2] {
    [Encoding::Postcard, Encoding::Json].map(|e| (proto::encode(msg, e).expect("encodes"), e))
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn mutated_observations_never_panic(
        msg in observation(),
        mutations in prop::collection::vec(mutation(), 0..4),
    ) {
        for (bytes, encoding) in encodings_of(&msg) {
            // Unmutated and finite (JSON has no NaN), the message comes back as it was sent.
            let finite = msg.obs.iter().chain(&msg.reward).all(|x| x.is_finite());
            if mutations.is_empty() && (finite || encoding == Encoding::Postcard) {
                let back = proto::decode::<Observation>(&bytes, encoding).unwrap();
                prop_assert_eq!(format!("{back:?}"), format!("{msg:?}"));
            }
            decode_everything(&mutate(bytes, &mutations), encoding);
        }
    }

    #[test]
    fn mutated_attach_requests_and_actions_never_panic(
        attach in attach_request(),
        act in action(),
        mutations in prop::collection::vec(mutation(), 1..4),
    ) {
        for (bytes, encoding) in encodings_of(&attach).into_iter().chain(encodings_of(&act)) {
            decode_everything(&mutate(bytes, &mutations), encoding);
        }
    }

    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
        decode_everything(&bytes, Encoding::Postcard);
        decode_everything(&bytes, Encoding::Json);
    }
}

/// A length prefix claiming billions of numbers in a few bytes is an error, decided without
/// reserving what the prefix claims (serde caps preallocation by what the input can hold).
#[test]
fn hostile_length_prefixes_are_refused() {
    let valid = proto::encode(
        &Observation::new(1, 2, vec![0.5; 4], Some(1.0), None),
        Encoding::Postcard,
    )
    .unwrap();
    // version, episode and step are one byte each here; the vector's length varint follows.
    let header = 3;
    for len in [u32::MAX as u64, u64::MAX >> 8, 1 << 40] {
        let mut bytes = valid[..header].to_vec();
        let mut v = len;
        while v >= 0x80 {
            bytes.push((v as u8) | 0x80);
            v >>= 7;
        }
        bytes.push(v as u8);
        bytes.extend_from_slice(&[0; 16]);
        assert!(proto::decode::<Observation>(&bytes, Encoding::Postcard).is_err());
    }
    let json = format!(
        r#"{{"version":{PROTOCOL_VERSION},"episode":0,"step":0,"obs":[{}"#,
        "1,".repeat(100_000)
    );
    assert!(proto::decode::<Observation>(json.as_bytes(), Encoding::Json).is_err());
}
