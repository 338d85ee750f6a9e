//! The checked-in JSON schemas (`python/ebmpc/schema/*.json`) are what the Rust types generate.
//!
//! After changing a message or the status report, write them again with
//! `EBMPC_WRITE_SCHEMA=1 cargo test -p planner-service --test json_schema` and commit them.

use planner_service::service::schema::json_schemas;
use proto::schema::file_text;
use std::collections::BTreeSet;
use std::path::PathBuf;

const FIX: &str =
    "write them again: EBMPC_WRITE_SCHEMA=1 cargo test -p planner-service --test json_schema";

fn schema_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../python/ebmpc/schema")
}

fn json_files() -> BTreeSet<String> {
    std::fs::read_dir(schema_dir())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".json"))
        .collect()
}

#[test]
fn checked_in_schemas_match_the_rust_types() {
    let dir = schema_dir();
    let generated = json_schemas();
    if std::env::var_os("EBMPC_WRITE_SCHEMA").is_some() {
        std::fs::create_dir_all(&dir).unwrap();
        for stale in json_files() {
            std::fs::remove_file(dir.join(stale)).unwrap();
        }
        for (name, schema) in &generated {
            std::fs::write(dir.join(format!("{name}.json")), file_text(schema)).unwrap();
        }
    }
    for (name, schema) in &generated {
        let path = dir.join(format!("{name}.json"));
        let on_disk = std::fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("{} unreadable ({e}): {FIX}", path.display()));
        assert!(
            on_disk == file_text(schema),
            "{} differs from the schema of the Rust types: {FIX}",
            path.display()
        );
    }
    // No stale file of a message that no longer exists.
    let expected: BTreeSet<String> = generated.iter().map(|(n, _)| format!("{n}.json")).collect();
    assert_eq!(json_files(), expected, "schema files: {FIX}");
}
