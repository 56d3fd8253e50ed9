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

use crate::camera::Camera;
use crate::densify::{densify_and_prune, DensifyConfig, DensifyReport, DensifyStats};
use crate::init::SplitMix64;
use crate::loss::{photometric_loss, psnr, ssim, ImageShape};
use crate::model::Param;
use crate::optim::{Adam, GroupRates};
use crate::raster::RasterSettings;
use crate::regularizer::IsotropicLoss;

use super::error::SunAwareError;
use super::light::box_sphere;
use super::model::{FramePass, SunAwareGrads, SunAwareModel};

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

/// Wall-clock split of one step, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepTimings {
    pub cull_ms: f64,
    pub shadow_pass_ms: f64,
    pub mlp_forward_ms: f64,
    pub raster_forward_ms: f64,
    pub loss_ms: f64,
    /// Rasterizer and network backward.
    pub backward_ms: f64,
    pub optimiser_ms: f64,
    pub total_ms: f64,
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
    /// Gaussians that survived culling (the networks' batch).
    pub visible: usize,
    pub gaussians: usize,
    pub position_lr: f32,
    /// The step was refused because something was non-finite.
    pub skipped: bool,
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

    /// One step; the caller has checked `grads` for finiteness and length.
    fn apply(&mut self, params: &mut [f32], grads: &[f32], lr: f32) {
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

/// Forward, loss and backward of one observation, without touching the model: the core of
/// a step, exposed so gradient checks run the very same code.
pub fn loss_and_grads(
    model: &SunAwareModel,
    obs: &Observation,
    sh_degree: u32,
    settings: &RasterSettings,
    visibility: Option<&[f32]>,
) -> Result<(LossParts, FramePass, Option<SunAwareGrads>, f64), SunAwareError> {
    let pass = model.forward(&obs.camera, obs.sun_dir, sh_degree, settings, visibility)?;
    let t0 = Instant::now();
    if !pass.image.iter().all(|v| v.is_finite()) {
        let nan = LossParts {
            total: f32::NAN,
            l1: f32::NAN,
            ssim: f32::NAN,
            iso: f32::NAN,
        };
        return Ok((nan, pass, None, t0.elapsed().as_secs_f64() * 1e3));
    }
    let loss = photometric_loss(
        &pass.image,
        obs.image,
        obs.mask,
        obs.shape(),
        model.config.lambda_dssim,
    )?;
    let loss_ms = t0.elapsed().as_secs_f64() * 1e3;
    let mut parts = LossParts {
        total: loss.loss,
        l1: loss.l1,
        ssim: loss.ssim,
        iso: 0.0,
    };
    if !(loss.loss.is_finite() && loss.d_rendered.iter().all(|v| v.is_finite())) {
        return Ok((parts, pass, None, loss_ms));
    }
    let mut grads = model.backward(&pass, &loss.d_rendered)?;
    if model.config.variant.uses_isotropic_loss() {
        let iso = IsotropicLoss::new(model.config.lambda_iso, model.config.iso_reduction)?;
        parts.iso = iso.value_and_grad(
            model.gaussians.params.get(Param::LogScale),
            grads.params.get_mut(Param::LogScale),
        )?;
        parts.total += parts.iso;
    }
    Ok((parts, pass, Some(grads), loss_ms))
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
    let mse = se / weight;
    Ok(if mse == 0.0 {
        f32::INFINITY
    } else {
        (-10.0 * mse.log10()) as f32
    })
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
        }
    }

    /// Target size used for the position rate and the clone/split boundary, metres.
    pub fn scene_extent(&self) -> f32 {
        2.0 * box_sphere(&self.model.scene_box).1
    }

    /// SH degree in use at the current step (configuration a).
    pub fn active_sh_degree(&self) -> u32 {
        let interval = self.model.config.sh_degree_interval.max(1);
        ((self.steps / interval).min(3) as u32).min(self.model.gaussians.layout().sh_degree)
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
        r
    }

    /// One optimisation step on one observation.
    pub fn step(
        &mut self,
        obs: &Observation,
        lr_progress_in_round: f32,
    ) -> Result<StepStats, SunAwareError> {
        obs.validate()?;
        if !lr_progress_in_round.is_finite() {
            return Err(SunAwareError::Config(
                "lr_progress_in_round must be finite".into(),
            ));
        }
        let t_start = Instant::now();
        let settings = self.model.raster_settings(false);
        let degree = self.active_sh_degree();
        let (parts, pass, grads, loss_ms) =
            loss_and_grads(&self.model, obs, degree, &settings, None)?;
        let position_lr = self.position_lr(lr_progress_in_round);
        let mut stats = StepStats {
            step: self.steps,
            loss: parts.total,
            l1: parts.l1,
            ssim: parts.ssim,
            iso: parts.iso,
            visible: pass.visible_list.len(),
            gaussians: self.model.len(),
            position_lr,
            skipped: false,
            timings: StepTimings {
                cull_ms: pass.timings.cull_ms,
                shadow_pass_ms: pass.timings.shadow_pass_ms,
                mlp_forward_ms: pass.timings.mlp_forward_ms,
                raster_forward_ms: pass.timings.raster_ms,
                loss_ms,
                ..StepTimings::default()
            },
        };
        let forward_ms = pass.timings.cull_ms
            + pass.timings.shadow_pass_ms
            + pass.timings.mlp_forward_ms
            + pass.timings.raster_ms
            + loss_ms;
        let total_before_backward = t_start.elapsed().as_secs_f64() * 1e3;
        stats.timings.backward_ms = (total_before_backward - forward_ms).max(0.0);
        let grads = match grads {
            Some(g) if parts.total.is_finite() && g.first_non_finite().is_none() => g,
            _ => {
                self.skipped_nonfinite += 1;
                stats.skipped = true;
                stats.timings.total_ms = t_start.elapsed().as_secs_f64() * 1e3;
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
                .apply(net.mlp.params_mut(), &grads.appearance, lr);
        }
        if let Some(net) = &mut self.model.shadow {
            let lr = self.model.config.lr.shadow_mlp;
            self.shadow_adam
                .apply(net.mlp.params_mut(), &grads.shadow, lr);
        }
        self.densify_stats
            .accumulate(&grads.mean2d_grad_ndc, pass.visible(), pass.radii_px())?;
        self.steps += 1;
        stats.step = self.steps;
        stats.timings.optimiser_ms = t_opt.elapsed().as_secs_f64() * 1e3;
        stats.timings.total_ms = t_start.elapsed().as_secs_f64() * 1e3;
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
        let pass = self.forward(camera, sun_dir, degree, &settings, None)?;
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
    use super::capped_grad_threshold;

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
