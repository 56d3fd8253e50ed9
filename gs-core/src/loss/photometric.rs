//! The training loss: `(1 - lambda) L1 + lambda (1 - SSIM)` with its analytic gradient
//! ([`photometric_loss`]), mask-weighted as the module header of `loss` describes.
//!
//! Invariant: images, mask and lambda are checked before any arithmetic; nothing
//! non-finite reaches the fused pass.

use super::fused::{default_band_rows, fused_pass, GradForm, Isa, Split};
use super::{check_image, pixel_weights, ImageShape, LossError, Real};

/// Value and gradient of the combined loss.
#[derive(Clone, Debug, PartialEq)]
pub struct LossOutput {
    /// `(1 - lambda) l1 + lambda (1 - ssim)`.
    pub loss: f32,
    /// (Masked) mean absolute error.
    pub l1: f32,
    /// (Masked) mean SSIM.
    pub ssim: f32,
    /// Gradient of `loss` with respect to the rendered image, same layout.
    pub d_rendered: Vec<f32>,
}

pub(super) fn photometric_loss_generic<T: Real>(
    rendered: &[T],
    target: &[T],
    weights: &[T],
    shape: ImageShape,
    lambda_dssim: f64,
) -> (T, T, T, Vec<T>) {
    let band_rows = default_band_rows(shape.height);
    photometric_loss_with(
        rendered,
        target,
        weights,
        shape,
        lambda_dssim,
        band_rows,
        Isa::Detect,
    )
}

/// [`photometric_loss_generic`] with the band height and instruction set chosen (tests).
pub(super) fn photometric_loss_with<T: Real>(
    rendered: &[T],
    target: &[T],
    weights: &[T],
    shape: ImageShape,
    lambda_dssim: f64,
    band_rows: usize,
    isa: Isa,
) -> (T, T, T, Vec<T>) {
    let lambda = T::from_f64(lambda_dssim);
    let one = T::from_f64(1.0);
    let l1_scale = one - lambda;
    let grad = if lambda_dssim > 0.0 {
        GradForm::Mixed {
            l1_scale,
            ssim_scale: lambda,
        }
    } else {
        // SSIM is not part of the loss: report it without paying for its backward.
        GradForm::L1 { l1_scale }
    };
    let out = fused_pass(
        rendered,
        target,
        shape,
        weights,
        true,
        grad,
        Split { band_rows, isa },
    );
    let loss = l1_scale * out.l1 + lambda * (one - out.ssim);
    (loss, out.l1, out.ssim, out.grad)
}

/// `(1 - lambda_dssim) L1 + lambda_dssim (1 - SSIM)` of `rendered` against `target`, with
/// its analytic gradient. See the module header for how `mask` enters.
pub fn photometric_loss(
    rendered: &[f32],
    target: &[f32],
    mask: Option<&[f32]>,
    shape: ImageShape,
    lambda_dssim: f32,
) -> Result<LossOutput, LossError> {
    check_image("rendered image", rendered, shape)?;
    check_image("target image", target, shape)?;
    if !(0.0..=1.0).contains(&lambda_dssim) {
        return Err(LossError::Lambda(lambda_dssim));
    }
    let weights = pixel_weights::<f32>(mask, shape)?;
    let (loss, l1, ssim, d_rendered) =
        photometric_loss_generic(rendered, target, &weights, shape, lambda_dssim as f64);
    Ok(LossOutput {
        loss,
        l1,
        ssim,
        d_rendered,
    })
}
