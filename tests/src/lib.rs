//! Harness for end-to-end tests that start the real `planner-service` and `sim-bridge`
//! binaries: it builds them once, picks free loopback ports, keeps every child process in a
//! guard that kills it when dropped (also when a test fails), and gives each test its own
//! temporary directory. Its modules speak for the other parties: [`config`] writes a test
//! planner's configuration, [`bridge`] runs sim-bridge and reads its episodes, [`client`] is a
//! scripted agent, [`etcd`] runs a real etcd for a fleet, [`proxy`] is a TCP link a test can
//! cut, [`python`] runs the Python package's tests, its example controller and its Gymnasium
//! driver, and [`transitions`] compares acknowledged transitions with stored ones bit for bit.

pub mod bridge;
pub mod client;
pub mod config;
pub mod etcd;
pub mod fleet;
pub mod kill_loop;
pub mod proxy;
pub mod python;
pub mod transitions;

use anyhow::{Context, Result, bail};
use planner_service::replay::ReplayBuffer;
use proto::Builtin;
use std::io::Read;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitStatus, Stdio};
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

/// Whether `name` is one of the variables cargo sets for the crate being run (this test
/// crate's manifest directory, package name and version, ...). The nested `cargo build` must
/// not inherit them: build scripts (ring's, under rustls and zenoh's TLS link) rerun when such
/// a variable differs from the last build, so an inherited `CARGO_PKG_NAME=ebmpc-e2e` made
/// every e2e run recompile ring, rustls and zenoh's links, and the next plain `cargo build`
/// recompile them back.
fn set_by_cargo_for_this_crate(name: &str) -> bool {
    const EXACT: &[&str] = &[
        "CARGO_MANIFEST_DIR",
        "CARGO_MANIFEST_PATH",
        "CARGO_MANIFEST_LINKS",
        "CARGO_CRATE_NAME",
        "CARGO_BIN_NAME",
        "CARGO_PRIMARY_PACKAGE",
        "CARGO_TARGET_TMPDIR",
        "CARGO_RUSTC_CURRENT_DIR",
        "OUT_DIR",
    ];
    EXACT.contains(&name) || name.starts_with("CARGO_PKG_") || name.starts_with("CARGO_BIN_EXE_")
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
        let mut build = Command::new(cargo);
        build.current_dir(workspace()).args(&args);
        for (name, _) in std::env::vars_os() {
            if name.to_str().is_some_and(set_by_cargo_for_this_crate) {
                build.env_remove(name);
            }
        }
        let status = build.status().expect("cargo runs");
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
        Ok(Self {
            process: serve(dir, config, Some(endpoint))?,
            endpoint: endpoint.to_string(),
            data_dir: dir.join("data"),
        })
    }

    /// SIGTERM, then a clean exit within 30 s.
    ///
    /// # Errors
    /// If the daemon does not exit, or exits unsuccessfully (the error holds its log).
    pub fn stop(&mut self) -> Result<()> {
        let status = self.process.terminate(Duration::from_secs(30))?;
        if !status.success() {
            bail!("planner exit: {status}\n{}", self.process.log());
        }
        Ok(())
    }

    /// The replay buffer the daemon keeps for `run` of `task` (open it once the daemon stopped).
    pub fn replay(&self, run: &str, task: Builtin) -> Result<ReplayBuffer> {
        let path = self.data_dir.join("runs").join(run);
        ReplayBuffer::read(&path, task.task()).with_context(|| format!("read {}", path.display()))
    }
}

/// The newest replay segment of `run` stored in `data_dir` (the file its owner writes to).
///
/// # Panics
/// If the run has no replay stored.
pub fn newest_replay_segment(data_dir: &Path, run: &str) -> PathBuf {
    let root = data_dir.join("runs").join(run);
    let newest = planner_service::replay::segments::list(&root)
        .expect("the run's replay segments can be listed")
        .pop()
        .expect("the run has stored replay");
    root.join(newest.name())
}

/// Starts `planner-service serve` with `config` (TOML) written to `dir/planner.toml`, serving
/// `dir/data` and listening on `listen` (if any: a daemon may also only connect, as its
/// config's Zenoh file says), and waits until it serves.
pub fn serve(dir: &Path, config: &str, listen: Option<&str>) -> Result<Guarded> {
    serve_data(dir, &dir.join("data"), config, listen)
}

/// As [`serve`], with the data directory `data_dir` (planners of a fleet share one).
pub fn serve_data(
    dir: &Path,
    data_dir: &Path,
    config: &str,
    listen: Option<&str>,
) -> Result<Guarded> {
    let mut process = spawn_planner(dir, data_dir, config, listen)?;
    process.wait_for_log("planner serving", Duration::from_secs(60))?;
    Ok(process)
}

/// As [`serve_data`], without waiting for the planner to serve (it may be resuming its
/// stored runs).
pub fn spawn_planner(
    dir: &Path,
    data_dir: &Path,
    config: &str,
    listen: Option<&str>,
) -> Result<Guarded> {
    std::fs::create_dir_all(dir)?;
    let config_path = dir.join("planner.toml");
    std::fs::write(&config_path, config)?;
    let mut cmd = Command::new(&binaries().planner);
    cmd.args(["serve", "--config"])
        .arg(&config_path)
        .arg("--data-dir")
        .arg(data_dir);
    if let Some(endpoint) = listen {
        cmd.args(["--listen", endpoint]);
    }
    cmd.env("RUST_LOG", "info,zenoh=warn");
    let log = dir.join(format!("planner-{}.log", free_port()));
    Guarded::spawn("planner-service", cmd, log)
}

/// A Zenoh router in this process, listening on `endpoint` (multicast scouting off), as a
/// site's `zenohd` would run: every process of a test connects to it. Closed when dropped.
pub async fn router(endpoint: &str) -> Result<zenoh::Session> {
    let mut config = zenoh::Config::default();
    for (key, value) in [
        ("mode", "\"router\"".to_string()),
        ("scouting/multicast/enabled", "false".to_string()),
        ("listen/endpoints", format!("[\"{endpoint}\"]")),
    ] {
        config
            .insert_json5(key, &value)
            .map_err(|e| anyhow::anyhow!("router config {key}: {e}"))?;
    }
    zenoh::open(config)
        .await
        .map_err(|e| anyhow::anyhow!("router: {e}"))
}

/// Runs `planner-service status --connect endpoint` with `args`; its exit status, stdout and
/// stderr.
pub fn status_cli(endpoint: &str, args: &[&str]) -> Result<(ExitStatus, String, String)> {
    let out = Command::new(&binaries().planner)
        .args(["status", "--connect", endpoint])
        .args(args)
        .env("RUST_LOG", "warn")
        .output()
        .context("run planner-service status")?;
    Ok((
        out.status,
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    ))
}
