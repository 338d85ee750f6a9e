//! The codec: messages ⇄ bytes. The one place where serialisation happens.
//!
//! Two encodings: `postcard` (compact, the default between ebmpc processes) and JSON (for
//! controllers in other languages; a sample whose Zenoh encoding is `application/json` is decoded
//! as JSON and answered in JSON). Both start with the protocol version, which is checked before
//! the rest of the message is decoded.

use crate::messages::PROTOCOL_VERSION;
use serde::{Serialize, de::DeserializeOwned};

/// The wire encoding of a message.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Encoding {
    #[default]
    Postcard,
    Json,
}

impl Encoding {
    /// The MIME type ebmpc puts on samples of this encoding.
    pub fn mime(self) -> &'static str {
        match self {
            Encoding::Postcard => "application/postcard",
            Encoding::Json => "application/json",
        }
    }

    /// The encoding of a sample from its MIME type: JSON if it says so, postcard otherwise.
    pub fn from_mime(mime: &str) -> Self {
        if mime.starts_with("application/json") || mime.starts_with("text/json") {
            Encoding::Json
        } else {
            Encoding::Postcard
        }
    }
}

/// Bytes that are not a valid message.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    #[error("protocol version {found} is not supported (this peer speaks {expected})")]
    Version { found: u16, expected: u16 },
    #[error("malformed {encoding:?} message: {reason}")]
    Malformed { encoding: Encoding, reason: String },
    #[error("could not encode message: {0}")]
    Encode(String),
}

/// Encodes a message.
pub fn encode<T: Serialize>(msg: &T, encoding: Encoding) -> Result<Vec<u8>, CodecError> {
    match encoding {
        Encoding::Postcard => {
            postcard::to_stdvec(msg).map_err(|e| CodecError::Encode(e.to_string()))
        }
        Encoding::Json => serde_json::to_vec(msg).map_err(|e| CodecError::Encode(e.to_string())),
    }
}

/// Decodes a message after checking its protocol version.
pub fn decode<T: DeserializeOwned>(bytes: &[u8], encoding: Encoding) -> Result<T, CodecError> {
    let malformed = |reason: String| CodecError::Malformed { encoding, reason };
    let version = match encoding {
        Encoding::Postcard => postcard::take_from_bytes::<u16>(bytes)
            .map(|(v, _)| v)
            .map_err(|e| malformed(e.to_string()))?,
        Encoding::Json => {
            #[derive(serde::Deserialize)]
            struct Versioned {
                version: u16,
            }
            serde_json::from_slice::<Versioned>(bytes)
                .map(|v| v.version)
                .map_err(|e| malformed(e.to_string()))?
        }
    };
    if version != PROTOCOL_VERSION {
        return Err(CodecError::Version {
            found: version,
            expected: PROTOCOL_VERSION,
        });
    }
    match encoding {
        Encoding::Postcard => match postcard::take_from_bytes::<T>(bytes) {
            Ok((msg, [])) => Ok(msg),
            Ok((_, rest)) => Err(malformed(format!("{} trailing bytes", rest.len()))),
            Err(e) => Err(malformed(e.to_string())),
        },
        Encoding::Json => serde_json::from_slice(bytes).map_err(|e| malformed(e.to_string())),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::messages::*;

    fn observation() -> Observation {
        Observation {
            version: PROTOCOL_VERSION,
            episode: 3,
            step: 7,
            obs: vec![0.5, -1.0, 2.0, 0.0],
            reward: Some(0.25),
            end: None,
            applied: Some(vec![1.5]),
            session: u64::MAX,
        }
    }

    #[test]
    fn both_encodings_round_trip() {
        for enc in [Encoding::Postcard, Encoding::Json] {
            let bytes = encode(&observation(), enc).unwrap();
            assert_eq!(decode::<Observation>(&bytes, enc).unwrap(), observation());
        }
    }

    #[test]
    fn json_is_readable_by_other_languages() {
        let json = r#"{"version":6,"episode":0,"step":0,"obs":[1,2,3,4]}"#;
        let obs: Observation = decode(json.as_bytes(), Encoding::Json).unwrap();
        assert_eq!(obs.obs, vec![1.0, 2.0, 3.0, 4.0]);
        assert_eq!((obs.reward, obs.applied), (None, None));
        assert_eq!(
            obs.session, 0,
            "a JSON observation without a token is in no session"
        );
    }

    /// A field a message does not have is refused by name, in every message type and at every
    /// depth: the attach request, its run spec, the overrides, the observation, and the
    /// messages the planner sends (a client decoding them with this codec is as strict).
    #[test]
    fn unknown_fields_are_refused_by_name_in_every_message() {
        let v = PROTOCOL_VERSION;
        let attach = |extra: &str, spec_extra: &str| {
            format!(
                r#"{{"version":{v},"agent":"typo2","spec":{{"task":"cartpole","preset":"cem","overrides":{{"population":20,"elites":2}},"mode":"sync","seed":1{spec_extra}}}{extra}}}"#
            )
        };
        // The exact message that used to be accepted, and the same well-formed without it.
        decode::<AttachRequest>(attach("", "").as_bytes(), Encoding::Json).unwrap();
        type Decode<'a> = Box<dyn Fn() -> Result<(), CodecError> + 'a>;
        let cases: Vec<(&str, Decode<'_>)> = vec![
            (
                "colour",
                Box::new(move || {
                    decode::<AttachRequest>(
                        attach("", r#","colour":"red""#).as_bytes(),
                        Encoding::Json,
                    )
                    .map(drop)
                }),
            ),
            (
                "sesion",
                Box::new(move || {
                    decode::<AttachRequest>(attach(r#","sesion":5"#, "").as_bytes(), Encoding::Json)
                        .map(drop)
                }),
            ),
            (
                "populaton",
                Box::new(move || {
                    let text = attach("", "").replace("\"population\"", "\"populaton\"");
                    decode::<AttachRequest>(text.as_bytes(), Encoding::Json).map(drop)
                }),
            ),
            (
                "rewrd",
                Box::new(move || {
                    let text = format!(
                        r#"{{"version":{v},"episode":0,"step":1,"obs":[1,2,3,4],"rewrd":1.0}}"#
                    );
                    decode::<Observation>(text.as_bytes(), Encoding::Json).map(drop)
                }),
            ),
            (
                "extra",
                Box::new(move || {
                    let mut value = serde_json::to_value(Action {
                        version: v,
                        episode: 0,
                        step: 0,
                        action: vec![0.0],
                        stats: PlanStats {
                            source: ActionSource::Random,
                            planning_ms: 0.0,
                            predicted_return: 0.0,
                            mean_energy: 0.0,
                            iterations: 0,
                            models_version: 0,
                            cut: false,
                            missed: false,
                        },
                        epoch: 1,
                    })
                    .unwrap();
                    value["stats"]["extra"] = 1.into();
                    decode::<Action>(value.to_string().as_bytes(), Encoding::Json).map(drop)
                }),
            ),
            (
                "hint",
                Box::new(move || {
                    let mut value =
                        serde_json::to_value(ErrorReport::new(ErrorCode::Refused, "no")).unwrap();
                    value["hint"] = "x".into();
                    decode::<ErrorReport>(value.to_string().as_bytes(), Encoding::Json).map(drop)
                }),
            ),
        ];
        for (field, decode) in cases {
            let err = decode().expect_err(field);
            let CodecError::Malformed { reason, .. } = &err else {
                panic!("{field}: {err}");
            };
            assert!(
                reason.contains(&format!("unknown field `{field}`")),
                "{field}: {reason}"
            );
        }
    }

    #[test]
    fn wrong_version_is_named() {
        let mut msg = observation();
        msg.version = 9;
        for enc in [Encoding::Postcard, Encoding::Json] {
            let bytes = encode(&msg, enc).unwrap();
            let err = decode::<Observation>(&bytes, enc).unwrap_err();
            assert_eq!(
                err,
                CodecError::Version {
                    found: 9,
                    expected: PROTOCOL_VERSION
                }
            );
        }
    }

    #[test]
    fn garbage_and_truncation_are_malformed() {
        let bytes = encode(&observation(), Encoding::Postcard).unwrap();
        for bad in [
            &bytes[..bytes.len() - 3],
            &[][..],
            &[PROTOCOL_VERSION as u8, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff][..],
        ] {
            assert!(
                matches!(
                    decode::<Observation>(bad, Encoding::Postcard),
                    Err(CodecError::Malformed { .. })
                ),
                "{bad:?}"
            );
        }
        let mut long = bytes.clone();
        long.push(0);
        assert!(matches!(
            decode::<Observation>(&long, Encoding::Postcard),
            Err(CodecError::Malformed { .. })
        ));
        assert!(matches!(
            decode::<Observation>(b"{not json", Encoding::Json),
            Err(CodecError::Malformed { .. })
        ));
    }

    #[test]
    fn random_bytes_never_panic() {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for len in 0..300 {
            let bytes: Vec<u8> = (0..len)
                .map(|_| {
                    state ^= state << 13;
                    state ^= state >> 7;
                    state ^= state << 17;
                    state as u8
                })
                .collect();
            let _ = decode::<Observation>(&bytes, Encoding::Postcard);
            let _ = decode::<AttachRequest>(&bytes, Encoding::Postcard);
            let _ = decode::<Action>(&bytes, Encoding::Json);
        }
    }
}
