//! Every JSON schema a client of this daemon reads: the wire messages' ([`proto::schema`]) and
//! the status report's, with the index that names them and the protocol version. Checked in
//! under `python/ebmpc/schema/`; `tests/json_schema.rs` compares them with these.

use super::status::PlannerStatus;
use proto::schema::{index, schema_of, wire_schemas};
use serde_json::Value;

/// `(file stem, schema)` of every schema file, the index ([`proto::schema::INDEX`]) last.
pub fn json_schemas() -> Vec<(String, Value)> {
    let mut files = wire_schemas();
    files.push(("PlannerStatus".into(), schema_of::<PlannerStatus>()));
    let names = index(files.iter().map(|(name, _)| name.as_str()));
    files.push((proto::schema::INDEX.into(), names));
    files
}
