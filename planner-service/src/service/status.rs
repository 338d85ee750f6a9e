//! The planner's status report, served as JSON on `{prefix}/planners/{id}/status`.

pub use crate::models::RunKernels;
pub use crate::run::stats::{LastRetraining, Latency, PlanRecord, PlanTally, Timings};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
pub struct PlannerStatus {
    pub planner_id: String,
    pub protocol_version: u16,
    pub uptime_seconds: f64,
    pub runs: Vec<RunStatus>,
    /// The fleet as this planner sees it, and its recent ownership events.
    pub fleet: crate::fleet::FleetStatus,
    /// Stored runs this planner could not open, set aside with the reason.
    #[serde(default)]
    pub failed_runs: Vec<FailedRun>,
    /// Stored runs whose opening failed on an I/O error that may pass: tried again with a
    /// backoff that doubles with every failure.
    #[serde(default)]
    pub retrying_runs: Vec<RetryingRun>,
    /// Stored runs left closed because opening them would go beyond a budget (`max_runs`, or
    /// `[storage] max_total_replay_bytes`): on disk untouched, opened on an agent's attach
    /// once the budget allows. The first [`DORMANT_LISTED`] by name; see `dormant_run_count`.
    #[serde(default)]
    pub dormant_runs: Vec<DormantRun>,
    /// How many stored runs are dormant (also those beyond the list).
    #[serde(default)]
    pub dormant_run_count: u64,
    /// Observations and attaches dropped unanswered because their key had a wildcard.
    #[serde(default)]
    pub wildcards_dropped: u64,
    /// Messages answered with an error report, by error code, since the daemon started.
    #[serde(default)]
    pub refused: std::collections::BTreeMap<String, u64>,
    /// How retrainings fared against continuous planning: their guaranteed share of the
    /// cores, the slices they took from plans, and whether one is starving now.
    #[serde(default)]
    pub retraining: crate::sched::TrainingShare,
    /// How close the daemon is to each of its budgets.
    #[serde(default)]
    pub budgets: Budgets,
    /// Kernel paths: measured peaks and per-network measurements.
    #[serde(default)]
    pub kernels: KernelStatus,
}

/// How much of one budget is used: `used` of `limit` (`limit` absent: unbounded).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub struct Usage {
    pub used: u64,
    pub limit: Option<u64>,
}

impl Usage {
    pub fn of(used: u64, limit: impl Into<Option<u64>>) -> Self {
        Self {
            used,
            limit: limit.into(),
        }
    }
}

/// The matrix kernels of this machine: each path's measured peak and the paths' measured times
/// on the networks planned so far (see `nn::kernel_path`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct KernelStatus {
    /// One core's measured peak in GFLOP/s per kernel path (`amx-bf16`, `avx512-bf16`,
    /// `avx512-f32`, `avx2-f32`), measured once in the background after the daemon starts;
    /// empty until then.
    #[serde(default)]
    pub peak_gflops: std::collections::BTreeMap<String, f64>,
    /// Every network shape whose path was chosen by measurement, with each path's time.
    #[serde(default)]
    pub measured: Vec<NetworkKernels>,
}

/// One network shape's measured forward pass through each candidate path.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct NetworkKernels {
    /// `[inputs, hidden…, outputs]`.
    pub sizes: Vec<usize>,
    /// The fastest path, which networks of this shape run under `auto`.
    pub chosen: String,
    /// Best time of one forward pass of `samples` samples, in microseconds, per path.
    pub microseconds: std::collections::BTreeMap<String, f64>,
    pub samples: usize,
}

impl KernelStatus {
    /// The peak measured so far and every measurement this process made.
    pub fn now() -> Self {
        use crate::nn::KernelPath;
        let peak_gflops = crate::nn::peak::background_peak()
            .map(|peak| {
                KernelPath::ALL
                    .into_iter()
                    .filter_map(|p| Some((p.name().to_string(), peak.for_path(p)?)))
                    .collect()
            })
            .unwrap_or_default();
        let measured = crate::nn::kernel_path::measurements()
            .into_iter()
            .map(|m| NetworkKernels {
                chosen: m.fastest().name().to_string(),
                microseconds: m
                    .timings
                    .iter()
                    .map(|t| (t.path.name().to_string(), t.seconds * 1e6))
                    .collect(),
                sizes: m.sizes,
                samples: crate::nn::kernel_path::BATCH,
            })
            .collect();
        Self {
            peak_gflops,
            measured,
        }
    }
}

/// The daemon's budgets: what each bounds, how much is used. A request that would go beyond
/// one is refused with an error naming the budget and its setting.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
pub struct Budgets {
    /// Runs hosted, of `max_runs`.
    pub runs: Usage,
    /// Bytes of the replay logs of every hosted run, of `[storage] max_total_replay_bytes`.
    pub replay_bytes: Usage,
    /// Bytes of the largest run's replay log, of `[storage] max_run_replay_bytes`.
    pub fullest_run_replay_bytes: Usage,
    /// Distinct task specs compiled in this process (catalog tasks included), of the most it
    /// compiles; only runs that were opened keep one.
    pub task_slots: Usage,
}

/// A stored run that could not be opened (it stays on disk untouched).
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
pub struct FailedRun {
    pub name: String,
    pub reason: String,
}

/// Most dormant runs [`PlannerStatus::dormant_runs`] names: a data directory may hold
/// thousands, and the report stays small.
pub const DORMANT_LISTED: usize = 100;

/// A stored run left closed at a budget.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
pub struct DormantRun {
    pub name: String,
    /// The budget that kept it closed, named by its setting.
    pub budget: String,
}

/// A stored run whose opening failed on an I/O error that may pass.
#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
pub struct RetryingRun {
    pub name: String,
    /// The last failure.
    pub reason: String,
    /// Tries that failed so far.
    pub attempts: u32,
    /// Seconds until the next try.
    pub next_try_seconds: f64,
}

#[derive(Clone, Debug, Serialize, Deserialize, JsonSchema)]
pub struct RunStatus {
    pub name: String,
    pub task: String,
    pub method: String,
    pub mode: proto::TrainMode,
    pub episodes: u32,
    pub transitions: usize,
    pub models_version: u64,
    /// The ownership epoch this planner holds the run at.
    pub epoch: u64,
    pub training: bool,
    pub exploring: bool,
    /// The last (up to 10) finished episodes: agent, episode, return.
    pub last_returns: Vec<(String, u32, f32)>,
    pub agents: Vec<String>,
    /// Each agent's observations waiting for an answer: in its inbox, or planned and waiting
    /// for the cores.
    #[serde(default)]
    pub queue_depth: std::collections::BTreeMap<String, u64>,
    pub planning_latency: Option<Latency>,
    /// The run's deadline in milliseconds (`None`: off).
    #[serde(default)]
    pub deadline_ms: Option<u32>,
    #[serde(default)]
    pub plan_tally: PlanTally,
    /// Bytes of the run's replay log file.
    #[serde(default)]
    pub replay_bytes: u64,
    /// The replay log's fsyncs (one at every episode end).
    #[serde(default)]
    pub replay_fsync: Timings,
    /// Retrainings that produced models, and their total time.
    #[serde(default)]
    pub retraining: Timings,
    #[serde(default)]
    pub last_retraining: Option<LastRetraining>,
    /// What could not be read when the run was opened (damaged records, a damaged header, a
    /// torn tail): the run resumed with everything else. `None`: nothing was lost.
    #[serde(default)]
    pub replay_damage: Option<String>,
    /// The kernel path each of the run's current networks runs.
    #[serde(default)]
    pub kernels: RunKernels,
}
