//! The planner daemon's Zenoh face: the attach queryable, the observation subscriber, the
//! per-agent workers that answer with actions, and the events and errors they publish.
//!
//! ```text
//! attach query ──▶ Service::attach ──▶ Run (created or joined) + agent worker task
//! obs sample ────▶ Service::route ───▶ agent worker (in order) ──▶ validate → store → act
//! fleet change ──▶ steward task ──▶ Service::rebalance: step down from lost runs, take free ones
//! ```
//! In a fleet of planners ([`crate::fleet`]) the service serves only the runs it owns (etcd
//! says which): it stays silent on other runs' attach queries and observations, so the
//! owner's answer is the only one, and acknowledges a step only while its etcd lease is valid.
//! A single daemon (no `[fleet]`) owns every run. Taking runs over and stepping down run on
//! a steward task of their own, beside serving: a slow takeover delays no other run's actions
//! and no shutdown.
//! Each agent has one worker task, so its observations are handled strictly in order while
//! agents (and runs) proceed concurrently; planning and storing (replay writes and fsyncs) run
//! on the blocking pool, and training on the run's trainer task, so none of them stalls the
//! transport, and one run's slow disk holds that run's agents only.

mod log_limit;
pub mod metrics;
pub mod schema;
pub mod status;
mod worker;

use crate::config::{Preset, ServiceConfig};
use crate::fleet::Fleet;
use crate::persist::{self, RunDir};
use crate::run::{EventSink, Hosting, LogDisk, Run};
use crate::trainer::TrainLimits;
use proto::{
    AttachAccepted, AttachOutcome, AttachReply, AttachRequest, Encoding, ErrorCode, ErrorReport,
    Keys, PROTOCOL_VERSION, RunEvent, RunEventKind, RunSpec,
};
use std::collections::{BTreeMap, HashMap};
use std::future::Future;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use tokio::sync::{Semaphore, mpsc};
use tokio::task::JoinHandle;
use worker::{AgentWorker, Incoming};
use zenoh::bytes::Encoding as ZEncoding;

/// Failures that stop the daemon (everything else is reported to the sender and logged).
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error(transparent)]
    SessionConfig(#[from] proto::session::SessionConfigError),
    #[error("joining the fleet: {0}")]
    Fleet(#[from] crate::fleet::FleetError),
    #[error(transparent)]
    DataDir(#[from] persist::admin::AdminError),
    #[error("metrics endpoint: {0}")]
    Metrics(String),
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
}

fn zenoh_err(e: impl std::fmt::Display) -> ServiceError {
    ServiceError::Zenoh(e.to_string())
}

/// Queue depth of one agent's worker. An agent waits for each action, so more than a couple of
/// queued observations means a misbehaving sender; beyond this they are refused.
const AGENT_QUEUE: usize = 64;

/// How long a vanished agent's session lingers before it is dropped. An agent's observations
/// and its liveliness token's deletion travel on different channels, and after a reconnection
/// (a planner restart) Zenoh does not order them: without the linger, an agent's last
/// observation, published just before it exits, could find its session already gone.
const AGENT_LINGER: std::time::Duration = std::time::Duration::from_secs(2);

/// How long the workers may take, together, to finish their messages in hand at shutdown.
/// The daemon promises to exit within 10 s of SIGTERM (systemd's `TimeoutStopSec` is well
/// above); this leaves the rest for closing the session and the blocking pool.
const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(5);

/// Bytes beyond `[limits] max_payload_bytes` that Zenoh's transport accepts in one message
/// (its key expression and headers), so that a payload just over the limit still arrives
/// and is refused with a clear error instead of being dropped silently.
const ZENOH_HEADROOM: u64 = 64 << 10;

/// Attach requests handled at once (each may open a run: disk I/O and model construction);
/// beyond this a request is refused at once instead of queueing without bound.
const CONCURRENT_ATTACHES: usize = 8;

/// Most attach queries for free runs preferred on another planner that wait out the free-run
/// grace at once (each holds only its query until then).
const FREE_RUN_WAITS: usize = 64;

struct AgentHandle {
    tx: mpsc::Sender<Incoming>,
    /// The agent's plans waiting for the cores (see [`AgentHandle::queue_depth`]).
    plans_waiting: crate::sched::Waiting,
    task: JoinHandle<()>,
    /// The session token handed to the agent at attach; its observations must carry it.
    session: u64,
    /// The token the agent presented when it attached (its previous session's, or for a first
    /// attach one it drew). An agent whose attach answer never reached it (the query timed out
    /// while this planner was still taking the run over) asks again with that same token, and
    /// is the agent.
    attached_with: Option<u64>,
    /// The agent's liveliness token went away (it is lingering for [`AGENT_LINGER`]): it
    /// counts as vanished, and its name may be attached again by anyone.
    token_gone: bool,
}

impl AgentHandle {
    /// Whether the agent's session is still live: its worker runs and its liveliness token
    /// was not seen going away. (A worker ends when its agent goes idle past
    /// `[limits] agent_idle_seconds` without a liveliness token.)
    fn is_live(&self) -> bool {
        !self.task.is_finished() && !self.token_gone
    }

    /// Whether an attach presenting `token` comes from this agent: it holds the session's
    /// token, or it asks again with the token it attached with, never having received the
    /// answer that carried the new one.
    fn is_held_by(&self, token: Option<u64>) -> bool {
        // No token and the no-session token 0 prove nothing (anyone can present them).
        let Some(token) = token.filter(|&t| t != proto::NO_SESSION) else {
            return false;
        };
        token == self.session || Some(token) == self.attached_with
    }

    /// The agent's observations waiting for an answer: in its inbox, or planned but waiting
    /// for the cores in the scheduler (an observation being stored or planned is not counted).
    fn queue_depth(&self) -> u64 {
        let inbox = self.tx.max_capacity() - self.tx.capacity();
        (inbox + self.plans_waiting.get()) as u64
    }
}

struct RunHandle {
    run: Arc<Run>,
    /// The run's plans, batched across its agents.
    plans: Arc<worker::PlanBatcher>,
    agents: HashMap<String, AgentHandle>,
    trainer: JoinHandle<()>,
}

/// Publishes encoded messages on keys; shared by the service and its workers.
#[derive(Clone)]
pub(crate) struct Outbox {
    session: zenoh::Session,
    keys: Keys,
    /// Refusals are logged at a bounded rate: a client controls how many it causes.
    refusal_log: Arc<log_limit::LogLimit>,
    metrics: Arc<metrics::Metrics>,
}

impl Outbox {
    pub(crate) fn keys(&self) -> &Keys {
        &self.keys
    }

    pub(crate) fn metrics(&self) -> &metrics::Metrics {
        &self.metrics
    }

    /// Publishes `msg` on `key` in `encoding`, logging (not failing) on transport errors: the
    /// peer may be gone, and the service must keep serving the others.
    pub(crate) async fn publish<T: serde::Serialize>(
        &self,
        key: &str,
        msg: &T,
        encoding: Encoding,
    ) {
        let bytes = match proto::encode(msg, encoding) {
            Ok(bytes) => bytes,
            Err(e) => {
                tracing::error!(%key, error = %e, "cannot encode message");
                return;
            }
        };
        if let Err(e) = self
            .session
            .put(key, bytes)
            .encoding(ZEncoding::from(encoding.mime()))
            .await
        {
            tracing::warn!(%key, error = %e, "publish failed");
        }
    }

    /// Whether `agent` of `run` holds a liveliness token now.
    pub(crate) async fn agent_alive(&self, run: &str, agent: &str) -> bool {
        match self
            .session
            .liveliness()
            .get(self.keys.agent_alive(run, agent))
            .timeout(std::time::Duration::from_secs(5))
            .await
        {
            Ok(replies) => replies.recv_async().await.is_ok(),
            // Cannot ask: count the agent as alive rather than close a working session.
            Err(_) => true,
        }
    }

    /// Reports an error to the agent that caused it, and logs it.
    pub(crate) async fn report(
        &self,
        run: &str,
        agent: &str,
        report: ErrorReport,
        encoding: Encoding,
    ) {
        self.metrics.record_refusal(report.code);
        self.refusal_log.warn(|| {
            let (run, agent) = (truncated(run), truncated(agent));
            tracing::warn!(%run, %agent, code = ?report.code, episode = ?report.episode, step = ?report.step, "rejected: {}", report.message);
        });
        self.publish(&self.keys.error(run, agent), &report, encoding)
            .await;
    }
}

/// Why this planner does not attach an agent.
enum Refusal {
    /// Said to the agent.
    Report(ErrorReport),
    /// Not said: another planner claimed the run's next ownership epoch first (so it answers).
    Contended,
    /// Said to the agent (it may attach again): opening the run failed on an I/O error that
    /// may pass (a disk or a network mount that is back a moment later).
    Transient(ErrorReport),
}

impl From<ErrorReport> for Refusal {
    fn from(report: ErrorReport) -> Self {
        Refusal::Report(report)
    }
}

/// The task of a run spec, as [`Service::task_for`] found it.
enum SpecTask {
    /// A task this process shares already: a catalog task, or a spec interned before.
    Shared(&'static proto::Task),
    /// A new spec's task, compiled but not interned: it is interned only once every check of
    /// the attach passed.
    Unshared(Box<proto::Task>),
}

impl SpecTask {
    fn task(&self) -> &proto::Task {
        match self {
            SpecTask::Shared(task) => task,
            SpecTask::Unshared(task) => task,
        }
    }
}

/// How often the steward looks at the fleet even when nothing woke it: a free run's grace
/// running out, a set-aside run's retry falling due, a lease that ran out without an event.
const STEWARD_TICK: std::time::Duration = std::time::Duration::from_secs(1);

/// How long a starting planner waits for its stored runs to be resumed before it serves:
/// normally all of them are open by then (so `status` lists them before any agent returns),
/// but a run whose disk stalls must not keep the planner from serving the others.
const RESUME_WAIT: std::time::Duration = std::time::Duration::from_secs(30);

/// The first wait before a stored run whose opening failed on an I/O error is tried again;
/// it doubles with every failure, up to [`MAX_OPEN_RETRY`].
const FIRST_OPEN_RETRY: std::time::Duration = std::time::Duration::from_secs(1);

/// The longest wait between two tries at opening a stored run.
const MAX_OPEN_RETRY: std::time::Duration = std::time::Duration::from_secs(300);

/// A stored run whose opening failed on an I/O error that may pass.
#[derive(Debug)]
struct Retrying {
    attempts: u32,
    next_at: std::time::Instant,
    reason: String,
}

/// The planner daemon.
pub struct Service {
    config: ServiceConfig,
    /// The tasks an agent may name: the built-ins and the configuration's declared tasks.
    catalog: proto::TaskCatalog,
    outbox: Outbox,
    fleet: Arc<Fleet>,
    runs: Mutex<HashMap<String, RunHandle>>,
    /// Stored runs that could not be opened, with the reason: listed by `status`, refused at
    /// attach, left on disk untouched for the operator. In a fleet its owner key is released
    /// at once, so another planner may try it.
    failed: Mutex<BTreeMap<String, String>>,
    /// Stored runs whose opening failed on an I/O error that may pass: tried again with
    /// backoff, listed by `status` meanwhile (released for the other planners meanwhile).
    retrying: Mutex<BTreeMap<String, Retrying>>,
    /// Stored runs left closed because opening them would go beyond a budget (`max_runs`,
    /// `[storage] max_total_replay_bytes`), with the budget: listed by `status`, opened when an
    /// agent attaches once the budget allows, refused with the reason until then.
    dormant: Mutex<BTreeMap<String, String>>,
    /// Stored runs nobody holds, since when this planner has seen them free (a fleet
    /// planner takes one it is not preferred on once it has been free for a grace period).
    free_since: Mutex<HashMap<String, std::time::Instant>>,
    /// Held while a new run is opened (off the event loop), so that two agents attaching to
    /// the same new run at once open it once. Hosted runs are joined without it.
    opening: tokio::sync::Mutex<()>,
    attach_slots: Arc<Semaphore>,
    /// Attach queries for free runs preferred elsewhere, waiting out the grace.
    free_run_waits: Arc<Semaphore>,
    /// Raised at shutdown: every run's training stops before its next minibatch.
    cancel_training: Arc<AtomicBool>,
    /// Every run's plans, given the cores by earliest deadline; retraining yields to them
    /// (see [`crate::sched`]).
    plans: Arc<crate::sched::Scheduler>,
    /// How the runs' replay logs reach the disk.
    log_disk: LogDisk,
    /// The replay byte budgets every run shares (`[storage]`).
    replay_budget: Arc<crate::run::ReplayBudget>,
    runtime: tokio::runtime::Handle,
    started: std::time::Instant,
}

impl Service {
    /// Serves until `shutdown` completes, then stops every worker and closes the session.
    pub async fn serve(
        config: ServiceConfig,
        shutdown: impl Future<Output = ()>,
    ) -> Result<(), ServiceError> {
        Self::serve_with(config, shutdown, LogDisk::direct()).await
    }

    /// As [`Service::serve`], with the runs' replay logs writing through `log_disk` (tests
    /// give one run a disk that blocks, and check that the others are served meanwhile).
    pub async fn serve_with(
        config: ServiceConfig,
        shutdown: impl Future<Output = ()>,
        log_disk: LogDisk,
    ) -> Result<(), ServiceError> {
        let catalog = config.catalog()?;
        // Held until serving ends: `planner-service runs delete|archive` refuse meanwhile.
        let _daemon_lock =
            persist::admin::DaemonLock::acquire(&config.data_dir, &config.planner_id)?;
        let base = match &config.zenoh_config {
            Some(path) => Some(zenoh::Config::from_file(path).map_err(zenoh_err)?),
            None => None,
        };
        let endpoints = proto::session::Endpoints {
            listen: config.listen.clone(),
            connect: config.connect.clone(),
        };
        let mut zconfig = proto::session::zenoh_config(&endpoints, base)?;
        if config.listen.is_empty() && config.zenoh_config.is_none() {
            // Nothing connects to this planner (it only connects, to a router): join as a
            // Zenoh client. A peer routes queries by the queryables and tokens it has heard
            // of, and right after connecting to a router it has heard of none, so the fleet's
            // first look at the live planners and leases would come back empty and a restarted
            // planner would take runs that others hold. A client asks the router, which knows.
            zconfig
                .insert_json5("mode", "\"client\"")
                .map_err(zenoh_err)?;
        }
        // Zenoh reassembles messages of up to 1 GiB by default: bound it near the payload
        // limit, so an oversized message is dropped by the transport before it is buffered.
        let max_message = config
            .limits
            .max_payload_bytes
            .saturating_add(ZENOH_HEADROOM);
        zconfig
            .insert_json5(
                "transport/link/rx/max_message_size",
                &max_message.to_string(),
            )
            .map_err(zenoh_err)?;
        let session = zenoh::open(zconfig).await.map_err(zenoh_err)?;
        let keys = Keys::new(&config.prefix);
        let planner_id = config.planner_id.clone();
        let fleet = match &config.fleet {
            Some(fleet) => {
                Fleet::join(session.clone(), keys.clone(), planner_id.clone(), fleet).await?
            }
            None => Fleet::alone(session.clone(), keys.clone(), planner_id.clone()),
        };
        let plans = Arc::new(crate::sched::Scheduler::new(config.retraining_share));
        let replay_budget = Arc::new(crate::run::ReplayBudget::new(
            config.storage.max_run_replay_bytes,
            config.storage.max_total_replay_bytes,
        ));
        let service = Arc::new(Service {
            outbox: Outbox {
                session: session.clone(),
                keys: keys.clone(),
                refusal_log: Arc::default(),
                metrics: Arc::default(),
            },
            fleet,
            config,
            catalog,
            runs: Mutex::new(HashMap::new()),
            failed: Mutex::new(BTreeMap::new()),
            retrying: Mutex::new(BTreeMap::new()),
            dormant: Mutex::new(BTreeMap::new()),
            free_since: Mutex::new(HashMap::new()),
            opening: tokio::sync::Mutex::new(()),
            attach_slots: Arc::new(Semaphore::new(CONCURRENT_ATTACHES)),
            free_run_waits: Arc::new(Semaphore::new(FREE_RUN_WAITS)),
            cancel_training: Arc::new(AtomicBool::new(false)),
            plans,
            replay_budget,
            log_disk,
            runtime: tokio::runtime::Handle::current(),
            started: std::time::Instant::now(),
        });
        crate::nn::peak::measure_in_background();
        tokio::pin!(shutdown);
        // Resume the stored runs that are ours (all of them for a planner without peers) on a
        // task of its own, waiting for it at most RESUME_WAIT, and never past a SIGTERM: a run
        // whose disk stalls delays neither serving the others nor stopping.
        // The sender goes when the task ends, however it ends.
        let (resumed, resumed_rx) = tokio::sync::oneshot::channel::<()>();
        let resume = {
            let service = service.clone();
            tokio::spawn(async move {
                service.rebalance().await;
                service.fleet.show_presence().await;
                drop(resumed);
            })
        };
        let resuming = resume.abort_handle();
        tokio::select! {
            biased;
            () = &mut shutdown => {
                tracing::info!("shutting down while resuming stored runs; the takeover is abandoned");
                resuming.abort();
                service.stop().await;
                service.fleet.leave().await;
                session.close().await.map_err(zenoh_err)?;
                return Ok(());
            }
            waited = tokio::time::timeout(RESUME_WAIT, resumed_rx) => {
                if waited.is_err() {
                    tracing::warn!(waited_s = RESUME_WAIT.as_secs(), "resuming the stored runs takes long (a stalled disk?); serving meanwhile");
                }
            }
        }
        let attach = session
            .declare_queryable(keys.all_attach())
            .await
            .map_err(zenoh_err)?;
        let observations = session
            .declare_subscriber(keys.all_obs())
            .await
            .map_err(zenoh_err)?;
        let status = session
            .declare_queryable(keys.planner_status(&planner_id))
            .await
            .map_err(zenoh_err)?;
        let agents_alive = session
            .liveliness()
            .declare_subscriber(keys.all_agents_alive())
            .await
            .map_err(zenoh_err)?;
        let metrics_endpoint = match service.config.metrics.listen {
            Some(addr) => Some(service.serve_metrics(addr).await?),
            None => None,
        };
        let steward = service.spawn_steward(resume);
        tracing::info!(planner = %planner_id, prefix = %keys.prefix(), "planner serving");

        loop {
            // Biased: observations are drained before liveliness changes. Zenoh delivers an
            // agent's last observation before its token's deletion, but they arrive on two
            // channels; an unbiased select could drop the agent first and refuse its last step.
            tokio::select! {
                biased;
                // Attaching may open a run (disk, model construction): it runs on a task of
                // its own, so the loop keeps routing every other agent's observations.
                query = attach.recv_async() => match query {
                    Ok(query) => service.spawn_attach(query),
                    Err(e) => { tracing::error!(error = %e, "attach queryable closed"); break; }
                },
                sample = observations.recv_async() => match sample {
                    Ok(sample) => service.route(sample).await,
                    Err(e) => { tracing::error!(error = %e, "observation subscriber closed"); break; }
                },
                query = status.recv_async() => match query {
                    Ok(query) => service.status(query).await,
                    Err(e) => { tracing::error!(error = %e, "status queryable closed"); break; }
                },
                token = agents_alive.recv_async() => match token {
                    Ok(token) => service.liveliness(token),
                    Err(e) => { tracing::error!(error = %e, "liveliness subscriber closed"); break; }
                },
                () = &mut shutdown => break,
            }
        }
        tracing::info!("shutting down");
        // A takeover in progress is abandoned where it stands: a run it created the owner key
        // of is freed with the lease, below.
        resuming.abort();
        steward.abort();
        if let Some(endpoint) = metrics_endpoint {
            endpoint.abort();
        }
        service.stop().await;
        service.fleet.leave().await;
        session.close().await.map_err(zenoh_err)?;
        Ok(())
    }

    /// Starts the steward: it rebalances whenever the fleet changed (changes coalesce: one
    /// rebalance covers all that came meanwhile) and every [`STEWARD_TICK`], on a task of its
    /// own, so the serve loop never waits for a takeover.
    /// It starts once `resume` (the first rebalance, at start) is done.
    fn spawn_steward(self: &Arc<Self>, resume: JoinHandle<()>) -> JoinHandle<()> {
        let service = self.clone();
        let changes = self.fleet.changes();
        self.runtime.spawn(async move {
            if let Err(e) = resume.await
                && e.is_panic()
            {
                tracing::error!(error = %e, "resuming the stored runs panicked; the steward goes on");
            }
            loop {
                tokio::select! {
                    () = changes.notified() => {}
                    () = tokio::time::sleep(STEWARD_TICK) => {}
                }
                service.fleet.show_presence().await;
                service.rebalance().await;
            }
        })
    }

    /// Serves the metrics as Prometheus text on `addr` (`GET /metrics`) on a task of its own.
    async fn serve_metrics(
        self: &Arc<Self>,
        addr: std::net::SocketAddr,
    ) -> Result<JoinHandle<()>, ServiceError> {
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .map_err(|e| ServiceError::Metrics(format!("cannot listen on {addr}: {e}")))?;
        let bound = listener
            .local_addr()
            .map_err(|e| ServiceError::Metrics(e.to_string()))?;
        tracing::info!(%bound, "metrics endpoint listening (GET /metrics)");
        // A weak reference: the endpoint must not keep a stopped service alive.
        let service = Arc::downgrade(self);
        Ok(self.runtime.spawn(metrics::serve(listener, move || {
            service
                .upgrade()
                .map(|s| s.outbox.metrics.render(&s.status_report()))
                .unwrap_or_default()
        })))
    }

    /// Stops every worker (each finishes the message in hand, within a grace period) and every
    /// trainer. The replay logs are synced at every episode end and every transition is
    /// handed to the OS before it is acknowledged, so nothing acknowledged is lost either way.
    ///
    /// Everything stops at once: training is cancelled (it ends before its next minibatch),
    /// and every worker is given the same [`SHUTDOWN_GRACE`], concurrently, so a daemon with
    /// many agents stops as fast as one with a single agent.
    async fn stop(&self) {
        self.cancel_training.store(true, Ordering::SeqCst);
        let runs: Vec<RunHandle> = self
            .runs
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .drain()
            .map(|(_, h)| h)
            .collect();
        let mut workers = Vec::new();
        for handle in runs {
            handle.trainer.abort();
            for (agent, worker) in handle.agents {
                drop(worker.tx);
                workers.push((handle.run.name().to_string(), agent, worker.task));
            }
        }
        let deadline = tokio::time::Instant::now() + SHUTDOWN_GRACE;
        let mut finishing = tokio::task::JoinSet::new();
        for (run, agent, task) in workers {
            finishing.spawn(async move {
                let abort = task.abort_handle();
                if tokio::time::timeout_at(deadline, task).await.is_err() {
                    tracing::warn!(%run, %agent, "worker did not finish in time; abandoned");
                    abort.abort();
                }
            });
        }
        while finishing.join_next().await.is_some() {}
    }

    fn event_sink(&self) -> EventSink {
        let outbox = self.outbox.clone();
        let runtime = self.runtime.clone();
        Arc::new(move |run: &str, kind: RunEventKind| {
            let outbox = outbox.clone();
            let event = RunEvent {
                version: PROTOCOL_VERSION,
                run: run.to_string(),
                kind,
            };
            runtime.spawn(async move {
                // Broadcast: each subscriber reads the encoding of the key it chose.
                for encoding in [Encoding::Postcard, Encoding::Json] {
                    let key = outbox.keys().events(&event.run, encoding);
                    outbox.publish(&key, &event, encoding).await;
                }
            });
        })
    }

    /// Handles an attach query on a task of its own, or refuses it at once when
    /// [`CONCURRENT_ATTACHES`] are already in hand.
    ///
    /// A query for a run another planner owns is dropped at once, unanswered (dropping it ends
    /// this planner's part in it), so the agent gets the owner's answer and no other: not
    /// even a refusal for want of a slot.
    fn spawn_attach(self: &Arc<Self>, query: zenoh::query::Query) {
        if query.key_expr().is_wild() {
            return self.drop_wildcard("attach", query.key_expr().as_str());
        }
        if let Some(run) = self.outbox.keys().parse_attach(query.key_expr().as_str())
            && !self.fleet.is_mine(run)
        {
            tracing::debug!(%run, owner = ?self.fleet.owner(run), "attach for a run owned elsewhere");
            if self.fleet.in_fleet() && !self.fleet.has_owner_key(run) {
                self.attach_if_still_free(run.to_string(), query);
            }
            return;
        }
        self.attach_in_a_slot(query);
    }

    /// Attaches on a task of its own in one of the attach slots, or refuses at once when all
    /// [`CONCURRENT_ATTACHES`] are in hand.
    fn attach_in_a_slot(self: &Arc<Self>, query: zenoh::query::Query) {
        match self.attach_slots.clone().try_acquire_owned() {
            Ok(slot) => {
                let service = self.clone();
                self.runtime.spawn(async move {
                    service.attach(query).await;
                    drop(slot);
                });
            }
            Err(_) => {
                let encoding = query_encoding(&query);
                let report = ErrorReport::new(
                    ErrorCode::Refused,
                    format!(
                        "{CONCURRENT_ATTACHES} attach requests are in hand already: try again shortly"
                    ),
                );
                self.runtime.spawn(async move {
                    reply_attach(&query, AttachOutcome::Rejected(report), encoding).await
                });
            }
        }
    }

    /// An attach for a run nobody holds, preferred on another planner: that planner should
    /// take it at once, but it may be cut off from etcd, or not a planner at all (a forged
    /// token). After [`crate::fleet::FREE_GRACE`], if the run is still free, this planner
    /// takes it (etcd lets only one of the planners that try succeed; the others stay
    /// silent). At most [`FREE_RUN_WAITS`] queries wait so at once (beyond that they are left to
    /// the other planners); waiting takes no attach slot, so the runs this planner owns keep
    /// theirs.
    fn attach_if_still_free(self: &Arc<Self>, run: String, query: zenoh::query::Query) {
        let Ok(waiting) = self.free_run_waits.clone().try_acquire_owned() else {
            return;
        };
        let service = self.clone();
        // The grace counts from when the steward first saw the run free, not from this query:
        // an agent asking again after its owner went waits only what is left of it.
        let free_for = self
            .free_since
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(&run)
            .map_or(std::time::Duration::ZERO, std::time::Instant::elapsed);
        self.runtime.spawn(async move {
            tokio::time::sleep(crate::fleet::FREE_GRACE.saturating_sub(free_for)).await;
            if !service.fleet.has_owner_key(&run)
                && service
                    .fleet
                    .may_take_unpreferred(&run, crate::fleet::FREE_GRACE)
            {
                service.attach_in_a_slot(query);
            }
            drop(waiting);
        });
    }

    async fn attach(&self, query: zenoh::query::Query) {
        let key = query.key_expr().as_str().to_string();
        let encoding = query_encoding(&query);
        let outcome = match self.outbox.keys().parse_attach(&key) {
            None => AttachOutcome::Rejected(ErrorReport::new(
                ErrorCode::Refused,
                format!("`{}` is not an attach key", truncated(&key)),
            )),
            Some(run) => {
                let size = query.payload().map_or(0, |p| p.len());
                let bytes = match self.check_payload(size) {
                    Ok(()) => query
                        .payload()
                        .map(|p| p.to_bytes().into_owned())
                        .unwrap_or_default(),
                    Err(report) => return self.refuse_attach(&query, &key, report, encoding).await,
                };
                match proto::decode::<AttachRequest>(&bytes, encoding) {
                    Err(e) => AttachOutcome::Rejected(codec_report(&e)),
                    Ok(request) => match self.attach_agent(run, request).await {
                        Ok(accepted) => AttachOutcome::Accepted(accepted),
                        Err(Refusal::Report(report) | Refusal::Transient(report)) => {
                            AttachOutcome::Rejected(report)
                        }
                        // Another planner is taking the run over at this moment: its answer
                        // is the one the agent must get.
                        Err(Refusal::Contended) => return,
                    },
                }
            }
        };
        if let AttachOutcome::Rejected(report) = &outcome {
            let key = truncated(&key);
            self.outbox.refusal_log.warn(|| {
                tracing::warn!(%key, code = ?report.code, "attach refused: {}", report.message);
            });
        }
        reply_attach(&query, outcome, encoding).await;
    }

    async fn refuse_attach(
        &self,
        query: &zenoh::query::Query,
        key: &str,
        report: ErrorReport,
        encoding: Encoding,
    ) {
        let key = truncated(key);
        self.outbox.refusal_log.warn(|| {
            tracing::warn!(%key, code = ?report.code, "attach refused: {}", report.message);
        });
        reply_attach(query, AttachOutcome::Rejected(report), encoding).await;
    }

    /// Refuses a message of `size` bytes over `[limits] max_payload_bytes`, before anything
    /// decodes (or copies) it.
    fn check_payload(&self, size: usize) -> Result<(), ErrorReport> {
        let limit = self.config.limits.max_payload_bytes;
        if size as u64 > limit {
            return Err(ErrorReport::new(
                ErrorCode::Refused,
                format!(
                    "a message of {size} bytes is over this planner's limit of {limit} bytes ([limits] max_payload_bytes)"
                ),
            ));
        }
        Ok(())
    }

    fn is_hosted(&self, run: &str) -> bool {
        self.runs
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .contains_key(run)
    }

    /// Creates or joins the run and starts the agent's worker.
    async fn attach_agent(
        &self,
        run_name: &str,
        request: AttachRequest,
    ) -> Result<AttachAccepted, Refusal> {
        let refuse = |msg: String| Refusal::Report(ErrorReport::new(ErrorCode::Refused, msg));
        proto::validate_name(run_name).map_err(|e| refuse(e.to_string()))?;
        proto::validate_name(&request.agent).map_err(|e| refuse(e.to_string()))?;
        if !self.is_hosted(run_name) {
            self.open_new_run(run_name, &self.with_declared_spec(&request.spec))
                .await?;
        }
        let mut runs = self.runs.lock().unwrap_or_else(PoisonError::into_inner);
        let handle = runs.get_mut(run_name).ok_or_else(|| {
            ErrorReport::new(
                ErrorCode::Internal,
                format!("run `{run_name}` closed while attaching: attach again"),
            )
        })?;
        let run = handle.run.clone();
        if let Some(difference) = spec_difference(run.spec(), &request.spec) {
            return Err(refuse(format!(
                "run `{run_name}` was created with {difference}: attach with the run's spec, or use another run name"
            )));
        }
        // Sessions that ended (idle without a liveliness token) free their slots.
        handle.agents.retain(|_, a| !a.task.is_finished());
        if let Some(current) = handle.agents.get(&request.agent) {
            // A live session is replaced only by the agent that holds its token (reconnecting,
            // or asking again for an answer it never got); anyone else using the name is
            // refused, and the live agent never notices.
            if current.is_live() && !current.is_held_by(request.session) {
                let idle = self.config.limits.agent_idle_seconds;
                return Err(refuse(format!(
                    "agent `{}` is attached to run `{run_name}` and live: attach under another name, attach again with its session token, or wait until it vanished (its liveliness token gone, or {idle} s idle without one)",
                    truncated(&request.agent)
                )));
            }
        }
        let session = proto::draw_token().map_err(|e| {
            ErrorReport::new(
                ErrorCode::Internal,
                format!("cannot draw a session token: {e}"),
            )
        })?;
        if let Some(old) = handle.agents.remove(&request.agent) {
            // The agent reconnecting, or its name reclaimed after it vanished: the old worker
            // ends, and any episode it left open is recorded as interrupted by the new
            // worker's first step.
            old.task.abort();
        } else if handle.agents.len() >= self.config.max_agents_per_run {
            return Err(refuse(format!(
                "run `{run_name}` already has its limit of {} agents",
                self.config.max_agents_per_run
            )));
        }
        let plans_waiting = crate::sched::Waiting::default();
        let worker = AgentWorker::new(
            run.clone(),
            request.agent.clone(),
            self.outbox.clone(),
            self.fleet.clone(),
            self.config.limits.magnitudes(run.task()),
            handle.plans.clone(),
            session,
        )?
        .counting_waits_in(plans_waiting.clone());
        let idle = std::time::Duration::from_secs(self.config.limits.agent_idle_seconds);
        let worker = worker.idle_after(idle);
        let (tx, rx) = mpsc::channel(AGENT_QUEUE);
        let task = self.runtime.spawn(worker.run(rx));
        handle.agents.insert(
            request.agent.clone(),
            AgentHandle {
                tx,
                plans_waiting,
                task,
                session,
                attached_with: request.session,
                token_gone: false,
            },
        );
        if !self.fleet.may_acknowledge(run_name, run.epoch()) {
            // This planner's lease ran out (or the run moved) meanwhile: its answer must not
            // be the one the agent acts on.
            if let Some(agent) = handle.agents.remove(&request.agent) {
                agent.task.abort();
            }
            return Err(Refusal::Contended);
        }
        let models = run.models();
        tracing::info!(run = %run_name, agent = %request.agent, task = %run.spec().task, method = %run.preset().method, "agent attached");
        Ok(AttachAccepted {
            planner_id: self.config.planner_id.clone(),
            task: run.spec().task.clone(),
            mode: run.mode(),
            episodes_done: run.episodes_stored(),
            models_version: models.version,
            next_episode: run.next_episode(&request.agent),
            epoch: run.epoch(),
            session,
        })
    }

    /// The task a run spec names: its own spec (validated against `[limits]`, compiled but
    /// not interned unless this process knows it already), or the catalog's entry of that
    /// name. A spec may not redefine a catalog task.
    fn task_for(&self, spec: &RunSpec) -> Result<SpecTask, ErrorReport> {
        let refuse = |msg: String| ErrorReport::new(ErrorCode::Refused, msg);
        let Some(task_spec) = &spec.task_spec else {
            return self
                .catalog
                .get(&spec.task)
                .map(SpecTask::Shared)
                .map_err(|e| ErrorReport::new(ErrorCode::UnknownTask, e.to_string()));
        };
        if task_spec.name != spec.task {
            return Err(refuse(format!(
                "the task spec is named `{}`, the run spec's task `{}`: they must agree",
                truncated(&task_spec.name),
                truncated(&spec.task)
            )));
        }
        if let Ok(known) = self.catalog.get(&spec.task) {
            return if known.spec() == task_spec {
                Ok(SpecTask::Shared(known))
            } else {
                Err(refuse(format!(
                    "task `{}` is in this planner's catalog with another spec: attach by name, or name your task otherwise",
                    spec.task
                )))
            };
        }
        let bounds = self.config.limits.spec_bounds();
        task_spec
            .validate(&bounds)
            .map_err(|e| refuse(e.to_string()))?;
        if let Some(task) = proto::Task::interned(task_spec) {
            return Ok(SpecTask::Shared(task));
        }
        proto::Task::compile_unshared(task_spec.clone(), &bounds)
            .map(|task| SpecTask::Unshared(Box::new(task)))
            .map_err(|e| refuse(e.to_string()))
    }

    /// `spec` with the full spec of an operator-declared task (`[tasks.NAME]`, `tasks_dir`)
    /// it names only by name: the run stores the spec it runs, as it does a client's, so
    /// that editing or removing the declaration later cannot silently change or orphan it
    /// (see [`Service::declaration_conflict`]). Built-in tasks are code, not declarations,
    /// and are stored by name.
    fn with_declared_spec(&self, spec: &RunSpec) -> RunSpec {
        let mut spec = spec.clone();
        if spec.task_spec.is_none()
            && let Ok(task) = self.catalog.get(&spec.task)
            && task.builtin().is_none()
        {
            spec.task_spec = Some(task.spec().clone());
        }
        spec
    }

    /// Why a stored run cannot resume under this daemon's declarations: its stored task spec
    /// differs from the daemon's declaration of the same name (`None`: no conflict; a run whose
    /// declaration was removed resumes with its stored spec). The run is set aside rather than
    /// resumed with a task it was not trained on.
    fn declaration_conflict(&self, spec: &RunSpec) -> Option<String> {
        let stored = spec.task_spec.as_ref()?;
        let declared = self.catalog.get(&spec.task).ok()?;
        (declared.spec() != stored).then(|| {
            format!(
                "this planner declares task `{}` with another spec than the one stored with the run (run.json): restore the declaration, or declare the changed task under another name",
                spec.task
            )
        })
    }

    /// The preset a run spec asks for, with the daemon's and the spec's overrides applied.
    fn preset_for(&self, spec: &RunSpec) -> Result<Preset, ErrorReport> {
        let refuse = |msg: String| ErrorReport::new(ErrorCode::Refused, msg);
        let task = self.task_for(spec)?;
        let method = spec.preset.as_deref();
        if let Some(m) = method
            && !self.config.allowed_presets.is_empty()
            && !self.config.allowed_presets.iter().any(|p| p == m)
        {
            return Err(refuse(format!(
                "preset `{m}` is not allowed here (allowed: {})",
                self.config.allowed_presets.join(", ")
            )));
        }
        let mut preset = match &task {
            SpecTask::Shared(task) => Preset::new(task, method),
            SpecTask::Unshared(task) => Preset::unshared(task, method),
        }
        .map_err(|e| refuse(e.to_string()))?;
        preset
            .apply(&self.config.overrides)
            .map_err(|e| refuse(format!("planner config: {e}")))?;
        preset
            .apply(&spec.overrides)
            .map_err(|e| refuse(e.to_string()))?;
        preset
            .cem
            .validate()
            .map_err(|e| refuse(format!("invalid planner configuration: {e}")))?;
        self.config
            .limits
            .check_for(&preset, task.task())
            .map_err(|e| refuse(e.to_string()))?;
        // Everything is checked: only now is a new task kept (interned), so a refused attach
        // keeps nothing and takes none of the process's task slots.
        if let SpecTask::Unshared(task) = task {
            preset.task = proto::Task::share(*task).map_err(|e| refuse(e.to_string()))?;
        }
        Ok(preset)
    }

    /// Opens a run that is not hosted yet (new, or stored but not resumed), one at a time.
    async fn open_new_run(&self, name: &str, spec: &RunSpec) -> Result<(), Refusal> {
        let refuse = |msg: String| ErrorReport::new(ErrorCode::Refused, msg);
        let _opening = self.opening.lock().await;
        if self.is_hosted(name) {
            return Ok(()); // another agent opened it meanwhile
        }
        if let Some(reason) = self
            .failed
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(name)
        {
            return Err(refuse(format!(
                "run `{name}` is stored here but cannot be opened ({reason}): ask the operator, or use another run name"
            ))
            .into());
        }
        let stored = RunDir::new(&self.config.data_dir, name).has_replay();
        if let Err(budget) = self.opening_budget(stored) {
            if !stored {
                return Err(refuse(budget).into());
            }
            let reason = format!(
                "run `{name}` is stored here but not open: {budget}; it stays on disk untouched \
                 (the operator raises the budget, or archives runs with `planner-service runs archive`)"
            );
            self.dormant
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .insert(name.to_string(), budget);
            return Err(refuse(reason).into());
        }
        let run = self.open_run(name, spec.clone()).await?;
        self.host(run);
        Ok(())
    }

    /// Whether one more run may be opened now: fewer than `max_runs` are hosted and, for a
    /// stored run (opening reads its whole replay into memory), the open runs' replay logs
    /// are below `[storage] max_total_replay_bytes`. These two bound the daemon's memory:
    /// `max_runs` runs' models, and replay of at most that budget plus the last run opened.
    /// The budget that is reached otherwise, named by its setting.
    fn opening_budget(&self, stored: bool) -> Result<(), String> {
        let hosted = self
            .runs
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .len();
        if hosted >= self.config.max_runs {
            return Err(format!(
                "this planner already hosts its limit of {} runs (max_runs)",
                self.config.max_runs
            ));
        }
        let (used, total) = (self.replay_budget.used(), self.replay_budget.total);
        if stored && used >= total {
            return Err(format!(
                "the open runs' replay logs hold {used} bytes, this planner's budget of {total} \
                 bytes ([storage] max_total_replay_bytes)"
            ));
        }
        Ok(())
    }

    /// Takes run `name` over (a new ownership epoch) and opens it in the data directory (new,
    /// or stored by this or another planner) on the blocking pool: claiming the epoch, reading
    /// the replay log and building the models may take a while, and a failure there (even a
    /// panic) is this run's alone.
    async fn open_run(&self, name: &str, spec: RunSpec) -> Result<Arc<Run>, Refusal> {
        let preset = self.preset_for(&spec)?;
        let dir = RunDir::new(&self.config.data_dir, name);
        let hosting = Hosting {
            events: self.event_sink(),
            train_limits: TrainLimits {
                max_seconds: self.config.limits.max_retrain_seconds,
                cancel: self.cancel_training.clone(),
                yield_to: Some(self.plans.clone()),
            },
            replay_capacity: self.config.storage.replay_capacity,
            replay_budget: self.replay_budget.clone(),
            log_disk: self.log_disk.clone(),
            histograms: self.outbox.metrics.for_run(name),
            sync_every_step: self.config.sync_every_step(),
            shared_dir: self.fleet.in_fleet(),
            still_owner: {
                let fleet = self.fleet.clone();
                Arc::new(move |run: &str, token: u64| fleet.may_acknowledge(run, token))
            },
        };
        let internal = |why: String| {
            Refusal::Report(ErrorReport::new(
                ErrorCode::Internal,
                format!("cannot open run `{name}`: {why}"),
            ))
        };
        let transient = |why: String| {
            Refusal::Transient(ErrorReport::new(
                ErrorCode::Storage,
                format!("cannot open run `{name}` now ({why}): attach again later"),
            ))
        };
        let token = match self.fleet.take(name, &dir).await {
            Ok(token) => token,
            Err(e) if e.is_contended() => return Err(Refusal::Contended),
            Err(crate::fleet::FleetError::Etcd(e)) => {
                tracing::info!(run = %name, error = %e, "cannot take the run over now");
                return Err(Refusal::Contended);
            }
            Err(e @ crate::fleet::FleetError::Persist(crate::persist::PersistError::Io { .. })) => {
                return Err(transient(format!("cannot take it over: {e}")));
            }
            Err(e) => return Err(internal(format!("cannot take it over: {e}"))),
        };
        let (fleet, planner, owned) = (
            self.fleet.clone(),
            self.config.planner_id.clone(),
            name.to_string(),
        );
        let opened = tokio::task::spawn_blocking(move || {
            Run::open(owned.clone(), spec, preset, dir, hosting, (token, &planner)).map_err(|e| {
                fleet.step_down(&owned, format!("the run could not be opened: {e}"));
                e
            })
        })
        .await;
        match opened {
            Ok(Ok(run)) => Ok(run),
            Ok(Err(e)) if e.is_transient() => Err(transient(e.to_string())),
            Ok(Err(e)) => Err(internal(e.to_string())),
            Err(e) => {
                self.fleet
                    .step_down(name, format!("opening the run failed: {e}"));
                Err(internal(e.to_string()))
            }
        }
    }

    fn host(&self, run: Arc<Run>) {
        self.retrying
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .remove(run.name());
        self.dormant
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .remove(run.name());
        let trainer = self.runtime.spawn(run.clone().trainer_loop());
        let mut runs = self.runs.lock().unwrap_or_else(PoisonError::into_inner);
        runs.insert(
            run.name().to_string(),
            RunHandle {
                plans: Arc::new(worker::PlanBatcher::new(run.clone(), self.plans.clone())),
                run,
                agents: HashMap::new(),
                trainer,
            },
        );
    }

    /// Brings the runs this planner hosts in line with the fleet: steps down from the runs it
    /// may no longer serve (its etcd lease ran out, etcd names another owner, a newer token
    /// on disk, or reported fenced by a worker), then takes over every stored run that is
    /// free and preferred here (or free for [`crate::fleet::FREE_GRACE`], wherever it is
    /// preferred). At start this resumes a restarted daemon's runs (every stored run, for a
    /// single daemon): status lists them at once, their trainers catch up with episodes stored
    /// after the last checkpoint, and agents re-attach to them. Runs are opened newest first
    /// (by their replay log's last write) while the budgets allow ([`Service::opening_budget`]:
    /// `max_runs`, the total replay bytes), so that a restart stays inside the memory a running
    /// daemon may use; the others stay dormant, on disk untouched, listed by `status`, and open
    /// on an agent's attach once a budget allows (refused with the budget's name until then).
    /// A run whose opening failed on an I/O error that may pass (a full disk, etcd
    /// unreachable while writing) is retried with a backoff, listed by `status` meanwhile. A
    /// run that cannot be opened (over today's limits, damaged, even one whose opening panics)
    /// is set aside: logged, listed by `status` as failed with the reason, refused at attach,
    /// not tried again by this daemon, and left on disk untouched; the daemon serves the
    /// others. Either way its owner key is released, so another planner may open it. Every
    /// disk read runs on the blocking pool.
    async fn rebalance(&self) {
        let mut lost: Vec<(String, String)> = self
            .fleet
            .take_fenced()
            .into_iter()
            .map(|run| {
                (
                    run,
                    "its token on disk is newer than this planner's".to_string(),
                )
            })
            .collect();
        lost.extend(self.fleet.lost_runs());
        let hosted: Vec<Arc<Run>> = self
            .runs
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .values()
            .map(|h| h.run.clone())
            .collect();
        let fenced = tokio::task::spawn_blocking(move || {
            hosted
                .iter()
                .filter_map(|run| {
                    run.check_owner()
                        .err()
                        .map(|e| (run.name().to_string(), e.to_string()))
                })
                .collect::<Vec<_>>()
        })
        .await
        .unwrap_or_default();
        lost.extend(fenced);
        for (name, reason) in lost {
            self.step_down(&name, reason).await;
        }
        self.fleet.release_strays().await;
        let data_dir = self.config.data_dir.clone();
        let listed = tokio::task::spawn_blocking(move || {
            let mut stored = persist::stored_runs(&data_dir)?;
            // Newest first: the runs in use resume before the long finished ones.
            let last_written = |dir: &RunDir| dir.replay_last_written();
            stored.sort_by_cached_key(|(_, dir)| std::cmp::Reverse(last_written(dir)));
            Ok::<_, crate::persist::PersistError>(stored)
        })
        .await;
        let stored = match listed {
            Ok(Ok(stored)) => stored,
            Ok(Err(e)) => {
                tracing::error!(error = %e, "cannot list stored runs; none taken over");
                return;
            }
            Err(e) => {
                tracing::error!(error = %e, "listing stored runs failed; none taken over");
                return;
            }
        };
        let now = std::time::Instant::now();
        let candidates: Vec<(String, RunDir)> = {
            let mut free_since = self
                .free_since
                .lock()
                .unwrap_or_else(PoisonError::into_inner);
            let free: std::collections::HashSet<String> = stored
                .iter()
                .map(|(name, _)| name.clone())
                .filter(|name| !self.fleet.has_owner_key(name))
                .collect();
            free_since.retain(|name, _| free.contains(name));
            stored
                .into_iter()
                .filter(|(name, _)| {
                    if self.is_hosted(name) {
                        return false;
                    }
                    if self.fleet.is_mine(name) {
                        return true;
                    }
                    if !free.contains(name) {
                        return false;
                    }
                    let since = *free_since.entry(name.clone()).or_insert(now);
                    self.fleet.may_take_unpreferred(name, now - since)
                })
                .collect()
        };
        let mut dormant = BTreeMap::new();
        for (name, dir) in candidates {
            let set_aside = self
                .failed
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .contains_key(&name);
            if set_aside || self.is_hosted(&name) || self.open_retry_waits(&name) {
                continue;
            }
            let spec = match tokio::task::spawn_blocking(move || dir.read_spec()).await {
                Ok(Ok(Some(spec))) => spec,
                Ok(Ok(None)) => {
                    tracing::debug!(run = %name, "stored run has no run.json; it resumes when an agent attaches");
                    continue;
                }
                Ok(Err(e)) => {
                    self.set_aside(&name, format!("cannot read its spec: {e}"));
                    continue;
                }
                Err(e) => {
                    self.set_aside(&name, format!("reading its spec failed: {e}"));
                    continue;
                }
            };
            // One opening at a time, as at attach: an agent may be opening this run now.
            let _opening = self.opening.lock().await;
            if self.is_hosted(&name) {
                continue;
            }
            if let Some(reason) = self.declaration_conflict(&spec) {
                self.set_aside(&name, reason);
                continue;
            }
            if let Err(budget) = self.opening_budget(true) {
                dormant.insert(name, budget);
                continue;
            }
            match self.open_run(&name, spec).await {
                Ok(run) => self.host(run),
                Err(Refusal::Transient(report)) => self.retry_open_later(&name, report.message),
                Err(Refusal::Report(report)) => self.set_aside(&name, report.message),
                Err(Refusal::Contended) => {
                    tracing::debug!(run = %name, "another planner holds the run, or etcd cannot be reached");
                }
            }
        }
        if !dormant.is_empty() {
            tracing::warn!(
                runs = dormant.len(),
                "stored runs left closed at a budget (see status: dormant_runs): {}",
                dormant.values().next().map_or("", String::as_str)
            );
        }
        *self.dormant.lock().unwrap_or_else(PoisonError::into_inner) = dormant;
    }

    /// Gives up run `name`: its trainer and workers stop, its lease goes, and each attached
    /// agent is told to attach again (its query then reaches the new owner).
    async fn step_down(&self, name: &str, reason: String) {
        let Some(handle) = self
            .runs
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .remove(name)
        else {
            return;
        };
        handle.trainer.abort();
        self.fleet.step_down(name, reason.clone());
        for (agent, worker) in handle.agents {
            worker.task.abort();
            let report = ErrorReport::new(
                ErrorCode::NotAttached,
                format!("run `{name}` moved to another planner ({reason}): attach again"),
            )
            .for_session(worker.session);
            // JSON: every agent decodes by the sample's declared encoding, and JSON is the one
            // all of them (Python included) speak.
            self.outbox
                .report(name, &agent, report, Encoding::Json)
                .await;
        }
    }

    /// Whether stored run `name` waits for its next try at opening.
    fn open_retry_waits(&self, name: &str) -> bool {
        self.retrying
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(name)
            .is_some_and(|r| r.next_at > std::time::Instant::now())
    }

    /// Opening stored run `name` failed on an I/O error that may pass: it is tried again
    /// after a backoff that doubles with every failure, from [`FIRST_OPEN_RETRY`] up to
    /// [`MAX_OPEN_RETRY`] (the steward looks every [`STEWARD_TICK`]), and `status` lists it
    /// meanwhile. Its owner key is released already, so another planner may open it first.
    fn retry_open_later(&self, name: &str, reason: String) {
        let mut retrying = self.retrying.lock().unwrap_or_else(PoisonError::into_inner);
        let attempts = retrying.get(name).map_or(0, |r| r.attempts) + 1;
        let backoff = FIRST_OPEN_RETRY
            .saturating_mul(1 << attempts.saturating_sub(1).min(16))
            .min(MAX_OPEN_RETRY);
        tracing::warn!(run = %name, attempts, retry_in_s = backoff.as_secs_f64(), "cannot open a stored run now, trying again later: {reason}");
        self.outbox.metrics.record_open_failure();
        retrying.insert(
            name.to_string(),
            Retrying {
                attempts,
                next_at: std::time::Instant::now() + backoff,
                reason,
            },
        );
    }

    /// Sets stored run `run` aside for good (for this daemon): it cannot be opened here. Its
    /// owner key (if it was taken) is released already, so another planner may try it.
    fn set_aside(&self, run: &str, reason: String) {
        tracing::error!(%run, "stored run set aside, not resumed: {reason}");
        self.outbox.metrics.record_open_failure();
        self.failed
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(run.to_string(), reason);
    }

    /// The status report of this planner.
    pub fn status_report(&self) -> status::PlannerStatus {
        // The runs and their agents' names, then each run's counters: no run's replay buffer
        // is locked, so a run busy on its disk delays no status report.
        let hosted: Vec<(Arc<Run>, BTreeMap<String, u64>)> = {
            let runs = self.runs.lock().unwrap_or_else(PoisonError::into_inner);
            runs.values()
                .map(|h| {
                    let queues = h
                        .agents
                        .iter()
                        .filter(|(_, a)| !a.task.is_finished())
                        .map(|(name, a)| (name.clone(), a.queue_depth()))
                        .collect();
                    (h.run.clone(), queues)
                })
                .collect()
        };
        let mut reports: Vec<status::RunStatus> = hosted
            .into_iter()
            .map(|(run, queue_depth)| {
                let tally = run.tally();
                let agents = queue_depth.keys().cloned().collect();
                status::RunStatus {
                    name: run.name().to_string(),
                    task: run.spec().task.to_string(),
                    method: run.preset().method.clone(),
                    mode: run.mode(),
                    episodes: tally.episodes,
                    transitions: tally.transitions,
                    models_version: run.models().version,
                    epoch: run.epoch(),
                    training: run.is_training(),
                    exploring: run.exploring(),
                    last_returns: tally.last_returns,
                    agents,
                    planning_latency: run.latency(),
                    deadline_ms: run.preset().deadline_ms,
                    plan_tally: run.plan_tally(),
                    queue_depth,
                    replay_bytes: tally.log_bytes,
                    replay_fsync: run.histograms().fsync_seconds.timings(),
                    retraining: run.histograms().retraining_seconds.timings(),
                    last_retraining: run.last_retraining(),
                    replay_damage: run.replay_damage().map(str::to_string),
                    kernels: run.models().kernels(run.preset().inference_precision),
                }
            })
            .collect();
        reports.sort_by(|a, b| a.name.cmp(&b.name));
        let hosted_runs = reports.len();
        let fullest_run = reports.iter().map(|r| r.replay_bytes).max().unwrap_or(0);
        let failed_runs = self
            .failed
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .iter()
            .map(|(name, reason)| status::FailedRun {
                name: name.clone(),
                reason: reason.clone(),
            })
            .collect();
        let (dormant_runs, dormant_run_count) = {
            let dormant = self.dormant.lock().unwrap_or_else(PoisonError::into_inner);
            let listed = dormant
                .iter()
                .take(status::DORMANT_LISTED)
                .map(|(name, budget)| status::DormantRun {
                    name: name.clone(),
                    budget: budget.clone(),
                })
                .collect();
            (listed, dormant.len() as u64)
        };
        let now = std::time::Instant::now();
        let retrying_runs = self
            .retrying
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .iter()
            .map(|(name, r)| status::RetryingRun {
                name: name.clone(),
                reason: r.reason.clone(),
                attempts: r.attempts,
                next_try_seconds: r.next_at.saturating_duration_since(now).as_secs_f64(),
            })
            .collect();
        status::PlannerStatus {
            planner_id: self.config.planner_id.clone(),
            protocol_version: PROTOCOL_VERSION,
            uptime_seconds: self.started.elapsed().as_secs_f64(),
            runs: reports,
            fleet: self.fleet.status(),
            failed_runs,
            retrying_runs,
            dormant_runs,
            dormant_run_count,
            wildcards_dropped: self.outbox.metrics.wildcards_dropped(),
            refused: self.outbox.metrics.refusals(),
            retraining: self.plans.training(),
            budgets: status::Budgets {
                runs: status::Usage::of(hosted_runs as u64, self.config.max_runs as u64),
                replay_bytes: status::Usage::of(
                    self.replay_budget.used(),
                    self.replay_budget.total,
                ),
                fullest_run_replay_bytes: status::Usage::of(
                    fullest_run,
                    self.replay_budget.per_run,
                ),
                task_slots: status::Usage::of(
                    proto::Task::interned_count() as u64,
                    proto::task::MAX_DISTINCT_TASKS as u64,
                ),
            },
            kernels: status::KernelStatus::now(),
        }
    }

    async fn status(&self, query: zenoh::query::Query) {
        let report = self.status_report();
        match serde_json::to_vec(&report) {
            Ok(bytes) => {
                let key = query.key_expr().as_str().to_string();
                if let Err(e) = query
                    .reply(key, bytes)
                    .encoding(ZEncoding::APPLICATION_JSON)
                    .await
                {
                    tracing::warn!(error = %e, "status reply failed");
                }
            }
            Err(e) => tracing::error!(error = %e, "cannot encode status"),
        }
    }

    /// An agent's liveliness token went away: after [`AGENT_LINGER`], drop its session (its
    /// worker records an open episode as interrupted), unless it attached again meanwhile.
    /// Agents that come back attach again.
    fn liveliness(self: &Arc<Self>, token: zenoh::sample::Sample) {
        let gone = token.kind() == zenoh::sample::SampleKind::Delete;
        let key = token.key_expr().as_str();
        let Some((run, agent)) = self.outbox.keys().parse_agent_alive(key) else {
            return;
        };
        let session = {
            let mut runs = self.runs.lock().unwrap_or_else(PoisonError::into_inner);
            runs.get_mut(run)
                .and_then(|handle| handle.agents.get_mut(agent))
                .map(|a| {
                    // A token that comes back (the link recovered) makes the agent live again.
                    a.token_gone = gone;
                    a.tx.clone()
                })
        };
        if !gone {
            return;
        }
        let Some(session) = session else { return };
        let (service, run, agent) = (self.clone(), run.to_string(), agent.to_string());
        self.runtime.spawn(async move {
            tokio::time::sleep(AGENT_LINGER).await;
            let removed = {
                let mut runs = service.runs.lock().unwrap_or_else(PoisonError::into_inner);
                runs.get_mut(&run).and_then(|handle| {
                    // The same session, not one the agent opened by attaching again.
                    let same = handle
                        .agents
                        .get(&agent)
                        .is_some_and(|a| a.tx.same_channel(&session));
                    same.then(|| handle.agents.remove(&agent)).flatten()
                })
            };
            drop(session);
            if let Some(handle) = removed {
                tracing::info!(%run, %agent, "agent vanished; its session is closed");
                // Dropping the sender ends the worker once it is done with the messages it
                // holds; it is not awaited here, so a worker waiting for training stalls no one.
                drop(handle);
            }
        });
    }

    /// Drops a `what` (observation or attach) put on a wildcard key, unanswered: an answer
    /// could only go to a key the sender chose, which matches every agent under it, so each
    /// of them would receive a report it did not cause. Counted, and logged at a bounded rate.
    fn drop_wildcard(&self, what: &str, key: &str) {
        self.outbox.metrics.record_wildcard();
        let key = truncated(key);
        self.outbox.refusal_log.warn(|| {
            tracing::warn!(%key, "dropped an {what} on a wildcard key, unanswered: send on your own agent's key");
        });
    }

    /// Hands an observation to its agent's worker, or reports why it cannot be handled.
    async fn route(&self, sample: zenoh::sample::Sample) {
        let received = std::time::Instant::now();
        if sample.key_expr().is_wild() {
            return self.drop_wildcard("observation", sample.key_expr().as_str());
        }
        let key = sample.key_expr().as_str().to_string();
        let encoding = Encoding::from_mime(&sample.encoding().to_string());
        let Some((run, agent)) = self
            .outbox
            .keys()
            .parse_agent_key(&key, proto::AgentChannel::Obs)
        else {
            let key = truncated(&key);
            self.outbox.refusal_log.warn(|| {
                tracing::warn!(%key, "ignoring sample on a key that is not an observation key");
            });
            return;
        };
        if !self.fleet.is_mine(run) {
            return; // its owner answers
        }
        let result = self.decode_for_session(run, agent, &sample, encoding).and_then(
            |(msg, tx)| {
                let incoming = Incoming {
                    msg,
                    encoding,
                    received,
                };
                tx.try_send(incoming).map_err(|e| match e {
                    mpsc::error::TrySendError::Full(_) => ErrorReport::new(
                        ErrorCode::Refused,
                        format!("more than {AGENT_QUEUE} observations queued: wait for each action before sending the next"),
                    ),
                    mpsc::error::TrySendError::Closed(_) => {
                        ErrorReport::new(ErrorCode::NotAttached, "the agent's session has ended: attach again")
                    }
                })
            },
        );
        if let Err(report) = result {
            self.outbox.report(run, agent, report, encoding).await;
        }
    }
}

impl Service {
    /// Checks an observation sample's size (before anything copies or decodes it), decodes it
    /// (a message of at most `[limits] max_payload_bytes`, so this is short work for the
    /// event loop) and checks that it carries the session token of `agent`'s live session:
    /// only then does it reach that session's worker, so a stranger's messages under the
    /// agent's name neither queue before the agent's own nor touch its episode. Bytes that
    /// are too large or do not decode name no session, so their report carries
    /// [`proto::NO_SESSION`]: the live agent of the name (if any) ignores it, whoever sent them.
    fn decode_for_session(
        &self,
        run: &str,
        agent: &str,
        sample: &zenoh::sample::Sample,
        encoding: Encoding,
    ) -> Result<(proto::Observation, mpsc::Sender<Incoming>), ErrorReport> {
        let unreadable = |report: ErrorReport| report.for_session(proto::NO_SESSION);
        self.check_payload(sample.payload().len())
            .map_err(unreadable)?;
        let (tx, session) = {
            let runs = self.runs.lock().unwrap_or_else(PoisonError::into_inner);
            match runs.get(run) {
                None => Err(ErrorReport::new(
                    ErrorCode::UnknownRun,
                    format!("run `{run}` is not hosted here: attach first"),
                )),
                Some(handle) => match handle.agents.get(agent) {
                    None => Err(ErrorReport::new(
                        ErrorCode::NotAttached,
                        format!("agent `{agent}` is not attached to run `{run}`: attach first"),
                    )),
                    Some(a) => Ok((a.tx.clone(), a.session)),
                },
            }
        }?;
        let msg: proto::Observation = proto::decode(&sample.payload().to_bytes(), encoding)
            .map_err(|e| unreadable(codec_report(&e)))?;
        if msg.session != session {
            return Err(ErrorReport::new(
                ErrorCode::Session,
                format!(
                    "session token {} is not the current session of agent `{agent}` of run `{run}`: attach to get a session of your own (a reconnecting agent attaches with its token)",
                    msg.session
                ),
            )
            .at(msg.episode, msg.step)
            .for_session(msg.session));
        }
        Ok((msg, tx))
    }
}

/// Characters of a received key shown in a log line: a key is client-chosen.
const SHOWN_KEY_CHARS: usize = 128;

/// `key` cut to [`SHOWN_KEY_CHARS`], for logs and replies.
fn truncated(key: &str) -> String {
    if key.chars().count() <= SHOWN_KEY_CHARS {
        return key.to_string();
    }
    let shown: String = key.chars().take(SHOWN_KEY_CHARS).collect();
    format!("{shown}… ({} bytes)", key.len())
}

/// The encoding a query's payload is in (its answer goes back in the same).
fn query_encoding(query: &zenoh::query::Query) -> Encoding {
    query
        .encoding()
        .map(|e| Encoding::from_mime(&e.to_string()))
        .unwrap_or_default()
}

async fn reply_attach(query: &zenoh::query::Query, outcome: AttachOutcome, encoding: Encoding) {
    let key = query.key_expr().as_str().to_string();
    let reply = AttachReply {
        version: PROTOCOL_VERSION,
        outcome,
    };
    match proto::encode(&reply, encoding) {
        Ok(bytes) => {
            if let Err(e) = query
                .reply(key.as_str(), bytes)
                .encoding(ZEncoding::from(encoding.mime()))
                .await
            {
                tracing::warn!(%key, error = %e, "attach reply failed");
            }
        }
        Err(e) => tracing::error!(error = %e, "cannot encode attach reply"),
    }
}

/// How a later attach's spec differs from the run's, in words (`None`: it does not). A run
/// has one spec: an agent asking for another one would otherwise be served a run it did not
/// ask for without knowing.
fn spec_difference(run: &RunSpec, asked: &RunSpec) -> Option<String> {
    if run.task != asked.task {
        return Some(format!("task {}, not {}", run.task, truncated(&asked.task)));
    }
    // An agent joining may leave the run's task spec out: the run knows it.
    if asked.task_spec.is_some() && asked.task_spec != run.task_spec {
        return Some(format!("another spec of task {}", run.task));
    }
    let preset = |p: &Option<String>| p.clone().unwrap_or_else(|| "(the default)".into());
    if run.preset != asked.preset {
        return Some(format!(
            "preset {}, not {}",
            preset(&run.preset),
            preset(&asked.preset)
        ));
    }
    if run.mode != asked.mode {
        return Some(format!("mode {:?}, not {:?}", run.mode, asked.mode));
    }
    if run.seed != asked.seed {
        return Some(format!("seed {}, not {}", run.seed, asked.seed));
    }
    if run.overrides != asked.overrides {
        let set = |o: &proto::PlannerOverrides| match serde_json::to_value(o) {
            Ok(serde_json::Value::Object(fields)) => {
                let set: serde_json::Map<_, _> =
                    fields.into_iter().filter(|(_, v)| !v.is_null()).collect();
                serde_json::Value::Object(set).to_string()
            }
            _ => format!("{o:?}"),
        };
        return Some(format!(
            "overrides {}, not {}",
            set(&run.overrides),
            set(&asked.overrides)
        ));
    }
    None
}

/// The error report for bytes that did not decode.
pub(crate) fn codec_report(e: &proto::CodecError) -> ErrorReport {
    let code = match e {
        proto::CodecError::Version { .. } => ErrorCode::ProtocolVersion,
        _ => ErrorCode::Malformed,
    };
    ErrorReport::new(code, e.to_string())
}
