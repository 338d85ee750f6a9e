//! Neural-network building blocks: plain MLPs with hand-written gradients, Adam, normalisers.
//!
//! No autodiff framework: the networks are MLPs with smooth activations, so the forward pass,
//! the parameter gradient, the input gradient and the DEEN double backprop are written out
//! ([`mlp`], [`backprop`], [`double_backprop`]) and each is checked against finite differences.
//! The time goes into [`matmul`] (register-blocked kernels, used instead of the `gemm` crate
//! because every `gemm` call allocates; they match or beat `gemm` on these shapes) and
//! [`activation`] (vectorised polynomial exp/log), both compiled for AVX-512/AVX2 and picked at
//! run time ([`simd`]). Inference ([`Mlp::forward`], the planner's hot loop) reads weights
//! packed once per model and fuses bias and activation into the kernel ([`lanes`]); it
//! never allocates once its [`ForwardScratch`] exists and the weights are packed. Training
//! threads flush denormals ([`denormals`]).
//!
//! Batches are feature-major throughout (see [`mlp`]).

pub mod activation;
pub mod adam;
pub mod aligned;
pub mod amx;
pub mod backprop;
pub mod cputime;
pub mod denormals;
pub mod double_backprop;
pub mod fastmath;
#[cfg(target_arch = "x86_64")]
pub mod fastmath256;
#[cfg(target_arch = "x86_64")]
pub mod fastmath512;
pub mod kernel_path;
#[cfg(target_arch = "x86_64")]
pub mod lanes;
pub mod matmul;
pub mod mlp;
pub mod normalizer;
pub mod peak;
#[cfg(test)]
pub(crate) mod reference;
pub mod simd;
pub mod train;
pub mod train_path;
pub mod vecops;

pub use activation::Activation;
pub use adam::Adam;
pub use backprop::Tape;
pub use denormals::FlushDenormals;
pub use double_backprop::InputGradTape;
pub use kernel_path::KernelPath;
pub use mlp::{ForwardScratch, Mlp, ShapeError};
pub use normalizer::Normalizer;
pub use proto::InferencePrecision as Precision;
pub use train::FitReport;
pub use train_path::TrainPath;
