//! gs-core: the Gaussian splatting engine. Model storage, camera, rasterizer (forward and
//! backward), colour models, losses, optimiser, densification and model files.
//!
//! No bus, no async, no file formats beyond the model's own (PLY, checkpoints).

pub mod camera;
pub mod model;

pub use camera::{Camera, Intrinsics};
pub use model::{GaussianModel, ModelError, ModelLayout, Param, ParamSet};
