//! Spherical-harmonic colour (degree 0-3) and its backward pass.
//!
//! Follows the reference 3DGS implementation exactly: the view direction is the unit
//! vector from the camera centre to the Gaussian's mean, the real SH basis uses the
//! 3DGS constants and signs, `0.5` is added to the result and each channel is clamped
//! at zero from below (not from above). A clamped channel passes no gradient.
//!
//! Invariants:
//! - `ShDc` holds 3 values per Gaussian; `ShRest` holds `(coeffs - 1) * 3` values,
//!   coefficient-major (`[c1.r, c1.g, c1.b, c2.r, ...]`);
//! - the active degree may be lower than the model's degree (the 3DGS degree schedule):
//!   the unused coefficients then get a zero gradient;
//! - a Gaussian at the camera centre (direction undefined) uses the direction
//!   `(0, 0, 1)` and passes no gradient to its mean, so nothing non-finite leaks out.

use glam::Vec3;
use rayon::prelude::*;

use crate::model::{sh_coeff_count, Param, ParamSet};

pub const SH_C0: f32 = 0.282_094_8;
pub const SH_C1: f32 = 0.488_602_52;
pub const SH_C2: [f32; 5] = [
    1.092_548_4,
    -1.092_548_4,
    0.315_391_57,
    -1.092_548_4,
    0.546_274_2,
];
pub const SH_C3: [f32; 7] = [
    -0.590_043_6,
    2.890_611_4,
    -0.457_045_8,
    0.373_176_33,
    -0.457_045_8,
    1.445_305_7,
    -0.590_043_6,
];

/// Rows per rayon task: SH evaluation is cheap, so small tasks cost more than they gain.
const ROWS_PER_TASK: usize = 4096;

/// Error from SH evaluation.
#[derive(Debug, Clone, PartialEq)]
pub enum ShError {
    /// The model carries a lower SH degree than the one asked for.
    Degree { requested: u32, available: u32 },
    /// An upstream gradient buffer had the wrong length.
    Length { expected: usize, got: usize },
    /// The gradient set has different group widths or row count from the parameters.
    GradientShape,
}

impl std::fmt::Display for ShError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ShError::Degree {
                requested,
                available,
            } => write!(
                f,
                "SH degree {requested} requested but the model stores degree {available}"
            ),
            ShError::Length { expected, got } => {
                write!(f, "expected {expected} colour gradient values, got {got}")
            }
            ShError::GradientShape => {
                write!(f, "gradient set does not match the parameter set's shape")
            }
        }
    }
}

impl std::error::Error for ShError {}

/// The 16 basis values at a unit direction (entries above the degree are zero).
pub fn sh_basis(degree: u32, dir: Vec3) -> [f32; 16] {
    let mut b = [0.0f32; 16];
    let (x, y, z) = (dir.x, dir.y, dir.z);
    b[0] = SH_C0;
    if degree >= 1 {
        b[1] = -SH_C1 * y;
        b[2] = SH_C1 * z;
        b[3] = -SH_C1 * x;
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        b[4] = SH_C2[0] * x * y;
        b[5] = SH_C2[1] * y * z;
        b[6] = SH_C2[2] * (2.0 * zz - xx - yy);
        b[7] = SH_C2[3] * x * z;
        b[8] = SH_C2[4] * (xx - yy);
        if degree >= 3 {
            b[9] = SH_C3[0] * y * (3.0 * xx - yy);
            b[10] = SH_C3[1] * x * y * z;
            b[11] = SH_C3[2] * y * (4.0 * zz - xx - yy);
            b[12] = SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
            b[13] = SH_C3[4] * x * (4.0 * zz - xx - yy);
            b[14] = SH_C3[5] * z * (xx - yy);
            b[15] = SH_C3[6] * x * (xx - 3.0 * yy);
        }
    }
    b
}

/// Partial derivatives of each basis function with respect to the (unnormalised) direction
/// components, `[d/dx, d/dy, d/dz]`, treating the basis as the polynomial in `x, y, z`.
fn sh_basis_jacobian(degree: u32, dir: Vec3) -> [Vec3; 16] {
    let mut j = [Vec3::ZERO; 16];
    let (x, y, z) = (dir.x, dir.y, dir.z);
    if degree >= 1 {
        j[1] = Vec3::new(0.0, -SH_C1, 0.0);
        j[2] = Vec3::new(0.0, 0.0, SH_C1);
        j[3] = Vec3::new(-SH_C1, 0.0, 0.0);
    }
    if degree >= 2 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        j[4] = SH_C2[0] * Vec3::new(y, x, 0.0);
        j[5] = SH_C2[1] * Vec3::new(0.0, z, y);
        j[6] = SH_C2[2] * Vec3::new(-2.0 * x, -2.0 * y, 4.0 * z);
        j[7] = SH_C2[3] * Vec3::new(z, 0.0, x);
        j[8] = SH_C2[4] * Vec3::new(2.0 * x, -2.0 * y, 0.0);
        if degree >= 3 {
            j[9] = SH_C3[0] * Vec3::new(6.0 * x * y, 3.0 * xx - 3.0 * yy, 0.0);
            j[10] = SH_C3[1] * Vec3::new(y * z, x * z, x * y);
            j[11] = SH_C3[2] * Vec3::new(-2.0 * x * y, 4.0 * zz - xx - 3.0 * yy, 8.0 * y * z);
            j[12] =
                SH_C3[3] * Vec3::new(-6.0 * x * z, -6.0 * y * z, 6.0 * zz - 3.0 * xx - 3.0 * yy);
            j[13] = SH_C3[4] * Vec3::new(4.0 * zz - 3.0 * xx - yy, -2.0 * x * y, 8.0 * x * z);
            j[14] = SH_C3[5] * Vec3::new(2.0 * x * z, -2.0 * y * z, xx - yy);
            j[15] = SH_C3[6] * Vec3::new(3.0 * xx - 3.0 * yy, -6.0 * x * y, 0.0);
        }
    }
    j
}

/// Unit view direction and the unnormalised length; `None` at the camera centre.
fn view_direction(mean: Vec3, camera_center: Vec3) -> Option<(Vec3, f32)> {
    let v = mean - camera_center;
    let len = v.length();
    (len.is_finite() && len > 1e-12).then(|| (v / len, len))
}

fn model_degree(params: &ParamSet) -> u32 {
    let rest = params.dim(Param::ShRest) / 3;
    match rest {
        0 => 0,
        3 => 1,
        8 => 2,
        _ => 3,
    }
}

fn check_degree(params: &ParamSet, active_degree: u32) -> Result<(), ShError> {
    let available = model_degree(params);
    if active_degree > available {
        return Err(ShError::Degree {
            requested: active_degree,
            available,
        });
    }
    Ok(())
}

/// Unclamped colour (before the zero clamp) of one Gaussian.
fn raw_colour(dc: &[f32], rest: &[f32], basis: &[f32; 16], coeffs: usize) -> [f32; 3] {
    let mut rgb = [0.5f32; 3];
    for c in 0..3 {
        rgb[c] += basis[0] * dc[c];
    }
    for k in 1..coeffs {
        for c in 0..3 {
            rgb[c] += basis[k] * rest[(k - 1) * 3 + c];
        }
    }
    rgb
}

/// RGB colour of every Gaussian seen from `camera_center`, `len * 3` values.
pub fn sh_to_rgb(
    params: &ParamSet,
    active_degree: u32,
    camera_center: Vec3,
) -> Result<Vec<f32>, ShError> {
    check_degree(params, active_degree)?;
    let coeffs = sh_coeff_count(active_degree);
    let rest_dim = params.dim(Param::ShRest);
    let means = params.get(Param::Mean);
    let dc = params.get(Param::ShDc);
    let rest = params.get(Param::ShRest);
    let mut out = vec![0.0f32; params.len() * 3];
    out.par_chunks_mut(ROWS_PER_TASK * 3)
        .enumerate()
        .for_each(|(task, chunk)| {
            for (local, rgb_out) in chunk.chunks_exact_mut(3).enumerate() {
                let i = task * ROWS_PER_TASK + local;
                let mean = Vec3::from_slice(&means[i * 3..i * 3 + 3]);
                let dir = view_direction(mean, camera_center).map_or(Vec3::Z, |(d, _)| d);
                let basis = sh_basis(active_degree, dir);
                let rgb = raw_colour(
                    &dc[i * 3..i * 3 + 3],
                    &rest[i * rest_dim..(i + 1) * rest_dim],
                    &basis,
                    coeffs,
                );
                for c in 0..3 {
                    rgb_out[c] = rgb[c].max(0.0);
                }
            }
        });
    Ok(out)
}

/// Backward of [`sh_to_rgb`]: adds the gradients of `d_rgb` (`len * 3`) to `grads`'
/// `ShDc`, `ShRest` and `Mean` groups.
pub fn sh_to_rgb_backward(
    params: &ParamSet,
    active_degree: u32,
    camera_center: Vec3,
    d_rgb: &[f32],
    grads: &mut ParamSet,
) -> Result<(), ShError> {
    check_degree(params, active_degree)?;
    if d_rgb.len() != params.len() * 3 {
        return Err(ShError::Length {
            expected: params.len() * 3,
            got: d_rgb.len(),
        });
    }
    if grads.dims() != params.dims() || grads.len() != params.len() {
        return Err(ShError::GradientShape);
    }
    let coeffs = sh_coeff_count(active_degree);
    let rest_dim = params.dim(Param::ShRest);
    let means = params.get(Param::Mean);
    let dc = params.get(Param::ShDc);
    let rest = params.get(Param::ShRest);

    // Per-row results are independent, so computing them in parallel and adding them in
    // row order afterwards keeps the result bit-identical for any thread count.
    struct RowGrad {
        d_dc: [f32; 3],
        d_rest: [f32; 45],
        d_mean: Vec3,
    }
    let rows: Vec<RowGrad> = (0..params.len())
        .into_par_iter()
        .with_min_len(ROWS_PER_TASK)
        .map(|i| {
            let mean = Vec3::from_slice(&means[i * 3..i * 3 + 3]);
            let view = view_direction(mean, camera_center);
            let dir = view.map_or(Vec3::Z, |(d, _)| d);
            let basis = sh_basis(active_degree, dir);
            let row_dc = &dc[i * 3..i * 3 + 3];
            let row_rest = &rest[i * rest_dim..(i + 1) * rest_dim];
            let raw = raw_colour(row_dc, row_rest, &basis, coeffs);
            let mut g = [0.0f32; 3];
            for c in 0..3 {
                // The clamp `max(raw, 0)` passes no gradient where it is active.
                g[c] = if raw[c] < 0.0 { 0.0 } else { d_rgb[i * 3 + c] };
            }
            let mut out = RowGrad {
                d_dc: [0.0; 3],
                d_rest: [0.0; 45],
                d_mean: Vec3::ZERO,
            };
            for (d, gc) in out.d_dc.iter_mut().zip(&g) {
                *d = basis[0] * gc;
            }
            for (chunk, b) in out.d_rest.chunks_exact_mut(3).zip(&basis[1..coeffs]) {
                for (d, gc) in chunk.iter_mut().zip(&g) {
                    *d = b * gc;
                }
            }
            if let (Some((dir, len)), true) = (view, coeffs > 1) {
                let jac = sh_basis_jacobian(active_degree, dir);
                let mut d_dir = Vec3::ZERO;
                for k in 1..coeffs {
                    let mut w = 0.0;
                    for c in 0..3 {
                        w += row_rest[(k - 1) * 3 + c] * g[c];
                    }
                    d_dir += jac[k] * w;
                }
                // d(v/|v|)/dv = (I - d d^T) / |v|, symmetric.
                out.d_mean = (d_dir - dir * dir.dot(d_dir)) / len;
            }
            out
        })
        .collect();

    let d_dc_all = grads.get_mut(Param::ShDc);
    for (i, r) in rows.iter().enumerate() {
        for c in 0..3 {
            d_dc_all[i * 3 + c] += r.d_dc[c];
        }
    }
    if rest_dim > 0 {
        let used = (coeffs - 1) * 3;
        let d_rest_all = grads.get_mut(Param::ShRest);
        for (i, r) in rows.iter().enumerate() {
            for (dst, src) in d_rest_all[i * rest_dim..i * rest_dim + used]
                .iter_mut()
                .zip(&r.d_rest[..used])
            {
                *dst += src;
            }
        }
    }
    let d_mean_all = grads.get_mut(Param::Mean);
    for (i, r) in rows.iter().enumerate() {
        d_mean_all[i * 3] += r.d_mean.x;
        d_mean_all[i * 3 + 1] += r.d_mean.y;
        d_mean_all[i * 3 + 2] += r.d_mean.z;
    }
    Ok(())
}

/// SH DC coefficient that renders as `rgb` (view-independent part), as 3DGS's `RGB2SH`.
pub fn rgb_to_sh_dc(rgb: f32) -> f32 {
    (rgb - 0.5) / SH_C0
}

/// Inverse of [`rgb_to_sh_dc`].
pub fn sh_dc_to_rgb(dc: f32) -> f32 {
    dc * SH_C0 + 0.5
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{GaussianModel, ModelLayout};

    /// Small deterministic generator for test data.
    fn lcg(state: &mut u64) -> f32 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((*state >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
    }

    fn random_model(n: usize, degree: u32, seed: u64) -> GaussianModel {
        let mut m = GaussianModel::new(ModelLayout::sh(degree)).unwrap();
        m.params.push_zeros(n);
        let mut s = seed;
        for p in [Param::Mean, Param::ShDc, Param::ShRest] {
            for v in m.params.get_mut(p) {
                *v = lcg(&mut s);
            }
        }
        // Keep the raw colour away from the clamp at zero so FD does not straddle it.
        for v in m.params.get_mut(Param::ShDc) {
            *v = v.abs() + 1.0;
        }
        m
    }

    #[test]
    fn degree_zero_is_the_dc_colour() {
        let m = random_model(5, 0, 1);
        let rgb = sh_to_rgb(&m.params, 0, Vec3::new(3.0, 0.0, 0.0)).unwrap();
        for (i, &v) in rgb.iter().enumerate() {
            let expected = sh_dc_to_rgb(m.params.get(Param::ShDc)[i]).max(0.0);
            assert_eq!(v, expected);
        }
        assert!((sh_dc_to_rgb(rgb_to_sh_dc(0.3)) - 0.3).abs() < 1e-6);
    }

    #[test]
    fn basis_is_orthonormal_on_the_sphere() {
        // Monte-Carlo-free check: integrate products over a Fibonacci sphere. With the
        // 3DGS sign conventions the basis is still orthonormal (signs do not matter).
        let n = 20000;
        let mut gram = [[0.0f64; 16]; 16];
        for i in 0..n {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f64 * std::f64::consts::PI * (3.0 - 5f64.sqrt());
            let d = Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32);
            let b = sh_basis(3, d);
            for (row, ba) in gram.iter_mut().zip(&b) {
                for (entry, bc) in row.iter_mut().zip(&b) {
                    *entry += *ba as f64 * *bc as f64 * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for (a, row) in gram.iter().enumerate() {
            for (c, entry) in row.iter().enumerate() {
                let expected = if a == c { 1.0 } else { 0.0 };
                // Quadrature error of 20k Fibonacci points on degree-6 polynomials.
                assert!((entry - expected).abs() < 2e-3, "gram[{a}][{c}] = {entry}");
            }
        }
    }

    #[test]
    fn lower_degree_ignores_higher_coefficients_and_too_high_is_an_error() {
        let m = random_model(4, 3, 2);
        let cam = Vec3::new(0.3, -4.0, 1.0);
        let a = sh_to_rgb(&m.params, 1, cam).unwrap();
        let mut m2 = m.clone();
        let rest = m2.params.get_mut(Param::ShRest);
        for i in 0..4 {
            for v in &mut rest[i * 45 + 9..(i + 1) * 45] {
                *v = 100.0;
            }
        }
        let b = sh_to_rgb(&m2.params, 1, cam).unwrap();
        assert_eq!(a, b);
        let low = random_model(2, 1, 3);
        assert!(matches!(
            sh_to_rgb(&low.params, 2, cam),
            Err(ShError::Degree { .. })
        ));
    }

    /// Central differences in f32 on a scalar loss `sum(w * rgb)`; the colour is a
    /// low-order polynomial of O(1) values, so h = 1e-2 has truncation error ~h^2 and a
    /// 2e-3 absolute tolerance is well above f32 round-off (~1e-5 / h).
    #[test]
    fn backward_matches_finite_differences() {
        for degree in 0..=3u32 {
            let m = random_model(6, 3, 10 + degree as u64);
            let cam = Vec3::new(0.4, -3.0, 2.5);
            let mut s = 99u64;
            let w: Vec<f32> = (0..m.len() * 3).map(|_| lcg(&mut s)).collect();
            let loss = |params: &ParamSet| -> f64 {
                let rgb = sh_to_rgb(params, degree, cam).unwrap();
                rgb.iter()
                    .zip(&w)
                    .map(|(a, b)| (*a as f64) * (*b as f64))
                    .sum()
            };
            let mut grads = m.params.zeros_like();
            sh_to_rgb_backward(&m.params, degree, cam, &w, &mut grads).unwrap();
            let h = 1e-2f32;
            for p in [Param::Mean, Param::ShDc, Param::ShRest] {
                for k in 0..m.params.get(p).len() {
                    let mut plus = m.params.clone();
                    plus.get_mut(p)[k] += h;
                    let mut minus = m.params.clone();
                    minus.get_mut(p)[k] -= h;
                    let fd = (loss(&plus) - loss(&minus)) / (2.0 * h as f64);
                    let an = grads.get(p)[k] as f64;
                    assert!(
                        (fd - an).abs() < 2e-3,
                        "degree {degree} {} [{k}]: fd {fd} analytic {an}",
                        p.name()
                    );
                }
            }
        }
    }

    #[test]
    fn clamped_channels_pass_no_gradient_and_centre_is_finite() {
        let mut m = random_model(2, 1, 5);
        m.params.get_mut(Param::ShDc)[0] = -10.0; // raw red of Gaussian 0 far below zero
        let cam = Vec3::from_slice(&m.params.get(Param::Mean)[3..6]); // Gaussian 1 at the camera
        let rgb = sh_to_rgb(&m.params, 1, cam).unwrap();
        assert_eq!(rgb[0], 0.0);
        assert!(rgb.iter().all(|v| v.is_finite()));
        let mut grads = m.params.zeros_like();
        sh_to_rgb_backward(&m.params, 1, cam, &[1.0; 6], &mut grads).unwrap();
        assert_eq!(grads.get(Param::ShDc)[0], 0.0);
        assert_eq!(grads.get(Param::ShRest)[0], 0.0);
        assert_eq!(&grads.get(Param::Mean)[3..6], &[0.0, 0.0, 0.0]);
        assert!(grads.get(Param::Mean).iter().all(|v| v.is_finite()));
        let bad = sh_to_rgb_backward(&m.params, 1, cam, &[1.0; 5], &mut grads);
        assert!(matches!(bad, Err(ShError::Length { .. })));
    }
}
