//! The library's top-level modules form layers: no module reaches, through `crate::` paths in
//! its code, a module that reaches it back. docs/architecture.md draws the same graph; a cycle
//! fails here with the files that close it, so the arrows keep pointing one way.

use std::collections::{BTreeMap, BTreeSet};
use std::fs;
use std::path::{Path, PathBuf};

/// Every `.rs` file under `dir`.
fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    for entry in fs::read_dir(dir).expect("readable source folder") {
        let path = entry.expect("readable entry").path();
        if path.is_dir() {
            rust_files(&path, out);
        } else if path.extension().is_some_and(|e| e == "rs") {
            out.push(path);
        }
    }
}

/// The code of a file without its comments and without its unit tests (everything from the
/// first `#[cfg(test)]`, which by the project's layout is the tests module at the end): tests
/// may reach anywhere.
fn code_of(path: &Path) -> String {
    let text = fs::read_to_string(path).expect("readable source file");
    let text = match text.find("#[cfg(test)]") {
        Some(at) => &text[..at],
        None => &text[..],
    };
    text.lines()
        .filter(|line| !line.trim_start().starts_with("//"))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The top-level modules each `crate::` path names.
fn crate_paths(code: &str) -> BTreeSet<String> {
    let mut found = BTreeSet::new();
    let mut rest = code;
    while let Some(at) = rest.find("crate::") {
        let name: String = rest[at + "crate::".len()..]
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect();
        found.insert(name);
        rest = &rest[at + "crate::".len()..];
    }
    found
}

/// module → (module it uses → the files that use it).
type Graph = BTreeMap<String, BTreeMap<String, BTreeSet<String>>>;

fn library_graph() -> Graph {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut modules = BTreeMap::new();
    for entry in fs::read_dir(&src).expect("src/") {
        let path = entry.expect("entry").path();
        let name = path
            .file_stem()
            .expect("named")
            .to_string_lossy()
            .to_string();
        if path.is_dir() && name != "bin" {
            let mut files = Vec::new();
            rust_files(&path, &mut files);
            modules.insert(name, files);
        } else if path.extension().is_some_and(|e| e == "rs") && name != "lib" && name != "main" {
            modules.insert(name, vec![path]);
        }
    }
    let mut graph = Graph::new();
    for (module, files) in &modules {
        let uses = graph.entry(module.clone()).or_default();
        for file in files {
            for used in crate_paths(&code_of(file)) {
                if &used != module && modules.contains_key(&used) {
                    let shown = file
                        .strip_prefix(&src)
                        .unwrap_or(file)
                        .display()
                        .to_string();
                    uses.entry(used).or_default().insert(shown);
                }
            }
        }
    }
    graph
}

/// A path from `from` back to `to` through the graph, if there is one.
fn path_between(graph: &Graph, from: &str, to: &str) -> Option<Vec<String>> {
    let mut stack = vec![vec![from.to_string()]];
    let mut seen = BTreeSet::new();
    while let Some(path) = stack.pop() {
        let last = path.last().expect("non-empty").clone();
        if last == to {
            return Some(path);
        }
        if !seen.insert(last.clone()) {
            continue;
        }
        for next in graph.get(&last).into_iter().flat_map(|uses| uses.keys()) {
            let mut longer = path.clone();
            longer.push(next.clone());
            stack.push(longer);
        }
    }
    None
}

#[test]
fn the_library_modules_form_layers_without_a_cycle() {
    let graph = library_graph();
    assert!(
        graph.len() > 10,
        "found the library's modules: {:?}",
        graph.keys()
    );
    let mut cycles = Vec::new();
    for (module, uses) in &graph {
        for (used, files) in uses {
            if let Some(back) = path_between(&graph, used, module) {
                cycles.push(format!(
                    "{module} -> {used} (in {files:?}) and back: {}",
                    back.join(" -> ")
                ));
            }
        }
    }
    assert!(cycles.is_empty(), "module cycles:\n{}", cycles.join("\n"));
}

#[test]
fn a_cycle_is_found_when_one_exists() {
    let mut graph = Graph::new();
    let edge = |graph: &mut Graph, a: &str, b: &str| {
        graph
            .entry(a.to_string())
            .or_default()
            .insert(b.to_string(), BTreeSet::from(["x.rs".to_string()]));
    };
    edge(&mut graph, "service", "run");
    edge(&mut graph, "run", "models");
    assert_eq!(path_between(&graph, "models", "service"), None);
    edge(&mut graph, "models", "service");
    assert_eq!(
        path_between(&graph, "models", "service"),
        Some(vec!["models".to_string(), "service".to_string()])
    );
    assert_eq!(
        crate_paths("use crate::run::stats::X; let y = crate::models::f();"),
        BTreeSet::from(["run".to_string(), "models".to_string()])
    );
}
