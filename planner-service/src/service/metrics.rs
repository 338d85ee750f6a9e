//! The daemon's metrics, kept in one Prometheus registry: the workers and the service count
//! into it as things happen, the status report reads the same counters, and `[metrics]
//! listen` serves the registry as Prometheus text on `GET /metrics`.
//!
//! Figures that live elsewhere (models version, replay size, episodes, agents, queue depths,
//! the last retraining's losses) are copied into gauges from the status report at each scrape,
//! and the status report reads the count and sum of each run's fsync and retraining histograms
//! ([`RunHistograms`]), so there is one source for each figure.

use super::status::{PlanRecord, PlannerStatus};
use crate::run::stats::{RunHistograms, Timed, fsync_histogram, retraining_histogram};
use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;
use std::collections::BTreeSet;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;
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

type Histograms = Family<RunLabel, Histogram, fn() -> Histogram>;
type FloatGauge = Gauge<f64, std::sync::atomic::AtomicU64>;

/// Every metric of the daemon.
pub struct Metrics {
    registry: Registry,
    plan_seconds: Histograms,
    plan_iterations: Histograms,
    plans_cut: Family<RunLabel, Counter>,
    deadline_misses: Family<RunLabel, Counter>,
    plan_step_backs: Family<RunLabel, Counter>,
    refused: Family<CodeLabel, Counter>,
    /// The codes refused so far, for the status report (a family cannot be listed).
    refused_codes: Mutex<BTreeSet<String>>,
    wildcards_dropped: Counter,
    /// Failed tries to open a stored run (each is retried after a backoff).
    open_failures: Counter,
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
    retraining_share: FloatGauge,
    retraining_slices: Gauge,
    retraining_waited_seconds: FloatGauge,
    retraining_starving: Gauge,
    dormant_runs: Gauge,
}

impl Default for Metrics {
    fn default() -> Self {
        let mut registry = Registry::with_prefix("ebmpc");
        let plan_seconds = Histograms::new_with_constructor(plan_histogram as fn() -> Histogram);
        let plan_iterations =
            Histograms::new_with_constructor(iterations_histogram as fn() -> Histogram);
        let plans_cut = Family::default();
        let deadline_misses = Family::default();
        let plan_step_backs = Family::default();
        let refused = Family::default();
        let wildcards_dropped = Counter::default();
        let open_failures = Counter::default();
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
        let retraining_share = FloatGauge::default();
        let retraining_slices = Gauge::default();
        let retraining_waited_seconds = FloatGauge::default();
        let retraining_starving = Gauge::default();
        let dormant_runs = Gauge::default();
        registry.register(
            "retraining_share",
            "Share of the cores a retraining is guaranteed while plans never stop",
            retraining_share.clone(),
        );
        registry.register(
            "retraining_slices",
            "Minibatches retrainings ran in slices taken from plans, since the daemon started",
            retraining_slices.clone(),
        );
        registry.register(
            "retraining_waited_seconds",
            "Seconds retrainings waited for plans before their minibatches, since the daemon started",
            retraining_waited_seconds.clone(),
        );
        registry.register(
            "retraining_starving",
            "1 while a retraining gets no idle time from the plans and advances at its guaranteed share only",
            retraining_starving.clone(),
        );
        registry.register(
            "dormant_runs",
            "Stored runs left closed because opening them would go beyond a budget",
            dormant_runs.clone(),
        );
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
            "plan_step_backs",
            "Times a run's plans stepped back from the cores for a more urgent plan",
            plan_step_backs.clone(),
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
            "run_open_failures",
            "Failed tries to open a stored run (each is retried after a backoff)",
            open_failures.clone(),
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
            plan_step_backs,
            refused,
            refused_codes: Mutex::default(),
            wildcards_dropped,
            open_failures,
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
            retraining_share,
            retraining_slices,
            retraining_waited_seconds,
            retraining_starving,
            dormant_runs,
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
    pub fn record_plan(&self, run_name: &str, seconds: f64, plan: PlanRecord) {
        let label = run(run_name);
        self.plan_seconds.get_or_create(&label).observe(seconds);
        self.plan_iterations
            .get_or_create(&label)
            .observe(f64::from(plan.iterations));
        // The counters exist (at 0) from a run's first plan on, so a dashboard shows a zero
        // rather than no data.
        self.plans_cut
            .get_or_create(&label)
            .inc_by(u64::from(plan.cut));
        self.deadline_misses
            .get_or_create(&label)
            .inc_by(u64::from(plan.missed));
        self.plan_step_backs
            .get_or_create(&label)
            .inc_by(u64::from(plan.stepped_back));
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

    /// A stored run could not be opened (it is tried again later).
    pub fn record_open_failure(&self) {
        self.open_failures.inc();
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
        self.copy_retraining(&status.retraining);
        self.dormant_runs
            .set(i64::try_from(status.dormant_run_count).unwrap_or(i64::MAX));
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
        self.text()
    }

    /// How retrainings fare against continuous planning, as the status report has it: a
    /// starving retraining is an alert an operator's Prometheus can fire on.
    fn copy_retraining(&self, training: &crate::sched::TrainingShare) {
        self.retraining_share.set(training.share);
        self.retraining_slices
            .set(i64::try_from(training.slices).unwrap_or(i64::MAX));
        self.retraining_waited_seconds.set(training.waited_seconds);
        self.retraining_starving.set(i64::from(training.starving));
    }

    /// The registry as Prometheus text, as it is now.
    fn text(&self) -> String {
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

/// The most bytes of a request head buffered (hyper's smallest read buffer; a scraper sends a
/// few hundred): a longer head is answered `431` and the connection closed.
const MAX_REQUEST_HEAD: usize = 8 << 10;
/// How long a connection may take to send its request head.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(5);
/// How long a connection may last in all, reading the answer included: a client that never
/// reads its answer is dropped then.
const CONNECTION_TIMEOUT: Duration = Duration::from_secs(15);
/// Connections served at once; more are closed at once, unanswered, so a flood of idle
/// connections costs a bounded number of tasks and sockets.
const MAX_CONNECTIONS: usize = 32;

/// Serves `GET /metrics` on `listener` until the task is aborted; `render` builds the body,
/// every other path is `404`. HTTP/1.1 through hyper, one request per connection (a scraper
/// every few seconds needs no more), each connection bounded in bytes, time and number, so a
/// slow or hostile client holds at most one of `MAX_CONNECTIONS` slots for at most
/// `CONNECTION_TIMEOUT` and never a thread the daemon serves agents with.
pub async fn serve(listener: TcpListener, render: impl Fn() -> String + Send + Sync + 'static) {
    let render = Arc::new(render);
    let slots = Arc::new(tokio::sync::Semaphore::new(MAX_CONNECTIONS));
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(accepted) => accepted,
            Err(e) => {
                tracing::warn!(error = %e, "metrics: accept failed");
                tokio::time::sleep(Duration::from_millis(100)).await;
                continue;
            }
        };
        let Ok(slot) = slots.clone().try_acquire_owned() else {
            tracing::debug!(%peer, "metrics: too many connections, this one is closed");
            continue;
        };
        let render = render.clone();
        tokio::spawn(async move {
            let service = hyper::service::service_fn(move |request| {
                let render = render.clone();
                async move { Ok::<_, std::convert::Infallible>(answer(&request, || render())) }
            });
            let connection = hyper::server::conn::http1::Builder::new()
                .timer(hyper_util::rt::TokioTimer::new())
                .header_read_timeout(REQUEST_TIMEOUT)
                .max_buf_size(MAX_REQUEST_HEAD)
                .keep_alive(false)
                .serve_connection(hyper_util::rt::TokioIo::new(stream), service);
            match tokio::time::timeout(CONNECTION_TIMEOUT, connection).await {
                Ok(Ok(())) => {}
                Ok(Err(e)) => tracing::debug!(%peer, error = %e, "metrics: connection failed"),
                Err(_) => tracing::debug!(%peer, "metrics: connection timed out"),
            }
            drop(slot);
        });
    }
}

type Body = http_body_util::Full<hyper::body::Bytes>;

/// The answer to one request: the metrics for `GET /metrics`, `404` for any other path, `405`
/// for another method there.
fn answer<B>(
    request: &hyper::Request<B>,
    render: impl FnOnce() -> String,
) -> hyper::Response<Body> {
    use hyper::{Method, StatusCode, header};
    let (status, body) = match (request.method(), request.uri().path()) {
        (&Method::GET, "/metrics") => (StatusCode::OK, render()),
        (_, "/metrics") => (
            StatusCode::METHOD_NOT_ALLOWED,
            "only GET /metrics is served here\n".to_string(),
        ),
        _ => (
            StatusCode::NOT_FOUND,
            "only GET /metrics is served here\n".to_string(),
        ),
    };
    let mut response = hyper::Response::new(Body::from(body));
    *response.status_mut() = status;
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        header::HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
    );
    response
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio::net::TcpStream;

    /// Sends `request` raw and reads the whole answer (the server closes the connection).
    async fn exchange(addr: std::net::SocketAddr, request: &[u8]) -> String {
        let mut stream = TcpStream::connect(addr).await.unwrap();
        // A server that closes early (a refused head) may reset the rest of a long write.
        let _ = stream.write_all(request).await;
        let mut answer = Vec::new();
        let _ = stream.read_to_end(&mut answer).await;
        String::from_utf8_lossy(&answer).into_owned()
    }

    async fn endpoint() -> std::net::SocketAddr {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        tokio::spawn(serve(listener, || "ebmpc_up 1\n".to_string()));
        addr
    }

    #[test]
    fn a_starving_retraining_shows_in_the_metrics() {
        let metrics = Metrics::default();
        let mut training = crate::sched::TrainingShare {
            share: 0.25,
            slices: 7,
            waited_seconds: 1.5,
            starving: true,
        };
        metrics.copy_retraining(&training);
        let text = metrics.text();
        for line in [
            "ebmpc_retraining_starving 1\n",
            "ebmpc_retraining_slices 7\n",
            "ebmpc_retraining_share 0.25\n",
            "ebmpc_retraining_waited_seconds 1.5\n",
        ] {
            assert!(text.contains(line), "{line:?} missing from\n{text}");
        }
        training.starving = false;
        metrics.copy_retraining(&training);
        assert!(metrics.text().contains("ebmpc_retraining_starving 0\n"));
    }

    #[tokio::test]
    async fn serves_metrics_on_its_path_only() {
        let addr = endpoint().await;
        let ok = exchange(addr, b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n").await;
        assert!(ok.starts_with("HTTP/1.1 200 OK\r\n"), "{ok}");
        assert!(ok.contains("text/plain; version=0.0.4"), "{ok}");
        assert!(ok.ends_with("ebmpc_up 1\n"), "{ok}");
        let other = exchange(addr, b"GET /metricsx HTTP/1.1\r\nHost: x\r\n\r\n").await;
        assert!(other.starts_with("HTTP/1.1 404"), "{other}");
        let post = exchange(addr, b"POST /metrics HTTP/1.1\r\nHost: x\r\n\r\n").await;
        assert!(post.starts_with("HTTP/1.1 405"), "{post}");
        let garbage = exchange(addr, b"\x00\x01 not http at all\r\n\r\n").await;
        assert!(!garbage.contains("ebmpc_up"), "{garbage}");
    }

    #[tokio::test]
    async fn a_silent_or_oversized_client_stalls_no_one_and_is_dropped() {
        let addr = endpoint().await;
        // Connects and sends nothing.
        let mut silent = TcpStream::connect(addr).await.unwrap();
        // Sends a head far over the bound, and never ends it.
        let mut huge = TcpStream::connect(addr).await.unwrap();
        let head = format!(
            "GET /metrics HTTP/1.1\r\nHost: x\r\nX-Big: {}\r\n",
            "a".repeat(1 << 20)
        );
        let _ = huge.write_all(head.as_bytes()).await;
        // Every connection slot but one taken by idle clients.
        let mut idle = Vec::new();
        for _ in 0..MAX_CONNECTIONS - 3 {
            idle.push(TcpStream::connect(addr).await.unwrap());
        }
        // Meanwhile a scraper is served.
        let ok = exchange(addr, b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n").await;
        assert!(ok.ends_with("ebmpc_up 1\n"), "{ok}");
        // The oversized head was refused, not buffered: answered 431 and closed (or reset).
        let mut answer = Vec::new();
        let _ = huge.read_to_end(&mut answer).await;
        let answer = String::from_utf8_lossy(&answer);
        assert!(
            answer.is_empty() || answer.starts_with("HTTP/1.1 431"),
            "{answer}"
        );
        // The silent client is closed once its time to send a head is up.
        let mut byte = [0u8; 1];
        let read = tokio::time::timeout(REQUEST_TIMEOUT * 4, silent.read(&mut byte)).await;
        assert!(
            matches!(read, Ok(Ok(0)) | Ok(Err(_))),
            "closed, not left open: {read:?}"
        );
    }
}
