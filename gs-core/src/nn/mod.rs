//! Small dense networks: positional encoding, MLP forward/backward on a GEMM, and the
//! input assembly of the appearance network Phi and the shadow network Psi.
//!
//! Everything here is deterministic: work is split into fixed row blocks (independent of
//! the thread count) and reductions across blocks run in block order, so the same inputs
//! give bit-identical outputs on any number of threads.

pub mod appearance;
pub mod encoding;
pub mod error;
mod gather;
pub mod matmul;
pub mod mlp;
mod rng;
pub mod shadow;

pub use appearance::AppearanceNet;
pub use encoding::PositionalEncoding;
pub use error::NnError;
pub use mlp::{HiddenActivation, Init, Mlp, MlpForward, TapeMode};
pub use shadow::{SceneBox, ShadowNet};
