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

/// A virtual environment made for one test from the system's Python (`$PYTHON`, or
/// `python3`), into which `pip install './python[gym]'` installed the package from the
/// working tree: its wheel, built by maturin, bundles this workspace's `planner-service`.
pub struct InstalledPackage {
    /// The venv's interpreter.
    pub python: PathBuf,
    /// The venv's scripts directory (`bin/`).
    pub bin: PathBuf,
    /// Seconds `pip install` took.
    pub install_seconds: f64,
}

/// Makes a clean venv in `dir/venv` and installs `./python[gym]` into it, as a user would
/// (killed after `timeout`).
///
/// The wheel's cargo build uses this test profile's target directory as its build directory
/// (`CARGO_BUILD_BUILD_DIR`: the compiled crates) and profile (maturin's `--profile dev` for
/// tests, `--release` for benches), so it reuses the crates [`binaries`] compiled instead of
/// building the workspace again: on CI that makes the install a compile of the binary's
/// `main.rs` and a link, not a release build of every dependency. Its final artifact goes to a
/// target directory of its own (`CARGO_TARGET_DIR=dir/cargo-target`), so the binary that the
/// other tests run from `target/<profile>` is never replaced under them. A user's
/// `pip install ./python` builds the release profile.
///
/// # Errors
/// If there is no Python with a `venv` module, or the installation fails (the error holds
/// pip's log).
pub fn install_package_in_clean_venv(dir: &Path, timeout: Duration) -> Result<InstalledPackage> {
    let target = binaries()
        .planner
        .parent()
        .expect("target/<profile>")
        .to_path_buf();
    let profile = if target.file_name().is_some_and(|name| name == "release") {
        "--release"
    } else {
        "--profile dev"
    };
    let target_dir = target.parent().expect("the target dir").to_path_buf();
    let base = std::env::var_os("PYTHON").unwrap_or_else(|| "python3".into());
    let venv = dir.join("venv");
    let bin = venv.join("bin");
    let python = bin.join("python");
    // Debian's python3 without python3-venv makes no pip: the base's pip installs then.
    let with_pip = Command::new(&base)
        .args(["-m", "venv"])
        .arg(&venv)
        .status()
        .is_ok_and(|s| s.success())
        && Command::new(&python)
            .args(["-m", "pip", "--version"])
            .output()
            .is_ok_and(|o| o.status.success());
    let mut pip = if with_pip {
        let mut pip = Command::new(&python);
        pip.args(["-m", "pip"]);
        pip
    } else {
        let _ = std::fs::remove_dir_all(&venv);
        let made = Command::new(&base)
            .args(["-m", "venv", "--without-pip"])
            .arg(&venv)
            .status()?;
        if !made.success() {
            bail!("cannot make a venv with {base:?} -m venv: install Python 3.9+ with venv");
        }
        let mut pip = Command::new(&base);
        pip.args(["-m", "pip", "--python"]).arg(&python);
        pip
    };
    let mut requirement = workspace().join("python").into_os_string();
    requirement.push("[gym]");
    pip.args([
        "install",
        "--disable-pip-version-check",
        "--progress-bar",
        "off",
    ])
    .arg(requirement)
    .current_dir(dir)
    .env("CARGO_TARGET_DIR", dir.join("cargo-target"))
    .env("CARGO_BUILD_BUILD_DIR", &target_dir)
    .env("MATURIN_PEP517_ARGS", profile)
    .env_remove("PYTHONPATH");
    for (name, _) in std::env::vars_os() {
        if name
            .to_str()
            .is_some_and(crate::set_by_cargo_for_this_crate)
        {
            pip.env_remove(name);
        }
    }
    let started = std::time::Instant::now();
    let mut process = Guarded::spawn("pip install", pip, dir.join("pip-install.log"))?;
    let status = process.wait(timeout)?;
    if !status.success() {
        bail!(
            "pip install './python[gym]' failed ({status}):\n{}",
            process.log()
        );
    }
    Ok(InstalledPackage {
        python,
        bin,
        install_seconds: started.elapsed().as_secs_f64(),
    })
}

impl InstalledPackage {
    /// Runs `python -m ebmpc.gym` of this venv with `args` to completion (killed after
    /// `timeout`), in `dir`, with nothing of the working tree on its path, no `EBMPC_*`
    /// setting, and `XDG_DATA_HOME=dir/xdg` (so the local planner's per-user data directory
    /// is `dir/xdg/ebmpc`); its exit status and everything it printed.
    pub fn run_gym_driver(
        &self,
        dir: &Path,
        args: &[&str],
        timeout: Duration,
    ) -> Result<(ExitStatus, String)> {
        let mut cmd = Command::new(&self.python);
        cmd.args(["-m", "ebmpc.gym"])
            .args(args)
            .current_dir(dir)
            .env_remove("PYTHONPATH")
            .env("XDG_DATA_HOME", dir.join("xdg"));
        for (name, _) in std::env::vars_os() {
            if name.to_str().is_some_and(|n| n.starts_with("EBMPC_")) {
                cmd.env_remove(name);
            }
        }
        let log = dir.join(format!("gym-{}.log", free_port()));
        let mut process = Guarded::spawn("python -m ebmpc.gym", cmd, log)?;
        let status = process.wait(timeout)?;
        Ok((status, process.log()))
    }
}
