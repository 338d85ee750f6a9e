//! The JSON schema of every wire message, generated from the Rust types (`schemars`).
//!
//! Controllers in other languages speak JSON (see [`crate::codec`]); the schemas tell them the
//! exact shape of each message. They are checked in under `python/ebmpc/schema/` (the Python
//! package validates messages against them) with the daemon's status report, which
//! `planner-service` adds; `planner-service/tests/json_schema.rs` fails when the checked-in files
//! differ from what the types generate, so the two cannot drift.

use crate::messages::{
    Action, AttachReply, AttachRequest, ErrorReport, Observation, PROTOCOL_VERSION, RunEvent,
};
use schemars::{JsonSchema, generate::SchemaSettings};
use serde_json::{Value, json};

/// The file name (without `.json`) of the index that names the protocol version and the files.
pub const INDEX: &str = "protocol";

/// The JSON schema (draft 2020-12) of `T`.
pub fn schema_of<T: JsonSchema>() -> Value {
    SchemaSettings::draft2020_12()
        .into_generator()
        .into_root_schema_for::<T>()
        .to_value()
}

/// Every wire message's schema, by message name.
pub fn wire_schemas() -> Vec<(String, Value)> {
    vec![
        ("AttachRequest".into(), schema_of::<AttachRequest>()),
        ("AttachReply".into(), schema_of::<AttachReply>()),
        ("Observation".into(), schema_of::<Observation>()),
        ("Action".into(), schema_of::<Action>()),
        ("ErrorReport".into(), schema_of::<ErrorReport>()),
        ("RunEvent".into(), schema_of::<RunEvent>()),
    ]
}

/// The index file ([`INDEX`]): the protocol version (every message's `version` must equal it)
/// and the names of the schemas beside it.
pub fn index<'a>(names: impl IntoIterator<Item = &'a str>) -> Value {
    json!({
        "protocol_version": PROTOCOL_VERSION,
        "messages": names.into_iter().collect::<Vec<_>>(),
    })
}

/// The text a schema file holds: pretty JSON with a final newline.
pub fn file_text(schema: &Value) -> String {
    let mut text = serde_json::to_string_pretty(schema).expect("a JSON value serialises");
    text.push('\n');
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The schemas carry the wire spellings: snake_case error codes, lowercase tasks, the
    /// externally tagged attach outcome.
    #[test]
    fn schemas_use_the_wire_spellings() {
        let files = wire_schemas();
        let find = |name: &str| &files.iter().find(|(n, _)| n == name).unwrap().1;
        let report = find("ErrorReport").to_string();
        assert!(report.contains("\"out_of_range\"") && report.contains("\"storage\""));
        let request = find("AttachRequest").to_string();
        assert!(request.contains("\"cartpole\"") && request.contains("\"halfcheetah\""));
        let reply = find("AttachReply").to_string();
        assert!(reply.contains("\"Accepted\"") && reply.contains("\"Rejected\""));
        assert_eq!(index(["Action"])["protocol_version"], PROTOCOL_VERSION);
    }
}
