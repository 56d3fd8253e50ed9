//! gs-core: the Gaussian splatting engine. Model storage, camera, rasterizer (forward and
//! backward), colour models, losses, optimiser, densification and model files.
//!
//! No bus, no async, no file formats beyond the model's own (PLY, checkpoints), and no
//! device code: a GPU backend (crate gs-wgpu) implements [`engine::Engine`].

pub mod camera;
pub mod densify;
pub mod fpmode;
pub mod heap;
pub mod hull;
pub mod init;
pub mod loss;
pub mod machine;
pub mod model;
pub mod nn;
pub mod optim;
pub mod ply;
pub mod raster;
pub mod regularizer;
pub mod rng;
pub mod sh;
pub mod srgb;
pub mod sunaware;

/// The device engine interface (`sunaware::engine`), at the root for the backend crates.
pub use sunaware::engine;

pub use camera::{Camera, Intrinsics};
pub use model::{GaussianModel, ModelError, ModelLayout, Param, ParamSet};
