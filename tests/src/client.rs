//! A scripted agent for end-to-end tests: it speaks the wire protocol directly (attach,
//! observations, actions, errors, events, status), so a test controls every step and byte and
//! can check exactly what the daemon answered.

use anyhow::{Context, Result, anyhow, bail};
use planner_service::service::status::PlannerStatus;
use proto::{
    Action, AttachAccepted, AttachOutcome, AttachReply, AttachRequest, Encoding, ErrorReport, Keys,
    Observation, PROTOCOL_VERSION, RunEvent, RunSpec,
};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;
use zenoh::handlers::{FifoChannelHandler, RingChannel, RingChannelHandler};
use zenoh::pubsub::Subscriber;
use zenoh::query::{ConsolidationMode, QueryTarget};
use zenoh::sample::Sample;

type Inbox = Subscriber<FifoChannelHandler<Sample>>;

/// The run's events: a ring that keeps the newest [`EVENTS_KEPT`]. A test that never reads
/// them must not stall the agent: Zenoh's default FIFO blocks the session's receiving once
/// 256 samples wait unread, and then this agent's actions, error reports and attach replies
/// would stop as well (a few hundred episodes emit that many events).
type EventInbox = Subscriber<RingChannelHandler<Sample>>;

/// Run events kept unread by [`Client::events`]; older ones are dropped.
pub const EVENTS_KEPT: usize = 4096;

/// How long a test waits for one answer before it calls the daemon unresponsive.
pub const ANSWER_TIMEOUT: Duration = Duration::from_secs(60);

/// What the daemon said in answer to an observation.
#[derive(Debug)]
pub enum Answer {
    Action(Action),
    Error(ErrorReport),
}

/// One agent of one run, with its own Zenoh session and liveliness token.
pub struct Client {
    pub session: zenoh::Session,
    pub keys: Keys,
    pub run: String,
    pub agent: String,
    pub actions: Inbox,
    pub errors: Inbox,
    pub events: EventInbox,
    /// The run's ownership epoch at the last attach; actions of older epochs are ignored.
    epoch: AtomicU64,
    /// The session token of the last accepted attach (0: none yet); [`Client::send`] stamps it
    /// on every observation.
    session_token: AtomicU64,
    /// The token the first attach presents (drawn at connect), so that asking again for a lost
    /// answer is accepted as this agent.
    first_claim: u64,
    _token: zenoh::liveliness::LivelinessToken,
}

impl Client {
    /// Connects to `endpoint` (multicast scouting off) as `agent` of `run`.
    pub async fn connect(endpoint: &str, run: &str, agent: &str) -> Result<Client> {
        let session = open_session(endpoint).await?;
        let keys = Keys::default();
        let subscribe = |key: String| {
            let session = session.clone();
            async move {
                session
                    .declare_subscriber(key)
                    .await
                    .map_err(|e| anyhow!("subscribe: {e}"))
            }
        };
        let actions = subscribe(keys.act(run, agent)).await?;
        let errors = subscribe(keys.error(run, agent)).await?;
        let events = session
            .declare_subscriber(keys.events(run, Encoding::Postcard))
            .with(RingChannel::new(EVENTS_KEPT))
            .await
            .map_err(|e| anyhow!("subscribe: {e}"))?;
        let token = session
            .liveliness()
            .declare_token(keys.agent_alive(run, agent))
            .await
            .map_err(|e| anyhow!("liveliness token: {e}"))?;
        Ok(Client {
            session,
            keys,
            run: run.into(),
            agent: agent.into(),
            actions,
            errors,
            events,
            epoch: AtomicU64::new(0),
            session_token: AtomicU64::new(0),
            first_claim: proto::draw_token()?,
            _token: token,
        })
    }

    /// Attaches with `spec`, retrying while no planner answers (it may be starting).
    pub async fn attach(&self, spec: &RunSpec) -> Result<AttachAccepted> {
        let payload = proto::encode(&self.attach_request(spec), Encoding::Postcard)?;
        match self
            .attach_raw(&self.run.clone(), payload, Encoding::Postcard.mime())
            .await?
            .outcome
        {
            AttachOutcome::Accepted(accepted) => {
                self.epoch.store(accepted.epoch, Ordering::SeqCst);
                self.session_token.store(accepted.session, Ordering::SeqCst);
                // Give the planner's subscriber a moment to match our publications.
                tokio::time::sleep(Duration::from_millis(300)).await;
                Ok(accepted)
            }
            AttachOutcome::Rejected(report) => bail!("attach refused: {report}"),
        }
    }

    /// The request [`Client::attach`] sends: this agent's claim to its name is its session's
    /// token, or before its first accepted attach the token it drew at connect.
    pub fn attach_request(&self, spec: &RunSpec) -> AttachRequest {
        AttachRequest {
            version: PROTOCOL_VERSION,
            agent: self.agent.clone(),
            spec: spec.clone(),
            session: Some(match self.session_token() {
                0 => self.first_claim,
                token => token,
            }),
        }
    }

    /// Sends `payload` (any bytes, in `mime`) as an attach query for `run` and decodes the
    /// reply, retrying while no planner answers (it may be starting, or taking the run over
    /// from a planner that died), as the sim-bridge does.
    pub async fn attach_raw(&self, run: &str, payload: Vec<u8>, mime: &str) -> Result<AttachReply> {
        let mut last_error = None;
        for _ in 0..300 {
            // Every planner gets the query, only the run's owner answers.
            let replies = self
                .session
                .get(self.keys.attach(run))
                .payload(payload.clone())
                .target(QueryTarget::All)
                .consolidation(ConsolidationMode::None)
                .encoding(zenoh::bytes::Encoding::from(mime))
                .timeout(Duration::from_secs(5))
                .await
                .map_err(|e| anyhow!("attach query: {e}"))?;
            // An error reply is zenoh's, not a planner's (planners refuse inside an
            // `AttachReply`): the query timed out while a taking-over planner was still
            // loading the run, say. The next query gets the answer.
            match first_sample(&replies).await {
                Ok(sample) => return decode(&sample),
                Err(error) => last_error = error.or(last_error),
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        match last_error {
            Some(error) => {
                bail!("attach to `{run}` got no answer; the last query ended in: {error}")
            }
            None => bail!("attach to `{run}` got no reply"),
        }
    }

    /// Publishes raw bytes on this agent's observation key (or another run's) with a MIME type.
    pub async fn send_raw(&self, run: &str, bytes: Vec<u8>, mime: &str) -> Result<()> {
        self.session
            .put(self.keys.obs(run, &self.agent), bytes)
            .encoding(zenoh::bytes::Encoding::from(mime))
            .await
            .map_err(|e| anyhow!("put: {e}"))
    }

    /// Publishes an observation (postcard) in this client's session (its token stamped on).
    pub async fn send(&self, obs: &Observation) -> Result<()> {
        let obs = obs.clone().in_session(self.session_token());
        let bytes = proto::encode(&obs, Encoding::Postcard)?;
        self.send_raw(&self.run.clone(), bytes, Encoding::Postcard.mime())
            .await
    }

    /// The session token of the last accepted attach (0 before any).
    pub fn session_token(&self) -> u64 {
        self.session_token.load(Ordering::SeqCst)
    }

    /// The ownership epoch of the run at the last attach.
    pub fn epoch(&self) -> u64 {
        self.epoch.load(Ordering::SeqCst)
    }

    /// The next action or error for this agent (actions of an epoch older than the one
    /// attached to come from a planner that lost the run, and error reports about another
    /// session using this agent's name, are skipped).
    pub async fn answer(&self, timeout: Duration) -> Result<Answer> {
        let deadline = tokio::time::Instant::now() + timeout;
        loop {
            tokio::select! {
                sample = self.actions.recv_async() => {
                    let sample = sample.map_err(|e| anyhow!("actions: {e}"))?;
                    let action: Action = decode(&sample)?;
                    if action.epoch >= self.epoch() {
                        return Ok(Answer::Action(action));
                    }
                }
                sample = self.errors.recv_async() => {
                    let sample = sample.map_err(|e| anyhow!("errors: {e}"))?;
                    let report: ErrorReport = decode(&sample)?;
                    if report.concerns(self.session_token()) {
                        return Ok(Answer::Error(report));
                    }
                }
                () = tokio::time::sleep_until(deadline) => bail!("no answer for `{}` within {timeout:?}", self.agent),
            }
        }
    }

    /// Sends `obs` and returns the action for it; an error report is an error.
    pub async fn step(&self, obs: &Observation) -> Result<Action> {
        self.send(obs).await?;
        match self.answer(ANSWER_TIMEOUT).await? {
            Answer::Action(action) if (action.episode, action.step) == (obs.episode, obs.step) => {
                Ok(action)
            }
            Answer::Action(action) => bail!(
                "action for episode {} step {} answered observation {}/{}",
                action.episode,
                action.step,
                obs.episode,
                obs.step
            ),
            Answer::Error(report) => bail!("step {}/{} refused: {report}", obs.episode, obs.step),
        }
    }

    /// The next error report about this client's session (for tests that provoke one).
    pub async fn next_error(&self) -> Result<ErrorReport> {
        loop {
            let sample = tokio::time::timeout(ANSWER_TIMEOUT, self.errors.recv_async())
                .await
                .context("no error report")?
                .map_err(|e| anyhow!("errors: {e}"))?;
            let report: ErrorReport = decode(&sample)?;
            if report.concerns(self.session_token()) {
                return Ok(report);
            }
        }
    }

    /// The next error report on this agent name's error key, whichever session it concerns
    /// (for tests that play someone else using the name).
    pub async fn next_error_any(&self) -> Result<ErrorReport> {
        let sample = tokio::time::timeout(ANSWER_TIMEOUT, self.errors.recv_async())
            .await
            .context("no error report")?
            .map_err(|e| anyhow!("errors: {e}"))?;
        decode(&sample)
    }

    /// Drops actions and error reports already received but not read (answers to messages
    /// sent before a restart, say) and returns them.
    pub fn take_pending(&self) -> Result<Vec<Answer>> {
        let mut pending = Vec::new();
        while let Ok(Some(sample)) = self.actions.try_recv() {
            pending.push(Answer::Action(decode(&sample)?));
        }
        while let Ok(Some(sample)) = self.errors.try_recv() {
            pending.push(Answer::Error(decode(&sample)?));
        }
        Ok(pending)
    }

    /// Run events received so far (without waiting).
    pub fn drain_events(&self) -> Result<Vec<RunEvent>> {
        let mut events = Vec::new();
        while let Ok(Some(sample)) = self.events.try_recv() {
            events.push(decode(&sample)?);
        }
        Ok(events)
    }

    /// Closes the session: the liveliness token goes with it, as when a process dies.
    pub async fn close(self) -> Result<()> {
        self.session
            .close()
            .await
            .map_err(|e| anyhow!("close: {e}"))
    }
}

/// A Zenoh session connected to `endpoint` only (no listening, multicast scouting off, as
/// every test process: parallel tests must not find each other's daemons).
pub async fn open_session(endpoint: &str) -> Result<zenoh::Session> {
    let endpoints = proto::session::Endpoints {
        listen: vec![],
        connect: vec![endpoint.to_string()],
    };
    zenoh::open(proto::session::zenoh_config(&endpoints, None)?)
        .await
        .map_err(|e| anyhow!("zenoh open: {e}"))
}

/// A multi-threaded Tokio runtime for a test's scripted agents (which run concurrently).
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("a tokio runtime")
}

/// Decodes a sample in the encoding it declares.
fn decode<T: serde::de::DeserializeOwned>(sample: &Sample) -> Result<T> {
    let encoding = Encoding::from_mime(&sample.encoding().to_string());
    Ok(proto::decode(&sample.payload().to_bytes(), encoding)?)
}

/// The first sample a query's replies bring, or what the last of its error replies (zenoh's:
/// a timeout, say) said, if any came.
async fn first_sample(
    replies: &zenoh::handlers::FifoChannelHandler<zenoh::query::Reply>,
) -> std::result::Result<zenoh::sample::Sample, Option<String>> {
    let mut last_error = None;
    while let Ok(reply) = replies.recv_async().await {
        match reply.into_result() {
            Ok(sample) => return Ok(sample),
            Err(e) => {
                last_error = Some(String::from_utf8_lossy(&e.payload().to_bytes()).into_owned())
            }
        }
    }
    Err(last_error)
}

/// Queries a planner's status over `session`, asking again for up to 10 s while no answer
/// comes (a peer session that just connected to a router does not know the planners'
/// queryables yet, and its query then ends at once with no answer).
pub async fn status(session: &zenoh::Session, planner_id: &str) -> Result<PlannerStatus> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        let replies = session
            .get(Keys::default().planner_status(planner_id))
            .timeout(Duration::from_secs(10))
            .await
            .map_err(|e| anyhow!("status query: {e}"))?;
        // An error reply is zenoh's (the query timed out on a busy machine): ask again.
        let last_error = match first_sample(&replies).await {
            Ok(sample) => return Ok(serde_json::from_slice(&sample.payload().to_bytes())?),
            Err(error) => error,
        };
        if tokio::time::Instant::now() >= deadline {
            bail!(
                "planner `{planner_id}` did not answer the status query{}",
                last_error.map_or_else(String::new, |e| format!(" (the last query ended in: {e})"))
            );
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

/// A toy cart-pole-shaped system for scripted agents: deterministic, bounded, and cheap, so a
/// test can play many steps without a simulator. (The daemon learns whatever it is fed.)
#[derive(Clone, Debug)]
pub struct ToySystem {
    pub state: [f32; 4],
}

impl ToySystem {
    pub fn new(seed: u32) -> Self {
        let s = seed as f32 * 0.01;
        Self {
            state: [s, -s, 0.0, 0.0],
        }
    }

    /// Applies `action` (first component) and returns the reward of the transition.
    pub fn step(&mut self, action: &[f32]) -> f32 {
        let a = action.first().copied().unwrap_or(0.0).clamp(-3.0, 3.0);
        let [x, theta, v, w] = self.state;
        let v = 0.95 * v + 0.04 * a;
        let w = 0.95 * w + 0.04 * (theta.sin() + 0.5 * a);
        self.state = [x + 0.04 * v, theta + 0.04 * w, v, w];
        -(x * x) - 0.01 * a * a
    }
}
