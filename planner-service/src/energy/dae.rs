//! The denoising autoencoder regulariser of Boney et al. (2019): a network `g` trained to map
//! corrupted vectors `x + σε` back to `x`.
//!
//! The optimal denoiser is `g(y) = y + σ² ∇ log p_σ(y)`, so `g(y) − y` estimates the score of the
//! smoothed data density directly, and `‖g(x) − x‖²` serves as a penalty that is small where
//! the data is dense. Unlike DEEN's energy it is not a log-density (the paper's point), but it
//! is the baseline the paper compares with. Works in standardised coordinates like
//! [`super::deen::Deen`].

use super::denoiser::{Denoiser, DenoisingLoss, Workspace};
use crate::nn::aligned::AlignedBuf;
use crate::nn::vecops::add_squared_diff;
use crate::nn::{ForwardScratch, Mlp, Tape, TrainPath};

/// The DAE's loss: the network outputs the denoised vector.
#[derive(Clone, Copy, Debug)]
pub struct DaeLoss;

/// A denoising autoencoder on `dim`-dimensional vectors.
pub type Dae = Denoiser<DaeLoss>;

/// Buffers of one DAE training step, reused across steps.
pub type DaeWorkspace = Workspace<DaeLoss>;

/// The network's tape and the batch's clean vectors (feature-major), the regression target.
#[derive(Clone, Debug)]
pub struct DaeTape {
    tape: Tape,
    clean: AlignedBuf,
}

impl DenoisingLoss for DaeLoss {
    const NAME: &'static str = "a DAE";
    type Tape = DaeTape;

    fn outputs(dim: usize) -> usize {
        dim
    }

    fn tape(mlp: &Mlp, batch_size: usize, path: TrainPath) -> DaeTape {
        let tape = Tape::with_path(mlp, batch_size, path);
        let clean = AlignedBuf::zeros(mlp.in_dim() * tape.ld());
        DaeTape { tape, clean }
    }

    fn ld(tape: &DaeTape) -> usize {
        tape.tape.ld()
    }

    fn path(tape: &DaeTape) -> TrainPath {
        tape.tape.path()
    }

    /// `Σᵢ ‖g(xᵢ + σεᵢ) − xᵢ‖² / n`, per dimension with its own `σ_f` and weight (see
    /// [`Denoiser`]'s noise units; `σ` and 1 in standardised units). Its penalty at planning
    /// time is in standardised coordinates in either units.
    fn loss_and_grad(
        dae: &Dae,
        set: &[f32],
        batch: &[usize],
        tape: &mut DaeTape,
        eps: &[f32],
        grads: &mut [f32],
    ) -> f32 {
        let (d, b) = (dae.dim(), batch.len());
        let (noise, weights) = (dae.noise_scales(), dae.loss_weights());
        let DaeTape { tape, clean } = tape;
        let ld = tape.ld();
        let clean = clean.as_mut_slice();
        let y = tape.input_mut();
        for (col, &idx) in batch.iter().enumerate() {
            for (f, &x) in set[idx * d..(idx + 1) * d].iter().enumerate() {
                clean[f * ld + col] = x;
                y[f * ld + col] = x + noise[f] * eps[f * ld + col];
            }
        }
        dae.mlp().forward_train(tape, b);
        let (out, grad) = tape.output_and_grad_mut();
        let scale = 2.0 / b as f32;
        let mut total = 0.0f32;
        for (f, &w) in weights.iter().enumerate().take(d) {
            for i in f * ld..f * ld + b {
                let r = out[i] - clean[i];
                total += w * r * r;
                grad[i] = scale * w * r;
            }
        }
        dae.mlp().backward(tape, grads, false);
        total / b as f32
    }
}

impl Dae {
    /// Buffers for [`Dae::energy_standardised`] on up to `max_rows` vectors.
    pub fn scratch(&self, max_rows: usize) -> ForwardScratch {
        ForwardScratch::new(self.mlp(), max_rows)
    }

    /// Penalties `‖g(x) − x‖²` of `samples` *standardised* vectors already written
    /// feature-major into `scratch.input_mut()`, into `out[..samples]`. Never allocates.
    pub fn energy_standardised(
        &self,
        samples: usize,
        scratch: &mut ForwardScratch,
        out: &mut [f32],
    ) {
        let ld = scratch.ld();
        let (x, g) = self.mlp().forward_io(samples, scratch);
        let out = &mut out[..samples];
        out.fill(0.0);
        for f in 0..self.dim() {
            add_squared_diff(
                out,
                &g[f * ld..f * ld + samples],
                &x[f * ld..f * ld + samples],
            );
        }
    }

    /// The denoising displacement `g(x) − x` of raw vectors, in standardised units (it
    /// estimates `σ² ∇ log p_σ` there), sample-major. Allocates.
    pub fn displacement_rows(&self, rows: &[f32]) -> Vec<f32> {
        let mut x = rows.to_vec();
        self.normalizer().normalize_rows(&mut x);
        let mut g = self.mlp().forward_rows(&x);
        for (g, x) in g.iter_mut().zip(&x) {
            *g -= x;
        }
        g
    }
}
