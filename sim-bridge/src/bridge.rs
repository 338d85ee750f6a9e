//! The bridge loop: runs episodes of a simulated task with actions from a planner over Zenoh.
//!
//! ```text
//! attach(run spec) ─▶ accepted{next_episode}
//! for each episode:  reset(seed + episode) ─▶ Obs{step 0}
//!                    ◀─ Act{step t}    step env ─▶ Obs{step t+1, reward, end?}   … until the end
//! ```
//! Each wait for an action has a deadline. The first action of every episode but this process's
//! first may wait for the planner to retrain (sync mode), so it gets the longer train timeout.
//! Training events are logged as they arrive, so a long wait shows what the planner is doing.
//! If the planner goes away (its liveliness token goes: it stopped, died, or lost the router) or
//! says it no longer knows this agent, the bridge attaches again, to whichever planner owns the
//! run then (the same one restarted, or another of the fleet that took the run over), and starts
//! the interrupted episode over under a new number; the old one is recorded as interrupted.
//! Actions of an ownership epoch older than the one attached to are ignored, and every
//! observation says which action was applied (the planned one clamped into the bounds).

use crate::deadline::EpisodeDeadline;
use crate::env::Env;
use crate::error::SimError;
use crate::link::{Inbound, PlannerLink};
use proto::session::Endpoints;
use proto::{
    Action, ActionSource, AttachAccepted, CodecError, EpisodeEnd, ErrorCode, ErrorReport, Keys,
    Observation, PlanStats, RunEvent, RunEventKind, RunSpec, Task, TrainMode,
};
use std::path::PathBuf;
use std::time::{Duration, Instant, SystemTime};

/// Everything one bridge process needs to know.
#[derive(Debug, Clone)]
pub struct BridgeConfig {
    /// Key prefix shared with the planner.
    pub prefix: String,
    /// Where to listen and what to connect to.
    pub endpoints: Endpoints,
    /// A zenoh configuration file to start from (endpoints and scouting are still set here).
    pub zenoh_config: Option<PathBuf>,
    /// Run to attach to (created by the planner with `spec` if it does not exist yet).
    pub run: String,
    /// This agent's name within the run.
    pub agent: String,
    /// The run spec sent when attaching; its task is the task simulated here.
    pub spec: RunSpec,
    /// Episodes to run.
    pub episodes: u32,
    /// Stop after the episode in which the steps run so far reach this many (whole episodes
    /// only; `None`: no step budget, `episodes` alone decides). An experiment budgeted in
    /// timesteps (the paper's "4,000 timesteps" on ant) asks for the steps it still lacks.
    pub timesteps: Option<u64>,
    /// Start no episode expected to end after this deadline: stop between episodes instead,
    /// before the simulator resets (`None`: no deadline).
    pub deadline: Option<EpisodeDeadline>,
    /// Episode `e` starts from the state drawn with seed `seed + e`.
    pub seed: u64,
    /// How long to keep asking for a planner before giving up.
    pub attach_timeout: Duration,
    /// How long to wait for an action.
    pub action_timeout: Duration,
    /// How long to wait for the first action of a later episode (the planner may be training).
    pub train_timeout: Duration,
    /// End every episode after at most this many steps (as a time limit); `None`: the task's
    /// episode length. For quick tests and demos.
    pub max_steps: Option<u32>,
    /// Write a PNG frame of every step here, one folder per episode (when the machine can
    /// render offscreen; otherwise the bridge says so and runs without frames).
    #[cfg(feature = "render")]
    pub render: Option<PathBuf>,
}

/// One finished episode, as the bridge saw it.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeRecord {
    /// The run's episode number (continues where a resumed run stopped).
    pub episode: u32,
    /// Sum of the rewards the simulator reported.
    pub episode_return: f32,
    /// Control steps taken.
    pub steps: u32,
    /// Why it ended.
    pub end: EpisodeEnd,
    /// Wall time from the first observation to the last, including waits for the planner.
    pub wall_seconds: f64,
    /// Where the episode's actions came from.
    pub actions: ActionTally,
    /// Seconds of retraining the planner reported (its models-updated events) while this
    /// episode waited for its first action or ran: in sync mode with one agent, the retraining
    /// on the episodes before it. Lets experiment logs separate learning cost from planning cost.
    pub train_seconds: f64,
}

/// Counts of an episode's actions by source, and the planner's cost.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ActionTally {
    /// Actions chosen by model-predictive control.
    pub planned: u32,
    /// Uniformly random exploration actions.
    pub random: u32,
    /// Total planning time the planner reported for the planned actions.
    pub planning_ms: f64,
    /// Version of the models behind the episode's last action (0 = untrained).
    pub models_version: u64,
}

impl ActionTally {
    fn add(&mut self, stats: &PlanStats) {
        match stats.source {
            ActionSource::Planned => {
                self.planned += 1;
                self.planning_ms += f64::from(stats.planning_ms);
            }
            ActionSource::Random => self.random += 1,
        }
        self.models_version = stats.models_version;
    }

    /// Mean planning time per planned action.
    pub fn mean_planning_ms(&self) -> f64 {
        if self.planned == 0 {
            0.0
        } else {
            self.planning_ms / f64::from(self.planned)
        }
    }
}

impl std::fmt::Display for ActionTally {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{} planned, {} random actions; models v{}",
            self.planned, self.random, self.models_version
        )?;
        if self.planned > 0 {
            write!(f, "; {:.1} ms per plan", self.mean_planning_ms())?;
        }
        Ok(())
    }
}

/// Why the bridge stopped.
#[derive(Debug, thiserror::Error)]
pub enum BridgeError {
    #[error("invalid {what}: {source}")]
    InvalidName {
        what: &'static str,
        #[source]
        source: proto::keys::InvalidName,
    },
    #[error(transparent)]
    Sim(#[from] SimError),
    #[error(transparent)]
    SessionConfig(#[from] proto::session::SessionConfigError),
    #[error("cannot draw the agent's attach token: {0}")]
    Token(#[from] proto::TokenError),
    #[error("zenoh: {what}: {reason}")]
    Zenoh { what: String, reason: String },
    #[error(
        "no planner answered on `{key}` in {:.1} s ({attempts} attempts): is planner-service running, \
         and are the endpoints right (--connect to the planner's --listen, or both to a router)?",
        waited.as_secs_f64()
    )]
    NoPlanner {
        key: String,
        waited: Duration,
        attempts: u32,
    },
    #[error("the planner refused to attach this agent on `{key}`: {report}")]
    AttachRejected { key: String, report: ErrorReport },
    #[error("sim-bridge simulates the built-in tasks only, not `{0}`")]
    NotSimulated(String),
    #[error("the planner attached us to a {found} run, but this bridge simulates {expected}")]
    TaskMismatch { expected: String, found: String },
    #[error("cannot encode a message: {0}")]
    Encode(#[source] CodecError),
    #[error("undecodable message on `{key}`: {source}")]
    Decode {
        key: String,
        #[source]
        source: CodecError,
    },
    #[error(
        "no action for episode {episode} step {step} after {:.1} s{hint}",
        waited.as_secs_f64(),
        hint = if *while_training { " (the planner may still be training: raise --train-timeout)" } else { " (raise --action-timeout if planning is this slow)" }
    )]
    ActionTimeout {
        episode: u32,
        step: u32,
        waited: Duration,
        while_training: bool,
    },
    #[error("the planner reported an error for episode {episode} step {step}: {report}")]
    Planner {
        episode: u32,
        step: u32,
        report: ErrorReport,
    },
    #[error(
        "lost the planner {attempts} times in a row without finishing an episode; last: {reason}"
    )]
    PlannerLost { reason: String, attempts: u32 },
    #[error("the planner sent an invalid action for episode {episode} step {step}: {reason}")]
    InvalidAction {
        episode: u32,
        step: u32,
        reason: String,
    },
}

/// Runs `config.episodes` episodes against the planner (fewer if `config.timesteps` is reached
/// first, or the next episode would end after `config.deadline`) and returns their records;
/// `on_episode` sees each record as soon as its episode ends (to write it out before the next
/// one starts).
pub async fn run(
    config: &BridgeConfig,
    mut on_episode: impl FnMut(&EpisodeRecord),
) -> Result<Vec<EpisodeRecord>, BridgeError> {
    for (what, name) in [("run name", &config.run), ("agent name", &config.agent)] {
        proto::validate_name(name).map_err(|source| BridgeError::InvalidName { what, source })?;
    }
    let task = proto::Builtin::from_name(&config.spec.task)
        .ok_or_else(|| BridgeError::NotSimulated(config.spec.task.clone()))?;
    let mut env = Env::new(task)?;
    env.cap_episode_length(config.max_steps);
    #[cfg(feature = "render")]
    if let Some(dir) = &config.render {
        match env.record_frames(dir) {
            Ok(()) => tracing::info!(dir = %dir.display(), "rendering every episode's frames"),
            Err(e) => tracing::warn!("--render {}: {e}; running without frames", dir.display()),
        }
    }
    let mut link = PlannerLink::open(
        Keys::new(&config.prefix),
        &config.run,
        &config.agent,
        &config.endpoints,
        config.zenoh_config.as_deref(),
    )
    .await?;
    let mut accepted = attach(&mut link, config).await?;

    let mut records = Vec::with_capacity(config.episodes as usize);
    let mut episode = accepted.next_episode;
    let mut reattached = 0;
    let mut steps = 0u64;
    while records.len() < config.episodes as usize
        && config.timesteps.is_none_or(|budget| steps < budget)
    {
        if let (Some(deadline), Some(last)) = (&config.deadline, records.last())
            && !deadline.admits(last, SystemTime::now())
        {
            tracing::info!(
                episode,
                "stopping before episode {episode}: expected to take {}, it would end after \
                 the deadline",
                deadline
                    .next_episode(last)
                    .map_or_else(String::new, |d| format!("{:.0} s", d.as_secs_f64()))
            );
            if accepted.mode == TrainMode::Sync && last.actions.planned > 0 {
                await_retraining(&mut link, last, deadline.at).await;
            }
            break;
        }
        // Sync mode: the planner holds an episode's first action until it has retrained on the
        // episodes before it.
        let first_wait = if !records.is_empty() && accepted.mode == TrainMode::Sync {
            FirstWait::Training(config.train_timeout)
        } else {
            FirstWait::Action
        };
        let at = (episode, accepted.epoch);
        match run_episode(&mut env, &mut link, config, at, first_wait).await? {
            EpisodeOutcome::Finished(record) => {
                reattached = 0;
                episode += 1;
                tracing::info!(
                    episode = record.episode,
                    steps = record.steps,
                    episode_return = record.episode_return,
                    end = ?record.end,
                    seconds = record.wall_seconds,
                    "episode {}/{} done: return {:.2} ({})",
                    records.len() + 1,
                    config.episodes,
                    record.episode_return,
                    record.actions
                );
                steps += u64::from(record.steps);
                on_episode(&record);
                records.push(record);
            }
            EpisodeOutcome::PlannerLost(reason) => {
                reattached += 1;
                if reattached > MAX_REATTACH {
                    return Err(BridgeError::PlannerLost {
                        reason,
                        attempts: MAX_REATTACH,
                    });
                }
                tracing::warn!(
                    episode,
                    "{reason}: attaching again; the episode starts over"
                );
                accepted = attach(&mut link, config).await?;
                // Never reuse the number of the abandoned episode.
                episode = accepted.next_episode.max(episode + 1);
            }
        }
    }
    link.close().await?;
    Ok(records)
}

/// Waits, until `until` at the latest, for the planner to finish retraining on the episode
/// `last` that just ended (models newer than those it planned with, or a failed training),
/// before a run stopped at its deadline goes: the planner checkpoints new models before it
/// announces them, while a planner stopped mid-retraining loses it, and the resumed run then
/// retrains before its first plan (minutes to hours at the paper's sizes). Only after an
/// episode that planned, in sync mode, where such a retraining always follows; after random
/// exploration the planner may wait for more steps and announce nothing.
async fn await_retraining(link: &mut PlannerLink, last: &EpisodeRecord, until: SystemTime) {
    let used = last.actions.models_version;
    let left = until
        .duration_since(SystemTime::now())
        .unwrap_or(Duration::ZERO);
    tracing::info!(
        episode = last.episode,
        "waiting up to {:.0} s for the planner's retraining on episode {}, so that the run \
         stops with its models checkpointed",
        left.as_secs_f64(),
        last.episode
    );
    let retrained = async {
        loop {
            match link.recv().await {
                Ok(Inbound::Event(event)) => {
                    log_event(&event);
                    match event.kind {
                        RunEventKind::ModelsUpdated { models_version, .. }
                            if models_version > used =>
                        {
                            return Ok(());
                        }
                        RunEventKind::TrainingFailed { .. } => return Ok(()),
                        _ => {}
                    }
                }
                Ok(Inbound::PlannerGone) => return Err("the planner went away".to_string()),
                Err(e) => return Err(e.to_string()),
                Ok(_) => {}
            }
        }
    };
    match tokio::time::timeout(left, retrained).await {
        Ok(Ok(())) => tracing::info!("the planner has retrained; stopping"),
        Ok(Err(why)) => tracing::warn!("{why} before the planner had retrained; stopping"),
        Err(_) => tracing::info!(
            "the deadline came before the retraining ended; the resumed run retrains first"
        ),
    }
}

/// Consecutive re-attachments without a finished episode before the bridge gives up.
const MAX_REATTACH: u32 = 3;

/// Attaches (or re-attaches) to the run and checks that it learns our task.
async fn attach(
    link: &mut PlannerLink,
    config: &BridgeConfig,
) -> Result<AttachAccepted, BridgeError> {
    let accepted = link.attach(&config.spec, config.attach_timeout).await?;
    if accepted.task != config.spec.task {
        return Err(BridgeError::TaskMismatch {
            expected: config.spec.task.clone(),
            found: accepted.task,
        });
    }
    log_attached(config, &accepted);
    Ok(accepted)
}

/// How an episode ended for the bridge.
#[derive(Debug)]
enum EpisodeOutcome {
    Finished(EpisodeRecord),
    /// The planner lost this agent (it restarted, or no longer knows the run or the agent):
    /// attach again and start a new episode.
    PlannerLost(String),
}

/// How long an episode's first action may take.
#[derive(Debug, Clone, Copy)]
enum FirstWait {
    Action,
    Training(Duration),
}

async fn run_episode(
    env: &mut Env,
    link: &mut PlannerLink,
    config: &BridgeConfig,
    (episode, epoch): (u32, u64),
    first_wait: FirstWait,
) -> Result<EpisodeOutcome, BridgeError> {
    let started = Instant::now();
    let obs = env
        .reset(config.seed.wrapping_add(u64::from(episode)))
        .to_vec();
    // Kept to send again if the planner could not store it (its disk was full).
    let mut sent = Observation::new(episode, 0, obs, None, None);
    link.send(&sent).await?;
    let mut episode_return = 0.0;
    let mut actions = ActionTally::default();
    let mut train_seconds = 0.0;
    let mut step = 0;
    loop {
        let (timeout, while_training) = match (step, first_wait) {
            (0, FirstWait::Training(t)) => (t, true),
            _ => (config.action_timeout, false),
        };
        let wait = Wait {
            task: env.spec(),
            episode,
            step,
            epoch,
            timeout,
            while_training,
        };
        let action = match wait_for_action(link, wait, &mut train_seconds).await? {
            Waited::Action(action) => action,
            Waited::PlannerLost(reason) => return Ok(EpisodeOutcome::PlannerLost(reason)),
            Waited::NotStored(report) => {
                tracing::warn!(
                    "the planner could not store step {step}; sending it again in {STORAGE_RETRY:?}: {report}"
                );
                tokio::time::sleep(STORAGE_RETRY).await;
                link.send(&sent).await?;
                continue;
            }
        };
        actions.add(&action.stats);
        let outcome = env.step(&action.action)?;
        episode_return += outcome.reward;
        step += 1;
        let end = if outcome.terminated {
            Some(EpisodeEnd::Terminated)
        } else if outcome.truncated {
            Some(EpisodeEnd::TimeLimit)
        } else {
            None
        };
        // Say what was applied (the planned action clamped into the task's bounds), so the
        // planner stores what really happened.
        sent = Observation::new(episode, step, outcome.obs, Some(outcome.reward), end)
            .with_applied(outcome.applied);
        link.send(&sent).await?;
        if let Some(end) = end {
            let wall_seconds = started.elapsed().as_secs_f64();
            return Ok(EpisodeOutcome::Finished(EpisodeRecord {
                episode,
                episode_return,
                steps: step,
                end,
                wall_seconds,
                actions,
                train_seconds,
            }));
        }
    }
}

/// What waiting for an action produced.
enum Waited {
    Action(Action),
    /// The planner lost this agent; the reason, for the log.
    PlannerLost(String),
    /// The planner could not store the observation (a full disk); the session did not move
    /// on, so the same observation is sent again.
    NotStored(ErrorReport),
}

/// How long to wait before sending an observation the planner could not store again.
const STORAGE_RETRY: Duration = Duration::from_secs(1);

/// What [`wait_for_action`] waits for, and for how long.
struct Wait {
    task: &'static Task,
    episode: u32,
    step: u32,
    /// The run's ownership epoch at attach: actions of older epochs come from a planner that
    /// lost the run and are ignored.
    epoch: u64,
    timeout: Duration,
    while_training: bool,
}

/// Waits for the action for `(episode, step)`, logging what else arrives meanwhile and adding
/// the seconds of every models update announced to `train_seconds`.
async fn wait_for_action(
    link: &mut PlannerLink,
    wait: Wait,
    train_seconds: &mut f64,
) -> Result<Waited, BridgeError> {
    let Wait {
        task,
        episode,
        step,
        epoch,
        timeout,
        while_training,
    } = wait;
    let started = tokio::time::Instant::now();
    let deadline = started + timeout;
    loop {
        let Ok(inbound) = tokio::time::timeout_at(deadline, link.recv()).await else {
            let waited = started.elapsed();
            return Err(BridgeError::ActionTimeout {
                episode,
                step,
                waited,
                while_training,
            });
        };
        match inbound? {
            Inbound::Action(stale) if stale.epoch < epoch => {
                tracing::warn!(
                    episode = stale.episode,
                    step = stale.step,
                    stale_epoch = stale.epoch,
                    epoch,
                    "ignoring an action from a planner that lost the run"
                );
            }
            Inbound::Action(action) if action.episode == episode && action.step == step => {
                proto::validate::validate_action(&action, task).map_err(|e| {
                    BridgeError::InvalidAction {
                        episode,
                        step,
                        reason: e.to_string(),
                    }
                })?;
                let stats = &action.stats;
                tracing::debug!(episode, step, source = ?stats.source, planning_ms = stats.planning_ms, "action");
                return Ok(Waited::Action(action));
            }
            Inbound::Action(stale) => {
                tracing::debug!(
                    episode = stale.episode,
                    step = stale.step,
                    "ignoring an action for another step"
                );
            }
            Inbound::Error(report)
                if matches!(report.code, ErrorCode::NotAttached | ErrorCode::UnknownRun) =>
            {
                return Ok(Waited::PlannerLost(format!(
                    "the planner no longer knows this agent ({report})"
                )));
            }
            Inbound::Error(report)
                if report.code == ErrorCode::Storage
                    && (report.episode, report.step) == (Some(episode), Some(step)) =>
            {
                return Ok(Waited::NotStored(report));
            }
            Inbound::Error(report) if is_fatal(&report, episode, step) => {
                return Err(BridgeError::Planner {
                    episode,
                    step,
                    report,
                });
            }
            Inbound::Error(report) => tracing::warn!("planner reported: {report}"),
            Inbound::Event(event) => {
                if let RunEventKind::ModelsUpdated { seconds, .. } = &event.kind {
                    *train_seconds += f64::from(*seconds);
                }
                log_event(&event);
            }
            // In a fleet another planner takes the run over; alone, the planner may come
            // back. Either way the observation in flight is lost: attach again (the attach
            // waits for whichever planner owns the run now).
            Inbound::PlannerGone => {
                return Ok(Waited::PlannerLost("the planner went away".into()));
            }
        }
    }
}

/// Whether an error report means the action being waited for will never come: one about the
/// message in flight, or one about no message in particular (e.g. one the planner could not
/// decode). Reports about earlier steps are only logged.
fn is_fatal(report: &ErrorReport, episode: u32, step: u32) -> bool {
    match (report.episode, report.step) {
        (Some(e), Some(s)) => e == episode && s == step,
        _ => true,
    }
}

fn log_attached(config: &BridgeConfig, accepted: &AttachAccepted) {
    tracing::info!(
        run = %config.run,
        agent = %config.agent,
        planner = %accepted.planner_id,
        task = %accepted.task,
        mode = ?accepted.mode,
        episodes_done = accepted.episodes_done,
        models_version = accepted.models_version,
        "attached; running {} episodes from episode {}",
        config.episodes,
        accepted.next_episode
    );
}

/// Shows the planner's training as it happens.
fn log_event(event: &RunEvent) {
    match &event.kind {
        RunEventKind::TrainingStarted { transitions } => {
            tracing::info!(run = %event.run, transitions, "planner: training started");
        }
        RunEventKind::ModelsUpdated {
            models_version,
            dynamics_loss,
            energy_loss,
            reward_loss,
            seconds,
            termination_accuracy,
        } => tracing::info!(
            run = %event.run,
            models_version,
            dynamics_loss,
            energy_loss,
            reward_loss = ?reward_loss,
            termination_accuracy = ?termination_accuracy,
            seconds,
            "planner: models updated"
        ),
        RunEventKind::TrainingFailed { message } => {
            tracing::warn!(run = %event.run, "planner: training failed ({message}); previous models stay in use");
        }
        RunEventKind::EpisodeFinished {
            agent,
            episode,
            episode_return,
            steps,
            end,
        } => tracing::debug!(
            run = %event.run,
            %agent,
            episode,
            episode_return,
            steps,
            end = ?end,
            "planner: episode stored"
        ),
    }
}
