//! Double backpropagation: the parameter gradient of a loss on a scalar network's *input
//! gradient*, as the DEEN objective `‖x − y + σ² ∂E/∂y‖²` needs.
//!
//! Notation (feature-major, one column per sample): `h₀ = y`, `zₗ = Wₗ₋₁ᵀ hₗ₋₁ + bₗ₋₁` and
//! `hₗ = σ(zₗ)` for hidden layers `l = 1..L−1`, `E = W_{L−1}ᵀ h_{L−1} + b_{L−1}`.
//!
//! **Input gradient** (reverse pass): `u_{L−1} = W_{L−1}` (the output is scalar, `∂E/∂E = 1`);
//! `δₗ = uₗ ⊙ σ'(zₗ)`; `uₗ₋₁ = Wₗ₋₁ δₗ`; the score is `s = ∂E/∂y = u₀`.
//!
//! **Its parameter gradient** (forward-over-reverse). A loss `L(s)` with `v = ∂L/∂s` has
//! `∇_θ L = ∇_θ ⟨s, v⟩ = ∇_θ (d/dε) E(y + εv) |₀ = (d/dε) ∇_θ E(y + εv) |₀`: the directional
//! derivative, along `v`, of the ordinary parameter gradient of `E`. That parameter gradient is
//! `∂E/∂Wₗ₋₁ = hₗ₋₁ δₗᵀ`, `∂E/∂bₗ₋₁ = δₗ 1`, so differentiating each quantity along `y + εv`
//! (dots denote `d/dε`):
//!
//! - tangent forward: `ḣ₀ = v`, `żₗ = Wₗ₋₁ᵀ ḣₗ₋₁`, `ḣₗ = σ'(zₗ) ⊙ żₗ`;
//! - tangent backward: `δ̇_L = 0`, `u̇ₗ = Wₗ δ̇ₗ₊₁`, `δ̇ₗ = u̇ₗ ⊙ σ'(zₗ) + uₗ ⊙ σ''(zₗ) ⊙ żₗ`;
//! - gradient: `∂L/∂Wₗ₋₁ = ḣₗ₋₁ δₗᵀ + hₗ₋₁ δ̇ₗᵀ`, `∂L/∂bₗ₋₁ = δ̇ₗ 1`; for the output layer
//!   (`δ_L = 1`, `δ̇_L = 0`) `∂L/∂W_{L−1} = ḣ_{L−1} 1` and `∂L/∂b_{L−1} = 0`.
//!
//! The cost is three passes' worth of products beyond the plain input gradient, and every
//! product has the batch as its short side, like the ordinary backward pass.

use super::aligned::{AlignedBuf, round_up};
use super::matmul::{Init, MatMut, MatRef, transpose};
use super::mlp::{Mlp, spans};
use super::train_path::{Products, TrainPath};
use super::vecops::{mul_add3, product2, product3, sum};

/// Buffers of one input-gradient pass and its double backpropagation, for batches of up to
/// `capacity` samples.
#[derive(Clone, Debug)]
pub struct InputGradTape {
    sizes: Vec<usize>,
    ld: usize,
    samples: usize,
    /// `h[0] = y`, `h[l]` hidden activations, `h[L] = E`.
    h: Vec<AlignedBuf>,
    /// `σ'(zₗ)`, `σ''(zₗ)` for hidden layer `l` at index `l − 1`.
    d1: Vec<AlignedBuf>,
    d2: Vec<AlignedBuf>,
    /// `uₗ = ∂E/∂hₗ` for `l = 0..L−1` (`u[0]` is the input gradient).
    u: Vec<AlignedBuf>,
    /// `δₗ` for hidden layer `l` at index `l − 1`.
    delta: Vec<AlignedBuf>,
    /// `v = ∂L/∂s`, written by the caller: the tangent `ḣ₀`.
    v: AlignedBuf,
    /// `żₗ`, `ḣₗ` for hidden layer `l` at index `l − 1`.
    zdot: Vec<AlignedBuf>,
    hdot: Vec<AlignedBuf>,
    /// Ping-pong buffers for `u̇ₗ`, turned into `δ̇ₗ` in place.
    udot: [AlignedBuf; 2],
    /// `[ḣₗ₋₁ hₗ₋₁]` side by side (feature-major, row stride `2 ld`) with a last row
    /// `[0ᵀ 1ᵀ]`, and `[δₗ; δ̇ₗ]ᵀ` (sample-major): the two factors of a layer's weight and
    /// bias gradient.
    hcat: AlignedBuf,
    gt: AlignedBuf,
    products: Products,
}

impl InputGradTape {
    /// Buffers for the scalar-output `mlp` on batches of up to `capacity` samples,
    /// multiplying in f32.
    pub fn new(mlp: &Mlp, capacity: usize) -> Self {
        Self::with_path(mlp, capacity, TrainPath::F32)
    }

    /// [`InputGradTape::new`] on the training path measured fastest for this network and
    /// batch (see [`TrainPath::measured`]): what a trainer uses.
    pub fn for_training(mlp: &Mlp, capacity: usize) -> Self {
        let path = TrainPath::measured(mlp.sizes(), mlp.activation(), capacity);
        Self::with_path(mlp, capacity, path)
    }

    /// [`InputGradTape::new`] with its products on `path`. Panics if this CPU cannot run it.
    pub fn with_path(mlp: &Mlp, capacity: usize, path: TrainPath) -> Self {
        assert_eq!(
            mlp.out_dim(),
            1,
            "the input gradient is taken of a scalar network"
        );
        let ld = round_up(capacity.max(1));
        let sizes = mlp.sizes().to_vec();
        let hidden = &sizes[1..sizes.len() - 1];
        let bufs = |dims: &[usize]| {
            dims.iter()
                .map(|&s| AlignedBuf::zeros(s * ld))
                .collect::<Vec<_>>()
        };
        let width = mlp.max_width();
        Self {
            h: bufs(&sizes),
            d1: bufs(hidden),
            d2: bufs(hidden),
            u: bufs(&sizes[..sizes.len() - 1]),
            delta: bufs(hidden),
            v: AlignedBuf::zeros(sizes[0] * ld),
            zdot: bufs(hidden),
            hdot: bufs(hidden),
            udot: [AlignedBuf::zeros(width * ld), AlignedBuf::zeros(width * ld)],
            hcat: AlignedBuf::zeros((width + 1) * 2 * ld),
            gt: AlignedBuf::zeros(2 * ld * round_up(width)),
            products: Products::new(path),
            sizes,
            ld,
            samples: 0,
        }
    }

    /// Row stride of every feature-major buffer (and the batch capacity).
    pub fn ld(&self) -> usize {
        self.ld
    }

    /// The kernels this tape's products run on.
    pub fn path(&self) -> TrainPath {
        self.products.path()
    }

    /// The feature-major input `y` to fill before [`Mlp::input_gradient_train`]: `in_dim × ld`.
    pub fn input_mut(&mut self) -> &mut [f32] {
        let n = self.sizes[0] * self.ld;
        &mut self.h[0].as_mut_slice()[..n]
    }

    /// The network's output `E` from the last pass (`1 × ld`).
    pub fn output(&self) -> &[f32] {
        &self.h[self.sizes.len() - 1].as_slice()[..self.ld]
    }

    /// The input `y` and its gradient `s = ∂E/∂y` from the last pass (`in_dim × ld` each), and
    /// the buffer (same shape) where the caller writes `v = ∂L/∂s` before
    /// [`Mlp::input_gradient_backward`].
    pub fn input_score_and_grad_mut(&mut self) -> (&[f32], &[f32], &mut [f32]) {
        let n = self.sizes[0] * self.ld;
        (
            &self.h[0].as_slice()[..n],
            &self.u[0].as_slice()[..n],
            &mut self.v.as_mut_slice()[..n],
        )
    }
}

impl Mlp {
    /// Forward pass and input gradient `s = ∂E/∂y` of this scalar network for the first
    /// `samples` columns of [`InputGradTape::input_mut`]; returns `s` (`in_dim × ld`).
    /// Records what [`Mlp::input_gradient_backward`] needs.
    pub fn input_gradient_train<'t>(
        &self,
        tape: &'t mut InputGradTape,
        samples: usize,
    ) -> &'t [f32] {
        assert_eq!(
            tape.sizes,
            self.sizes(),
            "tape built for another network shape"
        );
        assert!(
            samples <= tape.ld,
            "batch of {samples} exceeds the tape's {}",
            tape.ld
        );
        tape.samples = samples;
        tape.products.new_weights();
        let (ld, layers) = (tape.ld, self.layers());
        let sizes = self.sizes();
        for l in 0..layers {
            let (below, above) = tape.h.split_at_mut(l + 1);
            let z = above[0].as_mut_slice();
            tape.products.matmul_weights(
                MatMut::with_stride(z, sizes[l + 1], samples, ld),
                (l, MatRef::new(self.weight(l), sizes[l], sizes[l + 1]), true),
                MatRef::with_stride(below[l].as_slice(), sizes[l], samples, ld),
                Init::RowBias(self.bias(l)),
            );
            if l + 1 < layers {
                let (d1, d2) = (tape.d1[l].as_mut_slice(), tape.d2[l].as_mut_slice());
                for span in spans(sizes[l + 1], samples, ld) {
                    self.activation().apply_d2(
                        &mut z[span.clone()],
                        &mut d1[span.clone()],
                        &mut d2[span],
                    );
                }
            }
        }
        // u_{L−1}: every sample's column is the output layer's weight vector.
        let top = layers - 1;
        let w_out = self.weight(top);
        for (row, &w) in tape.u[top].as_mut_slice().chunks_mut(ld).zip(w_out) {
            row[..samples].fill(w);
        }
        for l in (1..layers).rev() {
            let delta = tape.delta[l - 1].as_mut_slice();
            let (u_l, d1) = (tape.u[l].as_slice(), tape.d1[l - 1].as_slice());
            for span in spans(sizes[l], samples, ld) {
                product2(&mut delta[span.clone()], &u_l[span.clone()], &d1[span]);
            }
            // u_{l−1} = W_{l−1} δ_l
            tape.products.matmul_weights(
                MatMut::with_stride(tape.u[l - 1].as_mut_slice(), sizes[l - 1], samples, ld),
                (
                    l - 1,
                    MatRef::new(self.weight(l - 1), sizes[l - 1], sizes[l]),
                    false,
                ),
                MatRef::with_stride(delta, sizes[l], samples, ld),
                Init::Zero,
            );
        }
        &tape.u[0].as_slice()[..sizes[0] * ld]
    }

    /// Overwrites `grads` (laid out as [`Mlp::params`]) with `∂L/∂θ` for the `v = ∂L/∂s`
    /// written into the tape (see [`InputGradTape::input_score_and_grad_mut`]) after
    /// [`Mlp::input_gradient_train`]. See the module docs for the derivation.
    pub fn input_gradient_backward(&self, tape: &mut InputGradTape, grads: &mut [f32]) {
        assert_eq!(grads.len(), self.params().len(), "gradient length");
        let (ld, samples, layers) = (tape.ld, tape.samples, self.layers());
        let sizes = self.sizes();
        // Tangent forward: ż_l = W_{l−1}ᵀ ḣ_{l−1}, ḣ_l = σ'(z_l) ⊙ ż_l.
        for l in 1..layers {
            let zdot = tape.zdot[l - 1].as_mut_slice();
            let hdot_prev = if l == 1 {
                tape.v.as_slice()
            } else {
                tape.hdot[l - 2].as_slice()
            };
            tape.products.matmul_weights(
                MatMut::with_stride(zdot, sizes[l], samples, ld),
                (
                    l - 1,
                    MatRef::new(self.weight(l - 1), sizes[l - 1], sizes[l]),
                    true,
                ),
                MatRef::with_stride(hdot_prev, sizes[l - 1], samples, ld),
                Init::Zero,
            );
            let (hdot, d1) = (tape.hdot[l - 1].as_mut_slice(), tape.d1[l - 1].as_slice());
            for span in spans(sizes[l], samples, ld) {
                product2(&mut hdot[span.clone()], &zdot[span.clone()], &d1[span]);
            }
        }
        // Output layer: ∂L/∂W_{L−1} = ḣ_{L−1} 1, ∂L/∂b_{L−1} = 0.
        let top = layers - 1;
        let hdot_top = if top == 0 {
            tape.v.as_slice()
        } else {
            tape.hdot[top - 1].as_slice()
        };
        let w_range = self.weight_range(top);
        for (g, row) in grads[w_range].iter_mut().zip(hdot_top.chunks(ld)) {
            *g = sum(&row[..samples]);
        }
        grads[self.bias_range(top)].fill(0.0);
        // Tangent backward, with each hidden layer's weight gradient as soon as δ̇ is known.
        let mut slot = 0;
        for l in (1..layers).rev() {
            let [a, b] = &mut tape.udot;
            let (ddot, udot_below) = if slot == 0 {
                (a.as_mut_slice(), b.as_mut_slice())
            } else {
                (b.as_mut_slice(), a.as_mut_slice())
            };
            let (u, d1, d2, zdot) = (
                tape.u[l].as_slice(),
                tape.d1[l - 1].as_slice(),
                tape.d2[l - 1].as_slice(),
                tape.zdot[l - 1].as_slice(),
            );
            for span in spans(sizes[l], samples, ld) {
                let s = span.clone();
                if l == top {
                    product3(&mut ddot[span], &u[s.clone()], &d2[s.clone()], &zdot[s]);
                } else {
                    mul_add3(
                        &mut ddot[span],
                        &d1[s.clone()],
                        &u[s.clone()],
                        &d2[s.clone()],
                        &zdot[s],
                    );
                }
            }
            // ∂L/∂W_{l−1} = ḣ_{l−1} δ_lᵀ + h_{l−1} δ̇_lᵀ, ∂L/∂b_{l−1} = δ̇_l 1.
            let (n_in, n_out) = (sizes[l - 1], sizes[l]);
            let hdot_prev = if l == 1 {
                tape.v.as_slice()
            } else {
                tape.hdot[l - 2].as_slice()
            };
            // One product with the batch twice over as its depth, `[ḣ h; 0ᵀ 1ᵀ] · [δ; δ̇]ᵀ`:
            // the 1 MB gradient block is written once instead of written and re-read, and
            // its last row, `0ᵀ δᵀ + 1ᵀ δ̇ᵀ`, is the bias gradient (one more kernel row
            // instead of a reduction call per output feature).
            let (hcat, gt) = (tape.hcat.as_mut_slice(), tape.gt.as_mut_slice());
            let h_prev = tape.h[l - 1].as_slice();
            for r in 0..n_in {
                let row = &mut hcat[r * 2 * ld..r * 2 * ld + 2 * samples];
                row[..samples].copy_from_slice(&hdot_prev[r * ld..r * ld + samples]);
                row[samples..].copy_from_slice(&h_prev[r * ld..r * ld + samples]);
            }
            let ones = &mut hcat[n_in * 2 * ld..n_in * 2 * ld + 2 * samples];
            ones[..samples].fill(0.0);
            ones[samples..].fill(1.0);
            // Rows of the transposes start on cache lines (aligned panel loads).
            let ldg = round_up(n_out);
            transpose(tape.delta[l - 1].as_slice(), n_out, samples, ld, gt, ldg);
            transpose(ddot, n_out, samples, ld, &mut gt[samples * ldg..], ldg);
            tape.products.matmul(
                MatMut::new(&mut grads[self.layer_range(l - 1)], n_in + 1, n_out),
                MatRef::with_stride(hcat, n_in + 1, 2 * samples, 2 * ld),
                MatRef::with_stride(gt, 2 * samples, n_out, ldg),
                Init::Zero,
            );
            if l > 1 {
                // u̇_{l−1} = W_{l−1} δ̇_l
                tape.products.matmul_weights(
                    MatMut::with_stride(udot_below, n_in, samples, ld),
                    (l - 1, MatRef::new(self.weight(l - 1), n_in, n_out), false),
                    MatRef::with_stride(ddot, n_out, samples, ld),
                    Init::Zero,
                );
            }
            slot = 1 - slot;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::reference;
    use crate::nn::train_path::tests::paths_and_activations;
    use rand::rngs::StdRng;
    use rand::{RngExt, SeedableRng};

    /// The double backprop's gradient of a batch is the sum of its samples' gradients within
    /// float rounding (1e-6 of the terms' magnitude), for a partial batch on a tape that ran a
    /// fuller one before: `⟨s, v⟩` is a sum over samples. The first layer's bias gradient is
    /// also checked against the gradient of the weights of an input that is 1 with no tangent
    /// in every sample: a bias row of the fused weight and bias product that is missing,
    /// scaled, stale or misplaced fails one of these.
    #[test]
    fn a_batch_gradient_is_the_sum_of_its_samples_gradients() {
        let mut rng = StdRng::seed_from_u64(12);
        let sizes = [4, 19, 13, 1];
        for (act, path) in paths_and_activations() {
            let mlp = Mlp::new(&sizes, act, &mut rng);
            let (all, batch, d) = (20, 6, 4);
            // Input feature 0 is 1 with no tangent (`v = 0`) in every sample: the gradient of
            // its weights, `ḣ₀ δ₁ᵀ + h₀ δ̇₁ᵀ = δ̇₁ᵀ`, is the first layer's bias gradient.
            let y: Vec<f32> = (0..all * d)
                .map(|i| match i % d {
                    0 => 1.0,
                    _ => rng.random_range(-2.0..2.0),
                })
                .collect();
            let v: Vec<f32> = (0..all * d)
                .map(|i| match i % d {
                    0 => 0.0,
                    _ => rng.random_range(-1.0..1.0),
                })
                .collect();
            let mut tape = InputGradTape::with_path(&mlp, all, path);
            let ld = tape.ld();
            let grads_of = |cols: std::ops::Range<usize>| -> Vec<f32> {
                let k = cols.len();
                transpose(
                    &y[cols.start * d..cols.end * d],
                    k,
                    d,
                    d,
                    tape.input_mut(),
                    ld,
                );
                mlp.input_gradient_train(&mut tape, k);
                let (_, _, v_in) = tape.input_score_and_grad_mut();
                transpose(&v[cols.start * d..cols.end * d], k, d, d, v_in, ld);
                let mut grads = vec![f32::NAN; mlp.params().len()];
                mlp.input_gradient_backward(&mut tape, &mut grads);
                grads
            };
            let what = format!("{act:?} on {path}");
            reference::assert_batch_gradient_sums_its_samples(&mlp, (all, batch), &what, grads_of);
        }
    }

    /// A DEEN-shaped loss `Σᵢ ‖xᵢ − yᵢ + σ² sᵢ‖² / n` of the input gradient `s`, differentiated by
    /// the double backprop and by central differences of the f64 reference.
    #[test]
    fn loss_on_input_gradient_matches_finite_differences() {
        let mut rng = StdRng::seed_from_u64(9);
        for (act, path) in paths_and_activations() {
            for sizes in [vec![3, 8, 6, 1], vec![2, 5, 1], vec![4, 1]] {
                let mlp = Mlp::new(&sizes, act, &mut rng);
                let (d, n, sigma2) = (sizes[0], 5, 0.3);
                let y: Vec<f32> = (0..n * d).map(|_| rng.random_range(-2.0..2.0)).collect();
                let x: Vec<f32> = (0..n * d).map(|_| rng.random_range(-2.0..2.0)).collect();

                let mut tape = InputGradTape::with_path(&mlp, n, path);
                let ld = tape.ld();
                transpose(&y, n, d, d, tape.input_mut(), ld);
                mlp.input_gradient_train(&mut tape, n);
                let (_, s, v) = tape.input_score_and_grad_mut();
                for f in 0..d {
                    for i in 0..n {
                        let r = x[i * d + f] - y[i * d + f] + sigma2 * s[f * ld + i];
                        v[f * ld + i] = 2.0 * sigma2 * r / n as f32;
                    }
                }
                let mut grads = vec![f32::NAN; mlp.params().len()];
                mlp.input_gradient_backward(&mut tape, &mut grads);

                let loss = |p: &[f64]| -> f64 {
                    (0..n)
                        .map(|i| {
                            let yi: Vec<f64> =
                                y[i * d..(i + 1) * d].iter().map(|&v| v as f64).collect();
                            let s = reference::input_gradient(&sizes, act, p, &yi);
                            (0..d)
                                .map(|f| {
                                    (x[i * d + f] as f64 - yi[f] + sigma2 as f64 * s[f]).powi(2)
                                })
                                .sum::<f64>()
                        })
                        .sum::<f64>()
                        / n as f64
                };
                let p64: Vec<f64> = mlp.params().iter().map(|&v| v as f64).collect();
                let fd = reference::finite_difference(&p64, loss);
                reference::assert_gradient(
                    path,
                    &grads,
                    &fd,
                    1e-4,
                    &format!("{act:?} {sizes:?} DEEN loss gradient on {path}"),
                );

                // The score itself matches the reference input gradient.
                for i in 0..n {
                    let yi: Vec<f64> = y[i * d..(i + 1) * d].iter().map(|&v| v as f64).collect();
                    let want = reference::input_gradient(&sizes, act, &p64, &yi);
                    let got: Vec<f32> = (0..d)
                        .map(|f| tape.input_score_and_grad_mut().1[f * ld + i])
                        .collect();
                    reference::assert_gradient(
                        path,
                        &got,
                        &want,
                        1e-4,
                        &format!("score on {path}"),
                    );
                }
            }
        }
    }
}
