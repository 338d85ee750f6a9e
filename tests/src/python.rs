//! Python as the tests run it: the `ebmpc` package's own tests (`python/tests`, pytest), the
//! example controller (`examples/python_controller.py`, a user of the package) and the
//! package's Gymnasium driver (`python -m ebmpc.gym`).
//!
//! The interpreter is `$EBMPC_PYTHON`, or `.venv/bin/python` in the workspace, where `make test`
//! installs the package's dependencies (`examples/setup-python.sh`). The package itself is
//! imported from `python/` (`PYTHONPATH`), so the tests run the working tree's code, never an
//! older installed copy. Without the interpreter the tests that need it fail: they never skip.

use crate::{Guarded, binaries, free_port, workspace};
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
        .args(args)
        .env("PYTHONPATH", workspace().join("python"));
    let log = dir.join(format!("python-{}.log", free_port()));
    let mut process = Guarded::spawn("python_controller.py", cmd, log)?;
    let status = process.wait(timeout)?;
    Ok((status, process.log()))
}

/// Runs the Gymnasium driver (`python -m ebmpc.gym`) with `args` to completion (killed after
/// `timeout`); its exit status and everything it printed. The environments come from the
/// `gymnasium[mujoco]` that `make test` installs with the package's `gym` extra.
pub fn run_gym_driver(
    dir: &Path,
    args: &[&str],
    timeout: Duration,
) -> Result<(ExitStatus, String)> {
    let mut cmd = Command::new(interpreter()?);
    cmd.args(["-m", "ebmpc.gym"])
        .args(args)
        .env("PYTHONPATH", workspace().join("python"));
    let log = dir.join(format!("gym-{}.log", free_port()));
    let mut process = Guarded::spawn("python -m ebmpc.gym", cmd, log)?;
    let status = process.wait(timeout)?;
    Ok((status, process.log()))
}

/// Runs the package's pytest suite (`python/tests`) against this build's `planner-service`,
/// killed after `timeout` (its daemons die with it: they hold a parent-death signal); its exit
/// status and everything it printed.
pub fn run_package_tests(dir: &Path, timeout: Duration) -> Result<(ExitStatus, String)> {
    let mut cmd = Command::new(interpreter()?);
    cmd.args(["-m", "pytest", "-q", "-p", "no:cacheprovider", "--basetemp"])
        .arg(dir.join("pytest"))
        .arg(workspace().join("python/tests"))
        .current_dir(workspace().join("python"))
        .env("PYTHONPATH", workspace().join("python"))
        .env("EBMPC_PLANNER_BIN", &binaries().planner);
    let log = dir.join(format!("pytest-{}.log", free_port()));
    let mut process = Guarded::spawn("pytest", cmd, log)?;
    let status = process.wait(timeout)?;
    Ok((status, process.log()))
}
