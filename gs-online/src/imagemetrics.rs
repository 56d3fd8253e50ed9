//! Photometric error of a predicted 8-bit image against the observed one: PSNR and SSIM.
//!
//! Both images are interleaved 8-bit (`channels` = 1 or 3), same size, compared on [0, 1].
//! SSIM uses the usual 11x11 Gaussian window (sigma 1.5), C1 = 0.01^2, C2 = 0.03^2, computed
//! per channel with zero padding outside the image ("same" convolution normalised by the
//! window weight inside the image) and averaged over pixels and channels.
//! Invariants: results are finite; identical images give PSNR clamped to
//! [`MAX_PSNR_DB`] and SSIM 1. Summation order is fixed, so results are deterministic.

use std::fmt;

/// PSNR reported for identical images (the bus message needs a finite number).
pub const MAX_PSNR_DB: f32 = 100.0;
const WINDOW_RADIUS: usize = 5;
const WINDOW_SIGMA: f64 = 1.5;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MetricsError {
    SizeMismatch { expected: usize, got: usize },
    Empty,
    BadChannels { channels: usize },
}

impl fmt::Display for MetricsError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::SizeMismatch { expected, got } => {
                write!(f, "image sizes differ: {expected} vs {got} bytes")
            }
            Self::Empty => f.write_str("empty image"),
            Self::BadChannels { channels } => write!(f, "{channels} channels (want 1 or 3)"),
        }
    }
}

impl std::error::Error for MetricsError {}

fn check(
    predicted: &[u8],
    observed: &[u8],
    width: usize,
    height: usize,
    channels: usize,
) -> Result<(), MetricsError> {
    if channels != 1 && channels != 3 {
        return Err(MetricsError::BadChannels { channels });
    }
    let expected = width * height * channels;
    if expected == 0 {
        return Err(MetricsError::Empty);
    }
    for got in [predicted.len(), observed.len()] {
        if got != expected {
            return Err(MetricsError::SizeMismatch { expected, got });
        }
    }
    Ok(())
}

/// Peak signal-to-noise ratio in dB on [0, 1] intensities.
pub fn psnr_db(
    predicted: &[u8],
    observed: &[u8],
    width: usize,
    height: usize,
    channels: usize,
) -> Result<f32, MetricsError> {
    check(predicted, observed, width, height, channels)?;
    let squared_error: u64 = predicted
        .iter()
        .zip(observed)
        .map(|(&a, &b)| {
            let d = u64::from(a.abs_diff(b));
            d * d
        })
        .sum();
    if squared_error == 0 {
        return Ok(MAX_PSNR_DB);
    }
    let mse = squared_error as f64 / (predicted.len() as f64 * 255.0 * 255.0);
    Ok((gs_core::loss::psnr_db_from_mse(mse) as f32).min(MAX_PSNR_DB))
}

fn gaussian_window() -> [f64; 2 * WINDOW_RADIUS + 1] {
    let mut w = [0.0; 2 * WINDOW_RADIUS + 1];
    for (i, value) in w.iter_mut().enumerate() {
        let x = i as f64 - WINDOW_RADIUS as f64;
        *value = (-x * x / (2.0 * WINDOW_SIGMA * WINDOW_SIGMA)).exp();
    }
    let sum: f64 = w.iter().sum();
    w.map(|v| v / sum)
}

/// Separable normalised Gaussian blur of one plane (weights renormalised at the borders).
fn blur(plane: &[f64], width: usize, height: usize, window: &[f64]) -> Vec<f64> {
    let r = WINDOW_RADIUS as isize;
    let pass = |input: &[f64], horizontal: bool| -> Vec<f64> {
        let mut out = vec![0.0; input.len()];
        for y in 0..height {
            for x in 0..width {
                let (mut acc, mut weight) = (0.0, 0.0);
                for k in -r..=r {
                    let (sx, sy) = if horizontal {
                        (x as isize + k, y as isize)
                    } else {
                        (x as isize, y as isize + k)
                    };
                    if sx < 0 || sy < 0 || sx >= width as isize || sy >= height as isize {
                        continue;
                    }
                    let w = window[(k + r) as usize];
                    acc += w * input[sy as usize * width + sx as usize];
                    weight += w;
                }
                out[y * width + x] = acc / weight;
            }
        }
        out
    };
    pass(&pass(plane, true), false)
}

/// Mean structural similarity on [0, 1] intensities, in [-1, 1].
pub fn ssim(
    predicted: &[u8],
    observed: &[u8],
    width: usize,
    height: usize,
    channels: usize,
) -> Result<f32, MetricsError> {
    check(predicted, observed, width, height, channels)?;
    const C1: f64 = 0.01 * 0.01;
    const C2: f64 = 0.03 * 0.03;
    let window = gaussian_window();
    let mut total = 0.0;
    for c in 0..channels {
        let plane = |img: &[u8]| -> Vec<f64> {
            img.iter()
                .skip(c)
                .step_by(channels)
                .map(|&v| f64::from(v) / 255.0)
                .collect()
        };
        let a = plane(predicted);
        let b = plane(observed);
        let product =
            |p: &[f64], q: &[f64]| -> Vec<f64> { p.iter().zip(q).map(|(x, y)| x * y).collect() };
        let mu_a = blur(&a, width, height, &window);
        let mu_b = blur(&b, width, height, &window);
        let aa = blur(&product(&a, &a), width, height, &window);
        let bb = blur(&product(&b, &b), width, height, &window);
        let ab = blur(&product(&a, &b), width, height, &window);
        for i in 0..a.len() {
            let var_a = aa[i] - mu_a[i] * mu_a[i];
            let var_b = bb[i] - mu_b[i] * mu_b[i];
            let cov = ab[i] - mu_a[i] * mu_b[i];
            total += ((2.0 * mu_a[i] * mu_b[i] + C1) * (2.0 * cov + C2))
                / ((mu_a[i] * mu_a[i] + mu_b[i] * mu_b[i] + C1) * (var_a + var_b + C2));
        }
    }
    let mean = total / (width * height * channels) as f64;
    Ok(mean.clamp(-1.0, 1.0) as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn psnr_matches_the_closed_form() {
        // Every byte off by 10: MSE = (10/255)^2, PSNR = 20 log10(255/10) = 28.1308 dB.
        let a = vec![100u8; 48];
        let b = vec![110u8; 48];
        let psnr = psnr_db(&a, &b, 4, 4, 3).unwrap();
        assert!((psnr - 28.130_8).abs() < 1e-3, "{psnr}");
        assert_eq!(psnr_db(&a, &a, 4, 4, 3).unwrap(), MAX_PSNR_DB);
    }

    #[test]
    fn ssim_is_one_for_identical_and_lower_for_noise() {
        let a: Vec<u8> = (0..32 * 32).map(|i| (i * 7 % 251) as u8).collect();
        assert!((ssim(&a, &a, 32, 32, 1).unwrap() - 1.0).abs() < 1e-6);
        let b: Vec<u8> = a.iter().map(|&v| 255 - v).collect();
        let s = ssim(&a, &b, 32, 32, 1).unwrap();
        assert!(s < 0.0, "inverted image should anti-correlate: {s}");
    }

    #[test]
    fn ssim_of_constant_images_follows_the_luminance_term() {
        // Constant images: variances and covariance vanish, so SSIM reduces to
        // (2 mu_a mu_b + C1) / (mu_a^2 + mu_b^2 + C1).
        let a = vec![51u8; 16 * 16];
        let b = vec![102u8; 16 * 16];
        let (ma, mb) = (0.2f64, 0.4f64);
        let expected = (2.0 * ma * mb + 1e-4) / (ma * ma + mb * mb + 1e-4);
        let s = ssim(&a, &b, 16, 16, 1).unwrap();
        assert!((f64::from(s) - expected).abs() < 1e-5, "{s} vs {expected}");
    }

    #[test]
    fn mismatched_sizes_are_errors() {
        assert_eq!(
            psnr_db(&[0; 3], &[0; 4], 1, 1, 3),
            Err(MetricsError::SizeMismatch {
                expected: 3,
                got: 4
            })
        );
        assert_eq!(ssim(&[], &[], 0, 0, 1), Err(MetricsError::Empty));
    }
}
