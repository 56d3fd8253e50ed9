//! An optional Lambertian shading factor on each Gaussian's colour, so that the model's
//! brightness follows the Sun direction by construction instead of only through Phi's
//! positional encoding of the Sun (which sees one cone of Sun directions during a
//! rendezvous and cannot extrapolate off it: docs/results/accuracy.md section 6).
//!
//! With [`Shading::Lambert`] a Gaussian's colour (Phi's output, or its SH colour in
//! configuration a) is multiplied by
//!
//! `f_i = k_a + (1 - k_a) * max(0, n_i . s)`
//!
//! with `s` the unit Sun vector (target body frame), `k_a` the ambient floor
//! (`SunAwareConfig::shading_ambient`) and `n_i` the Gaussian's shortest scale axis (a
//! column of its rotation), flipped to face the camera (GaussianShader / relightable 3DGS
//! style). The normal needs no new per-Gaussian state: checkpoints only carry the setting.
//!
//! Gradients: `f_i` flows into the colour (`dL/dc = f_i dL/dc'`) and, where the Gaussian is
//! lit (`n_i . s > 0`), into its rotation through `n_i`. The choice of axis (argmin of the
//! log-scales) and the flip toward the camera are piecewise constant: no gradient reaches
//! scales or means through them. A Gaussian with a non-finite or degenerate rotation or
//! scale (the rasterizer culls those) gets `f_i = 1` and no gradient, so nothing
//! non-finite leaves this module.

use std::str::FromStr;

use glam::Vec3;

use crate::model::{Param, ParamSet};
use crate::raster::project::MIN_QUAT_NORM2;

use super::error::SunAwareError;

/// How a Gaussian's colour depends on the Sun beyond Phi (see the module header).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Shading {
    /// The paper's form: the colour is Phi's output (or SH) as it is.
    #[default]
    None,
    /// `colour * (k_a + (1 - k_a) max(0, n . s))`, `n` the shortest scale axis facing the
    /// camera.
    Lambert,
}

impl Shading {
    pub fn name(self) -> &'static str {
        match self {
            Shading::None => "none",
            Shading::Lambert => "lambert",
        }
    }

    pub(crate) fn code(self) -> u8 {
        match self {
            Shading::None => 0,
            Shading::Lambert => 1,
        }
    }

    pub(crate) fn from_code(code: u8) -> Option<Self> {
        match code {
            0 => Some(Shading::None),
            1 => Some(Shading::Lambert),
            _ => None,
        }
    }
}

impl FromStr for Shading {
    type Err = SunAwareError;

    /// `none` or `lambert` (either case).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "none" => Ok(Shading::None),
            "lambert" => Ok(Shading::Lambert),
            other => Err(SunAwareError::Config(format!(
                "unknown shading {other:?}: expected none or lambert"
            ))),
        }
    }
}

impl std::fmt::Display for Shading {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Per-Gaussian shading of one view, kept from forward for backward.
#[derive(Clone, Debug, Default)]
pub struct ShadePass {
    /// `f_i` for every Gaussian (1 where it was not computed).
    pub factor: Vec<f32>,
    /// The colour before shading, `n * 3` (what `dL/d f_i` multiplies).
    pub unshaded: Vec<f32>,
    /// Index of the rotation column used as the normal, its sign (+1 or -1), or
    /// `u8::MAX` where `f_i` is constant (unlit, degenerate or not computed).
    axis: Vec<(u8, f32)>,
}

/// Column `k` of the rotation of the unit quaternion `q` (`[w, x, y, z]`, the
/// rasterizer's convention: axis `k` of the Gaussian is column `k`).
fn axis_of(q: [f32; 4], k: usize) -> [f32; 3] {
    let [w, x, y, z] = q;
    match k {
        0 => [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y + w * z),
            2.0 * (x * z - w * y),
        ],
        1 => [
            2.0 * (x * y - w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z + w * x),
        ],
        _ => [
            2.0 * (x * z + w * y),
            2.0 * (y * z - w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    }
}

/// `dL/dq` (unit quaternion `q`) from `dL/d axis_of(q, k)`.
fn axis_backward(q: [f32; 4], k: usize, d: [f32; 3]) -> [f32; 4] {
    let [w, x, y, z] = q;
    // Rows: d axis[r] / d (w, x, y, z).
    let jac: [[f32; 4]; 3] = match k {
        0 => [
            [0.0, 0.0, -4.0 * y, -4.0 * z],
            [2.0 * z, 2.0 * y, 2.0 * x, 2.0 * w],
            [-2.0 * y, 2.0 * z, -2.0 * w, 2.0 * x],
        ],
        1 => [
            [-2.0 * z, 2.0 * y, 2.0 * x, -2.0 * w],
            [0.0, -4.0 * x, 0.0, -4.0 * z],
            [2.0 * x, 2.0 * w, 2.0 * z, 2.0 * y],
        ],
        _ => [
            [2.0 * y, 2.0 * z, 2.0 * w, 2.0 * x],
            [-2.0 * x, -2.0 * w, 2.0 * z, 2.0 * y],
            [0.0, -4.0 * x, -4.0 * y, 0.0],
        ],
    };
    let mut out = [0.0f32; 4];
    for (r, row) in jac.iter().enumerate() {
        for (o, j) in out.iter_mut().zip(row) {
            *o += d[r] * j;
        }
    }
    out
}

/// The normal of Gaussian `g` (unit, its shortest scale axis turned toward `cam_pos`),
/// with the axis index, the sign applied and the cosine between the normal and the
/// direction to the camera; `None` for a non-finite or degenerate Gaussian. Where that
/// cosine crosses 0 the normal flips: `f_i` jumps there (as in GaussianShader), so finite
/// differences are only meaningful away from it.
pub fn facing_normal(params: &ParamSet, g: usize, cam_pos: Vec3) -> Option<FacingNormal> {
    let q = params.row(Param::Rotation, g);
    let ls = params.row(Param::LogScale, g);
    let mean = params.row(Param::Mean, g);
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    let q_norm2: f32 = q.iter().map(|v| v * v).sum();
    if !(finite(q) && finite(ls) && finite(mean) && q_norm2.is_finite()) || q_norm2 < MIN_QUAT_NORM2
    {
        return None;
    }
    let q_norm = q_norm2.sqrt();
    let q_hat = [q[0] / q_norm, q[1] / q_norm, q[2] / q_norm, q[3] / q_norm];
    // The first smallest scale: ties resolve the same way every run.
    let axis = (1..3).fold(0, |k, j| if ls[j] < ls[k] { j } else { k });
    let a = Vec3::from(axis_of(q_hat, axis));
    let to_cam = (cam_pos - Vec3::from([mean[0], mean[1], mean[2]])).normalize_or_zero();
    let facing = a.dot(to_cam);
    let sign = if facing < 0.0 { -1.0 } else { 1.0 };
    Some(FacingNormal {
        normal: a * sign,
        axis,
        sign,
        facing_cos: facing.abs(),
    })
}

/// See [`facing_normal`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FacingNormal {
    pub normal: Vec3,
    /// Which rotation column (the shortest scale axis).
    pub axis: usize,
    /// +1 or -1: the column turned toward the camera.
    pub sign: f32,
    /// `|axis . direction to the camera|`.
    pub facing_cos: f32,
}

/// `f_i` for the Gaussians in `list` (every other one keeps 1), with what backward needs.
/// `colour` is the unshaded colour, `n * 3`; it is scaled in place.
pub fn shade_forward(
    params: &ParamSet,
    list: &[u32],
    cam_pos: Vec3,
    sun_dir: Vec3,
    ambient: f32,
    colour: &mut [f32],
) -> ShadePass {
    let n = colour.len() / 3;
    let mut pass = ShadePass {
        factor: vec![1.0; n],
        unshaded: colour.to_vec(),
        axis: vec![(u8::MAX, 1.0); n],
    };
    for &g in list {
        let g = g as usize;
        let Some(normal) = facing_normal(params, g, cam_pos) else {
            continue;
        };
        let cos = normal.normal.dot(sun_dir);
        let f = if cos > 0.0 {
            pass.axis[g] = (normal.axis as u8, normal.sign);
            ambient + (1.0 - ambient) * cos
        } else {
            ambient
        };
        pass.factor[g] = f;
        for c in &mut colour[g * 3..g * 3 + 3] {
            *c *= f;
        }
    }
    pass
}

/// Backward of [`shade_forward`]: `d_colour` (`dL/d` shaded colour, `n * 3`) becomes
/// `dL/d` unshaded colour in place, and the normal's term is added to the rotation
/// gradient in `grads`.
pub fn shade_backward(
    pass: &ShadePass,
    params: &ParamSet,
    sun_dir: Vec3,
    ambient: f32,
    d_colour: &mut [f32],
    grads: &mut ParamSet,
) {
    let s = sun_dir.to_array();
    let d_rot = grads.get_mut(Param::Rotation);
    for (g, &f) in pass.factor.iter().enumerate() {
        let d = &mut d_colour[g * 3..g * 3 + 3];
        let d_f: f32 = (0..3).map(|c| d[c] * pass.unshaded[g * 3 + c]).sum();
        for v in d.iter_mut() {
            *v *= f;
        }
        let (k, sign) = pass.axis[g];
        if k == u8::MAX || d_f == 0.0 {
            continue;
        }
        let q = params.row(Param::Rotation, g);
        let q_norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        let q_hat = [q[0] / q_norm, q[1] / q_norm, q[2] / q_norm, q[3] / q_norm];
        let scale = d_f * (1.0 - ambient) * sign;
        let d_axis = [scale * s[0], scale * s[1], scale * s[2]];
        let d_hat = axis_backward(q_hat, k as usize, d_axis);
        // Through q_hat = q / |q|: the component along q_hat drops out.
        let dot: f32 = (0..4).map(|j| d_hat[j] * q_hat[j]).sum();
        let grad: Vec<f32> = (0..4)
            .map(|j| (d_hat[j] - q_hat[j] * dot) / q_norm)
            .collect();
        if grad.iter().all(|v| v.is_finite()) {
            for (o, v) in d_rot[g * 4..g * 4 + 4].iter_mut().zip(grad) {
                *o += v;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_unknown_ones_are_refused() {
        for s in [Shading::None, Shading::Lambert] {
            assert_eq!(s.name().parse::<Shading>().unwrap(), s);
            assert_eq!(Shading::from_code(s.code()), Some(s));
        }
        let err = "phong".parse::<Shading>().unwrap_err().to_string();
        assert!(err.contains("none or lambert"), "{err}");
        assert_eq!(Shading::from_code(7), None);
    }

    #[test]
    fn axis_jacobian_matches_finite_differences() {
        let q = [0.8f32, 0.3, -0.4, 0.33];
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        let q = q.map(|v| v / norm);
        let d = [0.7f32, -0.2, 0.5];
        for k in 0..3 {
            let analytic = axis_backward(q, k, d);
            for j in 0..4 {
                let eps = 1e-3f32;
                let (mut hi, mut lo) = (q, q);
                hi[j] += eps;
                lo[j] -= eps;
                let f = |q: [f32; 4]| -> f32 { (0..3).map(|r| axis_of(q, k)[r] * d[r]).sum() };
                let numeric = (f(hi) - f(lo)) / (2.0 * eps);
                assert!(
                    (analytic[j] - numeric).abs() < 2e-3,
                    "axis {k}, q[{j}]: {} vs {numeric}",
                    analytic[j]
                );
            }
        }
    }
}
