//! Renders and scores of a Sun-aware model: the images of a view at the full SH degree,
//! and PSNR / SSIM against an observation, over its mask's pixels or the whole image.
//!
//! Invariants: images are clamped to [0, 1] before scoring; a mask that is zero everywhere
//! is an error, never a NaN score.

use glam::Vec3;

use crate::camera::Camera;
use crate::loss::{photometric_loss, psnr, ssim, ImageShape};
use crate::sunaware::error::SunAwareError;
use crate::sunaware::model::SunAwareModel;

use super::{Observation, SunAwareTrainer};

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

impl SunAwareTrainer {
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
