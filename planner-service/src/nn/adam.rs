//! The Adam optimiser (Kingma & Ba), with PyTorch's bias correction.
//!
//! Weight decay is not a decoupled part of the optimiser: PETS adds an L2 penalty `λ/2 ‖W‖²` on
//! the weights to the loss (so its gradient `λ W` is then normalised by Adam like any other
//! term), and [`Adam::step_decaying`] does the same, adding `λ W` to each weight's gradient
//! inside the update's own pass over the parameters instead of in a pass of its own (the update
//! is bound by memory: a separate pass cost another read of every weight and gradient). Biases
//! are not decayed.

use super::denormals;
use super::mlp::Mlp;
use super::simd::multiversion;
use std::ops::Range;

/// Parameter vectors shorter than this are updated on one thread.
const PARALLEL_MIN: usize = 1 << 19;

/// Adam's state for one parameter vector.
#[derive(Clone, Debug, PartialEq)]
pub struct Adam {
    pub learning_rate: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub epsilon: f32,
    steps: u32,
    m: Vec<f32>,
    v: Vec<f32>,
}

multiversion! {
    fn adam_update(params: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32], k: [f32; 6]) {
        // k = [β1, β2, step size lr / (1 − β1ᵗ), 1 / √(1 − β2ᵗ), ε, weight decay λ]
        let [b1, b2, step, inv_bc2, eps, lambda] = k;
        let n = params.len();
        let (grads, m, v) = (&grads[..n], &mut m[..n], &mut v[..n]);
        for i in 0..n {
            let g = grads[i] + lambda * params[i];
            m[i] = b1 * m[i] + (1.0 - b1) * g;
            v[i] = b2 * v[i] + (1.0 - b2) * g * g;
            params[i] -= step * m[i] / (v[i].sqrt() * inv_bc2 + eps);
        }
    }
}

impl Adam {
    /// Fresh state for `n` parameters with the usual `β = (0.9, 0.999)`, `ε = 1e-8`.
    pub fn new(n: usize, learning_rate: f32) -> Self {
        Self {
            learning_rate,
            beta1: 0.9,
            beta2: 0.999,
            epsilon: 1e-8,
            steps: 0,
            m: vec![0.0; n],
            v: vec![0.0; n],
        }
    }

    /// Steps taken so far.
    pub fn steps(&self) -> u32 {
        self.steps
    }

    /// One update of `params` along `grads`.
    pub fn step(&mut self, params: &mut [f32], grads: &[f32]) {
        let k = self.next_step(params.len(), grads.len());
        self.update(params, grads, 0..params.len(), k, 0.0);
    }

    /// One update of `mlp`'s parameters along `grads` plus the gradient `λ W` of the L2
    /// penalty `λ/2 ‖W‖²` on its weight matrices (not its biases), in one pass.
    pub fn step_decaying(&mut self, mlp: &mut Mlp, grads: &[f32], lambda: f32) {
        let n = mlp.params().len();
        let k = self.next_step(n, grads.len());
        for l in 0..mlp.layers() {
            let weights = mlp.weight_range(l);
            let biases = weights.end..weights.end + mlp.sizes()[l + 1];
            self.update(mlp.params_mut(), grads, weights, k, lambda);
            self.update(mlp.params_mut(), grads, biases, k, 0.0);
        }
    }

    /// Counts a step and returns its coefficients (without the weight decay), after checking
    /// that `params` and `grads` have this state's length.
    fn next_step(&mut self, params: usize, grads: usize) -> [f32; 6] {
        assert!(
            params == self.m.len() && grads == self.m.len(),
            "Adam state for {} parameters",
            self.m.len()
        );
        self.steps += 1;
        let t = self.steps as i32;
        let bc1 = 1.0 - self.beta1.powi(t);
        let bc2 = 1.0 - self.beta2.powi(t);
        [
            self.beta1,
            self.beta2,
            self.learning_rate / bc1,
            1.0 / bc2.sqrt(),
            self.epsilon,
            0.0,
        ]
    }

    /// Updates the parameters in `range` with coefficients `k` and weight decay `lambda`.
    fn update(
        &mut self,
        params: &mut [f32],
        grads: &[f32],
        range: Range<usize>,
        mut k: [f32; 6],
        lambda: f32,
    ) {
        k[5] = lambda;
        let (p, g) = (&mut params[range.clone()], &grads[range.clone()]);
        let (m, v) = (&mut self.m[range.clone()], &mut self.v[range]);
        let n = p.len();
        if n < PARALLEL_MIN || rayon::current_num_threads() < 2 {
            adam_update(p, g, m, v, k);
            return;
        }
        // The update streams five arrays through memory: two cores move them nearly twice as
        // fast. The caller's floating-point mode is carried to the helper thread.
        let half = n / 2;
        let (p0, p1) = p.split_at_mut(half);
        let (g0, g1) = g.split_at(half);
        let (m0, m1) = m.split_at_mut(half);
        let (v0, v1) = v.split_at_mut(half);
        let mode = denormals::current_mode();
        rayon::join(
            || adam_update(p0, g0, m0, v0, k),
            || denormals::with_mode(mode, || adam_update(p1, g1, m1, v1, k)),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_step_moves_each_parameter_by_the_learning_rate() {
        // With bias correction, Adam's first step is lr · sign(g) (up to ε).
        let mut adam = Adam::new(3, 0.1);
        let mut p = vec![1.0, 2.0, 3.0];
        adam.step(&mut p, &[0.5, -4.0, 0.0]);
        assert!(
            (p[0] - 0.9).abs() < 1e-6 && (p[1] - 2.1).abs() < 1e-6 && p[2] == 3.0,
            "{p:?}"
        );
        assert_eq!(adam.steps(), 1);
    }

    #[test]
    fn minimises_an_ill_conditioned_quadratic() {
        // f(p) = Σ cᵢ (pᵢ − 1)² with curvatures four orders of magnitude apart.
        let c = [100.0f32, 1.0, 0.01];
        let mut adam = Adam::new(3, 0.01);
        let mut p = vec![0.0f32; 3];
        for _ in 0..5000 {
            let g: Vec<f32> = p.iter().zip(&c).map(|(p, c)| 2.0 * c * (p - 1.0)).collect();
            adam.step(&mut p, &g);
        }
        assert!(p.iter().all(|v| (v - 1.0).abs() < 0.02), "{p:?}");
    }

    #[test]
    fn parallel_update_equals_serial_update() {
        let n = PARALLEL_MIN + 37;
        let grads: Vec<f32> = (0..n).map(|i| ((i * 31) % 17) as f32 - 8.0).collect();
        let mut adam = Adam::new(n, 0.01);
        let mut p = vec![1.0f32; n];
        adam.step(&mut p, &grads);
        let (mut m, mut v, mut q) = (vec![0.0; n], vec![0.0; n], vec![1.0f32; n]);
        let (bc1, bc2) = (1.0 - 0.9f32.powi(1), 1.0 - 0.999f32.powi(1));
        adam_update(
            &mut q,
            &grads,
            &mut m,
            &mut v,
            [0.9, 0.999, 0.01 / bc1, 1.0 / bc2.sqrt(), 1e-8, 0.0],
        );
        assert!(p == q, "the split update differs from the serial one");
        assert!(p.iter().any(|&x| x != 1.0));
    }

    /// The decayed step is the step along the gradient with `λ W` added to every weight's
    /// component and nothing to the biases', bit for bit, step after step.
    #[test]
    fn a_decaying_step_adds_the_penalty_gradient_of_the_weights_only() {
        // 2 → 3 → 1: weights 0..6, biases 6..9, weights 9..12, bias 12.
        let params: Vec<f32> = (0..13).map(|i| 0.3 * i as f32 - 1.7).collect();
        let mut mlp = Mlp::from_params(
            &[2, 3, 1],
            crate::nn::activation::Activation::Swish,
            params.clone(),
        );
        let (mut decaying, mut plain) = (Adam::new(13, 0.01), Adam::new(13, 0.01));
        let mut reference = params;
        let lambda = 0.5;
        let weight = |i: usize| !(6..9).contains(&i) && i != 12;
        for step in 0..3 {
            let grads: Vec<f32> = (0..13).map(|i| ((i * 7 + step) % 5) as f32 - 2.0).collect();
            let with_penalty: Vec<f32> = grads
                .iter()
                .zip(&reference)
                .enumerate()
                .map(|(i, (g, w))| if weight(i) { g + lambda * w } else { *g })
                .collect();
            plain.step(&mut reference, &with_penalty);
            decaying.step_decaying(&mut mlp, &grads, lambda);
            assert_eq!(mlp.params(), &reference[..], "step {step}");
        }
        assert_eq!(decaying, plain);
    }
}
