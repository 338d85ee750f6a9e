//! Energy regularisers: how familiar is a transition `(s, a, s')`? DEEN (the paper) and DAE.
//!
//! A regulariser is a density model of the vectors `x = [s, a, s']` of the replay buffer; the
//! planner subtracts `α · energy(x)` from the return of every imagined transition (paper eq. 5).
//!
//! - [`config`]: sizes and training settings (Table 2's "DEEN" rows).
//! - [`deen`]: the Deep Energy Estimator Network, trained by double backpropagation.
//! - [`dae`]: the denoising autoencoder baseline (Boney et al. 2019).
//!
//! The planner's interface (on [`Regularizer`]; never allocating once the scratch exists):
//!
//! ```text
//! fn scratch(&self, max_rows: usize) -> EnergyScratch
//! fn energy(&self, obs: &[f32], act: &[f32], next_obs: &[f32], rows: usize,
//!           scratch: &mut EnergyScratch, out: &mut [f32])
//! EnergyScratch::fits(&self, regularizer: &Regularizer, rows: usize) -> bool
//! ```
//!
//! and the trainer's: `Regularizer::new(kind, &config, obs_dim, act_dim, &mut rng)`,
//! `Regularizer::fit(&mut self, &Transitions, epochs, &mut rng) -> FitReport`.

pub mod config;
pub mod dae;
pub mod deen;
pub mod denoiser;
pub mod mixture;

pub use config::{EnergyConfig, EnergyParts, NoiseUnits};
pub use dae::{Dae, DaeWorkspace};
pub use deen::{Deen, DeenWorkspace};
pub use denoiser::{Denoiser, DenoisingLoss};

use crate::data::Transitions;
use crate::nn::{FitReport, ForwardScratch, Normalizer, ShapeError, Tape};
use rand::rngs::StdRng;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// Which regulariser a run plans with. The wire and config name is the lowercase identifier.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RegularizerKind {
    /// No regulariser: the energy is zero.
    None,
    /// Denoising-autoencoder penalty `‖g(x) − x‖²`.
    Dae,
    /// DEEN energy (the paper).
    #[default]
    Deen,
}

impl RegularizerKind {
    pub const ALL: &'static [RegularizerKind] = &[
        RegularizerKind::None,
        RegularizerKind::Dae,
        RegularizerKind::Deen,
    ];

    /// Layer sizes of this regulariser's network for transitions `[s, a, s']` of
    /// `2 · obs_dim + act_dim` numbers (`None`: this kind has no network).
    pub fn layer_sizes(
        self,
        config: &EnergyConfig,
        obs_dim: usize,
        act_dim: usize,
    ) -> Option<Vec<usize>> {
        let dim = 2 * obs_dim + act_dim;
        match self {
            RegularizerKind::None => None,
            RegularizerKind::Dae => Some(config::layer_sizes(
                dim,
                config,
                <dae::DaeLoss as DenoisingLoss>::outputs(dim),
            )),
            RegularizerKind::Deen => Some(config::layer_sizes(
                dim,
                config,
                <deen::DeenLoss as DenoisingLoss>::outputs(dim),
            )),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            RegularizerKind::None => "none",
            RegularizerKind::Dae => "dae",
            RegularizerKind::Deen => "deen",
        }
    }
}

impl fmt::Display for RegularizerKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A regulariser name that is not `none`, `dae` or `deen`.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown regularizer `{0}` (known: none, dae, deen)")]
pub struct UnknownRegularizer(pub String);

impl FromStr for RegularizerKind {
    type Err = UnknownRegularizer;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        RegularizerKind::ALL
            .iter()
            .copied()
            .find(|k| k.name().eq_ignore_ascii_case(s.trim()))
            .ok_or_else(|| UnknownRegularizer(s.to_string()))
    }
}

/// A trained (or untrained) regulariser over transitions of `obs_dim`/`act_dim`.
#[derive(Clone, Debug)]
pub enum Regularizer {
    None,
    Dae(Dae),
    Deen(Deen),
}

/// Preallocated buffers for [`Regularizer::energy`] on up to `capacity` rows.
#[derive(Clone, Debug)]
pub struct EnergyScratch {
    capacity: usize,
    /// `None` for the `None` regulariser, which needs no buffers.
    forward: Option<ForwardScratch>,
}

impl EnergyScratch {
    /// Whether these buffers serve `regularizer` on `rows` rows.
    pub fn fits(&self, regularizer: &Regularizer, rows: usize) -> bool {
        rows <= self.capacity
            && match (regularizer, &self.forward) {
                (Regularizer::None, _) => true,
                (Regularizer::Dae(m), Some(f)) => f.fits(m.mlp(), rows),
                (Regularizer::Deen(m), Some(f)) => f.fits(m.mlp(), rows),
                _ => false,
            }
    }
}

/// Preallocated buffers for [`Regularizer::energy_and_gradient`] on up to `capacity` rows.
#[derive(Clone, Debug)]
pub struct EnergyGradScratch {
    capacity: usize,
    /// The DAE's forward pass (its output is held fixed: a stopped gradient).
    forward: Option<ForwardScratch>,
    /// DEEN's training tape: its energy is back-propagated to the input.
    tape: Option<Tape>,
}

impl EnergyGradScratch {
    /// Whether these buffers serve `regularizer` on `rows` rows.
    pub fn fits(&self, regularizer: &Regularizer, rows: usize) -> bool {
        rows <= self.capacity
            && match (regularizer, &self.forward, &self.tape) {
                (Regularizer::None, _, _) => true,
                (Regularizer::Dae(m), Some(f), _) => f.fits(m.mlp(), rows),
                (Regularizer::Deen(m), _, Some(t)) => t.fits(m.mlp(), rows),
                _ => false,
            }
    }
}

/// The vectors `[s, a, s']` of every transition, sample-major.
pub fn transition_rows(data: &Transitions) -> Vec<f32> {
    let (o, a) = (data.obs_dim(), data.act_dim());
    let mut rows = Vec::with_capacity(data.len() * (2 * o + a));
    for i in 0..data.len() {
        let (s, u, s1) = data.row(i);
        rows.extend_from_slice(s);
        rows.extend_from_slice(u);
        rows.extend_from_slice(s1);
    }
    rows
}

impl Regularizer {
    /// An untrained regulariser of `kind` for transitions `[s, a, s']` of `2 · obs_dim + act_dim`
    /// numbers.
    pub fn new(
        kind: RegularizerKind,
        config: &EnergyConfig,
        obs_dim: usize,
        act_dim: usize,
        rng: &mut StdRng,
    ) -> Self {
        let dim = 2 * obs_dim + act_dim;
        match kind {
            RegularizerKind::None => Regularizer::None,
            RegularizerKind::Dae => Regularizer::Dae(Dae::new(dim, config, rng)),
            RegularizerKind::Deen => Regularizer::Deen(Deen::new(dim, config, rng)),
        }
    }

    /// A regulariser of `kind` with stored parts (`None` for the `None` kind; see
    /// [`Regularizer::parts`]).
    pub fn from_parts(
        kind: RegularizerKind,
        config: &EnergyConfig,
        obs_dim: usize,
        act_dim: usize,
        parts: Option<EnergyParts>,
    ) -> Result<Self, ShapeError> {
        let dim = 2 * obs_dim + act_dim;
        match (kind, parts) {
            (RegularizerKind::None, None) => Ok(Regularizer::None),
            (RegularizerKind::Dae, Some(p)) => {
                Ok(Regularizer::Dae(Dae::from_parts(dim, config, p)?))
            }
            (RegularizerKind::Deen, Some(p)) => {
                Ok(Regularizer::Deen(Deen::from_parts(dim, config, p)?))
            }
            (_, p) => Err(ShapeError {
                what: "stored energy networks (one for dae and deen, none for none)",
                expected: usize::from(kind != RegularizerKind::None),
                got: usize::from(p.is_some()),
            }),
        }
    }

    /// What determines the energies — what persistence stores (`None` for `None`).
    /// Sets the number format of the energy network's planning-time inference.
    pub fn set_inference_precision(&mut self, precision: proto::InferencePrecision) {
        match self {
            Regularizer::None => {}
            Regularizer::Dae(m) => m.set_inference_precision(precision),
            Regularizer::Deen(m) => m.set_inference_precision(precision),
        }
    }

    /// Runs the network's inference on one kernel path, unmeasured.
    pub fn set_kernel_path(&mut self, path: crate::nn::KernelPath) {
        match self {
            Regularizer::None => {}
            Regularizer::Dae(m) => m.set_kernel_path(path),
            Regularizer::Deen(m) => m.set_kernel_path(path),
        }
    }

    /// The kernel path the network's inference runs (`None` without a network).
    pub fn kernel_path(&self) -> Option<crate::nn::KernelPath> {
        match self {
            Regularizer::None => None,
            Regularizer::Dae(m) => Some(m.mlp().kernel_path()),
            Regularizer::Deen(m) => Some(m.mlp().kernel_path()),
        }
    }

    pub fn parts(&self) -> Option<EnergyParts> {
        match self {
            Regularizer::None => None,
            Regularizer::Dae(m) => Some(m.parts()),
            Regularizer::Deen(m) => Some(m.parts()),
        }
    }

    pub fn kind(&self) -> RegularizerKind {
        match self {
            Regularizer::None => RegularizerKind::None,
            Regularizer::Dae(_) => RegularizerKind::Dae,
            Regularizer::Deen(_) => RegularizerKind::Deen,
        }
    }

    /// Trains on every transition of `data` for the budget's epochs (or until it says stop),
    /// continuing from the current weights (the normaliser is refitted on `data`).
    pub fn fit(
        &mut self,
        data: &Transitions,
        budget: impl Into<crate::nn::train::FitBudget>,
        rng: &mut StdRng,
    ) -> FitReport {
        let budget = budget.into();
        let epochs = budget.epochs;
        let report = match self {
            Regularizer::None => FitReport {
                samples: data.len(),
                epochs,
                loss: 0.0,
                ..FitReport::default()
            },
            Regularizer::Dae(m) => m.fit(&transition_rows(data), budget, rng),
            Regularizer::Deen(m) => m.fit(&transition_rows(data), budget, rng),
        };
        tracing::debug!(?report, kind = %self.kind(), "regularizer trained");
        report
    }

    /// Buffers for [`Regularizer::energy`] on up to `max_rows` rows.
    pub fn scratch(&self, max_rows: usize) -> EnergyScratch {
        let forward = match self {
            Regularizer::None => None,
            Regularizer::Dae(m) => Some(m.scratch(max_rows)),
            Regularizer::Deen(m) => Some(m.scratch(max_rows)),
        };
        EnergyScratch {
            capacity: max_rows,
            forward,
        }
    }

    /// The energy of each of `rows` transitions into `out[..rows]` (zero for `None`).
    /// `obs`, `act` and `next_obs` hold exactly `rows` rows each (`rows × obs_dim`,
    /// `rows × act_dim`, `rows × obs_dim`, sample-major); the dimensions are read from their
    /// lengths and checked against the model. Never allocates.
    pub fn energy(
        &self,
        obs: &[f32],
        act: &[f32],
        next_obs: &[f32],
        rows: usize,
        scratch: &mut EnergyScratch,
        out: &mut [f32],
    ) {
        assert!(
            scratch.fits(self, rows),
            "energy scratch of {} rows does not fit {rows} rows",
            scratch.capacity
        );
        assert!(out.len() >= rows, "output shorter than {rows} rows");
        if rows == 0 {
            return;
        }
        let (normalizer, forward) = match (self, scratch.forward.as_mut()) {
            (Regularizer::None, _) => {
                out[..rows].fill(0.0);
                return;
            }
            (Regularizer::Dae(m), Some(f)) => (m.normalizer(), f),
            (Regularizer::Deen(m), Some(f)) => (m.normalizer(), f),
            _ => unreachable!("checked by fits"),
        };
        fill_transitions(normalizer, obs, act, next_obs, rows, forward);
        match self {
            Regularizer::Dae(m) => m.energy_standardised(rows, forward, out),
            Regularizer::Deen(m) => {
                out[..rows].copy_from_slice(m.energy_standardised(rows, forward))
            }
            Regularizer::None => unreachable!(),
        }
    }
}

impl Regularizer {
    /// Buffers for [`Regularizer::energy_and_gradient`] on up to `max_rows` rows.
    pub fn grad_scratch(&self, max_rows: usize) -> EnergyGradScratch {
        let (forward, tape) = match self {
            Regularizer::None => (None, None),
            Regularizer::Dae(m) => (Some(m.scratch(max_rows)), None),
            Regularizer::Deen(m) => (None, Some(Tape::for_planning(m.mlp(), max_rows))),
        };
        EnergyGradScratch {
            capacity: max_rows,
            forward,
            tape,
        }
    }

    /// The energy of each of `rows` transitions into `out[..rows]` (as [`Regularizer::energy`])
    /// and the gradient gradient-based planning follows, `∂E/∂s`, `∂E/∂a`, `∂E/∂s'` into
    /// `d_obs`, `d_act`, `d_next` (sample-major, overwritten):
    /// - DAE: the penalty `‖g(x̃) − x̃‖²` (`x̃` standardised) with the gradient *stopped at the
    ///   autoencoder*, `∂E/∂x̃ = −2 (g(x̃) − x̃)`, as Boney et al. (2019) use it and the paper
    ///   describes it (§3: "stopping the gradient propagation through the denoising
    ///   autoencoder"): `g(x̃) − x̃ ≈ σ² ∇ log p` is their estimate of the score, so descending
    ///   the penalty moves `x` up the data density;
    /// - DEEN: the exact input gradient of its energy (a plain back-propagation);
    /// - none: zeros.
    ///
    /// The chain rule through the normaliser divides by each dimension's standard deviation.
    /// Never allocates.
    #[allow(clippy::too_many_arguments)]
    pub fn energy_and_gradient(
        &self,
        obs: &[f32],
        act: &[f32],
        next_obs: &[f32],
        rows: usize,
        scratch: &mut EnergyGradScratch,
        out: &mut [f32],
        d_obs: &mut [f32],
        d_act: &mut [f32],
        d_next: &mut [f32],
    ) {
        assert!(
            scratch.fits(self, rows),
            "energy gradient scratch of {} rows does not fit {rows} rows",
            scratch.capacity
        );
        let (o, a) = (obs.len() / rows.max(1), act.len() / rows.max(1));
        let parts = [(d_obs, o, 0), (d_act, a, o), (d_next, o, o + a)];
        match (self, scratch.forward.as_mut(), scratch.tape.as_mut()) {
            (Regularizer::None, _, _) => {
                out[..rows].fill(0.0);
                for (part, width, _) in parts {
                    part[..rows * width].fill(0.0);
                }
            }
            (Regularizer::Dae(m), Some(forward), _) => {
                let normalizer = m.normalizer();
                fill_transitions(normalizer, obs, act, next_obs, rows, forward);
                let ld = forward.ld();
                let (x, g) = m.mlp().forward_io(rows, forward);
                out[..rows].fill(0.0);
                for f in 0..m.dim() {
                    for (i, e) in out[..rows].iter_mut().enumerate() {
                        let r = g[f * ld + i] - x[f * ld + i];
                        *e += r * r;
                    }
                }
                for (part, width, offset) in parts {
                    for k in 0..width {
                        let f = offset + k;
                        let scale = -2.0 / normalizer.std()[f];
                        for i in 0..rows {
                            part[i * width + k] = scale * (g[f * ld + i] - x[f * ld + i]);
                        }
                    }
                }
            }
            (Regularizer::Deen(m), _, Some(tape)) => {
                let normalizer = m.normalizer();
                let ld = tape.ld();
                fill_standardised(normalizer, obs, act, next_obs, rows, tape.input_mut(), ld);
                let energy = m.mlp().forward_train(tape, rows);
                out[..rows].copy_from_slice(&energy[..rows]);
                let (_, out_grad) = tape.output_and_grad_mut();
                out_grad[..rows].fill(1.0);
                m.mlp().backward_input(tape);
                let grad = tape.input_grad();
                for (part, width, offset) in parts {
                    for k in 0..width {
                        let f = offset + k;
                        let inv = 1.0 / normalizer.std()[f];
                        for i in 0..rows {
                            part[i * width + k] = inv * grad[f * ld + i];
                        }
                    }
                }
            }
            _ => unreachable!("checked by fits"),
        }
    }
}

/// Writes the standardised vectors `[s, a, s']` of `rows` transitions feature-major into the
/// scratch's input.
fn fill_transitions(
    normalizer: &Normalizer,
    obs: &[f32],
    act: &[f32],
    next_obs: &[f32],
    rows: usize,
    forward: &mut ForwardScratch,
) {
    let ld = forward.ld();
    fill_standardised(
        normalizer,
        obs,
        act,
        next_obs,
        rows,
        forward.input_mut(),
        ld,
    );
}

/// Writes the standardised vectors `[s, a, s']` of `rows` transitions feature-major (row
/// stride `ld`) into `input`.
fn fill_standardised(
    normalizer: &Normalizer,
    obs: &[f32],
    act: &[f32],
    next_obs: &[f32],
    rows: usize,
    input: &mut [f32],
    ld: usize,
) {
    let (o, a) = (obs.len() / rows, act.len() / rows);
    assert!(
        obs.len() == rows * o
            && act.len() == rows * a
            && next_obs.len() == obs.len()
            && 2 * o + a == normalizer.dim(),
        "transitions of {} numbers expected; got {} / {} / {} floats for {rows} rows",
        normalizer.dim(),
        obs.len(),
        act.len(),
        next_obs.len()
    );
    for (part, width, offset) in [(obs, o, 0), (act, a, o), (next_obs, o, o + a)] {
        for k in 0..width {
            let f = offset + k;
            let row = &mut input[f * ld..f * ld + rows];
            for (i, v) in row.iter_mut().enumerate() {
                *v = normalizer.normalize(f, part[i * width + k]);
            }
        }
    }
}

#[cfg(test)]
mod tests;
