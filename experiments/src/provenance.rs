//! Where and how a run was produced: the record written beside each finished run's episodes
//! (`runs/<stem>.json`), so that a folder committed run by run, across days and machines,
//! still says for every episode of every run which binaries recorded it, on which CPU, along
//! which kernel paths (the ones the daemon measured and chose for the run's networks, and the
//! precision asked for) and under what load. A run resumed across sittings has one
//! [`Sitting`] per sitting that recorded episodes: kept in `runs/<stem>.sittings.json` while the
//! run is unfinished, and moved into the record when it finishes.

use serde::{Deserialize, Serialize};
use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

/// The machine a sitting runs on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Machine {
    pub hostname: String,
    /// `lscpu`'s "Model name" (from /proc/cpuinfo).
    pub cpu_model: String,
    /// CPU family and model numbers, e.g. "6/143".
    pub cpu_family_model: String,
    pub logical_cpus: usize,
    /// The kernel paths this CPU offers the planner, space-separated (e.g. `amx-bf16
    /// avx512-bf16 avx512-f32 avx2-f32 scalar-f32`): the candidates among which the daemon
    /// measures; which one each network ran is the run's [`RunKernels`].
    pub cpu_path: String,
}

impl Machine {
    /// This machine, as the running binaries see it.
    pub fn this() -> Self {
        let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
        let field = |key: &str| {
            cpuinfo
                .lines()
                .find(|l| l.split(':').next().is_some_and(|k| k.trim() == key))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
                .unwrap_or_else(|| "unknown".into())
        };
        let hostname = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .map(|h| h.trim().to_string())
            .unwrap_or_else(|_| "unknown".into());
        Machine {
            hostname,
            cpu_model: field("model name"),
            cpu_family_model: format!("{}/{}", field("cpu family"), field("model")),
            logical_cpus: std::thread::available_parallelism().map_or(1, |n| n.get()),
            cpu_path: cpu_path(),
        }
    }

    /// Whether `other` has this machine's CPU and as many logical CPUs: what a run's speed
    /// depends on (hostnames say nothing: virtual machines share them).
    pub fn same_cpu(&self, other: &Machine) -> bool {
        self.cpu_model == other.cpu_model
            && self.cpu_family_model == other.cpu_family_model
            && self.logical_cpus == other.logical_cpus
    }
}

/// The kernel paths the planner library can run here, space-separated, fastest-looking first.
pub fn cpu_path() -> String {
    planner_service::nn::KernelPath::available()
        .iter()
        .map(|p| p.name())
        .collect::<Vec<_>>()
        .join(" ")
}

/// What the daemon ran a run's networks on: the precision the run's preset asked for and the
/// kernel path of each network (chosen by measurement under `auto`), as the run's entry of
/// `planner-service status --json` reports them (`kernels`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct RunKernels {
    /// `auto`, `bf16` or `f32`.
    pub precision: String,
    pub dynamics: Option<String>,
    pub energy: Option<String>,
    pub reward: Option<String>,
}

/// How long [`run_kernels`] waits for `planner-service status`.
const STATUS_TIMEOUT: Duration = Duration::from_secs(20);

/// Asks the daemon at `endpoint` (through `planner-service status --json`, the binary at
/// `planner`) for the kernels of its run `run`. `None`, with the reason logged, when the daemon
/// does not answer in time or does not list the run: the record then says nothing rather than
/// something guessed.
pub fn run_kernels(planner: &Path, endpoint: &str, run: &str) -> Option<RunKernels> {
    let out = match status_json(planner, endpoint) {
        Ok(out) => out,
        Err(e) => {
            tracing::warn!(run, "no kernel paths for the run's record: {e}");
            return None;
        }
    };
    let kernels = kernels_of(&out, run);
    if kernels.is_none() {
        tracing::warn!(run, "the daemon's status does not list the run's kernels");
    }
    kernels
}

/// The `kernels` of run `run` in `status --json`'s output (an array of planner reports).
pub fn kernels_of(status_json: &str, run: &str) -> Option<RunKernels> {
    let reports: Vec<serde_json::Value> = serde_json::from_str(status_json).ok()?;
    reports
        .iter()
        .filter_map(|r| r.get("runs")?.as_array())
        .flatten()
        .find(|r| r.get("name").and_then(|n| n.as_str()) == Some(run))
        .and_then(|r| serde_json::from_value(r.get("kernels")?.clone()).ok())
}

/// `planner status --json --connect endpoint`'s standard output, killed after
/// [`STATUS_TIMEOUT`].
fn status_json(planner: &Path, endpoint: &str) -> std::io::Result<String> {
    use std::io::Read;
    let mut child = Command::new(planner)
        .args(["status", "--json", "--timeout", "5", "--connect", endpoint])
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::null())
        .spawn()?;
    let start = Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait()? {
            break status;
        }
        if start.elapsed() > STATUS_TIMEOUT {
            child.kill()?;
            child.wait()?;
            return Err(std::io::Error::new(
                std::io::ErrorKind::TimedOut,
                format!("`status` gave no answer in {STATUS_TIMEOUT:?}"),
            ));
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut out = String::new();
    if let Some(mut stdout) = child.stdout.take() {
        stdout.read_to_string(&mut out)?;
    }
    if !status.success() {
        return Err(std::io::Error::other(format!(
            "`status` exited with {status}"
        )));
    }
    Ok(out)
}

/// The 1-minute load average and whether this process runs at `SCHED_IDLE`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Load {
    pub load_average_1m: f64,
    pub sched_idle: bool,
}

impl Load {
    pub fn now() -> Self {
        let load_average_1m = std::fs::read_to_string("/proc/loadavg")
            .ok()
            .and_then(|t| t.split_whitespace().next()?.parse().ok())
            .unwrap_or(f64::NAN);
        // SAFETY: sched_getscheduler reads this process's policy and touches no memory.
        let policy = unsafe { libc::sched_getscheduler(0) };
        Load {
            load_average_1m,
            sched_idle: policy == libc::SCHED_IDLE,
        }
    }
}

/// What [`binaries_commit`] records when it cannot tell the commit.
pub const UNKNOWN_COMMIT: &str = "unknown";

/// The commit of the binaries in `bin_dir`: its `COMMIT` file (written when release binaries
/// are copied aside, see `experiments/figure4.sh`), else the commit of the git work tree the
/// folder lies in, with `-dirty` when that tree has uncommitted changes; `unknown` otherwise.
pub fn binaries_commit(bin_dir: &Path) -> String {
    if let Ok(text) = std::fs::read_to_string(bin_dir.join("COMMIT")) {
        let commit = text.trim();
        if !commit.is_empty() {
            return commit.to_string();
        }
    }
    let git = |args: &[&str]| {
        Command::new("git")
            .arg("-C")
            .arg(bin_dir)
            .args(args)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    match git(&["rev-parse", "HEAD"]) {
        Some(head) if !head.is_empty() => {
            let dirty = git(&["status", "--porcelain", "--untracked-files=no"])
                .is_some_and(|s| !s.is_empty());
            if dirty { format!("{head}-dirty") } else { head }
        }
        _ => UNKNOWN_COMMIT.into(),
    }
}

/// One sitting's share of a run: the episodes it recorded, on which machine, with which
/// binaries and kernels, under what load.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Sitting {
    pub machine: Machine,
    pub binaries_commit: String,
    /// The precision and kernel paths the daemon ran the run's networks on, read from its
    /// status when the sitting's bridge ended (`None`: the daemon did not say).
    pub kernels: Option<RunKernels>,
    /// UTC, RFC 3339, of the run's start and end in this sitting.
    pub started: String,
    pub ended: String,
    /// The load when the run started and ended in this sitting.
    pub load_at_start: Load,
    pub load_at_end: Load,
    /// The episode numbers it recorded (the episode files' `episode` column).
    pub episodes: Vec<u32>,
}

/// The sittings one run's file keeps, oldest first, and whether they are all of them.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct KeptSittings {
    pub sittings: Vec<Sitting>,
    /// False for a record written before records kept every sitting: its one sitting is the
    /// one that finished the run, and the episode numbers it recorded are not known.
    pub complete: bool,
}

/// The sittings kept in `path`: an unfinished run's `runs/<stem>.sittings.json`, or a finished
/// run's record (its `sittings`, or for a record older than that field the sitting its
/// top-level fields describe). None, complete, when the file does not exist yet.
pub fn read_sittings(path: &Path) -> std::io::Result<KeptSittings> {
    /// A record written before records kept every sitting: these fields describe the sitting
    /// that finished the run.
    #[derive(Deserialize)]
    struct OlderRecord {
        machine: Machine,
        binaries_commit: String,
        kernels: Option<RunKernels>,
        started: String,
        finished: String,
        load_at_start: Load,
        load_at_end: Load,
    }
    let text = match std::fs::read_to_string(path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return Ok(KeptSittings {
                sittings: Vec::new(),
                complete: true,
            });
        }
        Err(e) => return Err(e),
    };
    let value: serde_json::Value = serde_json::from_str(&text)?;
    let complete = |sittings| KeptSittings {
        sittings,
        complete: true,
    };
    if value.is_array() {
        return Ok(complete(serde_json::from_value(value)?));
    }
    if let Some(list) = value.get("sittings") {
        return Ok(complete(serde_json::from_value(list.clone())?));
    }
    let older: OlderRecord = serde_json::from_value(value)?;
    Ok(KeptSittings {
        sittings: vec![Sitting {
            machine: older.machine,
            binaries_commit: older.binaries_commit,
            kernels: older.kernels,
            started: older.started,
            ended: older.finished,
            load_at_start: older.load_at_start,
            load_at_end: older.load_at_end,
            episodes: Vec::new(),
        }],
        complete: false,
    })
}

/// Adds `sitting` to an unfinished run's sittings file `path` (written whole to a temporary
/// file, then renamed: a crash leaves the old list or the new one).
pub fn append_sitting(path: &Path, sitting: Sitting) -> std::io::Result<()> {
    let mut all = read_sittings(path)?.sittings;
    all.push(sitting);
    let text = serde_json::to_string_pretty(&all).map_err(std::io::Error::other)?;
    let tmp = path.with_extension("json.tmp");
    std::fs::write(&tmp, text + "\n")?;
    std::fs::rename(&tmp, path)
}

/// The record of one finished run, `runs/<stem>.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunRecord {
    pub task: String,
    pub method: String,
    pub seed: u64,
    pub scale: String,
    pub episodes: usize,
    pub steps: u64,
    /// The spec the daemon stored for the run (task, preset, overrides, mode, seed), when its
    /// folder was readable.
    pub spec: Option<serde_json::Value>,
    /// Every sitting that recorded episodes of the run, oldest first. Episodes recorded by a
    /// bridge whose launcher was killed belong to none.
    pub sittings: Vec<Sitting>,
    /// UTC, RFC 3339, of the run's end.
    pub finished: String,
    /// Wall seconds of the recorded episodes (all sittings).
    pub episode_wall_seconds: f64,
}

impl RunRecord {
    /// Writes the record to `path` (pretty JSON with a final newline).
    pub fn save(&self, path: &Path) -> std::io::Result<()> {
        let text = serde_json::to_string_pretty(self).map_err(std::io::Error::other)?;
        std::fs::write(path, text + "\n")
    }
}

/// Now, as `YYYY-MM-DDTHH:MM:SSZ`.
pub fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let (days, rem) = ((secs / 86_400) as i64, secs % 86_400);
    let (year, month, day) = civil_from_days(days);
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

/// The civil date of a day number since 1970-01-01 (Howard Hinnant's algorithm).
pub fn civil_from_days(days: i64) -> (i64, i64, i64) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    (yoe + era * 400 + i64::from(month <= 2), month, day)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn civil_dates() {
        assert_eq!(civil_from_days(0), (1970, 1, 1));
        assert_eq!(civil_from_days(19_723), (2024, 1, 1));
        assert_eq!(civil_from_days(20_783), (2026, 11, 26));
    }

    #[test]
    fn the_machine_and_load_are_read_from_this_one() {
        let m = Machine::this();
        assert!(m.logical_cpus >= 1);
        // Every CPU runs the portable path; it is listed last.
        assert!(m.cpu_path.ends_with("scalar-f32"), "{}", m.cpu_path);
        #[cfg(target_arch = "x86_64")]
        assert_ne!(m.cpu_model, "unknown");
        assert!(Load::now().load_average_1m >= 0.0);
    }

    #[test]
    fn a_runs_kernels_are_read_from_the_status_report() {
        let status = r#"[{"planner_id": "p", "runs": [
            {"name": "other", "kernels": {"precision": "f32", "dynamics": "avx512-f32"}},
            {"name": "cartpole-cem-deen-s0", "kernels": {"precision": "auto",
             "dynamics": "amx-bf16", "energy": "avx512-f32", "reward": null}}]}]"#;
        assert_eq!(
            kernels_of(status, "cartpole-cem-deen-s0"),
            Some(RunKernels {
                precision: "auto".into(),
                dynamics: Some("amx-bf16".into()),
                energy: Some("avx512-f32".into()),
                reward: None,
            })
        );
        assert_eq!(kernels_of(status, "missing"), None);
        // A run reported without kernels (an older daemon), or no report at all: nothing.
        assert_eq!(kernels_of(r#"[{"runs": [{"name": "r"}]}]"#, "r"), None);
        assert_eq!(kernels_of("not json", "r"), None);
    }

    #[test]
    fn a_silent_status_command_is_cut_off_and_says_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let planner = dir.path().join("planner-service");
        std::fs::write(&planner, "#!/bin/sh\nexit 1\n").unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&planner, std::fs::Permissions::from_mode(0o755)).unwrap();
        assert_eq!(run_kernels(&planner, "tcp/127.0.0.1:1", "r"), None);
    }

    #[test]
    fn sittings_accumulate_in_their_file_and_are_read_back_from_a_record() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("cem-s0.sittings.json");
        let none = read_sittings(&file).unwrap();
        assert_eq!(none.sittings, [], "no file yet: none");
        assert!(none.complete);
        let load = Load {
            load_average_1m: 0.5,
            sched_idle: true,
        };
        let sitting = |episodes: Vec<u32>| Sitting {
            machine: Machine::this(),
            binaries_commit: "abc".into(),
            kernels: None,
            started: "2026-11-29T08:00:00Z".into(),
            ended: "2026-11-29T09:00:00Z".into(),
            load_at_start: load.clone(),
            load_at_end: load.clone(),
            episodes,
        };
        append_sitting(&file, sitting(vec![0, 1])).unwrap();
        append_sitting(&file, sitting(vec![2])).unwrap();
        let kept = read_sittings(&file).unwrap();
        assert_eq!(kept.sittings, [sitting(vec![0, 1]), sitting(vec![2])]);
        assert!(kept.complete);
        // A record holds them under `sittings`.
        let record = dir.path().join("cem-s0.json");
        let with = serde_json::json!({ "task": "ant", "sittings": kept.sittings });
        std::fs::write(&record, with.to_string()).unwrap();
        assert_eq!(read_sittings(&record).unwrap(), kept);
        // One written before records kept them describes the finishing sitting at its top
        // level: that one, with no episode numbers, and not complete.
        let finishing = sitting(Vec::new());
        let older = serde_json::json!({
            "task": "ant",
            "machine": finishing.machine,
            "binaries_commit": "abc",
            "kernels": null,
            "started": finishing.started,
            "finished": finishing.ended,
            "load_at_start": load,
            "load_at_end": load,
        });
        std::fs::write(&record, older.to_string()).unwrap();
        let read = read_sittings(&record).unwrap();
        assert_eq!(read.sittings, [finishing]);
        assert!(!read.complete);
        for damaged in ["[{\"not\": \"a sitting\"}]", r#"{"task": "ant"}"#, "{"] {
            std::fs::write(&record, damaged).unwrap();
            assert!(
                read_sittings(&record).is_err(),
                "a damaged file is an error: {damaged}"
            );
        }
    }

    #[test]
    fn a_commit_file_names_the_binaries_commit() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("COMMIT"), "0123abc\n").unwrap();
        assert_eq!(binaries_commit(dir.path()), "0123abc");
        // Outside any work tree and without the file: unknown.
        let bare = tempfile::tempdir().unwrap();
        let found = binaries_commit(bare.path());
        assert!(
            found == "unknown" || found.len() >= 40,
            "a temporary folder in a work tree? {found}"
        );
    }
}
