//! The `ebmpc` Python package's own tests (`python/tests`, pytest) against this build's planner
//! daemon: attach, episodes, run events, status and typed errors through the package, every JSON
//! message on the run's keys checked against the schemas generated from the Rust types, and
//! `mypy --strict` over the package. Run through `cargo test` so that `make test` (CI) runs them.
//!
//! The interpreter is `$EBMPC_PYTHON`, or `.venv/bin/python` in the workspace (see
//! [`ebmpc_e2e::python`]); `make test` installs what it needs. Without it this test fails.

use ebmpc_e2e::TempDir;
use ebmpc_e2e::python::run_package_tests;
use std::time::Duration;

#[test]
fn python_package_tests_pass() {
    let dir = TempDir::new("python-package");
    let (status, log) = run_package_tests(dir.path(), Duration::from_secs(300)).unwrap();
    assert!(status.success(), "python/tests failed ({status}):\n{log}");
    assert!(log.contains(" passed"), "{log}");
    assert!(!log.contains("skipped"), "no package test may skip: {log}");
}
