//! Where and how a run was produced: the record written beside each finished run's episodes
//! (`runs/<stem>.json`), so that a folder committed run by run, across days and machines,
//! still says for every run which binaries ran it, on which CPU, along which kernel path and
//! under what load.

use serde::{Deserialize, Serialize};
use std::path::Path;
use std::process::Command;

/// The machine a sitting runs on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Machine {
    pub hostname: String,
    /// `lscpu`'s "Model name" (from /proc/cpuinfo).
    pub cpu_model: String,
    /// CPU family and model numbers, e.g. "6/143".
    pub cpu_family_model: String,
    pub logical_cpus: usize,
    /// The planner's numeric path on this CPU: the SIMD level its dispatched kernels run at,
    /// and whether bf16 dot products are available to packed inference layers.
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
}

/// The planner library's kernel path here, e.g. `Avx512+bf16`.
pub fn cpu_path() -> String {
    use planner_service::nn::simd;
    let level = format!("{:?}", simd::level());
    if simd::bf16_dot_available() {
        format!("{level}+bf16")
    } else {
        level
    }
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
        _ => "unknown".into(),
    }
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
    pub binaries_commit: String,
    pub machine: Machine,
    /// The load when the last sitting of the run started and when it finished.
    pub load_at_start: Load,
    pub load_at_end: Load,
    /// UTC, RFC 3339, of the last sitting's start and the run's end.
    pub started: String,
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
        assert!(
            ["Scalar", "Avx2", "Avx512"]
                .iter()
                .any(|l| m.cpu_path.starts_with(l)),
            "{}",
            m.cpu_path
        );
        #[cfg(target_arch = "x86_64")]
        assert_ne!(m.cpu_model, "unknown");
        assert!(Load::now().load_average_1m >= 0.0);
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
