//! The daemon's metrics, kept in one Prometheus registry: the workers and the service count
//! into it as things happen, the status report reads the same counters, and `[metrics]
//! listen` serves the registry as Prometheus text on `GET /metrics`.
//!
//! Figures that live elsewhere (models version, replay size, episodes, agents, queue depths,
//! the last retraining's losses) are copied into gauges from the status report at each scrape,
//! and the status report reads the count and sum of each run's fsync and retraining histograms
//! ([`RunHistograms`]), so there is one source for each figure.

use super::status::{PlannerStatus, Timings};
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use std::collections::BTreeSet;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpListener;

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct RunLabel {
    run: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct AgentLabel {
    run: String,
    agent: String,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct ModelLabel {
    run: String,
    /// `dynamics` or `energy` (the regulariser: DEEN or DAE).
    model: &'static str,
}

#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
struct CodeLabel {
    code: String,
}

/// Plan latency buckets: 1 ms to about 8 s, doubling.
fn plan_histogram() -> Histogram {
    Histogram::new(exponential_buckets(0.001, 2.0, 14))
}

/// Iterations-per-plan buckets: 0 (nothing fitted the deadline), 1, 2, 4 … 64.
fn iterations_histogram() -> Histogram {
    Histogram::new([0.0, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0])
}

/// Replay log fsync buckets: 50 µs to about 1.6 s, doubling.
fn fsync_histogram() -> Histogram {
    Histogram::new(exponential_buckets(50e-6, 2.0, 16))
}

/// Retraining buckets: 10 ms to about 20 min, doubling.
fn retraining_histogram() -> Histogram {
    Histogram::new(exponential_buckets(0.01, 2.0, 18))
}

type Histograms = Family<RunLabel, Histogram, fn() -> Histogram>;
type FloatGauge = Gauge<f64, std::sync::atomic::AtomicU64>;

/// A timed operation: each duration goes into a Prometheus histogram and into the count and
/// total the status report shows (`prometheus-client` does not read a histogram back), from
/// one call.
#[derive(Clone, Debug)]
pub struct Timed {
    histogram: Histogram,
    totals: Arc<Mutex<Timings>>,
}

impl Timed {
    fn new(histogram: Histogram) -> Self {
        Self {
            histogram,
            totals: Arc::default(),
        }
    }

    pub fn observe(&self, seconds: f64) {
        self.histogram.observe(seconds);
        let mut totals = self.totals.lock().unwrap_or_else(PoisonError::into_inner);
        totals.count += 1;
        totals.seconds_total += seconds;
    }

    /// How many durations were observed, and their sum: the histogram's `_count` and `_sum`.
    pub fn timings(&self) -> Timings {
        *self.totals.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// The durations a run times itself, since it is the run that syncs its replay log and
/// retrains: the daemon's registry serves them (see [`Metrics::for_run`]) and the status
/// report shows their count and total. The default ones are served nowhere (experiments,
/// tests).
#[derive(Clone, Debug)]
pub struct RunHistograms {
    /// Seconds per fsync of the run's replay log.
    pub fsync_seconds: Timed,
    /// Seconds per retraining that produced models.
    pub retraining_seconds: Timed,
}

impl Default for RunHistograms {
    fn default() -> Self {
        Self {
            fsync_seconds: Timed::new(fsync_histogram()),
            retraining_seconds: Timed::new(retraining_histogram()),
        }
    }
}

/// Every metric of the daemon.
pub struct Metrics {
    registry: Registry,
    plan_seconds: Histograms,
    plan_iterations: Histograms,
    plans_cut: Family<RunLabel, Counter>,
    deadline_misses: Family<RunLabel, Counter>,
    refused: Family<CodeLabel, Counter>,
    /// The codes refused so far, for the status report (a family cannot be listed).
    refused_codes: Mutex<BTreeSet<String>>,
    wildcards_dropped: Counter,
    models_version: Family<RunLabel, Gauge>,
    replay_transitions: Family<RunLabel, Gauge>,
    episodes: Family<RunLabel, Gauge>,
    agents: Family<RunLabel, Gauge>,
    queue_depth: Family<AgentLabel, Gauge>,
    replay_bytes: Family<RunLabel, Gauge>,
    fsync_seconds: Histograms,
    retraining_seconds: Histograms,
    /// Each run's [`RunHistograms`], so a run opened again (after a fleet hand-over) keeps
    /// counting where it left off, like its histograms do.
    run_histograms: Mutex<std::collections::HashMap<String, RunHistograms>>,
    training_loss: Family<ModelLabel, FloatGauge>,
}

impl Default for Metrics {
    fn default() -> Self {
        let mut registry = Registry::with_prefix("ebmpc");
        let plan_seconds = Histograms::new_with_constructor(plan_histogram as fn() -> Histogram);
        let plan_iterations =
            Histograms::new_with_constructor(iterations_histogram as fn() -> Histogram);
        let plans_cut = Family::default();
        let deadline_misses = Family::default();
        let refused = Family::default();
        let wildcards_dropped = Counter::default();
        let models_version = Family::default();
        let replay_transitions = Family::default();
        let episodes = Family::default();
        let agents = Family::default();
        let queue_depth = Family::default();
        let replay_bytes = Family::default();
        let fsync_seconds = Histograms::new_with_constructor(fsync_histogram as fn() -> Histogram);
        let retraining_seconds =
            Histograms::new_with_constructor(retraining_histogram as fn() -> Histogram);
        let training_loss = Family::default();
        registry.register(
            "plan_seconds",
            "Time from taking an observation to its planned action, per run",
            plan_seconds.clone(),
        );
        registry.register(
            "plan_iterations",
            "CEM/iCEM iterations run per plan, per run",
            plan_iterations.clone(),
        );
        registry.register(
            "plans_cut",
            "Plans whose iterations the run's deadline cut short",
            plans_cut.clone(),
        );
        registry.register(
            "deadline_misses",
            "Planned actions sent after the run's deadline, or with no iteration before it",
            deadline_misses.clone(),
        );
        registry.register(
            "refused_messages",
            "Messages answered with an error report, by error code",
            refused.clone(),
        );
        registry.register(
            "wildcard_keys_dropped",
            "Observations and attaches on wildcard keys, dropped unanswered",
            wildcards_dropped.clone(),
        );
        registry.register(
            "models_version",
            "Version of the models serving a run",
            models_version.clone(),
        );
        registry.register(
            "replay_transitions",
            "Transitions in a run's replay buffer",
            replay_transitions.clone(),
        );
        registry.register("episodes", "Episodes stored by a run", episodes.clone());
        registry.register("agents", "Agents attached to a run", agents.clone());
        registry.register(
            "agent_queue_depth",
            "An agent's observations waiting for an answer: in its inbox, or planned and waiting for the cores",
            queue_depth.clone(),
        );
        registry.register(
            "replay_bytes",
            "Bytes of a run's replay log file",
            replay_bytes.clone(),
        );
        registry.register(
            "replay_fsync_seconds",
            "Time per fsync of a run's replay log (one at every episode end)",
            fsync_seconds.clone(),
        );
        registry.register(
            "retraining_seconds",
            "Time per retraining that produced models, per run",
            retraining_seconds.clone(),
        );
        registry.register(
            "training_loss",
            "Final training loss of each model at a run's last retraining",
            training_loss.clone(),
        );
        Self {
            registry,
            plan_seconds,
            plan_iterations,
            plans_cut,
            deadline_misses,
            refused,
            refused_codes: Mutex::default(),
            wildcards_dropped,
            models_version,
            replay_transitions,
            episodes,
            agents,
            queue_depth,
            replay_bytes,
            fsync_seconds,
            retraining_seconds,
            run_histograms: Mutex::default(),
            training_loss,
        }
    }
}

fn run(name: &str) -> RunLabel {
    RunLabel {
        run: name.to_string(),
    }
}

impl Metrics {
    /// The histograms run `run_name` records into, served by this registry.
    pub fn for_run(&self, run_name: &str) -> RunHistograms {
        let label = run(run_name);
        self.run_histograms
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .entry(run_name.to_string())
            .or_insert_with(|| RunHistograms {
                fsync_seconds: Timed::new(self.fsync_seconds.get_or_create(&label).clone()),
                retraining_seconds: Timed::new(
                    self.retraining_seconds.get_or_create(&label).clone(),
                ),
            })
            .clone()
    }

    /// A planned action of `run`.
    pub fn record_plan(
        &self,
        run_name: &str,
        seconds: f64,
        iterations: u32,
        cut: bool,
        missed: bool,
    ) {
        let label = run(run_name);
        self.plan_seconds.get_or_create(&label).observe(seconds);
        self.plan_iterations
            .get_or_create(&label)
            .observe(f64::from(iterations));
        // Both series exist (at 0) from a run's first plan on, so a dashboard shows a zero
        // rather than no data.
        self.plans_cut.get_or_create(&label).inc_by(u64::from(cut));
        self.deadline_misses
            .get_or_create(&label)
            .inc_by(u64::from(missed));
    }

    /// A message answered with an error report of `code`.
    pub fn record_refusal(&self, code: proto::ErrorCode) {
        let code = code_name(code);
        self.refused
            .get_or_create(&CodeLabel { code: code.clone() })
            .inc();
        self.refused_codes
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .insert(code);
    }

    /// A message on a wildcard key, dropped.
    pub fn record_wildcard(&self) {
        self.wildcards_dropped.inc();
    }

    pub fn wildcards_dropped(&self) -> u64 {
        self.wildcards_dropped.get()
    }

    /// Refusals so far by error code (the status report's copy of `refused_messages`).
    pub fn refusals(&self) -> std::collections::BTreeMap<String, u64> {
        let codes = self
            .refused_codes
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        codes
            .into_iter()
            .map(|code| {
                let count = self
                    .refused
                    .get_or_create(&CodeLabel { code: code.clone() })
                    .get();
                (code, count)
            })
            .collect()
    }

    /// The registry as Prometheus text, with the gauges copied from `status` first.
    pub fn render(&self, status: &PlannerStatus) -> String {
        // Agents come and go: only the ones attached now have a queue.
        self.queue_depth.clear();
        for r in &status.runs {
            let label = run(&r.name);
            let gauge = |v: u64| i64::try_from(v).unwrap_or(i64::MAX);
            self.models_version
                .get_or_create(&label)
                .set(gauge(r.models_version));
            self.replay_transitions
                .get_or_create(&label)
                .set(gauge(r.transitions as u64));
            self.episodes
                .get_or_create(&label)
                .set(gauge(u64::from(r.episodes)));
            self.agents
                .get_or_create(&label)
                .set(gauge(r.agents.len() as u64));
            self.replay_bytes
                .get_or_create(&label)
                .set(gauge(r.replay_bytes));
            for (agent, depth) in &r.queue_depth {
                self.queue_depth
                    .get_or_create(&AgentLabel {
                        run: r.name.clone(),
                        agent: agent.clone(),
                    })
                    .set(gauge(*depth));
            }
            let last = r.last_retraining.as_ref();
            for (model, loss) in [
                ("dynamics", last.and_then(|l| l.dynamics_loss)),
                ("energy", last.and_then(|l| l.energy_loss)),
            ] {
                let label = ModelLabel {
                    run: r.name.clone(),
                    model,
                };
                match loss {
                    Some(loss) => {
                        self.training_loss
                            .get_or_create(&label)
                            .set(f64::from(loss));
                    }
                    None => {
                        self.training_loss.remove(&label);
                    }
                }
            }
        }
        let mut text = String::new();
        if let Err(e) = prometheus_client::encoding::text::encode(&mut text, &self.registry) {
            tracing::error!(error = %e, "cannot encode metrics");
        }
        text
    }
}

/// An error code's wire name (`out_of_range`, …).
fn code_name(code: proto::ErrorCode) -> String {
    serde_json::to_value(code)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_else(|| format!("{code:?}"))
}

/// The most bytes of a request head read (a scraper sends a few hundred).
const MAX_REQUEST_HEAD: usize = 8 << 10;
/// How long a connection may take to send its request.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);

/// Serves `GET /metrics` on `listener` until the task is aborted; `render` builds the body.
/// One request per connection (`Connection: close`): a scraper every few seconds needs no
/// more, and each connection is bounded in bytes and time.
pub async fn serve(listener: TcpListener, render: impl Fn() -> String + Send + Sync + 'static) {
    let render = std::sync::Arc::new(render);
    loop {
        let (mut stream, _) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(e) => {
                tracing::warn!(error = %e, "metrics: accept failed");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let render = render.clone();
        tokio::spawn(async move {
            let mut head = Vec::with_capacity(512);
            let mut buf = [0u8; 1024];
            let read = tokio::time::timeout(REQUEST_TIMEOUT, async {
                while !head.windows(4).any(|w| w == b"\r\n\r\n") && head.len() < MAX_REQUEST_HEAD {
                    match stream.read(&mut buf).await {
                        Ok(0) | Err(_) => return false,
                        Ok(n) => head.extend_from_slice(&buf[..n]),
                    }
                }
                true
            })
            .await;
            if !matches!(read, Ok(true)) {
                return;
            }
            let (status, body) = if head.starts_with(b"GET /metrics ") {
                ("200 OK", render())
            } else {
                (
                    "404 Not Found",
                    "only GET /metrics is served here\n".to_string(),
                )
            };
            let response = format!(
                "HTTP/1.1 {status}\r\nContent-Type: text/plain; version=0.0.4; charset=utf-8\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            );
            let _ = stream.write_all(response.as_bytes()).await;
            let _ = stream.shutdown().await;
        });
    }
}
