//! Harness for end-to-end tests that start the real `planner-service` and `sim-bridge`
//! binaries: it builds them once, picks free loopback ports, keeps every child process in a
//! guard that kills it when dropped (also when a test fails), and gives each test its own
//! temporary directory.

pub mod client;

use anyhow::{Context, Result, bail};
use std::io::Read;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Output, Stdio};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// The workspace root.
pub fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ is inside the workspace")
        .to_path_buf()
}

/// Paths of the two binaries, built (in the test profile's target dir) on first use.
pub struct Binaries {
    pub planner: PathBuf,
    pub bridge: PathBuf,
}

/// Builds `planner-service` and `sim-bridge` once per test process, in the profile the caller
/// was built in (tests: dev; `cargo bench`: release), and returns their paths.
pub fn binaries() -> &'static Binaries {
    static BINARIES: OnceLock<Binaries> = OnceLock::new();
    BINARIES.get_or_init(|| {
        // Test and bench executables live in target/<profile>/deps; binaries in target/<profile>.
        let exe = std::env::current_exe().expect("current exe");
        let dir = exe
            .parent()
            .and_then(Path::parent)
            .expect("target/<profile>")
            .to_path_buf();
        let mut args = vec!["build", "--workspace", "--bins"];
        if dir.file_name().is_some_and(|name| name == "release") {
            args.push("--release");
        }
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let status = Command::new(cargo)
            .current_dir(workspace())
            .args(&args)
            .status()
            .expect("cargo runs");
        assert!(status.success(), "building the binaries failed");
        let b = Binaries {
            planner: dir.join("planner-service"),
            bridge: dir.join("sim-bridge"),
        };
        assert!(
            b.planner.exists() && b.bridge.exists(),
            "binaries not found in {}",
            dir.display()
        );
        b
    })
}

/// A loopback TCP port that was free a moment ago.
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free port")
}

/// A Zenoh TCP endpoint on a free loopback port.
pub fn free_endpoint() -> String {
    format!("tcp/127.0.0.1:{}", free_port())
}

/// A directory removed when dropped.
pub struct TempDir(PathBuf);

impl TempDir {
    pub fn new(name: &str) -> Self {
        static COUNTER: AtomicUsize = AtomicUsize::new(0);
        let n = COUNTER.fetch_add(1, Ordering::SeqCst);
        let dir = std::env::temp_dir().join(format!("ebmpc-e2e-{}-{n}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).expect("temp dir");
        Self(dir)
    }

    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.0);
        } else {
            eprintln!("keeping {} for inspection", self.0.display());
        }
    }
}

/// A child process that is killed (and reaped) when dropped.
pub struct Guarded {
    child: Option<Child>,
    name: String,
    log: PathBuf,
}

impl Guarded {
    /// Starts `cmd` with stdout and stderr to `log`.
    pub fn spawn(name: &str, mut cmd: Command, log: PathBuf) -> Result<Self> {
        let file =
            std::fs::File::create(&log).with_context(|| format!("create {}", log.display()))?;
        cmd.stdout(file.try_clone()?)
            .stderr(file)
            .stdin(Stdio::null());
        let child = cmd.spawn().with_context(|| format!("start {name}"))?;
        Ok(Self {
            child: Some(child),
            name: name.to_string(),
            log,
        })
    }

    pub fn pid(&self) -> u32 {
        self.child.as_ref().expect("running").id()
    }

    /// Everything the process printed so far.
    pub fn log(&self) -> String {
        let mut text = String::new();
        if let Ok(mut f) = std::fs::File::open(&self.log) {
            let _ = f.read_to_string(&mut text);
        }
        text
    }

    /// Waits until the log contains `needle`, or fails after `timeout` (or if the process exits).
    pub fn wait_for_log(&mut self, needle: &str, timeout: Duration) -> Result<()> {
        let start = Instant::now();
        loop {
            if self.log().contains(needle) {
                return Ok(());
            }
            if let Some(status) = self.child.as_mut().expect("running").try_wait()? {
                bail!(
                    "{} exited ({status}) before logging `{needle}`:\n{}",
                    self.name,
                    self.log()
                );
            }
            if start.elapsed() > timeout {
                bail!(
                    "{} did not log `{needle}` within {timeout:?}:\n{}",
                    self.name,
                    self.log()
                );
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Waits for the process to exit on its own, killing it after `timeout`.
    pub fn wait(&mut self, timeout: Duration) -> Result<ExitStatus> {
        let start = Instant::now();
        let child = self.child.as_mut().expect("running");
        loop {
            if let Some(status) = child.try_wait()? {
                self.child = None;
                return Ok(status);
            }
            if start.elapsed() > timeout {
                let _ = child.kill();
                let _ = child.wait();
                self.child = None;
                bail!(
                    "{} still running after {timeout:?}; killed. Log:\n{}",
                    self.name,
                    self.log()
                );
            }
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Sends `signal` (e.g. "TERM", "KILL") to the process.
    pub fn signal(&self, signal: &str) -> Result<()> {
        let status = Command::new("kill")
            .arg(format!("-{signal}"))
            .arg(self.pid().to_string())
            .status()?;
        if !status.success() {
            bail!("kill -{signal} {} failed", self.pid());
        }
        Ok(())
    }

    /// SIGTERM, then wait for a clean exit.
    pub fn terminate(&mut self, timeout: Duration) -> Result<ExitStatus> {
        self.signal("TERM")?;
        self.wait(timeout)
    }
}

impl Drop for Guarded {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// A planner daemon listening on its own free loopback endpoint.
pub struct Planner {
    pub process: Guarded,
    pub endpoint: String,
    pub data_dir: PathBuf,
}

impl Planner {
    /// Starts a planner with `config` (TOML) written to `dir`, serving `dir/data`, and waits
    /// until it serves.
    pub fn start(dir: &Path, config: &str) -> Result<Self> {
        Self::start_on(dir, config, &free_endpoint())
    }

    /// As [`Planner::start`], on a given endpoint (to restart a planner where agents expect it).
    pub fn start_on(dir: &Path, config: &str, endpoint: &str) -> Result<Self> {
        let config_path = dir.join("planner.toml");
        std::fs::write(&config_path, config)?;
        let data_dir = dir.join("data");
        let mut cmd = Command::new(&binaries().planner);
        cmd.args(["serve", "--config"])
            .arg(&config_path)
            .args(["--listen", endpoint, "--data-dir"])
            .arg(&data_dir);
        cmd.env("RUST_LOG", "info,zenoh=warn");
        let log = dir.join(format!("planner-{}.log", free_port()));
        let mut process = Guarded::spawn("planner-service", cmd, log)?;
        process.wait_for_log("planner serving", Duration::from_secs(60))?;
        Ok(Self {
            process,
            endpoint: endpoint.to_string(),
            data_dir,
        })
    }
}

/// Runs `sim-bridge run` with `args` against `endpoint` to completion (killed after `timeout`).
pub fn run_bridge(
    dir: &Path,
    endpoint: &str,
    args: &[&str],
    timeout: Duration,
) -> Result<(ExitStatus, String)> {
    let mut cmd = Command::new(&binaries().bridge);
    cmd.arg("run").args(args).args(["--connect", endpoint]);
    cmd.env("RUST_LOG", "info,zenoh=warn");
    let log = dir.join(format!("bridge-{}.log", free_port()));
    let mut process = Guarded::spawn("sim-bridge", cmd, log)?;
    let status = process.wait(timeout)?;
    Ok((status, process.log()))
}

/// Runs a command to completion and returns its output.
pub fn output(cmd: &mut Command) -> Result<Output> {
    Ok(cmd.output()?)
}

/// Parses a CSV file with a header into rows of (column → value).
pub fn read_csv(path: &Path) -> Result<Vec<std::collections::BTreeMap<String, String>>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("read {}", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines.next().context("empty csv")?.split(',').collect();
    Ok(lines
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            header
                .iter()
                .map(|h| h.to_string())
                .zip(l.split(',').map(str::to_string))
                .collect()
        })
        .collect())
}
