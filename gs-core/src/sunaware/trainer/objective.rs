//! The objective of one observation: forward, `(1 - l) L1 + l (1 - SSIM)` on the (masked)
//! image, `+ lambda_iso L_iso` in configuration (d), and backward, without touching the model.
//!
//! Invariants: a non-finite render or loss returns no gradients (the step then counts a
//! skip); the masked-background tile skip leaves the loss and every gradient the same bits.

use std::time::Instant;

use crate::loss::{photometric_loss, SSIM_WINDOW};
use crate::model::Param;
use crate::raster::bin::TileSelection;
use crate::raster::RasterSettings;
use crate::regularizer::IsotropicLoss;
use crate::sunaware::error::SunAwareError;
use crate::sunaware::model::{FramePass, SunAwareGrads, SunAwareModel};

use super::{ms_since, Observation, StepTimings};

/// Loss parts of one image.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LossParts {
    pub total: f32,
    pub l1: f32,
    pub ssim: f32,
    pub iso: f32,
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
