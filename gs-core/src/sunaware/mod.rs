//! The paper's Sun-aware Gaussian splatting: configurations (a)-(d) of its Table I.
//!
//! - (a) plain 3DGS, SH colour;
//! - (b) + the appearance MLP Phi: per-Gaussian 72-D feature, the Sun vector and the view
//!   vector (target body frame) through `gamma_L`, RGB out;
//! - (c) + shadow splatting: per-Gaussian Sun visibility `V_i` from a light camera
//!   ([`sun_visibility`]), refined by the shadow network Psi, splatted from the camera as one more channel
//!   `S`; the image is `RGB * S`;
//! - (d) + the isotropic scale loss `lambda_iso L_iso`.
//!
//! Modules: [`config`] (variants and settings), [`keys`] (the settings and rates by name, as
//! files write them), [`sun_visibility`] (the Sun visibility pass),
//! [`model`] (model, forward and backward of one image), [`shading`] (an optional
//! Lambertian factor from a normal and the Sun, beyond the paper), [`trainer`] (Adam, steps,
//! densification, evaluation), [`checkpoint`] (bit-exact save/load), [`export`] (PLY baked
//! for one Sun and view), [`synthetic`] (a Sun-lit test scene with self-shadowing).
//!
//! Frames: the model's world frame IS the target body frame. Cameras, Sun vectors and
//! means are all expressed in it.

pub mod checkpoint;
pub mod config;
pub mod engine;
pub mod error;
pub mod export;
pub mod keys;
pub mod model;
pub mod shading;
pub mod sun_visibility;
pub mod synthetic;
pub mod trainer;

pub use config::{
    AppearanceInputs, BackendKind, ColourSpace, LightConfig, LightProjection, Shading,
    ShadowRefinement, SunAwareConfig, SunAwareRates, Variant,
};
pub use error::SunAwareError;
pub use keys::{ModelKey, RateOverrides};
pub use model::{FramePass, SunAwareGrads, SunAwareModel};
pub use trainer::{Observation, StepStats, StepTimings, SunAwareTrainer, ViewScore};
