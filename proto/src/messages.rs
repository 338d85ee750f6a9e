//! The messages that travel between agents and planners.
//!
//! Every message starts with `version: u16`, the protocol version. The codec reads that field
//! first, so a peer speaking another version gets a clear "wrong protocol version" error instead
//! of a garbled decode.
//!
//! Every message refuses a field it does not know (`deny_unknown_fields`): a JSON message
//! with a misspelt or invented field is refused as malformed, and the error names the field
//! and the fields the message has, so a typo is never silently ignored. Postcard has no field
//! names: a message longer than the fields it knows is refused as trailing bytes.

use crate::task::TaskSpec;
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// The protocol version this build speaks. Version 2 added the ownership epoch to
/// [`AttachAccepted`] and [`Action`], and the applied action to [`Observation`]; version 3
/// the agent's session token ([`AttachAccepted::session`], [`Observation::session`],
/// [`AttachRequest::session`], [`ErrorReport::session`]); version 4 names tasks by their name
/// string instead of a catalog index ([`RunSpec::task`], [`AttachAccepted::task`]) and appends
/// [`RunSpec::task_spec`], a whole task for a system the planner's catalog does not know;
/// version 5 the reward model's sizes ([`PlannerOverrides::reward_hidden_layers`],
/// [`PlannerOverrides::reward_hidden_size`]) and its loss in
/// [`RunEventKind::ModelsUpdated`], for tasks whose reward is learned; version 6 a learned
/// termination ([`crate::task::TerminationKind::Learned`]) and its model's held-out accuracy in
/// [`RunEventKind::ModelsUpdated`], and exploration budgets in steps
/// ([`PlannerOverrides::exploration_steps`]).
pub const PROTOCOL_VERSION: u16 = 6;

/// How well a learned termination predicts episode ends it was not trained on.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TerminationAccuracy {
    /// Held-out transitions it was scored on.
    pub held_out: u32,
    /// Of them, transitions that ended their episode as `terminated`.
    pub terminations: u32,
    /// Fraction of the held-out transitions classified right.
    pub accuracy: f32,
    /// Fraction of the held-out terminations predicted as ends (`NaN`-free: 1 when none).
    pub recall: f32,
}

/// How the trainer interacts with acting agents: whether an agent's next episode waits for the
/// models retrained on its last one.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum TrainMode {
    /// The agent's next episode starts once the models retrained on its last episode are in
    /// (the paper's protocol).
    #[default]
    Sync,
    /// Agents keep being served by the previous models while the trainer works.
    Async,
}

/// The energy regulariser a run plans with.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum RegularizerChoice {
    /// The unregularised planner (plain PETS-style CEM).
    None,
    /// Denoising-autoencoder penalty `‖g(x) − x‖²` (Boney et al. 2019).
    Dae,
    /// Deep Energy Estimator Network energy (the paper).
    #[default]
    Deen,
}

/// Number format of the planner's network inference (training is always f32).
///
/// `auto` (the default) times every kernel this CPU has on each network's own layer shapes
/// when the network is first used and runs the fastest: AMX tiles or AVX-512 BF16 dot
/// products (bf16 operands, f32 sums) or f32 FMA, whichever this CPU does best. `bf16` rounds
/// the operands of every layer (the normalised input included) to bf16 (8 significant bits)
/// and keeps f32 sums, a relative rounding of at most 2⁻⁸ per operand, far below a learned
/// model's own error; it runs the faster of the bf16 kernels, or f32 where the CPU has none.
/// `f32` plans in exact f32.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum InferencePrecision {
    F32,
    Bf16,
    Auto,
}

impl std::fmt::Display for InferencePrecision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            InferencePrecision::F32 => "f32",
            InferencePrecision::Bf16 => "bf16",
            InferencePrecision::Auto => "auto",
        })
    }
}

impl std::str::FromStr for InferencePrecision {
    type Err = String;

    /// `auto`, `f32` or `bf16`, as in the TOML configuration and the JSON attach message.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "f32" => Ok(InferencePrecision::F32),
            "bf16" => Ok(InferencePrecision::Bf16),
            "auto" => Ok(InferencePrecision::Auto),
            other => Err(format!(
                "unknown precision `{other}` (known: auto, f32, bf16)"
            )),
        }
    }
}

/// The units in which the energy model's noise scale `σ` is given.
///
/// The paper trains DEEN "by corrupting the transitions in the replay buffer using additive
/// Gaussian noise": `σ` in the transitions' own units, the same for a joint angle, a velocity
/// and an object's position. `standardised` applies `σ` to each dimension after scaling it to
/// unit variance over the buffer instead, so a dimension that barely varies in the data (an
/// object that random actions seldom touch) is corrupted by a tiny amount, and its energy
/// rises steeply as soon as an imagined transition moves it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum NoiseUnits {
    /// `σ` in standard deviations of each dimension of the training transitions.
    #[default]
    Standardised,
    /// `σ` in the transitions' own units, as the paper corrupts the replay buffer.
    Raw,
}

impl std::fmt::Display for NoiseUnits {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            NoiseUnits::Standardised => "standardised",
            NoiseUnits::Raw => "raw",
        })
    }
}

impl std::str::FromStr for NoiseUnits {
    type Err = String;

    /// `standardised` or `raw`, as in the JSON attach message.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "standardised" => Ok(NoiseUnits::Standardised),
            "raw" => Ok(NoiseUnits::Raw),
            other => Err(format!(
                "unknown noise units `{other}` (known: standardised, raw)"
            )),
        }
    }
}

/// The optimiser that searches action sequences in planning.
///
/// `cem` is the paper's (PETS-style CEM with Table 2's settings); `icem` is the improved CEM of
/// Pinneri et al. (CoRL 2020): colored noise, kept elites, population decay, best sequence
/// executed, with several times fewer imagined trajectories per plan (on learned models it kept
/// CEM's return on cartpole, not on half-cheetah or reacher3d); `adam` is
/// gradient-based trajectory optimisation through the learned model (Boney et al. 2019, the
/// paper's Adam + DAE baseline).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum Optimizer {
    #[default]
    Cem,
    Icem,
    Adam,
}

impl std::fmt::Display for Optimizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Optimizer::Cem => "cem",
            Optimizer::Icem => "icem",
            Optimizer::Adam => "adam",
        })
    }
}

impl std::str::FromStr for Optimizer {
    type Err = String;

    /// `cem`, `icem` or `adam`, as in the TOML configuration and the JSON attach message.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "cem" => Ok(Optimizer::Cem),
            "icem" => Ok(Optimizer::Icem),
            "adam" => Ok(Optimizer::Adam),
            other => Err(format!(
                "unknown optimizer `{other}` (known: cem, icem, adam)"
            )),
        }
    }
}

/// How training epochs decay with the number of finished episodes (the paper trains less as
/// the buffer grows, to avoid overfitting it). Part of a run's preset, and overridable.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, rename_all = "snake_case")]
pub enum EpochSchedule {
    /// The configured epochs after every episode.
    Constant,
    /// Half-cheetah: `epochs` for both models once `after_episodes` episodes are stored.
    DropAfter { after_episodes: u32, epochs: u32 },
    /// Ant: epochs multiplied by `dynamics_factor` / `energy_factor` for every time limit's
    /// worth of transitions gathered after the exploration episodes (at most once per planned
    /// episode, so an episode cut short counts for the share it lasted), never below
    /// `min_epochs`.
    Geometric {
        dynamics_factor: f32,
        energy_factor: f32,
        min_epochs: u32,
    },
}

/// Overrides of a run's preset: one field per preset field. Every field is optional: `None`
/// keeps the preset's value. A field this build does not know is refused (JSON names its
/// fields; postcard has no names, and a message longer than the fields it knows is refused
/// as trailing bytes), so a mistyped override is never silently ignored.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(default, deny_unknown_fields)]
pub struct PlannerOverrides {
    pub regularizer: Option<RegularizerChoice>,
    /// Weight `alpha` of the energy in the planning objective.
    pub energy_weight: Option<f32>,
    /// Members of the dynamics ensemble (1 = the paper's single model, 5 = PETS).
    pub ensemble_size: Option<u32>,
    /// Trajectory-sampling particles per candidate.
    pub particles: Option<u32>,
    pub horizon: Option<u32>,
    pub population: Option<u32>,
    pub elites: Option<u32>,
    pub cem_iterations: Option<u32>,
    /// Weight of the previous CEM distribution in each refit, in [0, 1).
    pub cem_smoothing: Option<f32>,
    /// CEM stops once every coordinate's variance is below this.
    pub cem_min_variance: Option<f32>,
    /// Sample the dynamics' predicted Gaussian in imagination (PETS TS∞) instead of its mean.
    pub sample_dynamics: Option<bool>,
    /// Episodes of uniformly random actions before planning starts.
    pub exploration_episodes: Option<u32>,
    pub dynamics_epochs: Option<u32>,
    pub dynamics_hidden_layers: Option<u32>,
    pub dynamics_hidden_size: Option<u32>,
    pub dynamics_batch_size: Option<u32>,
    pub dynamics_learning_rate: Option<f32>,
    pub dynamics_weight_decay: Option<f32>,
    /// Hidden layers of the reward model (used by a task whose reward is `learned`; it trains
    /// with the dynamics' epochs, batch size and learning rate).
    pub reward_hidden_layers: Option<u32>,
    /// Units per hidden layer of the reward model.
    pub reward_hidden_size: Option<u32>,
    pub energy_epochs: Option<u32>,
    pub energy_hidden_layers: Option<u32>,
    pub energy_hidden_size: Option<u32>,
    pub energy_batch_size: Option<u32>,
    pub energy_learning_rate: Option<f32>,
    /// Standard deviation `σ` of the energy model's corrupting noise (in `energy_noise_units`).
    pub energy_noise_sigma: Option<f32>,
    /// How training epochs change as episodes accumulate.
    pub epoch_schedule: Option<EpochSchedule>,
    /// Most gradient steps per model in one retraining (the epochs are cut short beyond it);
    /// absent in the paper's presets, which train their full epochs however large the buffer.
    pub max_gradient_steps: Option<u64>,
    /// Number format of planning-time inference.
    pub inference_precision: Option<InferencePrecision>,
    /// The planning optimiser (the preset's: `cem`).
    pub optimizer: Option<Optimizer>,
    /// iCEM: exponent β of the colored noise's `1/f^β` spectrum (0 = white noise).
    pub icem_noise_beta: Option<f32>,
    /// iCEM: fraction of the elites kept for the next iteration and step.
    pub icem_keep_elites: Option<f32>,
    /// iCEM: population decay factor per iteration (≥ 1).
    pub icem_population_decay: Option<f32>,
    /// Adam planning: step size as a fraction of each action's half-range.
    pub adam_learning_rate: Option<f32>,
    /// Milliseconds from an observation's arrival to its action: planning stops iterating
    /// when the next iteration would cross it. `0` turns the deadline off (every configured
    /// iteration runs, as a simulator that waits for its action wants); absent: the task's
    /// control period.
    pub deadline_ms: Option<u32>,
    /// The units of `energy_noise_sigma` (the preset's: `raw` for pusher, `standardised` for
    /// the other built-in tasks).
    pub energy_noise_units: Option<NoiseUnits>,
    /// Transitions of uniformly random actions before planning starts, on top of
    /// `exploration_episodes` (both must be reached): a task whose random episodes end
    /// after a few steps still gets enough data before its first plan.
    pub exploration_steps: Option<u64>,
}

/// What an agent asks for when it attaches: which task it is and how its run should plan.
///
/// The first agent to attach creates the run with this spec; later agents must agree on the task.
/// Fields are only ever appended: postcard is positional.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RunSpec {
    /// The task's name: a planner's catalog entry, or the name of `task_spec`.
    pub task: String,
    /// Named preset; `None` is the task's default preset.
    #[serde(default)]
    pub preset: Option<String>,
    #[serde(default)]
    pub overrides: PlannerOverrides,
    #[serde(default)]
    pub mode: TrainMode,
    /// Seed of the run's models and planner.
    #[serde(default)]
    pub seed: u64,
    /// The whole task, for a system the planner's catalog does not know (its `name` must be
    /// `task`). Validated against the planner's `[limits]` and stored with the run.
    #[serde(default)]
    pub task_spec: Option<TaskSpec>,
}

/// Sent as the payload of a query on the run's attach key.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct AttachRequest {
    pub version: u16,
    pub agent: String,
    pub spec: RunSpec,
    /// The agent's claim to its name: the token of its current session when it attaches again
    /// (it reconnects), or on its first attach a token it drew itself ([`crate::draw_token`]).
    /// The planner replaces a live session only for the agent holding that session's token or
    /// the token that session was attached with, so an agent whose attach answer was lost (the
    /// query timed out) asks again with the same token and is accepted as itself. Without it,
    /// a name whose session is live is refused, so no one can take an agent's place.
    #[serde(default)]
    pub session: Option<u64>,
}

/// The planner's answer to an [`AttachRequest`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct AttachReply {
    pub version: u16,
    pub outcome: AttachOutcome,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
pub enum AttachOutcome {
    Accepted(AttachAccepted),
    Rejected(ErrorReport),
}

/// The run as the agent joins it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct AttachAccepted {
    pub planner_id: String,
    /// The run's task name.
    pub task: String,
    pub mode: TrainMode,
    /// Episodes this run has already finished (across all its agents).
    pub episodes_done: u32,
    /// Version of the models currently in use (0 = untrained).
    pub models_version: u64,
    /// The episode number the agent should use next (resuming runs continue numbering).
    pub next_episode: u32,
    /// The run's ownership epoch: it grows by one each time a planner takes the run over. Every
    /// [`Action`] carries the epoch of the planner that sent it; an agent ignores actions of an
    /// epoch older than the newest it has seen (a planner that lost the run but does not know
    /// it yet).
    #[serde(default)]
    pub epoch: u64,
    /// The agent's session token: random (from the OS), never 0. Every [`Observation`] of
    /// this session carries it; the planner refuses observations that carry another.
    #[serde(default)]
    pub session: u64,
}

/// Why an episode ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum EpisodeEnd {
    /// The task's termination condition fired (e.g. the ant fell).
    Terminated,
    /// The episode reached its time limit.
    TimeLimit,
    /// The agent stopped early (lost its planner, was shut down): not a normal ending.
    Interrupted,
}

/// An agent's observation. `step = 0` starts an episode; step `t > 0` is the result of the
/// action the planner sent for step `t − 1`, with the reward of that transition.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Observation {
    pub version: u16,
    pub episode: u32,
    pub step: u32,
    pub obs: Vec<f32>,
    /// Reward of the transition into `obs` (absent at step 0).
    #[serde(default)]
    pub reward: Option<f32>,
    /// Set on the last observation of an episode. The planner answers it with no action.
    #[serde(default)]
    pub end: Option<EpisodeEnd>,
    /// The action the agent actually applied at the previous step, when it differs from the
    /// one planned (a robot clipped it, a safety layer or a person overrode it). The replay
    /// stores this one then, so the models learn what really happened. Absent at step 0; it
    /// must have the task's action dimension, be finite and lie within the action bounds.
    #[serde(default)]
    pub applied: Option<Vec<f32>>,
    /// The session token of the agent's attach ([`AttachAccepted::session`]). An observation
    /// whose token is not the agent's current session's is refused with
    /// [`ErrorCode::Session`] and touches nothing ([`NO_SESSION`], the default, is never a
    /// session).
    #[serde(default)]
    pub session: u64,
}

/// The session token of a message that carries none: an observation sent without attaching,
/// or bytes that could not be read far enough to find one (undecodable, over the payload
/// limit). Never a live session's token, so an error report about such a message
/// ([`ErrorReport::session`] = `Some(NO_SESSION)`) concerns no live agent under the name.
pub const NO_SESSION: u64 = 0;

impl Observation {
    /// An observation of the current protocol version.
    pub fn new(
        episode: u32,
        step: u32,
        obs: Vec<f32>,
        reward: Option<f32>,
        end: Option<EpisodeEnd>,
    ) -> Self {
        Self {
            version: PROTOCOL_VERSION,
            episode,
            step,
            obs,
            reward,
            end,
            applied: None,
            session: NO_SESSION,
        }
    }

    /// The same observation, in session `token` (see [`AttachAccepted::session`]).
    pub fn in_session(mut self, token: u64) -> Self {
        self.session = token;
        self
    }

    /// The same observation, saying that `action` was applied at the previous step.
    pub fn with_applied(mut self, action: Vec<f32>) -> Self {
        self.applied = Some(action);
        self
    }
}

/// Where an action came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "lowercase")]
pub enum ActionSource {
    /// Uniformly random (exploration episodes).
    Random,
    /// Model-predictive control.
    Planned,
}

/// Statistics of the plan behind an action.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PlanStats {
    pub source: ActionSource,
    /// Wall time the planner spent on this action.
    pub planning_ms: f32,
    /// Imagined return of the chosen sequence (rewards only).
    pub predicted_return: f32,
    /// Mean energy of the chosen sequence's imagined transitions (0 without regulariser).
    pub mean_energy: f32,
    /// CEM iterations run.
    pub iterations: u32,
    /// Version of the models that planned.
    pub models_version: u64,
    /// Iterations were left out because the next one would have crossed the run's deadline.
    pub cut: bool,
    /// The action was sent after the run's deadline, or no iteration fitted before it (the
    /// action is then the previous plan's next one).
    pub missed: bool,
}

/// The planner's answer to an observation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Action {
    pub version: u16,
    pub episode: u32,
    /// The step this action is for (equal to the observation's step).
    pub step: u32,
    pub action: Vec<f32>,
    pub stats: PlanStats,
    /// The ownership epoch of the planner that sent it (see [`AttachAccepted::epoch`]).
    #[serde(default)]
    pub epoch: u64,
}

/// Machine-readable kind of an [`ErrorReport`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum ErrorCode {
    /// The bytes could not be decoded.
    Malformed,
    /// The sender speaks another protocol version.
    ProtocolVersion,
    /// A vector has the wrong length.
    Dimension,
    /// A NaN or infinity where a finite number is required.
    NonFinite,
    /// The run does not exist (the agent never attached, or the run was removed).
    UnknownRun,
    /// The task is not in the catalog.
    UnknownTask,
    /// The agent is not attached to this run.
    NotAttached,
    /// Episode/step numbering does not follow on from the previous message.
    OutOfOrder,
    /// The planner refuses (limits, incompatible spec, invalid name).
    Refused,
    /// Something failed inside the planner.
    Internal,
    /// A finite number outside its allowed range: beyond the task's magnitude bound (it would
    /// overflow the models), or an applied action beyond the task's action bounds.
    OutOfRange,
    /// The planner could not store the message (e.g. its disk is full). Nothing of it was
    /// kept and the agent's session did not move on: send the same message again later.
    Storage,
    /// The observation's session token is not the agent's current session's (another
    /// process attached under this name, or the agent attached again since): nothing of it
    /// was used. Attach to get a session of your own.
    Session,
}

/// An error reported to the sender of a bad message, on its error key.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ErrorReport {
    pub version: u16,
    pub code: ErrorCode,
    pub message: String,
    /// The episode and step of the offending message, when known.
    #[serde(default)]
    pub episode: Option<u32>,
    #[serde(default)]
    pub step: Option<u32>,
    /// The session token the offending message carried, when known. Reports travel on the
    /// agent name's error key, which any process using that name hears: an agent ignores
    /// reports about a session that is not its own (an impostor's refused observations).
    /// Bytes that could not be read (undecodable, oversized) are reported with
    /// [`NO_SESSION`]: whoever sent them, they must not stop the live agent of the name.
    #[serde(default)]
    pub session: Option<u64>,
}

impl ErrorReport {
    pub fn new(code: ErrorCode, message: impl Into<String>) -> Self {
        Self {
            version: PROTOCOL_VERSION,
            code,
            message: message.into(),
            episode: None,
            step: None,
            session: None,
        }
    }

    /// Says which session token the offending message carried.
    pub fn for_session(mut self, token: u64) -> Self {
        self.session = Some(token);
        self
    }

    /// Whether this report concerns the session `token` (reports not tied to a session, such
    /// as a refused attach, concern every holder of the name).
    pub fn concerns(&self, token: u64) -> bool {
        self.session.is_none_or(|s| s == token)
    }

    /// Attaches the position of the offending message.
    pub fn at(mut self, episode: u32, step: u32) -> Self {
        self.episode = Some(episode);
        self.step = Some(step);
        self
    }
}

impl std::fmt::Display for ErrorReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:?}: {}", self.code, self.message)?;
        if let (Some(e), Some(s)) = (self.episode, self.step) {
            write!(f, " (episode {e}, step {s})")?;
        }
        Ok(())
    }
}

/// Something that happened to a run, published on its events key.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RunEvent {
    pub version: u16,
    pub run: String,
    pub kind: RunEventKind,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub enum RunEventKind {
    /// An agent finished an episode; its transitions are stored.
    EpisodeFinished {
        agent: String,
        episode: u32,
        episode_return: f32,
        steps: u32,
        end: EpisodeEnd,
    },
    /// The trainer started retraining on `transitions` stored transitions.
    TrainingStarted { transitions: u64 },
    /// New models are in use.
    ModelsUpdated {
        models_version: u64,
        dynamics_loss: f32,
        energy_loss: f32,
        /// The reward model's last-epoch loss (mean squared error of the standardised reward;
        /// `None` unless the task's reward is learned).
        reward_loss: Option<f32>,
        seconds: f32,
        /// The termination model's accuracy on transitions held out of its training, and
        /// its recall of the held-out terminations (`None` unless the task's termination is
        /// learned, or before any episode ended as `terminated`).
        termination_accuracy: Option<TerminationAccuracy>,
    },
    /// Training failed; the previous models stay in use.
    TrainingFailed { message: String },
}
