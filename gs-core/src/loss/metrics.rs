//! Image metrics for evaluation: mean SSIM and PSNR (in f64, on images clamped to
//! [0, 1], as 3DGS evaluates renders), and the project's one PSNR formula
//! ([`psnr_db_from_mse`]).
//!
//! Invariant: inputs are checked (size, finiteness) before any arithmetic; a bad image is a
//! [`LossError`], never a panic.

use super::fused::{fused_pass, GradForm, Split};
use super::{check_image, pixel_weights, ImageShape, LossError, Real};

/// Weighted SSIM of two images and optionally its gradient with respect to `x`.
///
/// `pixel_weight[p]` is the weight of pixel `p`'s SSIM values, already divided by the
/// normaliser, so the result is `sum_p sum_c pixel_weight[p] S_c(p)`.
fn weighted_ssim<T: Real>(
    x: &[T],
    y: &[T],
    shape: ImageShape,
    pixel_weight: &[T],
    want_grad: bool,
) -> (T, Option<Vec<T>>) {
    let grad = if want_grad {
        GradForm::Ssim
    } else {
        GradForm::None
    };
    let split = Split::default_for(shape.height);
    let out = fused_pass(x, y, shape, pixel_weight, false, grad, split);
    (out.ssim, want_grad.then_some(out.grad))
}

fn clamp_unit(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| x.clamp(0.0, 1.0) as f64).collect()
}

/// Mean SSIM over pixels and channels (same window as the loss), computed in f64 on
/// images clamped to [0, 1] as 3DGS evaluates renders.
pub fn ssim(a: &[f32], b: &[f32], shape: ImageShape) -> Result<f32, LossError> {
    check_image("first image", a, shape)?;
    check_image("second image", b, shape)?;
    let weights = pixel_weights::<f64>(None, shape)?;
    let (s, _) = weighted_ssim(&clamp_unit(a), &clamp_unit(b), shape, &weights, false);
    Ok(s as f32)
}

/// PSNR in dB of a mean squared error on [0, 1] intensities: `10 log10(1 / MSE)`; zero
/// error gives `f64::INFINITY` (callers that report a number clamp it). The one PSNR
/// formula of the project: every metric (masked, 8-bit, pooled) reduces to an MSE first.
pub fn psnr_db_from_mse(mse: f64) -> f64 {
    if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

/// PSNR in dB, `10 log10(1 / MSE)`, over all values of images clamped to [0, 1];
/// identical images give `f32::INFINITY`.
pub fn psnr(a: &[f32], b: &[f32], shape: ImageShape) -> Result<f32, LossError> {
    check_image("first image", a, shape)?;
    check_image("second image", b, shape)?;
    let mse: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = x.clamp(0.0, 1.0) as f64 - y.clamp(0.0, 1.0) as f64;
            d * d
        })
        .sum::<f64>()
        / a.len() as f64;
    Ok(psnr_db_from_mse(mse) as f32)
}
