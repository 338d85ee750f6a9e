//! The planner's search settings: the sizes every optimiser shares (horizon, population,
//! elites, iterations, particles), the choice of optimiser, and the iCEM and Adam parameters,
//! each with its validation. Presets and overrides write them (`config::preset`); the
//! optimisers ([`super::cem`], [`super::icem`], [`super::adam`]) only read them, so this
//! module imports none of them.

pub use proto::Optimizer;
use serde::{Deserialize, Serialize};

/// The CEM hyperparameters (PETS names in brackets).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CemConfig {
    /// Planning horizon in steps (`plan_hor`).
    pub horizon: usize,
    /// Candidates per iteration (`popsize`).
    pub population: usize,
    /// Candidates the distribution is refitted to (`num_elites`).
    pub elites: usize,
    /// Maximum iterations per solve (`max_iters`).
    pub iterations: usize,
    /// Weight of the previous distribution in the refit (`alpha`, 0.1).
    pub smoothing: f32,
    /// Stop once every coordinate's variance is below this (`epsilon`, 0.001).
    pub min_variance: f32,
    /// Imagined rollouts per candidate, averaged (`npart`); particle `p` uses ensemble member
    /// `p mod B`.
    pub particles: usize,
    /// The optimiser over these settings: this module's CEM (the paper's) or
    /// [`iCEM`](super::icem), which adds `icem`'s parameters.
    #[serde(default)]
    pub optimizer: Optimizer,
    /// iCEM's own parameters (unused by CEM).
    #[serde(default)]
    pub icem: IcemConfig,
    /// Adam planning's own parameters (unused by CEM and iCEM).
    #[serde(default)]
    pub adam: AdamConfig,
}

impl CemConfig {
    /// Checks the values against each other; the planner refuses an invalid configuration.
    pub fn validate(&self) -> Result<(), ConfigError> {
        for (name, value) in [
            ("horizon", self.horizon),
            ("population", self.population),
            ("elites", self.elites),
            ("iterations", self.iterations),
            ("particles", self.particles),
        ] {
            if value == 0 {
                return Err(ConfigError::Zero(name));
            }
        }
        if self.elites > self.population {
            return Err(ConfigError::TooManyElites {
                elites: self.elites,
                population: self.population,
            });
        }
        if !(0.0..1.0).contains(&self.smoothing) {
            return Err(ConfigError::Smoothing(self.smoothing));
        }
        if !(self.min_variance.is_finite() && self.min_variance >= 0.0) {
            return Err(ConfigError::MinVariance(self.min_variance));
        }
        Ok(())
    }
}

impl CemConfig {
    /// Candidates iCEM's `iteration`-th iteration draws: `max(N·γ^(−i), 2K)`, at most `N`.
    pub fn icem_population_at(&self, iteration: usize) -> usize {
        let n = self.population as f64;
        let decayed = n * f64::from(self.icem.population_decay).powi(-(iteration as i32));
        (decayed.round() as usize)
            .max(2 * self.elites)
            .min(self.population)
    }

    /// Candidate sequences a solve of `iterations` iterations scores: the population each
    /// time for CEM (and Adam's sequences, one forward rollout each), iCEM's decaying
    /// population ([`CemConfig::icem_population_at`]) summed.
    pub fn candidates_scored(&self, iterations: usize) -> usize {
        match self.optimizer {
            Optimizer::Cem | Optimizer::Adam => iterations * self.population,
            Optimizer::Icem => (0..iterations).map(|i| self.icem_population_at(i)).sum(),
        }
    }
}

/// Why a planner configuration was refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConfigError {
    #[error("CEM `{0}` must be at least 1")]
    Zero(&'static str),
    #[error("CEM elites ({elites}) exceed the population ({population})")]
    TooManyElites { elites: usize, population: usize },
    #[error("CEM smoothing must lie in [0, 1), got {0}")]
    Smoothing(f32),
    #[error("CEM min_variance must be finite and non-negative, got {0}")]
    MinVariance(f32),
    #[error("action bounds must be finite with low < high in every dimension")]
    Bounds,
    #[error("energy weight must be finite and non-negative, got {0}")]
    EnergyWeight(f32),
    #[error("iCEM `{0}` is out of its range, got {1}")]
    Icem(&'static str, f32),
    #[error("Adam planning `{0}` is out of its range, got {1}")]
    Adam(&'static str, f32),
}

/// iCEM's own parameters (the paper's names in brackets; defaults: its general values, which
/// a task's preset may replace: see `config::preset`'s `icem_for`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default)]
pub struct IcemConfig {
    /// Exponent `β` of the colored noise's `1/f^β` spectrum (`noise_beta`, 0 = white).
    pub noise_beta: f32,
    /// Fraction of the elites kept for the next iteration and the next step
    /// (`fraction_elites_reused`).
    pub keep_elites: f32,
    /// Population decay `γ ≥ 1` per iteration (`factor_decrease_num`).
    pub population_decay: f32,
}

impl Default for IcemConfig {
    fn default() -> Self {
        Self {
            noise_beta: 2.0,
            keep_elites: 0.3,
            population_decay: 1.25,
        }
    }
}

/// Limits of the iCEM parameters: beyond them the method stops making sense (a `β` above 4 is
/// a straight line; a decay above 8 leaves the floor of `2K` candidates from iteration 1).
pub const NOISE_BETA_RANGE: (f32, f32) = (0.0, 4.0);
pub const POPULATION_DECAY_RANGE: (f32, f32) = (1.0, 8.0);

impl IcemConfig {
    /// Checks each parameter against its limits.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let within = |v: f32, (lo, hi): (f32, f32)| v.is_finite() && (lo..=hi).contains(&v);
        if !within(self.noise_beta, NOISE_BETA_RANGE) {
            return Err(ConfigError::Icem("noise_beta", self.noise_beta));
        }
        if !within(self.keep_elites, (0.0, 1.0)) {
            return Err(ConfigError::Icem("keep_elites", self.keep_elites));
        }
        if !within(self.population_decay, POPULATION_DECAY_RANGE) {
            return Err(ConfigError::Icem("population_decay", self.population_decay));
        }
        Ok(())
    }
}

/// Adam planning's own parameter (the rest are [`CemConfig`]'s: `horizon`, `population` =
/// candidates optimised together, `iterations` = Adam steps, `particles`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    /// Step size as a fraction of each action's half-range `(ub − lb)/2`.
    pub learning_rate: f32,
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self { learning_rate: 0.1 }
    }
}

/// Largest accepted [`AdamConfig::learning_rate`]: a step of one half-range already crosses
/// the whole box in two steps.
pub const MAX_LEARNING_RATE: f32 = 1.0;

impl AdamConfig {
    /// Checks the learning rate: finite, positive, at most [`MAX_LEARNING_RATE`].
    pub fn validate(&self) -> Result<(), ConfigError> {
        let lr = self.learning_rate;
        if lr.is_finite() && lr > 0.0 && lr <= MAX_LEARNING_RATE {
            Ok(())
        } else {
            Err(ConfigError::Adam("learning_rate", lr))
        }
    }
}
