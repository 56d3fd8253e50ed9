//! Training of a [`SunAwareModel`]: loss, Adam over every Gaussian group and both networks,
//! densification, rendering and evaluation.
//!
//! One [`SunAwareTrainer::step`] = forward, `(1 - l) L1 + l (1 - SSIM)` on the (masked)
//! image, `+ lambda_iso L_iso` for configuration (d), backward, Adam. The position rate
//! decays log-linearly from `position_init` to `position_final` (times the scene extent)
//! as `lr_progress_in_round` goes from 0 to 1: the online trainer restarts it every round
//! (the paper's sawtooth). Other groups keep constant rates, as in 3DGS.
//!
//! Invariants:
//! - a step whose render, loss or any gradient is non-finite changes nothing but the
//!   `skipped_nonfinite` counter (NaN/Inf never enter the parameters or moments);
//! - all randomness (densification) comes from SplitMix64 streams seeded by
//!   `(config.seed, densify_count)`, so the trainer's whole state is plain data that a
//!   checkpoint restores exactly;
//! - the scene extent is the scene box's diagonal (the target's size): it scales the
//!   position rate and the clone/split boundary.

use std::time::Instant;

use glam::Vec3;

use super::engine::{Backend, ResidentTraining, SunAwareStepInput};
use crate::camera::Camera;
use crate::densify::{densify_and_prune, DensifyConfig, DensifyReport, DensifyStats};
use crate::init::SplitMix64;
use crate::loss::{photometric_loss, psnr, ssim, ImageShape, SSIM_WINDOW};
use crate::model::Param;
use crate::optim::{Adam, GroupRates};
use crate::raster::bin::TileSelection;
use crate::raster::RasterSettings;
use crate::regularizer::IsotropicLoss;

use super::error::SunAwareError;
use super::model::{BackwardTimings, ForwardTimings, FramePass, SunAwareGrads, SunAwareModel};
use super::sun_visibility::box_sphere;

/// One training or evaluation image.
#[derive(Clone, Copy, Debug)]
pub struct Observation<'a> {
    pub camera: Camera,
    /// Unit vector from the target towards the Sun, target body frame.
    pub sun_dir: Vec3,
    /// `H * W * 3` RGB in [0, 1], pixel-major.
    pub image: &'a [f32],
    /// Optional `H * W` foreground weights in [0, 1].
    pub mask: Option<&'a [f32]>,
}

impl Observation<'_> {
    pub fn shape(&self) -> ImageShape {
        let k = &self.camera.intrinsics;
        ImageShape::new(k.width as usize, k.height as usize, 3)
    }

    /// Sizes, finiteness and ranges; the error says what is wrong.
    pub fn validate(&self) -> Result<(), SunAwareError> {
        let bad = |m: String| Err(SunAwareError::BadObservation(m));
        let shape = self.shape();
        if shape.pixels() == 0 {
            return bad("camera image size is zero".into());
        }
        if self.image.len() != shape.values() {
            return bad(format!(
                "image has {} values, the camera needs {} (H * W * 3)",
                self.image.len(),
                shape.values()
            ));
        }
        if let Some(i) = self.image.iter().position(|v| !v.is_finite()) {
            return bad(format!("image value {i} is not finite"));
        }
        if !(self.sun_dir.is_finite() && self.sun_dir.length_squared() > 1e-12) {
            return bad(format!(
                "Sun vector {:?} is not finite and non-zero",
                self.sun_dir
            ));
        }
        if let Some(mask) = self.mask {
            if mask.len() != shape.pixels() {
                return bad(format!(
                    "mask has {} values, the camera needs {} (H * W)",
                    mask.len(),
                    shape.pixels()
                ));
            }
            if let Some(i) = mask.iter().position(|v| !(0.0..=1.0).contains(v)) {
                return bad(format!("mask value {i} is not in [0, 1]"));
            }
            if mask.iter().all(|&v| v == 0.0) {
                return bad("mask is zero everywhere".into());
            }
        }
        Ok(())
    }
}

/// Wall-clock split of one step by stage, milliseconds (`std::time::Instant`, a few tens
/// of nanoseconds per stage; timing only reads clocks, so the arithmetic of a step is the
/// same with or without anyone looking at it).
///
/// Invariant: the stages are disjoint intervals inside the step, so
/// [`StepTimings::stage_sum_ms`] never exceeds `total_ms` (up to the rounding of the
/// conversion to floating-point milliseconds); [`StepTimings::other_ms`] is the rest
/// (validation, bookkeeping, buffer allocation between stages).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepTimings {
    /// Projection of the Gaussians: the culling pass that fixes the networks' batch and
    /// the rasterizer's own projection.
    pub project_ms: f64,
    /// Depth sort and tile binning.
    pub sort_bin_ms: f64,
    /// The alpha-only pass that finds the Gaussians the blend reads, so the networks run
    /// on those alone (`SunAwareConfig::skip_noncontributing_in_mlp`; 0 when off).
    pub contribution_ms: f64,
    /// The light camera's pass that gives `V_i` (configurations c-d).
    pub shadow_pass_ms: f64,
    /// Phi forward with its input assembly (SH evaluation in configuration a).
    pub phi_forward_ms: f64,
    /// Psi forward with its input assembly.
    pub psi_forward_ms: f64,
    /// Tile blending, untiling and the `RGB * S` product.
    pub blend_forward_ms: f64,
    /// L1 + SSIM value and image gradient, plus `L_iso` and its gradient.
    pub loss_ms: f64,
    /// `d(RGB, S)` from `d(RGB * S)` and the tile blending backward.
    pub blend_backward_ms: f64,
    /// Per-Gaussian sum of the blend records, projection backward and gradient gather.
    pub project_backward_ms: f64,
    /// Phi backward with its gradient gather and scatter (SH backward in configuration a).
    pub phi_backward_ms: f64,
    /// Psi backward with its gradient gather and scatter.
    pub psi_backward_ms: f64,
    /// Adam on every group and both networks, densification statistics.
    pub optimizer_ms: f64,
    /// The whole step.
    pub total_ms: f64,
}

impl StepTimings {
    /// Stage names and times in pipeline order (`total_ms` not included).
    pub fn stages(&self) -> [(&'static str, f64); 13] {
        [
            ("project", self.project_ms),
            ("sort_bin", self.sort_bin_ms),
            ("contribution", self.contribution_ms),
            ("shadow_pass", self.shadow_pass_ms),
            ("phi_forward", self.phi_forward_ms),
            ("psi_forward", self.psi_forward_ms),
            ("blend_forward", self.blend_forward_ms),
            ("loss", self.loss_ms),
            ("blend_backward", self.blend_backward_ms),
            ("project_backward", self.project_backward_ms),
            ("phi_backward", self.phi_backward_ms),
            ("psi_backward", self.psi_backward_ms),
            ("optimizer", self.optimizer_ms),
        ]
    }

    /// Sum of the stage times.
    pub fn stage_sum_ms(&self) -> f64 {
        self.stages().iter().map(|(_, t)| t).sum()
    }

    /// Time of the step outside every named stage.
    pub fn other_ms(&self) -> f64 {
        self.total_ms - self.stage_sum_ms()
    }

    /// Both networks' forward.
    pub fn mlp_forward_ms(&self) -> f64 {
        self.phi_forward_ms + self.psi_forward_ms
    }

    /// Both networks' backward.
    pub fn mlp_backward_ms(&self) -> f64 {
        self.phi_backward_ms + self.psi_backward_ms
    }

    fn add_forward(&mut self, f: &ForwardTimings) {
        self.project_ms += f.cull_ms + f.raster.project_ms;
        self.sort_bin_ms += f.raster.sort_bin_ms;
        self.contribution_ms += f.contribution_ms;
        self.shadow_pass_ms += f.shadow_pass_ms;
        self.phi_forward_ms += f.phi_forward_ms;
        self.psi_forward_ms += f.psi_forward_ms;
        self.blend_forward_ms += f.raster.blend_ms + f.compose_ms;
    }

    fn add_backward(&mut self, b: &BackwardTimings) {
        self.blend_backward_ms += b.compose_ms + b.raster.blend_ms;
        self.project_backward_ms += b.raster.reduce_project_ms + b.raster_other_ms;
        self.phi_backward_ms += b.phi_backward_ms;
        self.psi_backward_ms += b.psi_backward_ms;
    }
}

/// What one step did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepStats {
    /// Steps applied so far (after this one).
    pub step: u64,
    /// Total loss (photometric + weighted L_iso).
    pub loss: f32,
    pub l1: f32,
    pub ssim: f32,
    /// `lambda_iso * L_iso` (0 unless configuration d).
    pub iso: f32,
    /// Gaussians that survived culling.
    pub visible: usize,
    /// Rows each network evaluated: the Gaussians the blend reads
    /// (`skip_noncontributing_in_mlp`), else `visible`.
    pub network_rows: usize,
    pub gaussians: usize,
    pub position_lr: f32,
    /// The step was refused because something was non-finite.
    pub skipped: bool,
    /// Device-resident steps only: 1 when a sort outgrew the capacity sized from recent
    /// steps and the step was redone at the exact count (nothing applied twice).
    pub device_sort_retries: usize,
    pub timings: StepTimings,
}

/// PSNR and SSIM of one render against its image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewScore {
    pub psnr_db: f32,
    pub ssim: f32,
}

/// Rendered images of one view.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderedImages {
    /// `H * W * 3`, `RGB * S`: what the camera should see.
    pub image: Vec<f32>,
    /// `H * W * 3` colour before the shadow product.
    pub rgb: Vec<f32>,
    /// `H * W` accumulated opacity.
    pub alpha: Vec<f32>,
    /// `H * W` shadow image S (configurations c-d), else empty.
    pub shadow: Vec<f32>,
}

/// Adam over one flat vector (a network's weights), same rule and constants as [`Adam`].
#[derive(Clone, Debug, PartialEq)]
pub struct FlatAdam {
    pub m: Vec<f32>,
    pub v: Vec<f32>,
    pub step: u64,
}

impl FlatAdam {
    pub fn new(len: usize) -> Self {
        Self {
            m: vec![0.0; len],
            v: vec![0.0; len],
            step: 0,
        }
    }

    /// One Adam step of `params` with `grads` at learning rate `lr` (the step counter
    /// first incremented). `params`, `grads` and both moments must have the same length,
    /// else `OptimError::Shape`; a gradient [`crate::optim::is_usable_gradient`] refuses
    /// gives `OptimError::NonFiniteFlatGradient`; either way nothing changes.
    pub fn apply(
        &mut self,
        params: &mut [f32],
        grads: &[f32],
        lr: f32,
    ) -> Result<(), crate::optim::OptimError> {
        let moment_rows = self.m.len().min(self.v.len());
        if grads.len() != params.len()
            || self.m.len() != params.len()
            || self.v.len() != params.len()
        {
            return Err(crate::optim::OptimError::Shape {
                params_rows: params.len(),
                grads_rows: grads.len(),
                moment_rows,
            });
        }
        if let Some(index) = grads
            .iter()
            .position(|&g| !crate::optim::is_usable_gradient(g))
        {
            return Err(crate::optim::OptimError::NonFiniteFlatGradient { index });
        }
        let (b1, b2, eps) = (0.9f32, 0.999f32, crate::optim::ADAM_EPS);
        self.step += 1;
        let t = self.step as i32;
        let bias1 = 1.0 - (b1 as f64).powi(t);
        let bias2 = 1.0 - (b2 as f64).powi(t);
        let step_size = (lr as f64 / bias1) as f32;
        let inv_sqrt_bias2 = (1.0 / bias2.sqrt()) as f32;
        for i in 0..params.len() {
            self.m[i] = b1 * self.m[i] + (1.0 - b1) * grads[i];
            self.v[i] = b2 * self.v[i] + (1.0 - b2) * grads[i] * grads[i];
            let denom = self.v[i].sqrt() * inv_sqrt_bias2 + eps;
            params[i] -= step_size * self.m[i] / denom;
        }
        Ok(())
    }
}

/// Loss parts of one image.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LossParts {
    pub total: f32,
    pub l1: f32,
    pub ssim: f32,
    pub iso: f32,
}

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// `settings` restricted to the tiles the masked loss reads
/// (`SunAwareConfig::skip_masked_background_tiles`, an observation with a mask; the wgpu
/// rasterizer ignores it): the mask dilated by the SSIM window's half width, since the
/// windowed SSIM of a mask pixel reads its neighbours. Every other pixel has
/// exactly zero loss gradient, so the loss and every gradient are the same bits as with all
/// tiles blended. `None` when the skip does not apply.
fn masked_background_tiles(
    model: &SunAwareModel,
    obs: &Observation,
    settings: &RasterSettings,
) -> Result<Option<RasterSettings>, SunAwareError> {
    let Some(mask) = obs.mask else {
        return Ok(None);
    };
    if !model.config.skip_masked_background_tiles || settings.blend_tiles.is_some() {
        return Ok(None);
    }
    // The SSIM of a mask pixel reads its window (also with lambda_dssim = 0: the reported
    // SSIM value must not change either).
    let reach_px = (SSIM_WINDOW / 2) as u32;
    let k = &obs.camera.intrinsics;
    let selection = TileSelection::from_mask(mask, k.width, k.height, reach_px)
        .map_err(|e| SunAwareError::BadObservation(format!("mask: {e}")))?;
    Ok(Some(RasterSettings {
        blend_tiles: Some(selection),
        ..settings.clone()
    }))
}

/// Forward, loss and backward of one observation, without touching the model: the core of
/// a step, exposed so gradient checks run the very same code. The timings cover every
/// stage but the optimizer (`total_ms` is this call's duration).
pub fn loss_and_grads(
    model: &SunAwareModel,
    obs: &Observation,
    sh_degree: u32,
    settings: &RasterSettings,
    visibility: Option<&[f32]>,
) -> Result<(LossParts, FramePass, Option<SunAwareGrads>, StepTimings), SunAwareError> {
    let t_call = Instant::now();
    let mut timings = StepTimings::default();
    let masked_settings;
    let settings = match masked_background_tiles(model, obs, settings)? {
        Some(s) => {
            masked_settings = s;
            &masked_settings
        }
        None => settings,
    };
    let pass = model.forward_for_step(&obs.camera, obs.sun_dir, sh_degree, settings, visibility)?;
    timings.add_forward(&pass.timings);
    let t0 = Instant::now();
    if crate::loss::first_non_finite(&pass.image).is_some() {
        let nan = LossParts {
            total: f32::NAN,
            l1: f32::NAN,
            ssim: f32::NAN,
            iso: f32::NAN,
        };
        timings.loss_ms = ms_since(t0);
        timings.total_ms = ms_since(t_call);
        return Ok((nan, pass, None, timings));
    }
    let loss = photometric_loss(
        &pass.image,
        obs.image,
        obs.mask,
        obs.shape(),
        model.config.lambda_dssim,
    )?;
    timings.loss_ms = ms_since(t0);
    let mut parts = LossParts {
        total: loss.loss,
        l1: loss.l1,
        ssim: loss.ssim,
        iso: 0.0,
    };
    if !(loss.loss.is_finite() && crate::loss::first_non_finite(&loss.d_rendered).is_none()) {
        timings.total_ms = ms_since(t_call);
        return Ok((parts, pass, None, timings));
    }
    let (mut grads, backward_timings) = model.backward_timed(&pass, &loss.d_rendered)?;
    timings.add_backward(&backward_timings);
    let t_iso = Instant::now();
    if model.config.variant.uses_isotropic_loss() {
        let iso = IsotropicLoss::new(model.config.lambda_iso, model.config.iso_reduction)?;
        parts.iso = iso.value_and_grad(
            model.gaussians.params.get(Param::LogScale),
            grads.params.get_mut(Param::LogScale),
        )?;
        parts.total += parts.iso;
    }
    timings.loss_ms += ms_since(t_iso);
    timings.total_ms = ms_since(t_call);
    Ok((parts, pass, Some(grads), timings))
}

/// PSNR over the pixels weighted by `mask` (all pixels when `None`), images clamped to [0, 1].
pub fn masked_psnr(
    a: &[f32],
    b: &[f32],
    mask: Option<&[f32]>,
    shape: ImageShape,
) -> Result<f32, SunAwareError> {
    let Some(mask) = mask else {
        return Ok(psnr(a, b, shape)?);
    };
    if a.len() != shape.values() || b.len() != shape.values() || mask.len() != shape.pixels() {
        return Err(SunAwareError::BadObservation(
            "image or mask size does not match the shape".into(),
        ));
    }
    let (mut se, mut weight) = (0.0f64, 0.0f64);
    for (px, &m) in mask.iter().enumerate() {
        let w = m as f64;
        for c in 0..shape.channels {
            let i = px * shape.channels + c;
            let d = a[i].clamp(0.0, 1.0) as f64 - b[i].clamp(0.0, 1.0) as f64;
            se += w * d * d;
        }
        weight += w * shape.channels as f64;
    }
    if weight.is_nan() || weight <= 0.0 {
        return Err(SunAwareError::BadObservation(
            "mask is zero everywhere".into(),
        ));
    }
    Ok(crate::loss::psnr_db_from_mse(se / weight) as f32)
}

/// SSIM weighted by `mask` (the loss's masked SSIM), images clamped to [0, 1].
pub fn masked_ssim(
    a: &[f32],
    b: &[f32],
    mask: Option<&[f32]>,
    shape: ImageShape,
) -> Result<f32, SunAwareError> {
    let Some(mask) = mask else {
        return Ok(ssim(a, b, shape)?);
    };
    let ca: Vec<f32> = a.iter().map(|v| v.clamp(0.0, 1.0)).collect();
    let cb: Vec<f32> = b.iter().map(|v| v.clamp(0.0, 1.0)).collect();
    Ok(photometric_loss(&ca, &cb, Some(mask), shape, 0.0)?.ssim)
}

/// A Sun-aware model with its optimiser state and counters.
#[derive(Clone, Debug, PartialEq)]
pub struct SunAwareTrainer {
    pub model: SunAwareModel,
    pub adam: Adam,
    pub appearance_adam: FlatAdam,
    pub shadow_adam: FlatAdam,
    pub densify_stats: DensifyStats,
    /// Steps applied (not counting skipped ones).
    pub steps: u64,
    /// Steps refused because of a non-finite render, loss or gradient.
    pub skipped_nonfinite: u64,
    /// Per-Gaussian rasterizer gradients replaced by zeros (non-finite), summed.
    pub raster_dropped: u64,
    /// Densification calls so far (seeds each call's random stream).
    pub densify_count: u64,
    /// Device-resident training on a device backend (not part of the trainer's value nor
    /// of its checkpoint).
    pub(crate) resident: ResidentSlot,
}

/// The device-resident training state ([`SunAwareTrainer::step_many`]): the engine (compiled kernels and device
/// buffers) is built on first use. Clones share the engine (each batch uploads its own
/// state, and a mutex serialises batches); equality ignores the slot.
#[derive(Clone, Default)]
pub(crate) struct ResidentSlot {
    engine: Option<std::sync::Arc<std::sync::Mutex<Box<dyn ResidentTraining>>>>,
}

impl PartialEq for ResidentSlot {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for ResidentSlot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("ResidentSlot")
    }
}

impl SunAwareTrainer {
    pub fn new(model: SunAwareModel) -> Self {
        let adam = Adam::new(&model.gaussians.params);
        let appearance_adam =
            FlatAdam::new(model.appearance.as_ref().map_or(0, |n| n.mlp.num_params()));
        let shadow_adam = FlatAdam::new(model.shadow.as_ref().map_or(0, |n| n.mlp.num_params()));
        let densify_stats = DensifyStats::new(model.len());
        Self {
            model,
            adam,
            appearance_adam,
            shadow_adam,
            densify_stats,
            steps: 0,
            skipped_nonfinite: 0,
            raster_dropped: 0,
            densify_count: 0,
            resident: ResidentSlot::default(),
        }
    }

    /// Moves the trainer to `backend` (see [`SunAwareModel::set_backend`]): on a device,
    /// [`SunAwareTrainer::step_many`] trains device-resident. The backend is not part of
    /// the trainer's value or of its checkpoint.
    pub fn set_backend(&mut self, backend: &Backend) -> Result<(), SunAwareError> {
        self.resident.engine = None;
        self.model.set_backend(backend)
    }

    /// True when steps run device-resident: on a device backend,
    /// [`SunAwareTrainer::step_many`] keeps every parameter, moment and statistic on the
    /// device for a batch of steps.
    pub fn is_device_resident(&self) -> bool {
        self.model.engine().is_some()
    }

    /// Target size used for the position rate and the clone/split boundary, metres.
    pub fn scene_extent(&self) -> f32 {
        2.0 * box_sphere(&self.model.scene_box).1
    }

    /// SH degree in use at the current step (configuration a).
    pub fn active_sh_degree(&self) -> u32 {
        self.sh_degree_after(self.steps)
    }

    /// SH degree in use after `steps` applied steps.
    fn sh_degree_after(&self, steps: u64) -> u32 {
        let interval = self.model.config.sh_degree_interval.max(1);
        ((steps / interval).min(3) as u32).min(self.model.gaussians.layout().sh_degree)
    }

    /// Position rate at `progress` in [0, 1] through a round.
    pub fn position_lr(&self, progress: f32) -> f32 {
        let lr = &self.model.config.lr;
        let extent = self.scene_extent();
        let (a, b) = (lr.position_init * extent, lr.position_final * extent);
        if a <= 0.0 || b <= 0.0 {
            return 0.0;
        }
        let t = progress.clamp(0.0, 1.0) as f64;
        ((a as f64).ln() * (1.0 - t) + (b as f64).ln() * t).exp() as f32
    }

    fn group_rates(&self, position_lr: f32) -> GroupRates {
        let lr = &self.model.config.lr;
        let mut r = [0.0f32; Param::COUNT];
        r[Param::Mean.index()] = position_lr;
        r[Param::LogScale.index()] = lr.scale;
        r[Param::Rotation.index()] = lr.rotation;
        r[Param::OpacityLogit.index()] = lr.opacity;
        r[Param::ShDc.index()] = lr.sh_dc;
        r[Param::ShRest.index()] = lr.sh_rest;
        r[Param::Feature.index()] = lr.feature;
        r[Param::ShadowLatent.index()] = lr.shadow_latent;
        r[Param::Normal.index()] = lr.normal;
        r
    }

    /// Optimisation steps on `batch` (observation, position-rate progress) in order: the
    /// same as calling [`SunAwareTrainer::step`] on each, but when the trainer is
    /// device-resident ([`SunAwareTrainer::is_device_resident`]) the whole batch runs on
    /// the device with one upload of the trainer's state before and one download after,
    /// so the host copy (`model`, the optimisers, the statistics) is current whenever no
    /// batch is running. Every observation is checked before any work; an error mid-batch
    /// leaves the trainer as it was before the batch.
    pub fn step_many(
        &mut self,
        batch: &[(Observation, f32)],
    ) -> Result<Vec<StepStats>, SunAwareError> {
        if !self.is_device_resident() {
            return batch.iter().map(|(o, p)| self.step(o, *p)).collect();
        }
        self.step_many_resident(batch)
    }

    fn step_many_resident(
        &mut self,
        batch: &[(Observation, f32)],
    ) -> Result<Vec<StepStats>, SunAwareError> {
        let mut suns = Vec::with_capacity(batch.len());
        for (obs, progress) in batch {
            obs.validate()?;
            if !progress.is_finite() {
                return Err(SunAwareError::Config(
                    "lr_progress_in_round must be finite".into(),
                ));
            }
            if !(obs.sun_dir.is_finite() && obs.sun_dir.length_squared() > 1e-12) {
                return Err(SunAwareError::BadObservation(format!(
                    "Sun vector {:?} is not a finite non-zero vector",
                    obs.sun_dir
                )));
            }
            suns.push(obs.sun_dir.normalize());
        }
        let Some(device) = self.model.engine() else {
            return Err(SunAwareError::Gpu("no device backend set".into()));
        };
        let engine = match &self.resident.engine {
            Some(e) => e.clone(),
            None => {
                let e = std::sync::Arc::new(std::sync::Mutex::new(device.resident()?));
                self.resident.engine = Some(e.clone());
                e
            }
        };
        let mut engine = engine
            .lock()
            .map_err(|_| SunAwareError::Gpu("resident engine lock poisoned".into()))?;
        engine.upload(
            &self.model,
            &self.adam,
            &self.appearance_adam,
            &self.shadow_adam,
            &self.densify_stats,
        )?;
        let (mut steps, mut skipped, mut dropped) = (self.steps, 0u64, 0u64);
        let mut out = Vec::with_capacity(batch.len());
        let mut failure = None;
        for ((obs, progress), sun) in batch.iter().zip(&suns) {
            let position_lr = self.position_lr(*progress);
            let rates = self.group_rates(position_lr);
            let lr = &self.model.config.lr;
            let input = SunAwareStepInput {
                camera: &obs.camera,
                sun_dir: *sun,
                target: obs.image,
                mask: obs.mask,
                rates: &rates,
                sh_degree: self.sh_degree_after(steps),
                appearance_lr: lr.appearance_mlp,
                shadow_lr: lr.shadow_mlp,
            };
            let report = match engine.step(&self.model, &input) {
                Ok(r) => r,
                Err(e) => {
                    failure = Some(e);
                    break;
                }
            };
            if report.refused {
                skipped += 1;
            } else {
                steps += 1;
                dropped += report.dropped_nonfinite as u64;
            }
            out.push(StepStats {
                step: steps,
                loss: report.loss,
                l1: report.l1,
                ssim: report.ssim,
                iso: report.iso,
                visible: report.visible,
                network_rows: report.network_rows,
                gaussians: self.model.len(),
                position_lr,
                skipped: report.refused,
                device_sort_retries: report.sort_retries,
                // Device stage times where the adapter has timestamp queries.
                timings: StepTimings {
                    total_ms: report.total_ms,
                    ..report.stages
                },
            });
        }
        if let Some(e) = failure {
            return Err(e);
        }
        engine.download(
            &mut self.model,
            &mut self.adam,
            &mut self.appearance_adam,
            &mut self.shadow_adam,
            &mut self.densify_stats,
        )?;
        self.steps = steps;
        self.skipped_nonfinite += skipped;
        self.raster_dropped += dropped;
        Ok(out)
    }

    /// One optimisation step on one observation (on a device-resident trainer, a batch of
    /// one: see [`SunAwareTrainer::step_many`]).
    pub fn step(
        &mut self,
        obs: &Observation,
        lr_progress_in_round: f32,
    ) -> Result<StepStats, SunAwareError> {
        if self.is_device_resident() {
            let mut stats = self.step_many(&[(*obs, lr_progress_in_round)])?;
            return stats
                .pop()
                .ok_or_else(|| SunAwareError::Gpu("a batch of one gave no step".into()));
        }
        obs.validate()?;
        if !lr_progress_in_round.is_finite() {
            return Err(SunAwareError::Config(
                "lr_progress_in_round must be finite".into(),
            ));
        }
        let t_start = Instant::now();
        let settings = self.model.raster_settings(false);
        let degree = self.active_sh_degree();
        let (parts, pass, grads, mut timings) =
            loss_and_grads(&self.model, obs, degree, &settings, None)?;
        let position_lr = self.position_lr(lr_progress_in_round);
        let mut stats = StepStats {
            step: self.steps,
            loss: parts.total,
            l1: parts.l1,
            ssim: parts.ssim,
            iso: parts.iso,
            visible: pass.visible_list.len(),
            network_rows: pass.network_list.len(),
            gaussians: self.model.len(),
            position_lr,
            skipped: false,
            device_sort_retries: 0,
            timings: StepTimings::default(),
        };
        let grads = match grads {
            Some(g) if parts.total.is_finite() && g.first_non_finite().is_none() => g,
            _ => {
                self.skipped_nonfinite += 1;
                stats.skipped = true;
                self.model.recycle(pass);
                timings.total_ms = ms_since(t_start);
                stats.timings = timings;
                return Ok(stats);
            }
        };
        let t_opt = Instant::now();
        self.raster_dropped += grads.raster_dropped as u64;
        let rates = self.group_rates(position_lr);
        self.adam
            .step(&mut self.model.gaussians.params, &grads.params, &rates)?;
        if let Some(net) = &mut self.model.appearance {
            let lr = self.model.config.lr.appearance_mlp;
            self.appearance_adam
                .apply(net.mlp.params_mut(), &grads.appearance, lr)?;
        }
        if let Some(net) = &mut self.model.shadow {
            let lr = self.model.config.lr.shadow_mlp;
            self.shadow_adam
                .apply(net.mlp.params_mut(), &grads.shadow, lr)?;
        }
        self.densify_stats
            .accumulate(&grads.mean2d_grad_ndc, pass.visible(), pass.radii_px())?;
        self.steps += 1;
        stats.step = self.steps;
        self.model.recycle(pass);
        timings.optimizer_ms = ms_since(t_opt);
        timings.total_ms = ms_since(t_start);
        stats.timings = timings;
        Ok(stats)
    }

    /// One 3DGS densify-and-prune on the statistics gathered since the last call. Before
    /// `densify_from_step` steps nothing is added (pruning still runs). `max_gaussians` is a
    /// hard cap: when more Gaussians pass the gradient threshold than there is room for,
    /// only the ones with the largest gradients are densified.
    pub fn densify_and_prune(&mut self) -> Result<DensifyReport, SunAwareError> {
        let config = &self.model.config;
        let room = config.max_gaussians.saturating_sub(self.model.len());
        let grad_threshold = if room == 0 || self.steps < config.densify_from_step {
            f32::INFINITY
        } else {
            capped_grad_threshold(
                &self.densify_stats.mean_grad(),
                config.densify.grad_threshold,
                room,
            )
        };
        let densify = DensifyConfig {
            grad_threshold,
            ..config.densify
        };
        let size_prune = config.size_prune;
        let seed = config.seed ^ 0xD3_5E_00_00;
        let mut rng =
            SplitMix64::new(seed ^ self.densify_count.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let extent = self.scene_extent();
        let report = densify_and_prune(
            &mut self.model.gaussians,
            &mut self.adam,
            &mut self.densify_stats,
            &densify,
            extent,
            size_prune,
            &mut rng,
        )?;
        self.densify_count += 1;
        Ok(report)
    }

    /// Renders a view (see [`SunAwareModel::render`]).
    pub fn render(&self, camera: &Camera, sun_dir: Vec3) -> Result<RenderedImages, SunAwareError> {
        self.model.render(camera, sun_dir)
    }

    /// PSNR and SSIM of the render of `obs`'s view against its image, over the mask's
    /// pixels when `masked` and the observation has one, else the whole image.
    pub fn evaluate(&self, obs: &Observation, masked: bool) -> Result<ViewScore, SunAwareError> {
        self.model.evaluate(obs, masked)
    }
}

/// The densify gradient threshold that lets at most `room` Gaussians through: `base`, or,
/// when more than `room` mean gradients reach it, just above the `room + 1`-th largest one.
/// Every densified Gaussian (a clone, or a split's two children replacing the parent) adds
/// exactly one, so the count after densification never exceeds the cap.
fn capped_grad_threshold(mean_grads: &[f32], base: f32, room: usize) -> f32 {
    let mut passing: Vec<f32> = mean_grads.iter().copied().filter(|&g| g >= base).collect();
    if passing.len() <= room {
        return base;
    }
    passing.sort_unstable_by(|a, b| b.total_cmp(a));
    // Strictly above the (room + 1)-th largest: ties at that value are all left out, so
    // at most `room` pass `g >= threshold`.
    let cut = passing[room];
    if cut.is_finite() {
        cut.next_up()
    } else {
        f32::INFINITY
    }
}

impl SunAwareModel {
    /// Images of a view at the model's full SH degree (inference).
    pub fn render(&self, camera: &Camera, sun_dir: Vec3) -> Result<RenderedImages, SunAwareError> {
        let settings = self.raster_settings(false);
        let degree = self.gaussians.layout().sh_degree;
        let pass = self.forward_for_step(camera, sun_dir, degree, &settings, None)?;
        Ok(RenderedImages {
            image: pass.image,
            rgb: pass.rgb,
            alpha: pass.alpha,
            shadow: pass.shadow_image,
        })
    }

    /// PSNR and SSIM of the render of `obs`'s view (see [`SunAwareTrainer::evaluate`]).
    pub fn evaluate(&self, obs: &Observation, masked: bool) -> Result<ViewScore, SunAwareError> {
        obs.validate()?;
        let img = self.render(&obs.camera, obs.sun_dir)?.image;
        let mask = if masked { obs.mask } else { None };
        Ok(ViewScore {
            psnr_db: masked_psnr(&img, obs.image, mask, obs.shape())?,
            ssim: masked_ssim(&img, obs.image, mask, obs.shape())?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::init::from_points;
    use crate::sunaware::config::{LightConfig, SunAwareConfig, Variant};
    use crate::sunaware::synthetic::{orbit_camera, sun_direction, SyntheticScene};

    /// A small configuration-d trainer on the synthetic scene and one observation of it.
    fn small_d_trainer() -> (SunAwareTrainer, Camera, Vec3, Vec<f32>, Vec<f32>) {
        let scene = SyntheticScene::plate_and_ball(14, 60).unwrap();
        let config = SunAwareConfig {
            light: LightConfig {
                resolution_px: 64,
                ..LightConfig::default()
            },
            ..SunAwareConfig::for_variant(Variant::D)
        };
        let (points, _, colours) = scene.surface_samples(0.02, 5);
        let init = from_points(&points, Some(&colours), config.layout()).unwrap();
        let model = SunAwareModel::new(init.model, scene.scene_box, config).unwrap();
        let camera = orbit_camera(1, 8, 2.4, 0.6, 40, 32);
        let sun = sun_direction(0.4, 0.9);
        let (image, mask) = scene.render(&camera, sun).unwrap();
        (SunAwareTrainer::new(model), camera, sun, image, mask)
    }

    #[test]
    fn network_adam_refuses_oversized_gradients_without_change() {
        let mut adam = FlatAdam::new(3);
        let mut params = vec![0.5f32; 3];
        for g in [1e21f32, f32::NAN] {
            let before = (params.clone(), adam.clone());
            let err = adam.apply(&mut params, &[0.0, g, 1.0], 1e-3);
            assert_eq!(
                err,
                Err(crate::optim::OptimError::NonFiniteFlatGradient { index: 1 })
            );
            assert_eq!((params.clone(), adam.clone()), before);
        }
        adam.apply(&mut params, &[0.0, 1e18, 1.0], 1e-3).unwrap();
        assert!(adam.v.iter().chain(&params).all(|v| v.is_finite()));
        assert_eq!(adam.step, 1);
    }

    #[test]
    fn step_timings_are_disjoint_stages_inside_the_step() {
        let (mut t, camera, sun, image, mask) = small_d_trainer();
        let obs = Observation {
            camera,
            sun_dir: sun,
            image: &image,
            mask: Some(&mask),
        };
        for s in 0..3 {
            let stats = t.step(&obs, s as f32 / 3.0).unwrap();
            assert!(!stats.skipped);
            let tm = stats.timings;
            for (name, ms) in tm.stages() {
                assert!(ms.is_finite() && ms >= 0.0, "{name} = {ms}");
            }
            // Every stage of configuration d runs, so each takes some time.
            for (name, ms) in tm.stages() {
                assert!(ms > 0.0, "stage {name} was not timed");
            }
            // Disjoint intervals inside the step: their sum cannot exceed it (1 ns covers
            // the rounding of twelve nanosecond counts converted to milliseconds).
            assert!(
                tm.stage_sum_ms() <= tm.total_ms + 1e-6,
                "stages sum to {} ms > total {} ms",
                tm.stage_sum_ms(),
                tm.total_ms
            );
            assert!(tm.other_ms() >= -1e-6);
            assert!(tm.mlp_forward_ms() >= tm.phi_forward_ms);
        }
    }

    #[test]
    fn forward_and_loss_timings_fit_inside_loss_and_grads() {
        let (t, camera, sun, image, _) = small_d_trainer();
        let obs = Observation {
            camera,
            sun_dir: sun,
            image: &image,
            mask: None,
        };
        let settings = t.model.raster_settings(false);
        let (_, _, grads, tm) = loss_and_grads(&t.model, &obs, 0, &settings, None).unwrap();
        assert!(grads.is_some());
        assert_eq!(tm.optimizer_ms, 0.0);
        assert!(tm.stage_sum_ms() <= tm.total_ms + 1e-6);
        assert!(tm.project_ms > 0.0 && tm.blend_backward_ms > 0.0 && tm.loss_ms > 0.0);
    }

    fn passing(grads: &[f32], threshold: f32) -> usize {
        grads.iter().filter(|&&g| g >= threshold).count()
    }

    #[test]
    fn densify_threshold_keeps_the_base_when_there_is_room() {
        let grads = [1e-4, 3e-4, 5e-4, 0.0];
        assert_eq!(capped_grad_threshold(&grads, 2e-4, 2), 2e-4);
        assert_eq!(capped_grad_threshold(&grads, 2e-4, 10), 2e-4);
    }

    #[test]
    fn densify_threshold_lets_through_only_the_largest_gradients_up_to_the_room() {
        let grads = [9e-4, 3e-4, 7e-4, 1e-4, 5e-4, 8e-4];
        let t = capped_grad_threshold(&grads, 2e-4, 2);
        assert_eq!(passing(&grads, t), 2);
        assert!(t > 7e-4 && t <= 8e-4, "threshold {t}");
        assert_eq!(passing(&grads, capped_grad_threshold(&grads, 2e-4, 0)), 0);
    }

    #[test]
    fn densify_threshold_never_exceeds_the_room_on_ties() {
        // Four equal gradients and room for two: none of the tied ones can be chosen
        // without exceeding the cap, so only the larger one passes.
        let grads = [6e-4, 6e-4, 6e-4, 6e-4, 9e-4];
        let t = capped_grad_threshold(&grads, 2e-4, 2);
        assert_eq!(passing(&grads, t), 1);
    }
}
