//! The planner daemon's Zenoh face: the attach queryable, the observation subscriber, the
//! per-agent workers that answer with actions, and the events and errors they publish.
//!
//! ```text
//! attach query ──▶ Service::attach ──▶ Run (created or joined) + agent worker task
//! obs sample ────▶ Service::route ───▶ agent worker (in order) ──▶ validate → store → act
//! fleet change ──▶ Service::rebalance ──▶ step down from lost runs, take over free ones
//! ```
//! In a fleet of planners ([`crate::fleet`]) the service serves only the runs it owns: it
//! stays silent on other runs' attach queries and observations, so the owner's answer is the
//! only one. A planner with no peers owns every run.
//! Each agent has one worker task, so its observations are handled strictly in order while
//! agents (and runs) proceed concurrently; planning itself runs on the blocking pool, and
//! training on the run's trainer task, so neither stalls the transport.

pub mod status;
mod worker;

use crate::config::{Preset, ServiceConfig};
use crate::fleet::{Fleet, FleetError, Owner};
use crate::persist::{self, PersistError, RunDir};
use crate::run::{EventSink, Run};
use proto::{
    AttachAccepted, AttachOutcome, AttachReply, AttachRequest, Encoding, ErrorCode, ErrorReport,
    Keys, PROTOCOL_VERSION, RunEvent, RunEventKind, RunSpec,
};
use std::collections::HashMap;
use std::future::Future;
use std::sync::{Arc, Mutex, PoisonError};
use tokio::sync::mpsc;
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

/// How long a worker may take to finish its message in hand at shutdown.
const SHUTDOWN_GRACE: std::time::Duration = std::time::Duration::from_secs(10);

struct AgentHandle {
    tx: mpsc::Sender<Incoming>,
    task: JoinHandle<()>,
}

struct RunHandle {
    run: Arc<Run>,
    agents: HashMap<String, AgentHandle>,
    trainer: JoinHandle<()>,
}

/// Publishes encoded messages on keys; shared by the service and its workers.
#[derive(Clone)]
pub(crate) struct Outbox {
    session: zenoh::Session,
    keys: Keys,
}

impl Outbox {
    pub(crate) fn keys(&self) -> &Keys {
        &self.keys
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

    /// Reports an error to the agent that caused it, and logs it.
    pub(crate) async fn report(
        &self,
        run: &str,
        agent: &str,
        report: ErrorReport,
        encoding: Encoding,
    ) {
        tracing::warn!(%run, %agent, code = ?report.code, episode = ?report.episode, step = ?report.step, "rejected: {}", report.message);
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
}

impl From<ErrorReport> for Refusal {
    fn from(report: ErrorReport) -> Self {
        Refusal::Report(report)
    }
}

/// The planner daemon.
pub struct Service {
    config: ServiceConfig,
    outbox: Outbox,
    fleet: Arc<Fleet>,
    runs: Mutex<HashMap<String, RunHandle>>,
    runtime: tokio::runtime::Handle,
    started: std::time::Instant,
}

impl Service {
    /// Serves until `shutdown` completes, then stops every worker and closes the session.
    pub async fn serve(
        config: ServiceConfig,
        shutdown: impl Future<Output = ()>,
    ) -> Result<(), ServiceError> {
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
        let session = zenoh::open(zconfig).await.map_err(zenoh_err)?;
        let keys = Keys::new(&config.prefix);
        let planner_id = config.planner_id.clone();
        let (fleet, mut fleet_changes) = Fleet::join(
            session.clone(),
            keys.clone(),
            planner_id.clone(),
            config.fleet.clone(),
        )
        .await?;
        let service = Arc::new(Service {
            outbox: Outbox {
                session: session.clone(),
                keys: keys.clone(),
            },
            fleet,
            config,
            runs: Mutex::new(HashMap::new()),
            runtime: tokio::runtime::Handle::current(),
            started: std::time::Instant::now(),
        });
        // Resume the stored runs that are ours (all of them for a planner without peers).
        service.rebalance().await;
        let _alive = session
            .liveliness()
            .declare_token(keys.planner_alive(&planner_id))
            .await
            .map_err(zenoh_err)?;
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
        tracing::info!(planner = %planner_id, prefix = %keys.prefix(), "planner serving");

        tokio::pin!(shutdown);
        loop {
            // Biased: observations are drained before liveliness changes. Zenoh delivers an
            // agent's last observation before its token's deletion, but they arrive on two
            // channels; an unbiased select could drop the agent first and refuse its last step.
            tokio::select! {
                biased;
                query = attach.recv_async() => match query {
                    Ok(query) => service.attach(query).await,
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
                Some(()) = fleet_changes.recv() => {
                    // One rebalance covers every change queued so far.
                    while fleet_changes.try_recv().is_ok() {}
                    service.rebalance().await;
                }
                () = &mut shutdown => break,
            }
        }
        tracing::info!("shutting down");
        service.stop().await;
        session.close().await.map_err(zenoh_err)?;
        Ok(())
    }

    /// Stops every worker (each finishes the message in hand, within a grace period) and every
    /// trainer. The replay logs are synced at every episode end and every transition is
    /// handed to the OS before it is acknowledged, so nothing acknowledged is lost either way.
    async fn stop(&self) {
        let runs: Vec<RunHandle> = self
            .runs
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .drain()
            .map(|(_, h)| h)
            .collect();
        for handle in runs {
            handle.trainer.abort();
            for (agent, worker) in handle.agents {
                drop(worker.tx);
                let abort = worker.task.abort_handle();
                if tokio::time::timeout(SHUTDOWN_GRACE, worker.task)
                    .await
                    .is_err()
                {
                    tracing::warn!(run = %handle.run.name(), %agent, "worker did not finish in time; abandoned");
                    abort.abort();
                }
            }
        }
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
                let key = outbox.keys().events(&event.run);
                outbox.publish(&key, &event, Encoding::Postcard).await;
            });
        })
    }

    async fn attach(&self, query: zenoh::query::Query) {
        let key = query.key_expr().as_str().to_string();
        // Another planner owns this run: stay silent (dropping the query ends this planner's
        // part in it), so the agent's query gets the owner's answer and no other.
        if let Some(run) = self.outbox.keys().parse_attach(&key)
            && !self.fleet.is_mine(run)
        {
            tracing::debug!(%key, owner = ?self.fleet.owner(run), "attach for a run owned elsewhere");
            return;
        }
        let encoding = query
            .encoding()
            .map(|e| Encoding::from_mime(&e.to_string()))
            .unwrap_or_default();
        let outcome = match self.outbox.keys().parse_attach(&key) {
            None => AttachOutcome::Rejected(ErrorReport::new(
                ErrorCode::Refused,
                format!("`{key}` is not an attach key"),
            )),
            Some(run) => {
                let bytes = query
                    .payload()
                    .map(|p| p.to_bytes().into_owned())
                    .unwrap_or_default();
                match proto::decode::<AttachRequest>(&bytes, encoding) {
                    Err(e) => AttachOutcome::Rejected(codec_report(&e)),
                    Ok(request) => match self.attach_agent(run, request) {
                        Ok(accepted) => AttachOutcome::Accepted(accepted),
                        Err(Refusal::Report(report)) => AttachOutcome::Rejected(report),
                        // Another planner is taking the run over at this moment: its answer
                        // is the one the agent must get.
                        Err(Refusal::Contended) => return,
                    },
                }
            }
        };
        if let AttachOutcome::Rejected(report) = &outcome {
            tracing::warn!(%key, code = ?report.code, "attach refused: {}", report.message);
        }
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

    /// Creates or joins the run and starts the agent's worker.
    fn attach_agent(
        &self,
        run_name: &str,
        request: AttachRequest,
    ) -> Result<AttachAccepted, Refusal> {
        let refuse = |msg: String| Refusal::Report(ErrorReport::new(ErrorCode::Refused, msg));
        proto::validate_name(run_name).map_err(|e| refuse(e.to_string()))?;
        proto::validate_name(&request.agent).map_err(|e| refuse(e.to_string()))?;
        let mut runs = self.runs.lock().unwrap_or_else(PoisonError::into_inner);
        if !runs.contains_key(run_name) {
            if runs.len() >= self.config.max_runs {
                return Err(refuse(format!(
                    "this planner already hosts its limit of {} runs",
                    self.config.max_runs
                )));
            }
            let run = self.open_run(run_name, request.spec.clone())?;
            self.host(&mut runs, run);
        }
        let handle = runs.get_mut(run_name).expect("inserted above");
        let run = handle.run.clone();
        if run.spec().task != request.spec.task {
            return Err(refuse(format!(
                "run `{run_name}` learns {}, not {}: use another run name",
                run.spec().task,
                request.spec.task
            )));
        }
        if let Some(old) = handle.agents.remove(&request.agent) {
            // The same agent attaching again (it restarted): its old worker ends, and any
            // episode it left open is recorded as interrupted by the new worker's first step.
            old.task.abort();
        } else if handle.agents.len() >= self.config.max_agents_per_run {
            return Err(refuse(format!(
                "run `{run_name}` already has its limit of {} agents",
                self.config.max_agents_per_run
            )));
        }
        let worker = AgentWorker::new(
            run.clone(),
            request.agent.clone(),
            self.outbox.clone(),
            self.fleet.clone(),
        )?;
        let (tx, rx) = mpsc::channel(AGENT_QUEUE);
        let task = self.runtime.spawn(worker.run(rx));
        handle
            .agents
            .insert(request.agent.clone(), AgentHandle { tx, task });
        let models = run.models();
        tracing::info!(run = %run_name, agent = %request.agent, task = %run.spec().task, method = %run.preset().method, "agent attached");
        Ok(AttachAccepted {
            planner_id: self.config.planner_id.clone(),
            task: run.spec().task,
            mode: run.mode(),
            episodes_done: run.episodes_stored(),
            models_version: models.version,
            next_episode: run.next_episode(&request.agent),
            epoch: run.epoch(),
        })
    }

    /// The preset a run spec asks for, with the daemon's and the spec's overrides applied.
    fn preset_for(&self, spec: &RunSpec) -> Result<Preset, ErrorReport> {
        let refuse = |msg: String| ErrorReport::new(ErrorCode::Refused, msg);
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
        let mut preset = Preset::new(spec.task, method).map_err(|e| refuse(e.to_string()))?;
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
        Ok(preset)
    }

    /// Takes run `name` over (a new ownership epoch) and opens it in the data directory (new,
    /// or stored by this or another planner).
    fn open_run(&self, name: &str, spec: RunSpec) -> Result<Arc<Run>, Refusal> {
        let preset = self.preset_for(&spec)?;
        let dir = RunDir::new(&self.config.data_dir, name);
        let internal = |what: String| ErrorReport::new(ErrorCode::Internal, what);
        let epoch = self.fleet.take(name, &dir).map_err(|e| match e {
            FleetError::Persist(PersistError::EpochTaken { .. }) => Refusal::Contended,
            e => internal(format!("cannot take run `{name}` over: {e}")).into(),
        })?;
        let ownership = (epoch, self.config.planner_id.as_str());
        Run::open(
            name.to_string(),
            spec,
            preset,
            dir,
            self.event_sink(),
            ownership,
        )
        .map_err(|e| {
            self.fleet
                .step_down(name, format!("the run could not be opened: {e}"));
            internal(format!("cannot open run `{name}`: {e}")).into()
        })
    }

    fn host(&self, runs: &mut HashMap<String, RunHandle>, run: Arc<Run>) {
        let trainer = self.runtime.spawn(run.clone().trainer_loop());
        runs.insert(
            run.name().to_string(),
            RunHandle {
                run,
                agents: HashMap::new(),
                trainer,
            },
        );
    }

    /// Brings the runs this planner hosts in line with the fleet's view: steps down from the
    /// runs another planner now owns (a newer lease, a newer epoch on disk, or reported fenced
    /// by a worker), then takes over every stored run that is free and placed here. At start
    /// this resumes a restarted daemon's runs (all stored runs, for a planner without peers):
    /// status lists them at once, their trainers catch up with episodes stored after the last
    /// checkpoint, and agents re-attach to them. Stored runs are taken even beyond `max_runs`
    /// (the limit is on creating runs, never on keeping data). A run that cannot be opened is
    /// logged and left on disk untouched.
    async fn rebalance(&self) {
        let mut lost: Vec<(String, String)> = self
            .fleet
            .take_fenced()
            .into_iter()
            .map(|run| {
                (
                    run,
                    "its epoch on disk is newer than this planner's".to_string(),
                )
            })
            .collect();
        {
            let runs = self.runs.lock().unwrap_or_else(PoisonError::into_inner);
            for (name, handle) in runs.iter() {
                if let Owner::Holder { planner, epoch } = self.fleet.owner(name)
                    && planner != self.config.planner_id
                {
                    lost.push((name.clone(), format!("{planner} holds it at epoch {epoch}")));
                } else if let Err(e) = handle.run.check_owner() {
                    lost.push((name.clone(), e.to_string()));
                }
            }
        }
        for (name, reason) in lost {
            self.step_down(&name, reason).await;
        }
        let stored = match persist::stored_runs(&self.config.data_dir) {
            Ok(stored) => stored,
            Err(e) => {
                tracing::error!(error = %e, "cannot list stored runs; none taken over");
                return;
            }
        };
        let mut runs = self.runs.lock().unwrap_or_else(PoisonError::into_inner);
        for (name, dir) in stored {
            if runs.contains_key(&name) || !self.fleet.is_mine(&name) {
                continue;
            }
            let spec = match dir.read_spec() {
                Ok(Some(spec)) => spec,
                Ok(None) => {
                    tracing::warn!(run = %name, "stored run has no run.json; it resumes when an agent attaches");
                    continue;
                }
                Err(e) => {
                    tracing::error!(run = %name, error = %e, "cannot read a stored run's spec; not resumed");
                    continue;
                }
            };
            match self.open_run(&name, spec) {
                Ok(run) => self.host(&mut runs, run),
                Err(Refusal::Report(report)) => {
                    tracing::error!(run = %name, "stored run not resumed: {}", report.message);
                }
                Err(Refusal::Contended) => {
                    tracing::info!(run = %name, "another planner took the run over first");
                }
            }
        }
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
            );
            // JSON: every agent decodes by the sample's declared encoding, and JSON is the one
            // all of them (Python included) speak.
            self.outbox
                .report(name, &agent, report, Encoding::Json)
                .await;
        }
    }

    /// The status report of this planner.
    pub fn status_report(&self) -> status::PlannerStatus {
        let runs = self.runs.lock().unwrap_or_else(PoisonError::into_inner);
        let mut reports: Vec<status::RunStatus> = runs
            .values()
            .map(|h| {
                let run = &h.run;
                let returns = run.returns();
                let mut agents: Vec<String> = h.agents.keys().cloned().collect();
                agents.sort();
                status::RunStatus {
                    name: run.name().to_string(),
                    task: run.spec().task.to_string(),
                    method: run.preset().method.clone(),
                    mode: run.mode(),
                    // Counted from the same snapshot as the returns, so the two always agree.
                    episodes: returns.len() as u32,
                    transitions: run.transitions_stored(),
                    models_version: run.models().version,
                    epoch: run.epoch(),
                    training: run.is_training(),
                    exploring: run.exploring(),
                    last_returns: returns[returns.len().saturating_sub(10)..].to_vec(),
                    agents,
                    planning_latency: run.latency(),
                }
            })
            .collect();
        reports.sort_by(|a, b| a.name.cmp(&b.name));
        status::PlannerStatus {
            planner_id: self.config.planner_id.clone(),
            protocol_version: PROTOCOL_VERSION,
            uptime_seconds: self.started.elapsed().as_secs_f64(),
            runs: reports,
            fleet: self.fleet.status(),
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
        if token.kind() != zenoh::sample::SampleKind::Delete {
            return;
        }
        let key = token.key_expr().as_str();
        let Some((run, agent)) = self.outbox.keys().parse_agent_alive(key) else {
            return;
        };
        let session = {
            let runs = self.runs.lock().unwrap_or_else(PoisonError::into_inner);
            runs.get(run)
                .and_then(|handle| handle.agents.get(agent))
                .map(|a| a.tx.clone())
        };
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

    /// Hands an observation to its agent's worker, or reports why it cannot be handled.
    async fn route(&self, sample: zenoh::sample::Sample) {
        let key = sample.key_expr().as_str().to_string();
        let encoding = Encoding::from_mime(&sample.encoding().to_string());
        let Some((run, agent)) = self
            .outbox
            .keys()
            .parse_agent_key(&key, proto::AgentChannel::Obs)
        else {
            tracing::warn!(%key, "ignoring sample on a key that is not an observation key");
            return;
        };
        if !self.fleet.is_mine(run) {
            return; // its owner answers
        }
        let tx = {
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
                    Some(a) => Ok(a.tx.clone()),
                },
            }
        };
        let result = match tx {
            Err(report) => Err(report),
            Ok(tx) => {
                let incoming = Incoming {
                    bytes: sample.payload().to_bytes().into_owned(),
                    encoding,
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
            }
        };
        if let Err(report) = result {
            self.outbox.report(run, agent, report, encoding).await;
        }
    }
}

/// The error report for bytes that did not decode.
pub(crate) fn codec_report(e: &proto::CodecError) -> ErrorReport {
    let code = match e {
        proto::CodecError::Version { .. } => ErrorCode::ProtocolVersion,
        _ => ErrorCode::Malformed,
    };
    ErrorReport::new(code, e.to_string())
}
