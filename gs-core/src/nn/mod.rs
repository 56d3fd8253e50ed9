//! Small dense networks: positional encoding, MLP forward/backward on a GEMM, and the
//! input assembly of the appearance network Phi and the shadow network Psi.
//!
//! Everything here is deterministic: work is split into fixed row blocks (independent of
//! the thread count) and reductions across blocks run in block order, so the same inputs
//! give bit-identical outputs on any number of threads.
//!
//! One training step of Phi for the Gaussians that survived culling (Psi is the same with
//! `ShadowNet`, visibilities, latents and a `SceneBox`):
//!
//! ```
//! use gs_core::nn::{AppearanceNet, PositionalEncoding, TapeMode};
//! # fn main() -> Result<(), gs_core::nn::NnError> {
//! let phi = AppearanceNet::new(72, PositionalEncoding::default(), 7)?;
//! let (features, means) = (vec![0.1f32; 2 * 72], vec![0.0f32, 0.0, 0.0, 0.5, 0.2, -0.1]);
//! let visible = [1u32, 0];
//! let (sun, camera) = ([0.0, 0.6, 0.8], [0.0, 0.0, 10.0]);
//! let mut input = Vec::new();
//! phi.assemble_input(&visible, &features, &means, sun, camera, &mut input)?;
//! let fwd = phi.mlp.forward_train(&input, visible.len(), TapeMode::Cache)?;
//! // fwd.output: one RGB row per visible Gaussian, in list order, for the rasterizer.
//! let d_rgb = vec![0.01f32; fwd.output.len()]; // from the rasterizer's backward
//! let mut d_phi = vec![0.0f32; phi.mlp.num_params()]; // accumulated; one Adam group
//! let mut d_input = vec![0.0f32; input.len()];
//! phi.mlp.backward(&input, &fwd, &d_rgb, &mut d_phi, Some(&mut d_input))?;
//! let (mut d_features, mut d_means) = (vec![0.0f32; 2 * 72], vec![0.0f32; 6]);
//! phi.scatter_input_grad(&visible, &means, camera, &d_input, &mut d_features, &mut d_means)?;
//! assert!(d_means.iter().any(|g| *g != 0.0));
//! # Ok(())
//! # }
//! ```

pub mod amx;
pub mod appearance;
pub mod avx2;
pub mod avx512;
pub mod bf16;
pub mod encoding;
pub mod error;
mod gather;
#[cfg(test)]
mod kernel_tests;
pub mod matmul;
pub mod mlp;
pub mod shadow_net;
#[cfg(target_arch = "x86_64")]
mod tiled;

pub use appearance::{AppearanceInputs, AppearanceNet};
pub use encoding::PositionalEncoding;
pub use error::NnError;
pub use matmul::{check_kernel_env, Bf16Kernel, F32Kernel, MatmulPrecision, Products};
pub use mlp::{HiddenActivation, Init, Mlp, MlpForward, TapeMode};
pub use shadow_net::{SceneBox, ShadowNet};
