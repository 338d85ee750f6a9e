//! The agent's Zenoh side: one session, the keys of one agent of one run, typed messages in and
//! out.
//!
//! Everything that touches Zenoh or the codec is here, so the episode loop in [`crate::bridge`]
//! deals only in proto's messages. Subscriptions are declared before the agent attaches: the
//! planner receives our declarations before our attach query (they travel in order on the same
//! link), so it can never answer an observation before we listen for the answer.

use crate::bridge::BridgeError;
use proto::session::Endpoints;
use proto::{
    Action, AttachAccepted, AttachOutcome, AttachReply, AttachRequest, Encoding, ErrorReport, Keys,
    Observation, PROTOCOL_VERSION, RunEvent, RunSpec,
};
use std::path::Path;
use std::time::Duration;
use tokio::time::Instant;
use zenoh::bytes::Encoding as ZEncoding;
use zenoh::handlers::FifoChannelHandler;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::{Publisher, Subscriber};
use zenoh::qos::CongestionControl;
use zenoh::query::{ConsolidationMode, QueryTarget};
use zenoh::sample::{Sample, SampleKind};

/// The encoding this agent speaks (the planner answers in the encoding it receives).
const ENCODING: Encoding = Encoding::Postcard;

/// The longest one attach query waits for a reply before it is sent again.
const ATTACH_QUERY_TIMEOUT: Duration = Duration::from_secs(5);

/// Pause between attach attempts while no planner answers.
const ATTACH_RETRY_PAUSE: Duration = Duration::from_millis(500);

/// Something the planner side sent this agent.
#[derive(Debug)]
pub(crate) enum Inbound {
    /// An answer on the agent's act key.
    Action(Action),
    /// A report on the agent's error key.
    Error(ErrorReport),
    /// Something that happened to the run (training, models, other agents' episodes).
    Event(RunEvent),
    /// The attached planner's liveliness token went away (it stopped, died, or the link broke):
    /// attach again, to whichever planner owns the run then.
    PlannerGone,
}

/// One agent's connection to its run.
pub(crate) struct PlannerLink {
    session: zenoh::Session,
    keys: Keys,
    run: String,
    agent: String,
    observations: Publisher<'static>,
    actions: Subscriber<FifoChannelHandler<Sample>>,
    errors: Subscriber<FifoChannelHandler<Sample>>,
    events: Subscriber<FifoChannelHandler<Sample>>,
    /// Set once attached: the planner's liveliness, so its departure is noticed.
    planner_alive: Option<Subscriber<FifoChannelHandler<Sample>>>,
    /// Whether the planner's token went away since the last attach.
    planner_gone: bool,
    /// The session token of the last accepted attach (0: none yet): stamped on every
    /// observation, and sent when attaching again so the planner knows it is us reconnecting.
    session_token: u64,
    /// The token the first attach presents (drawn at open): asking again after an answer that
    /// never arrived, this agent proves it is the one the planner attached.
    first_claim: u64,
    _token: LivelinessToken,
}

fn zenoh_err(what: impl Into<String>) -> impl FnOnce(zenoh::Error) -> BridgeError {
    let what = what.into();
    move |e| BridgeError::Zenoh {
        what,
        reason: e.to_string(),
    }
}

impl PlannerLink {
    /// Opens the session (explicit endpoints, no multicast scouting), declares the agent's
    /// liveliness token and its subscriptions.
    pub async fn open(
        keys: Keys,
        run: &str,
        agent: &str,
        endpoints: &Endpoints,
        zenoh_config: Option<&Path>,
    ) -> Result<Self, BridgeError> {
        let base = match zenoh_config {
            Some(path) => Some(
                zenoh::Config::from_file(path).map_err(|e| BridgeError::Zenoh {
                    what: format!("reading the zenoh configuration {}", path.display()),
                    reason: e.to_string(),
                })?,
            ),
            None => None,
        };
        let config = proto::session::zenoh_config(endpoints, base)?;
        let session = zenoh::open(config)
            .await
            .map_err(zenoh_err("opening the zenoh session"))?;
        let token = session
            .liveliness()
            .declare_token(keys.agent_alive(run, agent))
            .await
            .map_err(zenoh_err("declaring the agent's liveliness token"))?;
        let subscribe = |key: String| {
            let session = session.clone();
            async move {
                session
                    .declare_subscriber(key.clone())
                    .await
                    .map_err(zenoh_err(format!("subscribing to {key}")))
            }
        };
        let actions = subscribe(keys.act(run, agent)).await?;
        let errors = subscribe(keys.error(run, agent)).await?;
        let events = subscribe(keys.events(run, ENCODING)).await?;
        let observations = session
            .declare_publisher(keys.obs(run, agent))
            .encoding(ZEncoding::from(ENCODING.mime()))
            // A control loop must not lose a message to a full queue: block instead.
            .congestion_control(CongestionControl::Block)
            .express(true)
            .await
            .map_err(zenoh_err("declaring the observation publisher"))?;
        Ok(Self {
            session,
            keys,
            run: run.to_string(),
            agent: agent.to_string(),
            observations,
            actions,
            errors,
            events,
            planner_alive: None,
            planner_gone: false,
            session_token: 0,
            first_claim: proto::draw_token()?,
            _token: token,
        })
    }

    /// Sends the attach query until a planner answers or `patience` runs out, then waits until
    /// the planner's observation subscriber is visible, so the first observation is not lost.
    ///
    /// # Errors
    /// The planner's rejection as it stated it, no answer within `patience`, or a reply that
    /// does not decode.
    pub async fn attach(
        &mut self,
        spec: &RunSpec,
        patience: Duration,
    ) -> Result<AttachAccepted, BridgeError> {
        let key = self.keys.attach(&self.run);
        let request = AttachRequest {
            version: PROTOCOL_VERSION,
            agent: self.agent.clone(),
            spec: spec.clone(),
            session: Some(match self.session_token {
                0 => self.first_claim,
                token => token,
            }),
        };
        let payload = proto::encode(&request, ENCODING).map_err(BridgeError::Encode)?;
        let started = Instant::now();
        let deadline = started + patience;
        let mut attempts = 0u32;
        let accepted = loop {
            attempts += 1;
            let wait = deadline
                .saturating_duration_since(Instant::now())
                .clamp(ATTACH_RETRY_PAUSE, ATTACH_QUERY_TIMEOUT);
            if let Some(reply) = self.attach_once(&key, &payload, wait).await? {
                match reply.outcome {
                    AttachOutcome::Accepted(accepted) => break accepted,
                    AttachOutcome::Rejected(report) => {
                        return Err(BridgeError::AttachRejected { key, report });
                    }
                }
            }
            if Instant::now() + ATTACH_RETRY_PAUSE >= deadline {
                return Err(BridgeError::NoPlanner {
                    key,
                    waited: started.elapsed(),
                    attempts,
                });
            }
            if attempts == 1 {
                tracing::info!(%key, "no planner answered yet; retrying until one does");
            }
            tokio::time::sleep(ATTACH_RETRY_PAUSE).await;
        };

        let alive_key = self.keys.planner_alive(&accepted.planner_id);
        let alive = self
            .session
            .liveliness()
            .declare_subscriber(alive_key.clone())
            .await
            .map_err(zenoh_err(format!("watching {alive_key}")))?;
        self.planner_alive = Some(alive);
        self.planner_gone = false;
        self.session_token = accepted.session;

        while !self.planner_listens().await? {
            if Instant::now() >= deadline {
                return Err(BridgeError::Zenoh {
                    what: format!(
                        "waiting for the planner to subscribe to {}",
                        self.keys.obs(&self.run, &self.agent)
                    ),
                    reason: format!(
                        "no subscriber after {:.1} s",
                        started.elapsed().as_secs_f64()
                    ),
                });
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        Ok(accepted)
    }

    /// One attach query: the first reply, or `None` if no queryable answered within `wait`.
    async fn attach_once(
        &self,
        key: &str,
        payload: &[u8],
        wait: Duration,
    ) -> Result<Option<AttachReply>, BridgeError> {
        // All planners get the query; only the run's owner answers (the others stay silent),
        // and without consolidation its answer is delivered as soon as it comes.
        let replies = self
            .session
            .get(key)
            .payload(payload.to_vec())
            .encoding(ZEncoding::from(ENCODING.mime()))
            .target(QueryTarget::All)
            .consolidation(ConsolidationMode::None)
            .timeout(wait)
            .await
            .map_err(zenoh_err(format!("querying {key}")))?;
        // The get ends (the channel closes) when every matching queryable has answered or the
        // query timed out; no reply at all means no planner serves this key (yet).
        while let Ok(reply) = replies.recv_async().await {
            match reply.into_result() {
                Ok(sample) => {
                    let encoding = Encoding::from_mime(&sample.encoding().to_string());
                    let bytes = sample.payload().to_bytes();
                    return proto::decode::<AttachReply>(&bytes, encoding)
                        .map(Some)
                        .map_err(|source| BridgeError::Decode {
                            key: key.to_string(),
                            source,
                        });
                }
                Err(e) => {
                    let reason = String::from_utf8_lossy(&e.payload().to_bytes()).into_owned();
                    tracing::warn!(%key, %reason, "attach query failed");
                }
            }
        }
        Ok(None)
    }

    /// Whether some subscriber (the planner's) matches this agent's observation key.
    async fn planner_listens(&self) -> Result<bool, BridgeError> {
        let status = self
            .observations
            .matching_status()
            .await
            .map_err(zenoh_err(
                "checking for the planner's observation subscriber",
            ))?;
        Ok(status.matching())
    }

    /// Publishes an observation on the agent's obs key, in this agent's session.
    pub async fn send(&self, obs: &Observation) -> Result<(), BridgeError> {
        let obs = obs.clone().in_session(self.session_token);
        let bytes = proto::encode(&obs, ENCODING).map_err(BridgeError::Encode)?;
        self.observations
            .put(bytes)
            .await
            .map_err(zenoh_err(format!(
                "publishing episode {} step {}",
                obs.episode, obs.step
            )))
    }

    /// The next message for this agent. Messages that do not decode are logged and skipped:
    /// the attach reply already checked that the planner speaks our protocol, so after it one
    /// is a stray or hostile publisher's, and ending the run over it would hand anyone on the
    /// network a way to stop the bridge (a planner that truly sends nothing usable ends the
    /// wait with the action timeout, the skipped message's error logged before it). The only
    /// error is a subscription that closed.
    pub async fn recv(&mut self) -> Result<Inbound, BridgeError> {
        loop {
            let alive = async {
                match &self.planner_alive {
                    Some(sub) => sub.recv_async().await,
                    None => std::future::pending().await,
                }
            };
            tokio::select! {
                sample = self.actions.recv_async() => {
                    let sample = sample.map_err(|e| closed("actions", e))?;
                    match decode(&sample) {
                        Ok(action) => return Ok(Inbound::Action(action)),
                        Err(e) => tracing::warn!(error = %e, "ignoring an undecodable action"),
                    }
                }
                sample = self.errors.recv_async() => {
                    let sample = sample.map_err(|e| closed("errors", e))?;
                    match decode::<ErrorReport>(&sample) {
                        // Another process using our name (its refused observations) is not us.
                        Ok(report) if report.concerns(self.session_token) => {
                            return Ok(Inbound::Error(report));
                        }
                        Ok(report) => tracing::warn!(%report, "ignoring an error report about another session under this agent's name"),
                        Err(e) => tracing::warn!(error = %e, "ignoring an undecodable error report"),
                    }
                }
                sample = self.events.recv_async() => {
                    let sample = sample.map_err(|e| closed("events", e))?;
                    match decode(&sample) {
                        Ok(event) => return Ok(Inbound::Event(event)),
                        Err(e) => tracing::warn!(error = %e, "ignoring an undecodable run event"),
                    }
                }
                sample = alive => {
                    let sample = sample.map_err(|e| closed("planner liveliness", e))?;
                    if sample.kind() == SampleKind::Delete && !self.planner_gone {
                        self.planner_gone = true;
                        return Ok(Inbound::PlannerGone);
                    }
                }
            }
        }
    }

    /// Withdraws the token and subscriptions and closes the session.
    pub async fn close(self) -> Result<(), BridgeError> {
        let session = self.session.clone();
        drop(self);
        session
            .close()
            .await
            .map_err(zenoh_err("closing the zenoh session"))
    }
}

fn closed(what: &str, e: impl std::fmt::Display) -> BridgeError {
    BridgeError::Zenoh {
        what: format!("receiving {what}"),
        reason: e.to_string(),
    }
}

fn decode<T: serde::de::DeserializeOwned>(sample: &Sample) -> Result<T, BridgeError> {
    let encoding = Encoding::from_mime(&sample.encoding().to_string());
    proto::decode(&sample.payload().to_bytes(), encoding).map_err(|source| BridgeError::Decode {
        key: sample.key_expr().as_str().to_string(),
        source,
    })
}
