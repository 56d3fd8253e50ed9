//! Photometric losses (L1, SSIM) with analytic backward, and metrics (PSNR, SSIM).
//!
//! Images are `height * width * channels` values, pixel-major (`[p0.r, p0.g, p0.b, p1.r,
//! ...]`), rows top to bottom, as the rasterizer writes them.
//!
//! SSIM follows the reference 3DGS code: an 11x11 Gaussian window (sigma 1.5, normalised
//! to sum 1) applied separably with ZERO padding and "same" output size, C1 = 0.01^2,
//! C2 = 0.03^2, one SSIM map per channel, then the mean over pixels and channels.
//! The backward pass is analytic: with `mu = F x`, `m_xx = F x^2`, `m_xy = F (x y)`
//! (F the window filter, y the fixed target), the per-pixel derivatives of the SSIM map
//! with respect to `mu`, `m_xx`, `m_xy` are filtered back with F^T (= F: the window is
//! symmetric and zero padding makes the transpose the same operation) and combined as
//! `dL/dx = F^T g_mu + 2 x F^T g_xx + y F^T g_xy`.
//!
//! One fused pass computes it all (`fused::fused_pass`): bands of rows in
//! parallel, each streaming rows through two ring buffers of 11 rows (moments filtered along
//! rows; the map's derivatives filtered along rows), so nothing image-sized is stored but the
//! result; the L1 term rides along. Filters are lane loops over 16 columns at a time, compiled
//! for AVX-512F / AVX2 where the CPU has them and plainly otherwise (the same bits: Rust never
//! fuses multiplies and adds). Each filtered value is the same sum in the same order as
//! filtering whole planes one after another, so the gradient does not depend on bands, threads
//! or instruction set; the totals are summed per row in a fixed lane order, then over rows in
//! order, so they do not either (and are far more accurate in f32 than one serial sum over
//! every pixel: tested against f64 within 1e-6).
//!
//! How the foreground mask enters (`mask`: one weight in [0, 1] per pixel): both terms
//! become mask-weighted means over pixels, `L1 = sum_p m_p sum_c |x - y| / (C sum_p m_p)`
//! and `SSIM = sum_p m_p sum_c S_c(p) / (C sum_p m_p)`. The images themselves are NOT
//! masked: the SSIM window of a pixel inside the mask still sees its neighbours outside
//! it, so pixels within 5 px of the mask receive gradient too; pixels farther out get
//! exactly zero. An all-zero mask is an error (nothing to learn from).
//!
//! The loss is `(1 - lambda) L1 + lambda (1 - SSIM)`, 3DGS uses lambda = 0.2.
//! Internally the maths is generic over f32 (training) and f64 (metrics, gradient
//! checks), so the finite-difference reference runs the very same code in double.

use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub};

/// SSIM stabilisers for a dynamic range of 1.
pub const SSIM_C1: f64 = 0.01 * 0.01;
pub const SSIM_C2: f64 = 0.03 * 0.03;
/// Window side and standard deviation, pixels.
pub const SSIM_WINDOW: usize = 11;
pub const SSIM_SIGMA_PX: f64 = 1.5;
const HALF: usize = SSIM_WINDOW / 2;

/// Size of an image buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageShape {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
}

impl ImageShape {
    pub fn new(width: usize, height: usize, channels: usize) -> Self {
        Self {
            width,
            height,
            channels,
        }
    }

    pub fn pixels(&self) -> usize {
        self.width * self.height
    }

    pub fn values(&self) -> usize {
        self.pixels() * self.channels
    }
}

/// Error from a loss or metric.
#[derive(Debug, Clone, PartialEq)]
pub enum LossError {
    /// A buffer did not match the image shape.
    Length {
        what: &'static str,
        expected: usize,
        got: usize,
    },
    /// Zero width, height or channels.
    EmptyImage,
    /// A NaN or infinity in an input buffer.
    NonFinite { what: &'static str, index: usize },
    /// A mask weight outside [0, 1].
    MaskRange { index: usize, value: f32 },
    /// The mask is zero everywhere.
    EmptyMask,
    /// `lambda_dssim` outside [0, 1].
    Lambda(f32),
}

impl std::fmt::Display for LossError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LossError::Length {
                what,
                expected,
                got,
            } => write!(f, "{what}: expected {expected} values, got {got}"),
            LossError::EmptyImage => write!(f, "image has zero width, height or channels"),
            LossError::NonFinite { what, index } => {
                write!(f, "{what}: non-finite value at index {index}")
            }
            LossError::MaskRange { index, value } => {
                write!(f, "mask weight {value} at pixel {index} is outside [0, 1]")
            }
            LossError::EmptyMask => write!(f, "mask is zero everywhere"),
            LossError::Lambda(l) => write!(f, "lambda_dssim {l} is outside [0, 1]"),
        }
    }
}

impl std::error::Error for LossError {}

/// The scalar type the loss maths runs in (f32 for training, f64 for references).
pub(crate) trait Real:
    Copy
    + Send
    + Sync
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
{
    const ZERO: Self;
    fn from_f64(v: f64) -> Self;
}

impl Real for f32 {
    const ZERO: Self = 0.0;
    fn from_f64(v: f64) -> Self {
        v as f32
    }
}

impl Real for f64 {
    const ZERO: Self = 0.0;
    fn from_f64(v: f64) -> Self {
        v
    }
}

/// Normalised 1D Gaussian window taps (sum 1), computed in f64.
pub fn ssim_window() -> [f64; SSIM_WINDOW] {
    let mut w = [0.0f64; SSIM_WINDOW];
    for (k, v) in w.iter_mut().enumerate() {
        let d = k as f64 - HALF as f64;
        *v = (-d * d / (2.0 * SSIM_SIGMA_PX * SSIM_SIGMA_PX)).exp();
    }
    let sum: f64 = w.iter().sum();
    w.iter_mut().for_each(|v| *v /= sum);
    w
}

fn check_image(what: &'static str, v: &[f32], shape: ImageShape) -> Result<(), LossError> {
    if shape.values() == 0 {
        return Err(LossError::EmptyImage);
    }
    if v.len() != shape.values() {
        return Err(LossError::Length {
            what,
            expected: shape.values(),
            got: v.len(),
        });
    }
    if let Some(index) = first_non_finite(v) {
        return Err(LossError::NonFinite { what, index });
    }
    Ok(())
}

/// Index of the first NaN or infinity. Whole chunks are tested without an early exit (the
/// test vectorises; a plain `position` runs one value per cycle), then the first bad chunk
/// is searched.
pub(crate) fn first_non_finite(v: &[f32]) -> Option<usize> {
    const CHUNK: usize = 512;
    for (ci, chunk) in v.chunks(CHUNK).enumerate() {
        if !chunk.iter().fold(true, |ok, x| ok & x.is_finite()) {
            return chunk
                .iter()
                .position(|x| !x.is_finite())
                .map(|i| ci * CHUNK + i);
        }
    }
    None
}

/// Per-pixel weights `m_p / (C sum m)`, in the loss's scalar type.
fn pixel_weights<T: Real>(mask: Option<&[f32]>, shape: ImageShape) -> Result<Vec<T>, LossError> {
    let n = shape.pixels();
    match mask {
        None => {
            let w = T::from_f64(1.0 / (n * shape.channels) as f64);
            Ok(vec![w; n])
        }
        Some(m) => {
            if m.len() != n {
                return Err(LossError::Length {
                    what: "mask",
                    expected: n,
                    got: m.len(),
                });
            }
            if let Some(index) = m.iter().position(|v| !v.is_finite()) {
                return Err(LossError::NonFinite {
                    what: "mask",
                    index,
                });
            }
            if let Some(index) = m.iter().position(|&v| !(0.0..=1.0).contains(&v)) {
                return Err(LossError::MaskRange {
                    index,
                    value: m[index],
                });
            }
            let sum: f64 = m.iter().map(|&v| v as f64).sum();
            if sum <= 0.0 {
                return Err(LossError::EmptyMask);
            }
            let norm = 1.0 / (sum * shape.channels as f64);
            Ok(m.iter().map(|&v| T::from_f64(v as f64 * norm)).collect())
        }
    }
}

mod filter;
mod fused;
mod metrics;
mod photometric;
#[cfg(test)]
mod reference;
#[cfg(test)]
mod tests;

pub use metrics::{psnr, psnr_db_from_mse, ssim};
pub use photometric::{photometric_loss, LossOutput};
