//! The device engine interface: what the Sun-aware model and trainer need from a compute
//! device other than the CPU. gs-core defines it and runs everything on the CPU itself; a
//! backend crate (`gs-wgpu`) implements it, and the binaries choose one at start
//! ([`Backend`]), so gs-core never names a device API.
//!
//! An [`Engine`] renders (the camera pass's blend and the shadow pass) and opens
//! [`ResidentTraining`] states: the trainer's whole state (Gaussians, network weights,
//! every Adam state, the densification statistics) on the device for a batch of steps,
//! uploaded before and downloaded after (`SunAwareTrainer::step_many`).
//!
//! Invariants: an engine declares the model configurations it runs
//! ([`Engine::supports`]) and the model refuses to move to it otherwise, with the engine's
//! reason; a device failure is an error, never a silent fallback to the CPU; the backend
//! is no part of a model's value or of its checkpoint.

use std::sync::Arc;

use glam::Vec3;

use super::config::SunAwareConfig;
use super::error::SunAwareError;
use super::model::SunAwareModel;
use super::trainer::{FlatAdam, StepTimings};
use crate::camera::Camera;
use crate::densify::DensifyStats;
use crate::optim::{Adam, GroupRates};
use crate::raster::{GaussianView, RasterSettings};

/// Where the Sun-aware model renders and trains.
#[derive(Clone, Debug, Default)]
pub enum Backend {
    /// Everything on the CPU (`crate::raster`, `crate::sunaware::light`, `crate::nn`,
    /// `crate::optim`): the reference.
    #[default]
    Cpu,
    /// A device engine (e.g. `gs_wgpu::WgpuEngine`). A missing adapter is an error when
    /// the engine is opened, never a silent fallback.
    Device(Arc<dyn Engine>),
}

impl Backend {
    /// The device in words (`None` on the CPU).
    pub fn describe(&self) -> Option<String> {
        match self {
            Backend::Cpu => None,
            Backend::Device(engine) => Some(engine.describe()),
        }
    }
}

/// Opens a device engine; `deterministic` asks for bit-identical results from run to run.
/// The error is the device's reason, in words.
pub type OpenEngine = fn(deterministic: bool) -> Result<Arc<dyn Engine>, String>;

/// The device engines a binary was built with, by [`super::BackendKind`]: the
/// binaries fill it from their cargo features (`None`: not compiled in).
#[derive(Clone, Copy, Debug, Default)]
pub struct DeviceEngines {
    pub wgpu: Option<OpenEngine>,
}

/// The camera pass's render on a device: per pixel `channels` values and alpha, per
/// Gaussian whether it survived the projection and its screen radius.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DeviceRender {
    /// `H * W * channels`, row-major.
    pub color: Vec<f32>,
    /// `H * W`.
    pub alpha: Vec<f32>,
    pub visible: Vec<bool>,
    pub radii_px: Vec<f32>,
}

/// A compute device the Sun-aware model can render and train on.
pub trait Engine: Send + Sync + std::fmt::Debug {
    /// The device in words (adapter, driver, API).
    fn describe(&self) -> String;

    /// `Ok` when this engine runs models of `config`; otherwise why not, naming the
    /// setting (the model refuses to move to the engine with this reason).
    fn supports(&self, config: &SunAwareConfig) -> Result<(), String>;

    /// The camera pass's blend of `view` (projection, sort and binning included).
    fn render(
        &self,
        camera: &Camera,
        view: &GaussianView,
        settings: &RasterSettings,
    ) -> Result<DeviceRender, SunAwareError>;

    /// `V_i` of every Gaussian of `model` for a camera position and a unit Sun vector
    /// (the shadow pass, `crate::sunaware::sun_visibility::sun_visibility` on the CPU).
    fn sun_visibility(
        &self,
        model: &SunAwareModel,
        camera_position_m: Vec3,
        sun_dir: Vec3,
    ) -> Result<Vec<f32>, SunAwareError>;

    /// A device-resident training state for one trainer (kernels compiled, no state yet:
    /// [`ResidentTraining::upload`] puts one there).
    fn resident(&self) -> Result<Box<dyn ResidentTraining>, SunAwareError>;
}

/// One resident step's inputs: an observation, the Gaussians' per-group rates and the
/// networks'.
#[derive(Clone, Copy, Debug)]
pub struct SunAwareStepInput<'a> {
    pub camera: &'a Camera,
    /// Unit vector towards the Sun, target body frame (normalised by the caller).
    pub sun_dir: Vec3,
    /// `H * W * 3` RGB.
    pub target: &'a [f32],
    /// Optional `H * W` foreground weights in [0, 1].
    pub mask: Option<&'a [f32]>,
    pub rates: &'a GroupRates,
    /// Active SH degree (configuration (a); unused with the appearance network).
    pub sh_degree: u32,
    pub appearance_lr: f32,
    pub shadow_lr: f32,
}

/// What one resident step did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SunAwareStepReport {
    /// A non-finite or degenerate value somewhere in the step: nothing was changed.
    pub refused: bool,
    /// Steps redone because a sort outgrew its capacity (0 or 1).
    pub sort_retries: usize,
    /// Gaussians whose rasterizer gradient came out non-finite and was zeroed.
    pub dropped_nonfinite: usize,
    /// Photometric loss, its parts (masked means), and `lambda_iso L_iso`.
    pub loss: f32,
    pub l1: f32,
    pub ssim: f32,
    pub iso: f32,
    /// Gaussians that survived the projection.
    pub visible: usize,
    /// The networks' rows: the Gaussians the blend reads with
    /// `skip_noncontributing_in_mlp`, else `visible`.
    pub network_rows: usize,
    /// (tile, Gaussian) pairs blended in the camera pass and in the light pass.
    pub tile_entries: usize,
    pub light_entries: usize,
    /// Wall time of the step, recording and waiting included, ms.
    pub total_ms: f64,
    /// Device time per stage where the device can measure it (else zeros; `total_ms` is
    /// always set): `project_ms` the rasterizer rows, the camera pass's projection, sort
    /// and binning and the networks' list (contribution pass included), `shadow_pass_ms`
    /// the light pass, `phi_forward_ms`/`psi_forward_ms` the networks' input assembly,
    /// forward and scatter, `blend_forward_ms` the blend, `loss_ms` `RGB * S`, the loss and
    /// its backward, `blend_backward_ms` the whole rasterizer backward, `phi_backward_ms`
    /// the geometry gradients and Phi's backward, `psi_backward_ms` Psi's,
    /// `optimizer_ms` the checks, statistics and every Adam step.
    pub stages: StepTimings,
}

/// A trainer's state on a device (see the module header).
pub trait ResidentTraining: Send + std::fmt::Debug {
    /// Replaces the device state with the trainer's parts: the model's Gaussians and
    /// networks, the three optimisers and the statistics.
    fn upload(
        &mut self,
        model: &SunAwareModel,
        adam: &Adam,
        appearance_adam: &FlatAdam,
        shadow_adam: &FlatAdam,
        stats: &DensifyStats,
    ) -> Result<(), SunAwareError>;

    /// One training step of `model`'s configuration on the device state (the model
    /// supplies the settings, the scene box and the networks' shapes; its host values are
    /// not read).
    fn step(
        &mut self,
        model: &SunAwareModel,
        input: &SunAwareStepInput,
    ) -> Result<SunAwareStepReport, SunAwareError>;

    /// Copies the device state into the trainer's parts (same shapes as uploaded).
    fn download(
        &self,
        model: &mut SunAwareModel,
        adam: &mut Adam,
        appearance_adam: &mut FlatAdam,
        shadow_adam: &mut FlatAdam,
        stats: &mut DensifyStats,
    ) -> Result<(), SunAwareError>;
}
