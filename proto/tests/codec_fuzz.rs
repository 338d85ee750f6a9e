//! Fuzz target for the codec and validation: valid encodings of the messages a planner or an
//! agent receives, mutated (bits flipped, bytes inserted, removed, overwritten with extreme
//! values, cut short), and plain random bytes, decoded in both encodings as every message type
//! and validated against every task. No input may panic, and hostile length prefixes must be
//! refused without allocating what they claim.
//!
//! CI runs a fixed budget ([`DEFAULT_INPUTS`], a few seconds). By hand, for as many inputs as
//! wanted: `EBMPC_FUZZ_INPUTS=10000000 cargo test -p ebmpc-proto --test codec_fuzz --
//! --nocapture` (it prints the count, seed and wall time). The generator is plain `rand` (no
//! nightly toolchain for cargo-fuzz, and no second build of the dependency tree).

use proto::task::{Builtin, SpecBounds};
use proto::validate::{validate_action, validate_observation};
use proto::{
    Action, ActionSource, AttachReply, AttachRequest, Encoding, EpisodeEnd, ErrorReport,
    Observation, PROTOCOL_VERSION, PlanStats, PlannerOverrides, RunEvent, RunSpec, TrainMode,
};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::time::Instant;

/// Inputs per run in CI (a few seconds on the development machine).
const DEFAULT_INPUTS: u64 = 200_000;

/// Floats including the extremes and non-finite values.
fn float(rng: &mut StdRng) -> f32 {
    match rng.random_range(0..6) {
        0 => f32::from_bits(rng.random()),
        1 => f32::MAX,
        2 => f32::MIN,
        3 => f32::NAN,
        4 => f32::INFINITY,
        _ => rng.random_range(-10.0..10.0),
    }
}

fn floats(rng: &mut StdRng, max: usize) -> Vec<f32> {
    let n = rng.random_range(0..=max);
    (0..n).map(|_| float(rng)).collect()
}

fn text(rng: &mut StdRng) -> String {
    let n = rng.random_range(0..20);
    (0..n)
        .map(|_| char::from_u32(rng.random_range(0..0x11_0000)).unwrap_or('x'))
        .collect()
}

fn observation(rng: &mut StdRng) -> Observation {
    let end = match rng.random_range(0..4) {
        0 => Some(EpisodeEnd::Terminated),
        1 => Some(EpisodeEnd::TimeLimit),
        2 => Some(EpisodeEnd::Interrupted),
        _ => None,
    };
    let reward = rng.random_bool(0.5).then(|| float(rng));
    let obs = Observation::new(rng.random(), rng.random(), floats(rng, 40), reward, end)
        .in_session(rng.random());
    if rng.random_bool(0.5) {
        obs.with_applied(floats(rng, 12))
    } else {
        obs
    }
}

fn builtin(rng: &mut StdRng) -> Builtin {
    Builtin::ALL[rng.random_range(0..Builtin::ALL.len())]
}

/// A catalog spec with some of its numbers replaced by extreme ones.
fn task_spec(rng: &mut StdRng) -> proto::TaskSpec {
    let mut spec = builtin(rng).spec();
    if rng.random_bool(0.5) {
        spec.action_low = floats(rng, 12);
        spec.control_dt = float(rng).into();
        spec.obs_dim = rng.random::<u64>() as usize;
        spec.magnitudes.observation = float(rng);
    }
    spec
}

fn attach_request(rng: &mut StdRng) -> AttachRequest {
    let size = rng.random_bool(0.5).then(|| rng.random());
    AttachRequest {
        version: PROTOCOL_VERSION,
        agent: text(rng),
        spec: RunSpec {
            task: builtin(rng).name().to_string(),
            preset: rng.random_bool(0.5).then(|| text(rng)),
            overrides: PlannerOverrides {
                dynamics_hidden_size: size,
                population: size,
                energy_weight: rng.random_bool(0.5).then(|| float(rng)),
                ..PlannerOverrides::default()
            },
            mode: if rng.random_bool(0.5) {
                TrainMode::Sync
            } else {
                TrainMode::Async
            },
            seed: rng.random(),
            task_spec: rng.random_bool(0.3).then(|| task_spec(rng)),
        },
        session: rng.random_bool(0.5).then(|| rng.random()),
    }
}

fn action(rng: &mut StdRng) -> Action {
    let x = float(rng);
    Action {
        version: PROTOCOL_VERSION,
        episode: rng.random(),
        step: rng.random(),
        action: floats(rng, 12),
        stats: PlanStats {
            source: ActionSource::Planned,
            planning_ms: x,
            predicted_return: x,
            mean_energy: x,
            iterations: rng.random(),
            models_version: rng.random(),
            cut: rng.random(),
            missed: rng.random(),
        },
        epoch: rng.random(),
    }
}

/// Bytes that make extreme varints, lengths and JSON tokens.
fn nasty(rng: &mut StdRng) -> Vec<u8> {
    match rng.random_range(0..6) {
        0 => vec![0xff, 0xff, 0xff, 0xff, 0x0f],
        1 => vec![0xff; 10],
        2 => b"1e999".to_vec(),
        3 => b"[[[[[[[[[[[[[[[[".to_vec(),
        4 => b"\"\\u0000".to_vec(),
        _ => {
            let n = rng.random_range(1..8);
            (0..n).map(|_| rng.random()).collect()
        }
    }
}

/// Up to three edits of `bytes`: a bit flipped, a byte overwritten, bytes inserted or removed,
/// the tail cut off.
fn mutate(rng: &mut StdRng, mut bytes: Vec<u8>) -> Vec<u8> {
    for _ in 0..rng.random_range(0..=3) {
        let n = bytes.len();
        match rng.random_range(0..5) {
            0 if n > 0 => bytes[rng.random_range(0..n)] ^= 1 << rng.random_range(0..8),
            1 if n > 0 => bytes[rng.random_range(0..n)] = rng.random(),
            2 => {
                let at = rng.random_range(0..=n);
                let new = nasty(rng);
                bytes.splice(at..at, new);
            }
            3 if n > 0 => {
                let at = rng.random_range(0..n);
                let len = rng.random_range(1..8);
                bytes.drain(at..(at + len).min(n));
            }
            4 => bytes.truncate(rng.random_range(0..=n)),
            _ => {}
        }
    }
    bytes
}

/// Decodes `bytes` as every message type in `encoding`, validating what decodes. Must not
/// panic; the results are dropped (an error is the expected outcome of most inputs).
fn decode_everything(bytes: &[u8], encoding: Encoding) {
    if let Ok(obs) = proto::decode::<Observation>(bytes, encoding) {
        for task in Builtin::ALL.iter().map(|b| b.task()) {
            let _ = validate_observation(&obs, task, &task.magnitudes);
        }
    }
    if let Ok(action) = proto::decode::<Action>(bytes, encoding) {
        for task in Builtin::ALL.iter().map(|b| b.task()) {
            let _ = validate_action(&action, task);
        }
    }
    if let Ok(attach) = proto::decode::<AttachRequest>(bytes, encoding)
        && let Some(spec) = attach.spec.task_spec
    {
        let _ = spec.validate(&SpecBounds::default());
    }
    let _ = proto::decode::<AttachReply>(bytes, encoding);
    let _ = proto::decode::<ErrorReport>(bytes, encoding);
    let _ = proto::decode::<RunEvent>(bytes, encoding);
}

/// One fuzz input: a message of a random kind, encoded, mutated; or random bytes.
fn input(rng: &mut StdRng) -> (Vec<u8>, Encoding) {
    let encoding = if rng.random_bool(0.5) {
        Encoding::Postcard
    } else {
        Encoding::Json
    };
    let encoded = match rng.random_range(0..4) {
        0 => proto::encode(&observation(rng), encoding),
        1 => proto::encode(&attach_request(rng), encoding),
        2 => proto::encode(&action(rng), encoding),
        _ => {
            let n = rng.random_range(0..256);
            return ((0..n).map(|_| rng.random()).collect(), encoding);
        }
    };
    (
        mutate(rng, encoded.expect("a generated message encodes")),
        encoding,
    )
}

/// The fuzz loop: `EBMPC_FUZZ_INPUTS` inputs (default [`DEFAULT_INPUTS`]) from seed
/// `EBMPC_FUZZ_SEED` (default: the time). A panic prints the seed, the input's index and its
/// bytes, so it can be replayed.
#[test]
fn no_input_panics_the_codec_or_validation() {
    let env = |name: &str| std::env::var(name).ok().and_then(|v| v.parse::<u64>().ok());
    let inputs = env("EBMPC_FUZZ_INPUTS").unwrap_or(DEFAULT_INPUTS);
    let seed = env("EBMPC_FUZZ_SEED").unwrap_or_else(|| {
        std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64)
    });
    let mut rng = StdRng::seed_from_u64(seed);
    let started = Instant::now();
    for i in 0..inputs {
        let (bytes, encoding) = input(&mut rng);
        let outcome = std::panic::catch_unwind(|| decode_everything(&bytes, encoding));
        if outcome.is_err() {
            panic!("input {i} of seed {seed} ({encoding:?}) panicked: {bytes:02x?}");
        }
    }
    println!(
        "fuzz: {inputs} inputs from seed {seed} in {:.1} s, no panic",
        started.elapsed().as_secs_f64()
    );
}

/// Unmutated, every generated message comes back as it was sent (NaN aside: JSON has none).
#[test]
fn generated_messages_round_trip() {
    let mut rng = StdRng::seed_from_u64(7);
    for _ in 0..2_000 {
        let msg = observation(&mut rng);
        for encoding in [Encoding::Postcard, Encoding::Json] {
            let finite = msg
                .obs
                .iter()
                .chain(&msg.reward)
                .chain(msg.applied.iter().flatten())
                .all(|x| x.is_finite());
            if encoding == Encoding::Json && !finite {
                continue;
            }
            let bytes = proto::encode(&msg, encoding).unwrap();
            let back: Observation = proto::decode(&bytes, encoding).unwrap();
            assert_eq!(format!("{back:?}"), format!("{msg:?}"));
        }
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
