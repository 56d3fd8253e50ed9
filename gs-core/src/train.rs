//! Vanilla 3DGS training loop over posed images.
//!
//! One iteration (1-based, as in 3DGS): take the next view of a seeded shuffle (the
//! order is reshuffled each time every view has been used once), evaluate SH colour at
//! the active degree (+1 every `sh_degree_interval` iterations up to the model's degree),
//! render, take `(1 - lambda) L1 + lambda (1 - SSIM)` against the view's image (on its
//! mask, see [`crate::loss`]), backpropagate through the rasterizer and the SH colour, and
//! take one Adam step with the 3DGS learning rates (position rate on the exponential
//! schedule times the scene extent). While `iteration < densify_until_iter` it gathers
//! densification statistics, densifies and prunes every `densify_interval` iterations
//! after `densify_from_iter`, and resets opacities every `opacity_reset_interval`.
//!
//! It runs on the CPU: the Sun-aware trainer (`crate::sunaware`, configuration (a) is this
//! model) is the one that also trains on a device.
//!
//! [`Trainer`] is the same loop one step at a time (for an online scheduler that picks
//! views itself and runs its own learning-rate sawtooth); [`train`] drives it over a
//! fixed view set.
//!
//! Invariants:
//! - deterministic: same model, views, config and thread count give bit-identical results
//!   (the only randomness is a [`SplitMix64`] seeded from `config.seed`);
//! - a step whose gradients contain NaN/Inf is never applied: it is counted in
//!   `TrainResult::skipped_non_finite_steps` and its densification stats are dropped;
//! - bad views or configuration are reported before any work, as [`TrainError`].

use std::time::Instant;

use glam::Vec3;

use crate::camera::Camera;
use crate::densify::{
    densify_and_prune, reset_opacity, DensifyConfig, DensifyReport, DensifyStats,
};
use crate::init::SplitMix64;
use crate::loss::{photometric_loss, psnr, ssim, ImageShape, LossError, LossOutput};
use crate::model::{GaussianModel, Param, ParamSet};
use crate::optim::{Adam, ExponentialSchedule, GroupRates, OptimError};
use crate::raster::{
    render, render_backward, GaussianView, PixelGrads, RasterError, RasterSettings,
};
use crate::sh::{sh_to_rgb, sh_to_rgb_backward, ShError};

/// Per-group learning rates (3DGS defaults).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LearningRates {
    /// Position rate at the start, times the scene extent.
    pub position_init: f32,
    /// Position rate at `position_max_steps`, times the scene extent.
    pub position_final: f32,
    /// Iterations over which the position rate decays; `None`: the whole run.
    pub position_max_steps: Option<u64>,
    pub sh_dc: f32,
    pub sh_rest: f32,
    pub opacity: f32,
    pub scale: f32,
    pub rotation: f32,
    pub feature: f32,
    pub shadow_latent: f32,
}

impl Default for LearningRates {
    fn default() -> Self {
        Self {
            position_init: 1.6e-4,
            position_final: 1.6e-6,
            position_max_steps: None,
            sh_dc: 2.5e-3,
            sh_rest: 2.5e-3 / 20.0,
            opacity: 0.025,
            scale: 5e-3,
            rotation: 1e-3,
            feature: 0.0,
            shadow_latent: 0.0,
        }
    }
}

/// Training configuration (3DGS defaults where it has one).
#[derive(Clone, Debug, PartialEq)]
pub struct TrainConfig {
    pub iterations: usize,
    pub lr: LearningRates,
    pub densify: DensifyConfig,
    pub densify_from_iter: usize,
    pub densify_until_iter: usize,
    pub densify_interval: usize,
    /// 0 disables opacity resets.
    pub opacity_reset_interval: usize,
    /// Opacities are capped at this value by a reset.
    pub opacity_reset_value: f32,
    /// The active SH degree grows by one every this many iterations.
    pub sh_degree_interval: usize,
    pub lambda_dssim: f32,
    pub seed: u64,
    /// RGB background composited behind the Gaussians.
    pub background: [f32; 3],
    /// Scene extent (metres) for the position rate and densification; `None`: 1.1 times
    /// the largest distance of a camera centre from their mean (3DGS `getNerfppNorm`).
    pub scene_extent: Option<f32>,
    pub near_m: f32,
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            iterations: 30_000,
            lr: LearningRates::default(),
            densify: DensifyConfig::default(),
            densify_from_iter: 500,
            densify_until_iter: 15_000,
            densify_interval: 100,
            opacity_reset_interval: 3000,
            opacity_reset_value: 0.01,
            sh_degree_interval: 1000,
            lambda_dssim: 0.2,
            seed: 0,
            background: [0.0; 3],
            scene_extent: None,
            near_m: 0.01,
        }
    }
}

/// One posed training image.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainView {
    pub camera: Camera,
    /// `H * W * 3` RGB in [0, 1], pixel-major.
    pub image: Vec<f32>,
    /// Optional `H * W` foreground weights in [0, 1].
    pub mask: Option<Vec<f32>>,
}

/// What one iteration did, for progress reporting.
#[derive(Clone, Debug, PartialEq)]
pub struct IterationStats {
    /// 1-based.
    pub iteration: usize,
    pub view_index: usize,
    pub loss: f32,
    pub l1: f32,
    pub ssim: f32,
    pub gaussians: usize,
    pub active_sh_degree: u32,
    pub position_lr: f32,
    /// Whether this iteration's step was skipped for non-finite gradients.
    pub skipped: bool,
    pub densified: Option<DensifyReport>,
    pub opacity_reset: bool,
    /// Wall-clock split, milliseconds (informative only; not part of determinism):
    /// SH colour + render, loss and its gradient, rasterizer + SH backward, Adam step +
    /// densification.
    pub forward_ms: f64,
    pub loss_ms: f64,
    pub backward_ms: f64,
    pub step_ms: f64,
}

/// The trained model and its history.
#[derive(Clone, Debug)]
pub struct TrainResult {
    pub model: GaussianModel,
    /// Loss of every iteration.
    pub losses: Vec<f32>,
    /// Steps refused because a gradient was NaN or infinite.
    pub skipped_non_finite_steps: usize,
    /// Gaussians whose gradient the rasterizer replaced by zeros (non-finite), summed.
    pub raster_dropped_gradients: usize,
    /// Densification steps, with their iteration.
    pub densify_reports: Vec<(usize, DensifyReport)>,
    pub scene_extent: f32,
}

/// Training error.
#[derive(Debug, Clone, PartialEq)]
pub enum TrainError {
    NoViews,
    /// A view is unusable; `reason` says why.
    BadView {
        index: usize,
        reason: String,
    },
    /// A configuration value is unusable; the message says which.
    Config(String),
    /// The starting model holds NaN or infinite values.
    NonFiniteModel {
        param: Param,
        index: usize,
    },
    Raster(RasterError),
    Loss(LossError),
    Sh(ShError),
    Optim(OptimError),
    Densify(crate::densify::DensifyError),
}

impl std::fmt::Display for TrainError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TrainError::NoViews => write!(f, "no training views"),
            TrainError::BadView { index, reason } => write!(f, "view {index}: {reason}"),
            TrainError::Config(why) => write!(f, "training config: {why}"),
            TrainError::NonFiniteModel { param, index } => write!(
                f,
                "starting model has a non-finite {} value at index {index}",
                param.name()
            ),
            TrainError::Raster(e) => write!(f, "rasterizer: {e}"),
            TrainError::Loss(e) => write!(f, "loss: {e}"),
            TrainError::Sh(e) => write!(f, "SH colour: {e}"),
            TrainError::Optim(e) => write!(f, "optimiser: {e}"),
            TrainError::Densify(e) => write!(f, "densification: {e}"),
        }
    }
}

impl std::error::Error for TrainError {}

impl From<RasterError> for TrainError {
    fn from(e: RasterError) -> Self {
        TrainError::Raster(e)
    }
}
impl From<LossError> for TrainError {
    fn from(e: LossError) -> Self {
        TrainError::Loss(e)
    }
}
impl From<ShError> for TrainError {
    fn from(e: ShError) -> Self {
        TrainError::Sh(e)
    }
}
impl From<OptimError> for TrainError {
    fn from(e: OptimError) -> Self {
        TrainError::Optim(e)
    }
}
impl From<crate::densify::DensifyError> for TrainError {
    fn from(e: crate::densify::DensifyError) -> Self {
        TrainError::Densify(e)
    }
}

/// 3DGS `getNerfppNorm` radius: 1.1 times the largest distance of a camera centre from
/// the mean centre. Zero for a single camera.
pub fn camera_extent(cameras: &[Camera]) -> f32 {
    if cameras.is_empty() {
        return 0.0;
    }
    let centres: Vec<Vec3> = cameras.iter().map(Camera::position).collect();
    let mean = centres.iter().copied().sum::<Vec3>() / centres.len() as f32;
    1.1 * centres
        .iter()
        .map(|c| (*c - mean).length())
        .fold(0.0f32, f32::max)
}

fn image_shape(camera: &Camera) -> ImageShape {
    ImageShape::new(
        camera.intrinsics.width as usize,
        camera.intrinsics.height as usize,
        3,
    )
}

fn check_view(index: usize, view: &TrainView) -> Result<(), TrainError> {
    let bad = |reason: String| TrainError::BadView { index, reason };
    let shape = image_shape(&view.camera);
    if shape.pixels() == 0 {
        return Err(bad("camera image size is zero".into()));
    }
    if view.image.len() != shape.values() {
        return Err(bad(format!(
            "image has {} values, camera needs {} (H * W * 3)",
            view.image.len(),
            shape.values()
        )));
    }
    if let Some(i) = view.image.iter().position(|v| !v.is_finite()) {
        return Err(bad(format!("image value {i} is not finite")));
    }
    if let Some(mask) = &view.mask {
        if mask.len() != shape.pixels() {
            return Err(bad(format!(
                "mask has {} values, camera needs {} (H * W)",
                mask.len(),
                shape.pixels()
            )));
        }
        if let Some(i) = mask.iter().position(|v| !(0.0..=1.0).contains(v)) {
            return Err(bad(format!("mask value {i} is not in [0, 1]")));
        }
        if mask.iter().all(|&v| v == 0.0) {
            return Err(bad("mask is zero everywhere".into()));
        }
    }
    Ok(())
}

fn check_config(config: &TrainConfig) -> Result<(), TrainError> {
    let err = |s: &str| Err(TrainError::Config(s.to_string()));
    if !(0.0..=1.0).contains(&config.lambda_dssim) {
        return err("lambda_dssim must be in [0, 1]");
    }
    if config.densify_interval == 0 {
        return err("densify_interval must be positive");
    }
    if config.sh_degree_interval == 0 {
        return err("sh_degree_interval must be positive");
    }
    if !config.background.iter().all(|v| v.is_finite()) {
        return err("background must be finite");
    }
    let lr = &config.lr;
    let rates = [
        lr.position_init,
        lr.position_final,
        lr.sh_dc,
        lr.sh_rest,
        lr.opacity,
        lr.scale,
        lr.rotation,
        lr.feature,
        lr.shadow_latent,
    ];
    if !rates.iter().all(|r| r.is_finite() && *r >= 0.0) {
        return err("learning rates must be finite and non-negative");
    }
    if !(config.opacity_reset_value > 0.0 && config.opacity_reset_value < 1.0) {
        return err("opacity_reset_value must be in (0, 1)");
    }
    Ok(())
}

/// Active SH degree at a 1-based iteration (3DGS: one up every `interval` iterations).
pub fn active_sh_degree(iteration: usize, interval: usize, model_degree: u32) -> u32 {
    ((iteration / interval.max(1)) as u32).min(model_degree)
}

/// Renders `model` from `camera` as RGB (`H * W * 3`) at SH degree `sh_degree`.
pub fn render_rgb(
    model: &GaussianModel,
    camera: &Camera,
    sh_degree: u32,
    background: [f32; 3],
) -> Result<Vec<f32>, TrainError> {
    let colours = sh_to_rgb(&model.params, sh_degree, camera.position())?;
    let view = GaussianView::from_model(model, &colours, 3);
    let settings = RasterSettings {
        background: background.to_vec(),
        ..RasterSettings::default()
    };
    Ok(render(camera, &view, &settings)?.color)
}

/// PSNR and SSIM of one view's render against its image (whole image, unmasked).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewScore {
    pub psnr_db: f32,
    pub ssim: f32,
}

/// Scores `model` on `views` at the model's full SH degree.
pub fn evaluate(
    model: &GaussianModel,
    views: &[TrainView],
    background: [f32; 3],
) -> Result<Vec<ViewScore>, TrainError> {
    views
        .iter()
        .enumerate()
        .map(|(i, v)| {
            check_view(i, v)?;
            let img = render_rgb(model, &v.camera, model.layout().sh_degree, background)?;
            let shape = image_shape(&v.camera);
            Ok(ViewScore {
                psnr_db: psnr(&img, &v.image, shape)?,
                ssim: ssim(&img, &v.image, shape)?,
            })
        })
        .collect()
}

fn group_rates(lr: &LearningRates, position_lr: f32) -> GroupRates {
    let mut r = [0.0f32; Param::COUNT];
    r[Param::Mean.index()] = position_lr;
    r[Param::LogScale.index()] = lr.scale;
    r[Param::Rotation.index()] = lr.rotation;
    r[Param::OpacityLogit.index()] = lr.opacity;
    r[Param::ShDc.index()] = lr.sh_dc;
    r[Param::ShRest.index()] = lr.sh_rest;
    r[Param::Feature.index()] = lr.feature;
    r[Param::ShadowLatent.index()] = lr.shadow_latent;
    r
}

/// Parameter-shaped gradients from the rasterizer's per-Gaussian gradients.
fn gather_grads(params: &ParamSet, g: &crate::raster::GaussianGrads) -> ParamSet {
    let mut out = params.zeros_like();
    out.get_mut(Param::Mean).copy_from_slice(&g.d_means);
    out.get_mut(Param::LogScale)
        .copy_from_slice(&g.d_log_scales);
    out.get_mut(Param::Rotation).copy_from_slice(&g.d_rotations);
    out.get_mut(Param::OpacityLogit)
        .copy_from_slice(&g.d_opacity_logits);
    out
}

/// The loss of a render against the view (on its mask); `None` when the render, the
/// loss or its gradient is not finite (a model gone numerically wild: the step is
/// counted and skipped rather than handed to the backward, which rejects it).
fn score(
    color: &[f32],
    view: &TrainView,
    lambda_dssim: f32,
) -> Result<Option<LossOutput>, TrainError> {
    if !color.iter().all(|v| v.is_finite()) {
        return Ok(None);
    }
    let loss = photometric_loss(
        color,
        &view.image,
        view.mask.as_deref(),
        image_shape(&view.camera),
        lambda_dssim,
    )?;
    let finite = loss.loss.is_finite() && loss.d_rendered.iter().all(|v| v.is_finite());
    Ok(finite.then_some(loss))
}

fn nan_loss() -> LossOutput {
    LossOutput {
        loss: f32::NAN,
        l1: f32::NAN,
        ssim: f32::NAN,
        d_rendered: Vec::new(),
    }
}

/// Stepwise trainer: the model, its optimiser and densification state, and the 3DGS
/// schedules keyed on its own iteration counter. [`train`] drives it over a fixed view
/// set; an online scheduler can call [`Trainer::step`] with whatever view it picks and
/// override the position learning rate (e.g. a per-round sawtooth).
#[derive(Debug)]
pub struct Trainer {
    model: GaussianModel,
    adam: Adam,
    stats: DensifyStats,
    rng: SplitMix64,
    config: TrainConfig,
    schedule: ExponentialSchedule,
    settings: RasterSettings,
    scene_extent: f32,
    iteration: usize,
    skipped_steps: usize,
    raster_dropped: usize,
    densify_reports: Vec<(usize, DensifyReport)>,
}

/// What the backend-specific part of a step did.
struct StepArithmetic {
    loss: LossOutput,
    /// Gradients non-finite (or the render or loss): nothing was applied.
    skipped: bool,
    dropped_nonfinite: usize,
    forward_ms: f64,
    loss_ms: f64,
    backward_ms: f64,
}

/// Seed offset so the densification samples do not reuse the view-shuffle stream.
const DENSIFY_STREAM: u64 = 0xD1B5_4A32_D192_ED03;

impl Trainer {
    /// Checks the configuration and the model; `scene_extent` (metres) scales the
    /// position learning rate and the densification size limits.
    pub fn new(
        model: GaussianModel,
        config: &TrainConfig,
        scene_extent: f32,
    ) -> Result<Self, TrainError> {
        check_config(config)?;
        if let Some((param, index)) = Adam::first_non_finite(&model.params) {
            return Err(TrainError::NonFiniteModel { param, index });
        }
        if !(scene_extent.is_finite() && scene_extent > 0.0) {
            return Err(TrainError::Config(format!(
                "scene extent {scene_extent} is not positive (one camera position?): \
                 set scene_extent"
            )));
        }
        let schedule = ExponentialSchedule {
            lr_init: config.lr.position_init * scene_extent,
            lr_final: config.lr.position_final * scene_extent,
            delay_steps: 0,
            delay_mult: 0.01,
            max_steps: config
                .lr
                .position_max_steps
                .unwrap_or(config.iterations as u64),
        };
        Ok(Self {
            adam: Adam::new(&model.params),
            stats: DensifyStats::new(model.len()),
            rng: SplitMix64::new(config.seed ^ DENSIFY_STREAM),
            schedule,
            settings: RasterSettings {
                near_m: config.near_m,
                background: config.background.to_vec(),
                smooth_cutoff: false,
                ..RasterSettings::default()
            },
            config: config.clone(),
            scene_extent,
            iteration: 0,
            skipped_steps: 0,
            raster_dropped: 0,
            densify_reports: Vec::new(),
            model,
        })
    }

    pub fn model(&self) -> &GaussianModel {
        &self.model
    }

    /// The optimiser's state.
    pub fn optimiser(&self) -> &Adam {
        &self.adam
    }

    /// Iterations taken so far.
    pub fn iteration(&self) -> usize {
        self.iteration
    }

    pub fn scene_extent(&self) -> f32 {
        self.scene_extent
    }

    /// One iteration on `view` with the scheduled position learning rate.
    pub fn step(
        &mut self,
        view: &TrainView,
        view_index: usize,
    ) -> Result<IterationStats, TrainError> {
        let lr = self.schedule.at(self.iteration as u64 + 1);
        self.step_with_position_lr(view, view_index, lr)
    }

    /// One iteration on `view` with an explicit position learning rate (metres per unit
    /// step; the caller applies the scene extent). The view is validated first.
    pub fn step_with_position_lr(
        &mut self,
        view: &TrainView,
        view_index: usize,
        position_lr: f32,
    ) -> Result<IterationStats, TrainError> {
        check_view(view_index, view)?;
        if !(position_lr.is_finite() && position_lr >= 0.0) {
            return Err(TrainError::Config(format!(
                "position learning rate {position_lr} is not finite and non-negative"
            )));
        }
        let iteration = self.iteration + 1;
        let degree = active_sh_degree(
            iteration,
            self.config.sh_degree_interval,
            self.model.layout().sh_degree,
        );
        let rates = group_rates(&self.config.lr, position_lr);
        let accumulate_stats = iteration < self.config.densify_until_iter;
        let arithmetic = self.cpu_arithmetic(view, degree, &rates, accumulate_stats)?;
        let t2 = Instant::now();
        self.raster_dropped += arithmetic.dropped_nonfinite;

        let config = &self.config;
        let skipped = arithmetic.skipped;
        let mut densified = None;
        let mut opacity_reset = false;
        if !skipped && accumulate_stats {
            let densify_now = iteration > config.densify_from_iter
                && iteration.is_multiple_of(config.densify_interval);
            // 3DGS also resets once at `densify_from_iter` on a white background.
            let white_reset =
                config.background == [1.0; 3] && iteration == config.densify_from_iter;
            let periodic_reset = config.opacity_reset_interval > 0
                && iteration.is_multiple_of(config.opacity_reset_interval);
            let reset_now = periodic_reset || white_reset;
            if densify_now || reset_now {
                let config = &self.config;
                if densify_now {
                    let screen_limit = iteration > config.opacity_reset_interval
                        && config.opacity_reset_interval > 0;
                    let report = densify_and_prune(
                        &mut self.model,
                        &mut self.adam,
                        &mut self.stats,
                        &config.densify,
                        self.scene_extent,
                        screen_limit,
                        &mut self.rng,
                    )?;
                    self.densify_reports.push((iteration, report));
                    densified = Some(report);
                }
                if reset_now {
                    reset_opacity(&mut self.model, &mut self.adam, config.opacity_reset_value);
                    opacity_reset = true;
                }
            }
        }
        if skipped {
            self.skipped_steps += 1;
        }
        self.iteration = iteration;
        let t3 = Instant::now();
        Ok(IterationStats {
            iteration,
            view_index,
            loss: arithmetic.loss.loss,
            l1: arithmetic.loss.l1,
            ssim: arithmetic.loss.ssim,
            gaussians: self.model.len(),
            active_sh_degree: degree,
            position_lr,
            skipped,
            densified,
            opacity_reset,
            forward_ms: arithmetic.forward_ms,
            loss_ms: arithmetic.loss_ms,
            backward_ms: arithmetic.backward_ms,
            step_ms: (t3 - t2).as_secs_f64() * 1e3,
        })
    }

    /// The step's arithmetic on the CPU: SH colour, render, loss, backward, Adam, stats.
    fn cpu_arithmetic(
        &mut self,
        view: &TrainView,
        degree: u32,
        rates: &GroupRates,
        accumulate_stats: bool,
    ) -> Result<StepArithmetic, TrainError> {
        let camera = &view.camera;
        let t0 = Instant::now();
        let colours = sh_to_rgb(&self.model.params, degree, camera.position())?;
        let gview = GaussianView::from_model(&self.model, &colours, 3);
        let forward = render(camera, &gview, &self.settings)?;
        let t_loss = Instant::now();
        let loss = score(&forward.color, view, self.config.lambda_dssim)?;
        let t1 = Instant::now();
        let mut dropped_nonfinite = 0;
        let backward = match &loss {
            Some(loss) => {
                let pixel_grads = PixelGrads {
                    d_color: &loss.d_rendered,
                    d_alpha: None,
                    d_depth: None,
                };
                let g = render_backward(camera, &gview, &self.settings, &forward, &pixel_grads)?;
                dropped_nonfinite = g.dropped_nonfinite;
                let mut grads = gather_grads(&self.model.params, &g);
                sh_to_rgb_backward(
                    &self.model.params,
                    degree,
                    camera.position(),
                    &g.d_channels,
                    &mut grads,
                )?;
                Adam::first_unusable_gradient(&grads)
                    .is_none()
                    .then_some((g, grads))
            }
            None => None,
        };
        let skipped = backward.is_none();
        if let Some((g, grads)) = backward {
            self.adam.step(&mut self.model.params, &grads, rates)?;
            if accumulate_stats {
                self.stats
                    .accumulate(&g.mean2d_grad_ndc, &forward.visible, &forward.radii_px)?;
            }
        }
        Ok(StepArithmetic {
            loss: loss.unwrap_or_else(nan_loss),
            skipped,
            dropped_nonfinite,
            forward_ms: (t_loss - t0).as_secs_f64() * 1e3,
            loss_ms: (t1 - t_loss).as_secs_f64() * 1e3,
            backward_ms: t1.elapsed().as_secs_f64() * 1e3,
        })
    }

    /// The trained model and the run's counters; `losses` is the caller's loss history.
    pub fn finish(self, losses: Vec<f32>) -> TrainResult {
        TrainResult {
            model: self.model,
            losses,
            skipped_non_finite_steps: self.skipped_steps,
            raster_dropped_gradients: self.raster_dropped,
            densify_reports: self.densify_reports,
            scene_extent: self.scene_extent,
        }
    }
}

/// Trains `model` on `views` for `config.iterations`; `progress` sees every iteration.
pub fn train(
    model: GaussianModel,
    views: &[TrainView],
    config: &TrainConfig,
    mut progress: impl FnMut(&IterationStats),
) -> Result<TrainResult, TrainError> {
    if views.is_empty() {
        return Err(TrainError::NoViews);
    }
    for (i, v) in views.iter().enumerate() {
        check_view(i, v)?;
    }
    let scene_extent = match config.scene_extent {
        Some(e) => e,
        None => camera_extent(&views.iter().map(|v| v.camera).collect::<Vec<_>>()),
    };
    let mut trainer = Trainer::new(model, config, scene_extent)?;
    let mut shuffle = SplitMix64::new(config.seed);
    let mut order: Vec<usize> = Vec::new();
    let mut losses = Vec::with_capacity(config.iterations);
    for _ in 0..config.iterations {
        if order.is_empty() {
            order = (0..views.len()).collect();
            shuffle.shuffle(&mut order);
        }
        let view_index = order.pop().expect("refilled above");
        let stats = trainer.step(&views[view_index], view_index)?;
        losses.push(stats.loss);
        progress(&stats);
    }
    Ok(trainer.finish(losses))
}
