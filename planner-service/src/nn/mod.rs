//! Neural-network building blocks: MLPs with hand-written gradients, Adam, normalisers.

pub mod activation;
pub mod aligned;
pub mod backprop;
pub mod denormals;
pub mod double_backprop;
pub mod fastmath;
pub mod matmul;
pub mod mlp;
#[cfg(test)]
mod reference;
pub mod simd;
