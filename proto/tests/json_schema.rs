//! The checked-in JSON schemas (`python/ebmpc/schema/*.json`) are what the Rust types generate.
//!
//! After changing a message, write them again with
//! `EBMPC_WRITE_SCHEMA=1 cargo test -p ebmpc-proto --test json_schema` and commit the result.

use proto::schema::{file_text, wire_schemas};
use std::collections::BTreeSet;
use std::path::PathBuf;

fn schema_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../python/ebmpc/schema")
}

#[test]
fn checked_in_schemas_match_the_rust_types() {
    let dir = schema_dir();
    let generated = wire_schemas();
    if std::env::var_os("EBMPC_WRITE_SCHEMA").is_some() {
        std::fs::create_dir_all(&dir).unwrap();
        for entry in std::fs::read_dir(&dir).unwrap() {
            let path = entry.unwrap().path();
            if path.extension().is_some_and(|e| e == "json") {
                std::fs::remove_file(path).unwrap();
            }
        }
        for (name, schema) in &generated {
            std::fs::write(dir.join(format!("{name}.json")), file_text(schema)).unwrap();
        }
    }
    const FIX: &str =
        "write them again: EBMPC_WRITE_SCHEMA=1 cargo test -p ebmpc-proto --test json_schema";
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
    let present: BTreeSet<String> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".json"))
        .collect();
    assert_eq!(
        present,
        expected,
        "schema files in {}: {FIX}",
        dir.display()
    );
}
