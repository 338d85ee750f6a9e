//! One agent's worker: takes its observations in order, stores what they complete, and
//! answers each with an action — uniformly random while the run explores, planned otherwise.

mod batch;

pub(crate) use batch::PlanBatcher;

use super::Outbox;
use super::status::PlanRecord;
use crate::agent::AgentSession;
use crate::fleet::Fleet;
use crate::plan::MpcPlanner;
use crate::run::{Refused, Run, StoreError};
use crate::sched::Waiting;
use batch::{Expected, Planned, Request};
use proto::task::Magnitudes;
use proto::{
    Action, ActionSource, Encoding, ErrorCode, ErrorReport, Observation, PROTOCOL_VERSION,
    PlanStats, TrainMode,
};
use rand::rngs::StdRng;
use rand::{RngExt, SeedableRng};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tokio::sync::mpsc;

/// A received observation of the worker's session, decoded, with the encoding the answer
/// goes back in.
pub(crate) struct Incoming {
    pub msg: Observation,
    pub encoding: Encoding,
    /// When the service took it off the transport: the run's deadline counts from here, so
    /// time spent queued behind the agent's earlier messages counts against it too.
    pub received: Instant,
}

/// Time kept back from a plan's deadline for building and publishing its action.
const ANSWER_MARGIN: Duration = Duration::from_millis(1);

pub(crate) struct AgentWorker {
    run: Arc<Run>,
    name: String,
    outbox: Outbox,
    fleet: Arc<Fleet>,
    /// The largest observation and reward magnitudes accepted from this agent.
    magnitudes: Magnitudes,
    session: AgentSession,
    /// Taken while a plan runs on the blocking pool, then put back.
    planner: Option<MpcPlanner>,
    explore_rng: StdRng,
    /// Sync mode: finished episodes the models must cover before this agent's next episode.
    wait_for_episodes: Option<u32>,
    /// How long the worker waits for an observation before it checks that the agent still
    /// holds its liveliness token (and closes the session if not).
    idle: std::time::Duration,
    /// The run's batched plans (this agent's with the other agents' waiting at the same
    /// time), and whether it expects this agent's next observation. Through it the plans
    /// take the cores in deadline order, and retraining yields to them.
    expected: Expected,
    /// This agent's plans waiting for the cores (its queue depth, with its inbox).
    waiting: Waiting,
    /// The session token this worker serves; every report it sends names it.
    token: u64,
}

/// A stable seed per (run seed, agent name), so runs are reproducible.
fn agent_seed(run_seed: u64, agent: &str) -> u64 {
    agent
        .bytes()
        .fold(run_seed ^ 0xcbf2_9ce4_8422_2325, |h, b| {
            (h ^ b as u64).wrapping_mul(0x100_0000_01b3)
        })
}

/// The agent's planner for the run's preset. The preset was checked when the run was created,
/// so this only fails for a preset that was already refused.
fn new_planner(run: &Run, seed: u64) -> Result<MpcPlanner, ErrorReport> {
    let preset = run.preset();
    MpcPlanner::new(
        run.task(),
        preset.cem.clone(),
        preset.energy_weight,
        preset.sample_dynamics,
        seed,
    )
    .map_err(|e| {
        ErrorReport::new(
            ErrorCode::Refused,
            format!("invalid planner configuration: {e}"),
        )
    })
}

fn finite_or_min(x: f32) -> f32 {
    if x.is_finite() { x } else { f32::MIN }
}

impl AgentWorker {
    pub(crate) fn new(
        run: Arc<Run>,
        name: String,
        outbox: Outbox,
        fleet: Arc<Fleet>,
        magnitudes: Magnitudes,
        plans: Arc<PlanBatcher>,
        token: u64,
    ) -> Result<Self, ErrorReport> {
        let seed = agent_seed(run.spec().seed, &name);
        Ok(Self {
            session: AgentSession::new(name.clone(), run.task().episode_len),
            planner: Some(new_planner(&run, seed)?),
            explore_rng: StdRng::seed_from_u64(seed.rotate_left(17)),
            wait_for_episodes: None,
            idle: std::time::Duration::MAX,
            run,
            name,
            outbox,
            fleet,
            magnitudes,
            expected: Expected::new(plans),
            waiting: Waiting::default(),
            token,
        })
    }

    /// Counts this agent's plans waiting for the cores in `waiting`, which the service reads
    /// as part of the agent's queue depth.
    pub(crate) fn counting_waits_in(mut self, waiting: Waiting) -> Self {
        self.waiting = waiting;
        self
    }

    /// Closes the session after `idle` without an observation if the agent then holds no
    /// liveliness token.
    pub(crate) fn idle_after(mut self, idle: std::time::Duration) -> Self {
        self.idle = idle;
        self
    }

    /// The next observation; `None` when the service dropped the channel, or when the agent
    /// was silent for the idle time and holds no liveliness token.
    async fn next(&self, rx: &mut mpsc::Receiver<Incoming>) -> Option<Incoming> {
        loop {
            match tokio::time::timeout(self.idle, rx.recv()).await {
                Ok(incoming) => return incoming,
                Err(_) if self.outbox.agent_alive(self.run.name(), &self.name).await => {}
                Err(_) => {
                    tracing::info!(run = %self.run.name(), agent = %self.name, idle_seconds = self.idle.as_secs(), "agent idle without a liveliness token; its session is closed");
                    return None;
                }
            }
        }
    }

    /// Handles observations until the service drops the channel (or the agent is gone idle),
    /// then records an unfinished episode as interrupted.
    pub(crate) async fn run(mut self, mut rx: mpsc::Receiver<Incoming>) {
        while let Some(incoming) = self.next(&mut rx).await {
            let encoding = incoming.encoding;
            let handled = self.handle(incoming).await;
            // Answered mid-episode, the agent sends its next observation soon: a batch of the
            // run's plans that starts meanwhile lingers for it.
            self.expected.set(matches!(handled, Ok(true)));
            if let Err(report) = handled {
                let report = report.for_session(self.token);
                self.outbox
                    .report(self.run.name(), &self.name, report, encoding)
                    .await;
            }
        }
        if let Some(summary) = self.session.interrupt()
            && let Err(e) = self.run.store_interrupted(summary).await
        {
            if let StoreError::Fenced(_) = e {
                self.fleet.report_fenced(self.run.name());
            }
            tracing::error!(run = %self.run.name(), agent = %self.name, error = %e, "cannot record interrupted episode")
        }
    }

    /// Stores `incoming` and answers it; `Ok(true)` when it was answered with an action.
    async fn handle(&mut self, incoming: Incoming) -> Result<bool, ErrorReport> {
        let msg = incoming.msg;
        let position = |r: ErrorReport| r.at(msg.episode, msg.step);
        proto::validate::validate_observation(&msg, self.run.task(), &self.magnitudes)
            .map_err(|e| e.report(msg.episode, msg.step))?;
        // Stored (and an episode's end synced to disk) before this agent's next message is
        // taken, and before the observation is answered.
        let (accepted, stored) =
            self.run
                .accept(&mut self.session, &msg)
                .await
                .map_err(|refused| match refused {
                    Refused::Step(report) => report,
                    Refused::Fenced(fenced) => {
                        // Another planner owns the run now: step down, and send the agent there.
                        self.fleet.report_fenced(self.run.name());
                        position(ErrorReport::new(
                            ErrorCode::NotAttached,
                            format!("{fenced}: attach again"),
                        ))
                    }
                })?;
        let must_cover = stored.must_cover;
        if let Some(finished) = &accepted.finished {
            tracing::info!(run = %self.run.name(), agent = %self.name, episode = finished.episode, steps = finished.steps, episode_return = finished.episode_return, "episode finished");
            if self.run.mode() == TrainMode::Sync {
                self.wait_for_episodes = must_cover;
            }
        }
        if !accepted.needs_action() {
            return Ok(false);
        }
        if msg.step == 0 {
            if let Some(episodes) = self.wait_for_episodes.take() {
                self.run.wait_for_training(episodes).await;
            }
            if let Some(planner) = self.planner.as_mut() {
                planner.reset();
            }
        }
        let deadline = self
            .run
            .preset()
            .deadline_ms
            .map(|ms| incoming.received + Duration::from_millis(u64::from(ms)));
        let action = self.act(&msg, deadline).await.map_err(position)?;
        // The action acknowledges the step: in a fleet, only while this planner's etcd lease
        // is valid by its own clock and it still holds the run at its token. Checked after
        // planning, right before sending, so a lease that ran out during planning counts.
        if !self
            .fleet
            .may_acknowledge(self.run.name(), self.run.epoch())
        {
            self.fleet.report_fenced(self.run.name());
            return Err(position(ErrorReport::new(
                ErrorCode::NotAttached,
                format!(
                    "this planner may no longer serve run `{}` (its ownership lease ran out or the run moved): attach again",
                    self.run.name()
                ),
            )));
        }
        self.session.acted(msg.step, &action.action);
        let key = self.outbox.keys().act(self.run.name(), &self.name);
        self.outbox.publish(&key, &action, incoming.encoding).await;
        Ok(true)
    }

    /// Plans `msg` with the run's models, in a batch with whichever of the run's other agents
    /// wait at the same time.
    async fn plan(
        &mut self,
        msg: &Observation,
        deadline: Option<Instant>,
    ) -> Result<Planned, ErrorReport> {
        let planner = self.planner.take().ok_or_else(|| {
            ErrorReport::new(
                ErrorCode::Internal,
                "this agent's planner was lost in an earlier failure: attach again",
            )
        })?;
        let (reply, answer) = tokio::sync::oneshot::channel();
        let request = Request {
            planner,
            obs: msg.obs.clone(),
            deadline: deadline.map(|d| d - ANSWER_MARGIN),
            waiting: self.waiting.clone(),
            reply,
        };
        let batcher = self.expected.batcher().clone();
        batcher.submit(request, &mut self.expected);
        answer.await.map_err(|_| {
            // The batch panicked: start this agent over with a fresh planner.
            self.planner =
                new_planner(&self.run, agent_seed(self.run.spec().seed, &self.name)).ok();
            ErrorReport::new(
                ErrorCode::Internal,
                "planning failed (the planner's log says why)",
            )
        })
    }

    /// The action for `msg`: random while exploring, planned with the run's models otherwise,
    /// within `deadline` when the run has one.
    async fn act(
        &mut self,
        msg: &Observation,
        deadline: Option<Instant>,
    ) -> Result<Action, ErrorReport> {
        let started = Instant::now();
        let task = self.run.task();
        let (
            action,
            source,
            models_version,
            predicted_return,
            mean_energy,
            iterations,
            cut,
            stepped_back,
        ) = if self.run.exploring() {
            let action: Vec<f32> = task
                .action_low
                .iter()
                .zip(&task.action_high)
                .map(|(&lo, &hi)| self.explore_rng.random_range(lo..=hi))
                .collect();
            let version = self.run.models().version;
            (action, ActionSource::Random, version, 0.0, 0.0, 0, false, 0)
        } else {
            let Planned {
                planner,
                action,
                predicted_return,
                mean_energy,
                iterations,
                cut,
                stepped_back,
                models_version,
            } = self.plan(msg, deadline).await?;
            self.planner = Some(planner);
            // A model that diverged on every elite scores −inf; JSON cannot carry that, and
            // the statistic is informational, so report the most negative finite number.
            (
                action,
                ActionSource::Planned,
                models_version,
                finite_or_min(predicted_return),
                finite_or_min(mean_energy),
                iterations,
                cut,
                stepped_back,
            )
        };
        let planning_ms = started.elapsed().as_secs_f32() * 1e3;
        let planned = source == ActionSource::Planned;
        let late = deadline.is_some_and(|d| Instant::now() > d);
        let missed = planned && (late || (deadline.is_some() && iterations == 0));
        if planned {
            let record = PlanRecord {
                iterations,
                cut,
                missed,
                stepped_back,
            };
            self.run.record_plan(planning_ms, record);
            self.outbox.metrics().record_plan(
                self.run.name(),
                f64::from(planning_ms) / 1e3,
                record,
            );
        }
        Ok(Action {
            version: PROTOCOL_VERSION,
            episode: msg.episode,
            step: msg.step,
            action,
            stats: PlanStats {
                source,
                planning_ms,
                predicted_return,
                mean_energy,
                iterations,
                models_version,
                cut,
                missed,
            },
            epoch: self.run.epoch(),
        })
    }
}
