//! The error type of the Sun-aware pipeline: every failure of a lower layer, wrapped, plus
//! configuration, observation and checkpoint errors with a message saying what is wrong.

use crate::densify::DensifyError;
use crate::init::InitError;
use crate::loss::LossError;
use crate::model::ModelError;
use crate::nn::NnError;
use crate::optim::OptimError;
use crate::ply::PlyError;
use crate::raster::RasterError;
use crate::regularizer::RegularizerError;
use crate::sh::ShError;

/// Error from the Sun-aware model, trainer, checkpoint or export.
#[derive(Debug)]
pub enum SunAwareError {
    /// A setting is out of range; the message names it.
    Config(String),
    /// An observation (image, mask, camera, Sun vector) is unusable; the message says why.
    BadObservation(String),
    /// A checkpoint is malformed, truncated, of another version or fails its checksum.
    Checkpoint(String),
    Io(std::io::Error),
    Raster(RasterError),
    Nn(NnError),
    Loss(LossError),
    Optim(OptimError),
    Densify(DensifyError),
    Model(ModelError),
    Regularizer(RegularizerError),
    Sh(ShError),
    Init(InitError),
    Ply(PlyError),
    /// A device backend failed (device, pipeline, readback, sizes beyond the device's
    /// limits); the message is the backend's. Never raised on the CPU backend.
    Gpu(String),
}

impl std::fmt::Display for SunAwareError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SunAwareError::Config(m) => write!(f, "invalid Sun-aware configuration: {m}"),
            SunAwareError::BadObservation(m) => write!(f, "unusable observation: {m}"),
            SunAwareError::Checkpoint(m) => write!(f, "checkpoint: {m}"),
            SunAwareError::Io(e) => write!(f, "i/o: {e}"),
            SunAwareError::Raster(e) => write!(f, "rasterizer: {e}"),
            SunAwareError::Nn(e) => write!(f, "network: {e}"),
            SunAwareError::Loss(e) => write!(f, "loss: {e}"),
            SunAwareError::Optim(e) => write!(f, "optimiser: {e}"),
            SunAwareError::Densify(e) => write!(f, "densification: {e}"),
            SunAwareError::Model(e) => write!(f, "model: {e}"),
            SunAwareError::Regularizer(e) => write!(f, "regulariser: {e}"),
            SunAwareError::Sh(e) => write!(f, "spherical harmonics: {e}"),
            SunAwareError::Init(e) => write!(f, "initialisation: {e}"),
            SunAwareError::Ply(e) => write!(f, "PLY: {e}"),
            SunAwareError::Gpu(m) => write!(f, "device backend: {m}"),
        }
    }
}

impl std::error::Error for SunAwareError {}

macro_rules! wrap {
    ($variant:ident, $ty:ty) => {
        impl From<$ty> for SunAwareError {
            fn from(e: $ty) -> Self {
                SunAwareError::$variant(e)
            }
        }
    };
}

wrap!(Io, std::io::Error);
wrap!(Raster, RasterError);
wrap!(Nn, NnError);
wrap!(Loss, LossError);
wrap!(Optim, OptimError);
wrap!(Densify, DensifyError);
wrap!(Model, ModelError);
wrap!(Regularizer, RegularizerError);
wrap!(Sh, ShError);
wrap!(Init, InitError);
wrap!(Ply, PlyError);
