//! An optional Lambertian shading factor on each Gaussian's colour, so that the model's
//! brightness follows the Sun direction by construction instead of only through Phi's
//! positional encoding of the Sun (which sees one cone of Sun directions during a
//! rendezvous and cannot extrapolate off it: docs/results/accuracy.md section 6).
//!
//! With [`Shading::Lambert`] or [`Shading::LambertLearned`] a Gaussian's colour (Phi's
//! output) is multiplied by
//!
//! `f_i = k_a + (1 - k_a) * max(0, n_i . s)`
//!
//! with `s` the unit Sun vector (target body frame), `k_a` the ambient floor
//! (`SunAwareConfig::shading_ambient`) and `n_i` a unit normal flipped to face the camera
//! (GaussianShader / relightable 3DGS style):
//! - `Lambert`: the Gaussian's shortest scale axis (a column of its rotation). No new
//!   per-Gaussian state: checkpoints only carry the setting.
//! - `LambertLearned`: `v_i / |v_i|` with `v_i` the Gaussian's own parameter group
//!   `Param::Normal` (width 3 only under this setting), so the shading is oriented
//!   independently of the Gaussian's shape (configuration d's isotropic loss makes the
//!   shortest axis a poor normal). [`initial_normals`] starts `v_i` from what the
//!   initialiser knew (a surface normal) or from the Gaussian's shape and position.
//!
//! Gradients: `f_i` flows into the colour (`dL/dc = f_i dL/dc'`) and, where the Gaussian is
//! lit (`n_i . s > 0`), into its rotation (`Lambert`) or into `v_i` through the
//! normalisation (`LambertLearned`). The choice of axis (argmin of the log-scales) and the
//! flip toward the camera are piecewise constant: no gradient reaches scales or means
//! through them. A Gaussian with a non-finite or degenerate rotation, scale or normal
//! (`|v_i|^2 < MIN_NORMAL_NORM2`) gets `f_i = 1` and no gradient, so nothing non-finite
//! leaves this module.
//!
//! Local inputs of Phi (`SunAwareConfig::appearance_inputs` = `Local` / `LocalNoSun`,
//! `LambertLearned` only): [`local_inputs`] gives `[n.s, n.v, n.h]` with `n` the same
//! facing learned normal as the shading ([`learned_facing_normal`]), `s` the unit Sun, `v`
//! the unit vector from the Gaussian to the camera and `h = (s + v) / |s + v|`;
//! [`local_inputs_backward`] routes their gradient into `Param::Normal` (through the
//! normalisation; the flip is piecewise constant) and into the mean (through `v` and `h`).
//! A degenerate normal gives three zeros and no gradient; `|s + v|^2 <`
//! [`MIN_HALF_NORM2`] gives `n.h = 0` with no gradient through it.
//!
//! Devices: the wgpu backend's device-resident step runs `LambertLearned` and the local
//! inputs with these functions' operations ported in order (gs-wgpu `network_io`: the
//! factor in Phi's scatter and output gradient, tested against [`shade_forward`] and
//! [`shade_backward`]; the local inputs in Phi's input rows and input gradient, tested
//! against [`assemble_phi_input`] and [`scatter_local_input_grad`]); `Lambert` is CPU-only
//! (the engine refuses it).

use std::str::FromStr;

use glam::Vec3;
use rayon::prelude::*;

use crate::model::{Param, ParamSet};
use crate::nn::appearance::{view_direction, LOCAL_INPUTS};
use crate::nn::AppearanceNet;
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
    /// The same factor with `n` the Gaussian's learned normal (`Param::Normal`, used as
    /// `v / |v|`) facing the camera.
    LambertLearned,
}

/// `|v|^2` below which a learned normal is degenerate (factor 1, no gradient): the
/// rasterizer's threshold for quaternions, for the same reason (a direction from a vector
/// that small is noise).
pub const MIN_NORMAL_NORM2: f32 = MIN_QUAT_NORM2;

/// The `axis` code of [`FacingNormal`] for a learned normal.
pub const LEARNED_AXIS: usize = 3;

impl Shading {
    pub fn name(self) -> &'static str {
        match self {
            Shading::None => "none",
            Shading::Lambert => "lambert",
            Shading::LambertLearned => "lambert_learned",
        }
    }

    pub(crate) fn code(self) -> u8 {
        match self {
            Shading::None => 0,
            Shading::Lambert => 1,
            Shading::LambertLearned => 2,
        }
    }

    pub(crate) fn from_code(code: u8) -> Option<Self> {
        match code {
            0 => Some(Shading::None),
            1 => Some(Shading::Lambert),
            2 => Some(Shading::LambertLearned),
            _ => None,
        }
    }
}

impl FromStr for Shading {
    type Err = SunAwareError;

    /// `none`, `lambert` or `lambert_learned` (either case).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "none" => Ok(Shading::None),
            "lambert" => Ok(Shading::Lambert),
            "lambert_learned" => Ok(Shading::LambertLearned),
            other => Err(SunAwareError::Config(format!(
                "unknown shading {other:?}: expected none, lambert or lambert_learned"
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
    /// Index of the rotation column used as the normal ([`LEARNED_AXIS`] for a learned
    /// normal), its sign (+1 or -1), or `u8::MAX` where `f_i` is constant (unlit,
    /// degenerate or not computed).
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
    let axis = first_shortest_axis(ls);
    let a = Vec3::from(axis_of(unit_quaternion(q, q_norm2), axis));
    Some(turned_toward(a, axis, mean, cam_pos))
}

/// Index of the first smallest of three log-scales: ties resolve the same way every run.
fn first_shortest_axis(ls: &[f32]) -> usize {
    (1..3).fold(0, |k, j| if ls[j] < ls[k] { j } else { k })
}

/// `q / |q|` for a quaternion whose squared norm `q_norm2` is finite and not degenerate.
fn unit_quaternion(q: &[f32], q_norm2: f32) -> [f32; 4] {
    let q_norm = q_norm2.sqrt();
    [q[0] / q_norm, q[1] / q_norm, q[2] / q_norm, q[3] / q_norm]
}

/// The unit direction `a` (normal `axis`) of the Gaussian at `mean`, turned to face
/// `cam_pos`.
fn turned_toward(a: Vec3, axis: usize, mean: &[f32], cam_pos: Vec3) -> FacingNormal {
    let to_cam = (cam_pos - Vec3::new(mean[0], mean[1], mean[2])).normalize_or_zero();
    let facing = a.dot(to_cam);
    let sign = if facing < 0.0 { -1.0 } else { 1.0 };
    FacingNormal {
        normal: a * sign,
        axis,
        sign,
        facing_cos: facing.abs(),
    }
}

/// The learned normal of Gaussian `g` (`v / |v|` of its `Param::Normal` row) turned
/// toward `cam_pos`, as [`facing_normal`] with `axis` = [`LEARNED_AXIS`]; `None` where the
/// model has no normal group, or the normal or mean is non-finite or degenerate.
pub fn learned_facing_normal(params: &ParamSet, g: usize, cam_pos: Vec3) -> Option<FacingNormal> {
    if params.dim(Param::Normal) != 3 {
        return None;
    }
    let v = params.row(Param::Normal, g);
    let mean = params.row(Param::Mean, g);
    let norm2: f32 = v.iter().map(|x| x * x).sum();
    if !(norm2.is_finite() && mean.iter().all(|x| x.is_finite())) || norm2 < MIN_NORMAL_NORM2 {
        return None;
    }
    let a = Vec3::new(v[0], v[1], v[2]) / norm2.sqrt();
    Some(turned_toward(a, LEARNED_AXIS, mean, cam_pos))
}

/// The normal `shading` uses for Gaussian `g` ([`facing_normal`] or
/// [`learned_facing_normal`]); `None` for `Shading::None`.
pub fn shading_normal(
    shading: Shading,
    params: &ParamSet,
    g: usize,
    cam_pos: Vec3,
) -> Option<FacingNormal> {
    match shading {
        Shading::None => None,
        Shading::Lambert => facing_normal(params, g, cam_pos),
        Shading::LambertLearned => learned_facing_normal(params, g, cam_pos),
    }
}

/// Starts every learned normal that the initialiser left unset (`|v|^2` below
/// [`MIN_NORMAL_NORM2`], e.g. the zeros of `init::from_points`): the Gaussian's shortest
/// scale axis where one axis is strictly the shortest, else (a round or needle-like
/// Gaussian, as every isotropic initial Gaussian is) the direction from `centre` to its
/// mean, outward as a convex body's surface normal is. Rows already set (a surface normal)
/// are kept. Does nothing without a normal group. Every value written is finite and unit
/// length; a Gaussian at `centre` with no shortest axis gets +x.
pub fn initial_normals(params: &mut ParamSet, centre: Vec3) {
    if params.dim(Param::Normal) != 3 {
        return;
    }
    for g in 0..params.len() {
        let v = params.row(Param::Normal, g);
        let norm2: f32 = v.iter().map(|x| x * x).sum();
        if norm2.is_finite() && norm2 >= MIN_NORMAL_NORM2 {
            continue;
        }
        let ls = params.row(Param::LogScale, g);
        let q = params.row(Param::Rotation, g);
        let q_norm2: f32 = q.iter().map(|x| x * x).sum();
        let k = first_shortest_axis(ls);
        let strictly_shortest = (0..3).all(|j| j == k || ls[k] < ls[j]);
        let mean = params.row(Param::Mean, g);
        let radial = Vec3::new(mean[0], mean[1], mean[2]) - centre;
        let normal = if strictly_shortest && q_norm2.is_finite() && q_norm2 >= MIN_QUAT_NORM2 {
            Vec3::from(axis_of(unit_quaternion(q, q_norm2), k))
        } else {
            radial
        };
        let normal = normal.try_normalize().unwrap_or(Vec3::X);
        params
            .row_mut(Param::Normal, g)
            .copy_from_slice(&normal.to_array());
    }
}

/// `|s + v|^2` below which the half vector is undefined (the Sun straight behind the
/// Gaussian as seen from the camera): `n.h` is then 0 with no gradient.
pub const MIN_HALF_NORM2: f32 = 1e-8;

/// Unit vector from `mean` to `cam_pos` and the distance: Phi's own view direction.
fn unit_view(mean: &[f32], cam_pos: Vec3) -> (Vec3, f32) {
    let (view, r) = view_direction(mean, cam_pos.to_array());
    (Vec3::from(view), r)
}

/// What [`local_inputs`] and its backward share for Gaussian `g`.
struct LocalFrame {
    normal: FacingNormal,
    view: Vec3,
    view_dist: f32,
    /// The unit half vector and `|s + v|`, unless degenerate.
    half: Option<(Vec3, f32)>,
}

fn local_frame(params: &ParamSet, g: usize, cam_pos: Vec3, sun_dir: Vec3) -> Option<LocalFrame> {
    let normal = learned_facing_normal(params, g, cam_pos)?;
    let (view, view_dist) = unit_view(params.row(Param::Mean, g), cam_pos);
    if !(view_dist.is_finite() && view_dist > 0.0) {
        return None;
    }
    let sum = sun_dir + view;
    let sum2 = sum.length_squared();
    let half = (sum2.is_finite() && sum2 >= MIN_HALF_NORM2).then(|| {
        let len = sum2.sqrt();
        (sum / len, len)
    });
    Some(LocalFrame {
        normal,
        view,
        view_dist,
        half,
    })
}

/// `[n.s, n.v, n.h]` of Gaussian `g` in its local frame (see the module header): `n` its
/// learned normal facing `cam_pos`, `s = sun_dir` (unit), `v` the unit vector to the
/// camera, `h` the unit half vector. Zeros where the normal is missing or degenerate;
/// `n.h = 0` where `|s + v|^2 <` [`MIN_HALF_NORM2`].
pub fn local_inputs(params: &ParamSet, g: usize, cam_pos: Vec3, sun_dir: Vec3) -> [f32; 3] {
    let Some(f) = local_frame(params, g, cam_pos, sun_dir) else {
        return [0.0; 3];
    };
    let n = f.normal.normal;
    [
        n.dot(sun_dir),
        n.dot(f.view),
        f.half.map_or(0.0, |(h, _)| n.dot(h)),
    ]
}

/// Backward of [`local_inputs`] for `d = dL/d[n.s, n.v, n.h]`: `(dL/d v_i, dL/d mean_i)`,
/// `v_i` the unnormalised `Param::Normal` row; `None` (no gradient) where the forward gave
/// zeros or a value would be non-finite.
pub fn local_inputs_backward(
    params: &ParamSet,
    g: usize,
    cam_pos: Vec3,
    sun_dir: Vec3,
    d: [f32; 3],
) -> Option<([f32; 3], [f32; 3])> {
    let f = local_frame(params, g, cam_pos, sun_dir)?;
    let n_hat = f.normal.normal;
    let u = f.view;
    // dL/d n_hat, n_hat = sign v / |v|.
    let mut d_n = sun_dir * d[0] + u * d[1];
    // dL/d u: through n.v, and through h = (s + u) / |s + u|.
    let mut d_u = n_hat * d[1];
    if let Some((h, len)) = f.half {
        d_n += h * d[2];
        d_u += (n_hat - h * h.dot(n_hat)) * (d[2] / len);
    }
    let v = params.row(Param::Normal, g);
    let v = Vec3::new(v[0], v[1], v[2]);
    let v_norm = v.length();
    let n = v / v_norm;
    let d_v = (d_n - n * n.dot(d_n)) * (f.normal.sign / v_norm);
    // u = (c - mean) / |c - mean|: d u / d mean = -(I - u u^T) / r.
    let d_mean = -(d_u - u * u.dot(d_u)) / f.view_dist;
    (d_v.is_finite() && d_mean.is_finite()).then(|| (d_v.to_array(), d_mean.to_array()))
}

/// Phi's whole input row for each listed Gaussian (row `r` for `list[r]`): the paper's
/// columns (`AppearanceNet::assemble_input`: feature, encoded Sun and view) and, for local
/// inputs, [`local_inputs`]. The one way the model builds Phi's input, so no caller can
/// leave the local columns unfilled.
pub fn assemble_phi_input(
    net: &AppearanceNet,
    params: &ParamSet,
    list: &[u32],
    cam_pos: Vec3,
    sun_dir: Vec3,
    input: &mut Vec<f32>,
) -> Result<(), SunAwareError> {
    net.assemble_input(
        list,
        params.get(Param::Feature),
        params.get(Param::Mean),
        sun_dir.to_array(),
        cam_pos.to_array(),
        input,
    )?;
    fill_local_inputs(net, params, list, cam_pos, sun_dir, input);
    Ok(())
}

/// Writes [`local_inputs`] of each listed Gaussian into its row of Phi's assembled
/// `input` (row `r` for `list[r]`, from column `net.local_start()`); nothing for Phi
/// without local inputs.
fn fill_local_inputs(
    net: &AppearanceNet,
    params: &ParamSet,
    list: &[u32],
    cam_pos: Vec3,
    sun_dir: Vec3,
    input: &mut [f32],
) {
    if net.inputs().local_width() == 0 {
        return;
    }
    let (width, start) = (net.input_width(), net.local_start());
    input
        .par_chunks_mut(width)
        .zip(list.par_iter())
        .for_each(|(row, &g)| {
            row[start..start + LOCAL_INPUTS]
                .copy_from_slice(&local_inputs(params, g as usize, cam_pos, sun_dir));
        });
}

/// Adds the gradient of the local inputs in Phi's input gradient `d_input` (rows as in
/// `fill_local_inputs`) into `d_normal` (`Param::Normal`, `count x 3`) and `d_means`
/// (`count x 3`); nothing for Phi without local inputs. Rows are summed in list order.
#[allow(clippy::too_many_arguments)]
pub fn scatter_local_input_grad(
    net: &AppearanceNet,
    params: &ParamSet,
    list: &[u32],
    cam_pos: Vec3,
    sun_dir: Vec3,
    d_input: &[f32],
    d_normal: &mut [f32],
    d_means: &mut [f32],
) {
    if net.inputs().local_width() == 0 {
        return;
    }
    let (width, start) = (net.input_width(), net.local_start());
    let rows: Vec<Option<([f32; 3], [f32; 3])>> = d_input
        .par_chunks(width)
        .zip(list.par_iter())
        .map(|(row, &g)| {
            let d = [row[start], row[start + 1], row[start + 2]];
            if d == [0.0; 3] {
                return None;
            }
            local_inputs_backward(params, g as usize, cam_pos, sun_dir, d)
        })
        .collect();
    for (&g, grads) in list.iter().zip(rows) {
        let Some((d_v, d_mean)) = grads else {
            continue;
        };
        let g = g as usize;
        for j in 0..3 {
            d_normal[g * 3 + j] += d_v[j];
            d_means[g * 3 + j] += d_mean[j];
        }
    }
}

/// See [`facing_normal`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FacingNormal {
    pub normal: Vec3,
    /// Which rotation column (the shortest scale axis), or [`LEARNED_AXIS`].
    pub axis: usize,
    /// +1 or -1: the column turned toward the camera.
    pub sign: f32,
    /// `|axis . direction to the camera|`.
    pub facing_cos: f32,
}

/// `f_i` of `shading` for the Gaussians in `list` (every other one keeps 1), with what
/// backward needs. `colour` is the unshaded colour, `n * 3`; it is scaled in place.
pub fn shade_forward(
    shading: Shading,
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
        let Some(normal) = shading_normal(shading, params, g, cam_pos) else {
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
/// gradient (`Lambert`) or the learned normal's (`LambertLearned`) in `grads`.
pub fn shade_backward(
    pass: &ShadePass,
    params: &ParamSet,
    sun_dir: Vec3,
    ambient: f32,
    d_colour: &mut [f32],
    grads: &mut ParamSet,
) {
    let s = sun_dir.to_array();
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
        if k as usize == LEARNED_AXIS {
            // f = k_a + (1 - k_a) sign (v / |v|) . s: d f / d v = (1 - k_a) sign
            // (s - n (n . s)) / |v|, n = v / |v| (the normalisation removes the radial part).
            let v = params.row(Param::Normal, g);
            let v_norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            let n_hat = [v[0] / v_norm, v[1] / v_norm, v[2] / v_norm];
            let n_dot_s: f32 = (0..3).map(|j| n_hat[j] * s[j]).sum();
            let scale = d_f * (1.0 - ambient) * sign / v_norm;
            let grad: Vec<f32> = (0..3)
                .map(|j| scale * (s[j] - n_hat[j] * n_dot_s))
                .collect();
            if grad.iter().all(|x| x.is_finite()) {
                for (o, x) in grads.row_mut(Param::Normal, g).iter_mut().zip(grad) {
                    *o += x;
                }
            }
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
            for (o, v) in grads.row_mut(Param::Rotation, g).iter_mut().zip(grad) {
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
        for s in [Shading::None, Shading::Lambert, Shading::LambertLearned] {
            assert_eq!(s.name().parse::<Shading>().unwrap(), s);
            assert_eq!(Shading::from_code(s.code()), Some(s));
        }
        let err = "phong".parse::<Shading>().unwrap_err().to_string();
        assert!(err.contains("none, lambert or lambert_learned"), "{err}");
        assert_eq!(Shading::from_code(7), None);
        assert_eq!(
            " Lambert_Learned ".parse::<Shading>().unwrap(),
            Shading::LambertLearned
        );
        assert_eq!(Shading::LambertLearned.code(), 2);
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

    #[test]
    fn initial_normals_keep_set_rows_then_use_the_shortest_axis_else_the_radial() {
        use crate::model::ModelLayout;
        let layout = ModelLayout {
            normal_dim: 3,
            ..ModelLayout::sh(0)
        };
        let mut p = ParamSet::new(layout.dims());
        p.push_zeros(5);
        let h = std::f32::consts::FRAC_1_SQRT_2;
        for g in 0..5 {
            p.row_mut(Param::Rotation, g)
                .copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
            p.row_mut(Param::Mean, g)
                .copy_from_slice(&[1.0, 2.0 + g as f32, 3.0]);
        }
        // 0: a surface normal from the initialiser (not unit: kept as it is).
        p.row_mut(Param::Normal, 0)
            .copy_from_slice(&[0.0, 0.0, 2.0]);
        // 1: flat along its y axis, rotated 90 degrees about z (its y axis is world -x).
        p.row_mut(Param::LogScale, 1)
            .copy_from_slice(&[0.0, -2.0, 0.0]);
        p.row_mut(Param::Rotation, 1)
            .copy_from_slice(&[h, 0.0, 0.0, h]);
        // 2: round; 3: a needle (two shortest axes tie): both radial from the centre.
        p.row_mut(Param::LogScale, 3)
            .copy_from_slice(&[-1.0, -1.0, 0.0]);
        // 4: round and at the centre: +x.
        p.row_mut(Param::Mean, 4).copy_from_slice(&[1.0, 2.0, 3.0]);
        // A NaN normal is unset too.
        p.row_mut(Param::Normal, 2)[0] = f32::NAN;
        initial_normals(&mut p, Vec3::new(1.0, 2.0, 3.0));
        let row = |g: usize| Vec3::from_slice(p.row(Param::Normal, g));
        assert_eq!(row(0), Vec3::new(0.0, 0.0, 2.0));
        assert!(
            (row(1) - Vec3::new(-1.0, 0.0, 0.0)).length() < 1e-6,
            "{}",
            row(1)
        );
        assert!((row(2) - Vec3::Y).length() < 1e-6, "{}", row(2));
        assert!((row(3) - Vec3::Y).length() < 1e-6, "{}", row(3));
        assert_eq!(row(4), Vec3::X);
        assert!(p.get(Param::Normal).iter().all(|v| v.is_finite()));
    }

    fn one_gaussian(normal: [f32; 3], mean: [f32; 3]) -> ParamSet {
        use crate::model::ModelLayout;
        let layout = ModelLayout {
            normal_dim: 3,
            ..ModelLayout::sh(0)
        };
        let mut p = ParamSet::new(layout.dims());
        p.push_zeros(1);
        p.row_mut(Param::Normal, 0).copy_from_slice(&normal);
        p.row_mut(Param::Mean, 0).copy_from_slice(&mean);
        p
    }

    /// `[n.s, n.v, n.h]` in f64 from the raw normal row and mean, with the flip `sign`
    /// held fixed (it is piecewise constant): the reference for the analytic gradient.
    fn local_inputs_f64(
        v: [f64; 3],
        mean: [f64; 3],
        cam: [f64; 3],
        s: [f64; 3],
        sign: f64,
    ) -> [f64; 3] {
        let dot = |a: [f64; 3], b: [f64; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        let unit = |a: [f64; 3]| {
            let l = dot(a, a).sqrt();
            [a[0] / l, a[1] / l, a[2] / l]
        };
        let n = unit(v).map(|x| x * sign);
        let u = unit([cam[0] - mean[0], cam[1] - mean[1], cam[2] - mean[2]]);
        let h = unit([s[0] + u[0], s[1] + u[1], s[2] + u[2]]);
        [dot(n, s), dot(n, u), dot(n, h)]
    }

    #[test]
    fn local_inputs_gradients_match_f64_central_differences() {
        let cam = Vec3::new(0.4, -0.3, 3.0);
        let sun = Vec3::new(0.5, 0.6, 0.3).normalize();
        let cases = [
            // Normals of length 0.5..2 (the normalisation matters), both flips.
            ([0.3f32, -0.2, 1.1], [0.1f32, 0.2, -0.1]),
            ([-0.2, 0.4, -0.25], [-0.3, 0.1, 0.4]),
            ([1.2, 0.9, 0.7], [0.5, -0.4, 0.2]),
        ];
        let d = [0.7f32, -1.3, 0.9];
        let mut flips = [false; 2];
        for (v, mean) in cases {
            let p = one_gaussian(v, mean);
            let f = learned_facing_normal(&p, 0, cam).unwrap();
            flips[(f.sign < 0.0) as usize] = true;
            let sign = f.sign as f64;
            let (d_v, d_mean) = local_inputs_backward(&p, 0, cam, sun, d).unwrap();
            let values = local_inputs(&p, 0, cam, sun);
            let to64 = |a: [f32; 3]| a.map(|x| x as f64);
            let (cam64, sun64) = (to64(cam.to_array()), to64(sun.to_array()));
            let reference = local_inputs_f64(to64(v), to64(mean), cam64, sun64, sign);
            for k in 0..3 {
                assert!(
                    (values[k] as f64 - reference[k]).abs() < 1e-6,
                    "{values:?} {reference:?}"
                );
            }
            let objective = |v: [f64; 3], m: [f64; 3]| -> f64 {
                let x = local_inputs_f64(v, m, cam64, sun64, sign);
                (0..3).map(|k| d[k] as f64 * x[k]).sum()
            };
            let eps = 1e-6;
            for j in 0..3 {
                let (mut hi, mut lo) = (to64(v), to64(v));
                hi[j] += eps;
                lo[j] -= eps;
                let numeric = (objective(hi, to64(mean)) - objective(lo, to64(mean))) / (2.0 * eps);
                assert!(
                    (d_v[j] as f64 - numeric).abs() < 1e-4 * (1.0 + numeric.abs()),
                    "normal[{j}]: {} vs {numeric}",
                    d_v[j]
                );
                let (mut hi, mut lo) = (to64(mean), to64(mean));
                hi[j] += eps;
                lo[j] -= eps;
                let numeric = (objective(to64(v), hi) - objective(to64(v), lo)) / (2.0 * eps);
                assert!(
                    (d_mean[j] as f64 - numeric).abs() < 1e-4 * (1.0 + numeric.abs()),
                    "mean[{j}]: {} vs {numeric}",
                    d_mean[j]
                );
            }
            // No gradient along v itself: the values depend on v / |v| only.
            let radial: f32 = (0..3).map(|j| d_v[j] * v[j]).sum();
            assert!(radial.abs() < 1e-5, "{d_v:?}");
        }
        assert_eq!(flips, [true, true], "both flips exercised");
    }

    /// `fill_local_inputs` writes each row's local block and `scatter_local_input_grad`
    /// routes that block's gradient to the listed Gaussian's normal and mean (and only
    /// there), as `local_inputs` / `local_inputs_backward` give them.
    #[test]
    fn local_blocks_fill_and_scatter_per_listed_gaussian() {
        use crate::model::ModelLayout;
        use crate::nn::{AppearanceInputs, PositionalEncoding};
        let net = AppearanceNet::with_inputs(
            2,
            4,
            PositionalEncoding::default(),
            AppearanceInputs::Local,
            1,
        )
        .unwrap();
        let layout = ModelLayout {
            normal_dim: 3,
            ..ModelLayout::sh(0)
        };
        let mut p = ParamSet::new(layout.dims());
        p.push_zeros(3);
        for (g, (v, m)) in [
            ([0.3f32, -0.2, 1.1], [0.1f32, 0.2, -0.1]),
            ([-0.2, 0.4, -0.25], [-0.3, 0.1, 0.4]),
            ([1.2, 0.9, 0.7], [0.5, -0.4, 0.2]),
        ]
        .into_iter()
        .enumerate()
        {
            p.row_mut(Param::Normal, g).copy_from_slice(&v);
            p.row_mut(Param::Mean, g).copy_from_slice(&m);
        }
        let cam = Vec3::new(0.4, -0.3, 3.0);
        let sun = Vec3::new(0.5, 0.6, 0.3).normalize();
        let list = [2u32, 0];
        let (w, start) = (net.input_width(), net.local_start());
        let mut input = vec![7.0f32; list.len() * w];
        fill_local_inputs(&net, &p, &list, cam, sun, &mut input);
        for (r, &g) in list.iter().enumerate() {
            let row = &input[r * w..(r + 1) * w];
            assert_eq!(&row[start..], &local_inputs(&p, g as usize, cam, sun));
            assert!(row[..start].iter().all(|&x| x == 7.0));
        }
        let mut d_input = vec![5.0f32; list.len() * w];
        let d = [[0.7f32, -1.3, 0.9], [-0.4, 0.2, 1.1]];
        for r in 0..2 {
            d_input[r * w + start..(r + 1) * w].copy_from_slice(&d[r]);
        }
        let (mut d_normal, mut d_means) = (vec![0.0f32; 9], vec![0.0f32; 9]);
        scatter_local_input_grad(
            &net,
            &p,
            &list,
            cam,
            sun,
            &d_input,
            &mut d_normal,
            &mut d_means,
        );
        for (r, &g) in list.iter().enumerate() {
            let g = g as usize;
            let (d_v, d_m) = local_inputs_backward(&p, g, cam, sun, d[r]).unwrap();
            assert_eq!(&d_normal[g * 3..g * 3 + 3], &d_v);
            assert_eq!(&d_means[g * 3..g * 3 + 3], &d_m);
            assert!(d_v.iter().chain(&d_m).any(|&x| x != 0.0));
        }
        // Gaussian 1 is not listed: untouched.
        assert_eq!(
            (&d_normal[3..6], &d_means[3..6]),
            (&[0.0; 3][..], &[0.0; 3][..])
        );
    }

    #[test]
    fn degenerate_local_inputs_are_zero_without_gradient() {
        let cam = Vec3::new(0.0, 0.0, 3.0);
        let sun = Vec3::new(0.6, 0.0, 0.8);
        let d = [1.0f32, 1.0, 1.0];
        // A degenerate or non-finite normal, or no normal group at all: zeros, no gradient.
        for v in [[0.0f32, 0.0, 1e-4], [0.0; 3], [f32::NAN, 0.0, 1.0]] {
            let p = one_gaussian(v, [0.0; 3]);
            assert_eq!(local_inputs(&p, 0, cam, sun), [0.0; 3], "{v:?}");
            assert!(local_inputs_backward(&p, 0, cam, sun, d).is_none(), "{v:?}");
        }
        let mut plain = ParamSet::new(crate::model::ModelLayout::sh(0).dims());
        plain.push_zeros(1);
        assert_eq!(local_inputs(&plain, 0, cam, sun), [0.0; 3]);
        // The Sun straight behind the Gaussian (s = -v): n.h is 0 and carries no
        // gradient, n.s and n.v keep theirs.
        let p = one_gaussian([0.3, 0.0, 1.0], [0.0; 3]);
        let behind = Vec3::new(0.0, 0.0, -1.0);
        let x = local_inputs(&p, 0, cam, behind);
        assert!(x[0] < 0.0 && x[1] > 0.0 && x[2] == 0.0, "{x:?}");
        let (d_v, d_mean) = local_inputs_backward(&p, 0, cam, behind, [0.0, 0.0, 1.0]).unwrap();
        assert_eq!((d_v, d_mean), ([0.0; 3], [0.0; 3]));
        let (d_v, _) = local_inputs_backward(&p, 0, cam, behind, [1.0, 0.0, 0.0]).unwrap();
        assert!(d_v.iter().any(|&x| x != 0.0));
    }

    #[test]
    fn a_degenerate_learned_normal_shades_nothing() {
        use crate::model::ModelLayout;
        let layout = ModelLayout {
            normal_dim: 3,
            ..ModelLayout::sh(0)
        };
        let mut p = ParamSet::new(layout.dims());
        p.push_zeros(3);
        p.row_mut(Param::Normal, 0)
            .copy_from_slice(&[0.0, 0.0, 1.0]);
        p.row_mut(Param::Normal, 1)
            .copy_from_slice(&[0.0, 0.0, 1e-4]);
        p.row_mut(Param::Normal, 2)
            .copy_from_slice(&[f32::INFINITY, 0.0, 1.0]);
        let mut colour = vec![1.0f32; 9];
        let cam = Vec3::new(0.0, 0.0, 5.0);
        let sun = Vec3::new(0.6, 0.0, 0.8);
        let pass = shade_forward(
            Shading::LambertLearned,
            &p,
            &[0, 1, 2],
            cam,
            sun,
            0.1,
            &mut colour,
        );
        assert!((pass.factor[0] - (0.1 + 0.9 * 0.8)).abs() < 1e-6);
        assert_eq!(&pass.factor[1..], &[1.0, 1.0]);
        let mut grads = p.zeros_like();
        let mut d = vec![1.0f32; 9];
        shade_backward(&pass, &p, sun, 0.1, &mut d, &mut grads);
        assert_eq!(&grads.get(Param::Normal)[3..], &[0.0; 6]);
        // Only the lit, valid normal gets a gradient, and it is tangent to the normal.
        let g0 = grads.row(Param::Normal, 0);
        assert!(g0[0] > 0.0 && g0[2] == 0.0, "{g0:?}");
        assert!(grads.get(Param::Rotation).iter().all(|&v| v == 0.0));
    }
}
