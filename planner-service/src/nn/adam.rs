//! The Adam optimiser (Kingma & Ba), with PyTorch's bias correction.
//!
//! Weight decay is not part of the optimiser: PETS adds an L2 penalty `λ/2 ‖W‖²` on the weights
//! to the loss (so its gradient `λ W` is then normalised by Adam like any other term), and the
//! models here do the same with [`add_weight_decay`]. Biases are not decayed.

use super::denormals;
use super::mlp::Mlp;
use super::simd::multiversion;

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
    fn adam_update(params: &mut [f32], grads: &[f32], m: &mut [f32], v: &mut [f32], k: [f32; 5]) {
        // k = [β1, β2, step size lr / (1 − β1ᵗ), 1 / √(1 − β2ᵗ), ε]
        let [b1, b2, step, inv_bc2, eps] = k;
        let n = params.len();
        let (grads, m, v) = (&grads[..n], &mut m[..n], &mut v[..n]);
        for i in 0..n {
            let g = grads[i];
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
        assert!(
            params.len() == self.m.len() && grads.len() == self.m.len(),
            "Adam state for {} parameters",
            self.m.len()
        );
        self.steps += 1;
        let t = self.steps as i32;
        let bc1 = 1.0 - self.beta1.powi(t);
        let bc2 = 1.0 - self.beta2.powi(t);
        let k = [
            self.beta1,
            self.beta2,
            self.learning_rate / bc1,
            1.0 / bc2.sqrt(),
            self.epsilon,
        ];
        let n = params.len();
        if n < PARALLEL_MIN || rayon::current_num_threads() < 2 {
            adam_update(params, grads, &mut self.m, &mut self.v, k);
            return;
        }
        // The update streams five arrays through memory: two cores move them nearly twice as
        // fast. The caller's floating-point mode is carried to the helper thread.
        let half = n / 2;
        let (p0, p1) = params.split_at_mut(half);
        let (g0, g1) = grads.split_at(half);
        let (m0, m1) = self.m.split_at_mut(half);
        let (v0, v1) = self.v.split_at_mut(half);
        let mode = denormals::current_mode();
        rayon::join(
            || adam_update(p0, g0, m0, v0, k),
            || denormals::with_mode(mode, || adam_update(p1, g1, m1, v1, k)),
        );
    }
}

/// Adds the gradient `λ W` of the L2 penalty `λ/2 ‖W‖²` on every weight matrix of `mlp`.
pub fn add_weight_decay(mlp: &Mlp, grads: &mut [f32], lambda: f32) {
    if lambda == 0.0 {
        return;
    }
    for l in 0..mlp.layers() {
        let range = mlp.weight_range(l);
        for (g, w) in grads[range.clone()].iter_mut().zip(&mlp.params()[range]) {
            *g += lambda * w;
        }
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
            [0.9, 0.999, 0.01 / bc1, 1.0 / bc2.sqrt(), 1e-8],
        );
        assert!(p == q, "the split update differs from the serial one");
        assert!(p.iter().any(|&x| x != 1.0));
    }

    #[test]
    fn weight_decay_touches_weights_only() {
        let mlp = Mlp::from_params(
            &[1, 2],
            crate::nn::activation::Activation::Swish,
            vec![3.0, -2.0, 5.0, 7.0],
        );
        let mut g = vec![0.0; 4];
        add_weight_decay(&mlp, &mut g, 0.5);
        assert_eq!(g, vec![1.5, -1.0, 0.0, 0.0]);
    }
}
