//! The Python example controller (`examples/python_controller.py`, `eclipse-zenoh`, JSON
//! encoding) as the tests run it.
//!
//! The interpreter is `$EBMPC_PYTHON`, or `.venv/bin/python` in the workspace, where `make test`
//! installs `eclipse-zenoh`. Without it the tests that need it fail: they never skip.

use crate::{Guarded, free_port, workspace};
use anyhow::{Result, bail};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitStatus};
use std::time::Duration;

/// The Python interpreter with `eclipse-zenoh`.
///
/// # Errors
/// If there is none, saying how to get one.
pub fn interpreter() -> Result<PathBuf> {
    let python = std::env::var_os("EBMPC_PYTHON")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join(".venv/bin/python"));
    const FIX: &str =
        "run `make test`, which installs eclipse-zenoh into .venv/, or set EBMPC_PYTHON";
    let probe = match Command::new(&python).args(["-c", "import zenoh"]).output() {
        Ok(probe) => probe,
        Err(e) => bail!("no Python interpreter at {} ({e}): {FIX}", python.display()),
    };
    if !probe.status.success() {
        bail!(
            "{} cannot import zenoh: {FIX}\n{}",
            python.display(),
            String::from_utf8_lossy(&probe.stderr)
        );
    }
    Ok(python)
}

/// Runs the example controller with `args` to completion (killed after `timeout`); its exit
/// status and everything it printed.
pub fn run_controller(
    dir: &Path,
    args: &[&str],
    timeout: Duration,
) -> Result<(ExitStatus, String)> {
    let mut cmd = Command::new(interpreter()?);
    cmd.arg(workspace().join("examples/python_controller.py"))
        .args(args);
    let log = dir.join(format!("python-{}.log", free_port()));
    let mut process = Guarded::spawn("python_controller.py", cmd, log)?;
    let status = process.wait(timeout)?;
    Ok((status, process.log()))
}
