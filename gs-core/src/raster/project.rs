//! Per-Gaussian projection (EWA splatting) and its exact backward pass.
//!
//! Forward: world mean -> camera frame -> pixel mean; `Sigma3 = R S S^T R^T` from the
//! normalised quaternion and exp(log-scales); `Sigma2 = T Sigma3 T^T` with `T = J W`,
//! the perspective Jacobian `J` built from x/z, y/z clamped to `1.3 tan(fov/2)`;
//! `0.3 px^2` added to the diagonal; conic = inverse of that.
//!
//! Invariants:
//! - a Gaussian with any non-finite input, `|q|^2 < 1e-6`, depth below the near plane,
//!   a non-positive or non-finite 2D covariance, or an opacity below the blending
//!   threshold is culled ([`Culled`]); everything a surviving Gaussian produces is finite;
//! - [`footprint_certainly_misses`] (the early frustum cull) only flags Gaussians whose
//!   blend rectangle would be empty, so culling them changes no output;
//! - [`project_backward`] recomputes the forward with exactly the same operations and
//!   differentiates every step, including the Jacobian clamp (a clamped ratio passes no
//!   gradient to x or y, but its `1/z` factor does pass gradient to z).

// Small fixed-size matrix code reads best with explicit indices.
#![allow(clippy::needless_range_loop)]

/// Added to the 2D covariance diagonal, px^2 (anti-aliasing floor of 3DGS).
pub const COV2D_DILATION_PX2: f32 = 0.3;
/// x/z and y/z are clamped to this multiple of tan(fov/2) when building the Jacobian.
pub const JACOBIAN_CLAMP_FACTOR: f32 = 1.3;
/// Quaternions with a smaller squared norm are culled.
pub const MIN_QUAT_NORM2: f32 = 1e-6;

pub type M3 = [[f32; 3]; 3];

/// The camera reduced to what projection needs (row-major world-to-camera rotation).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraFrame {
    pub rot_cam_from_world: M3,
    pub translation: [f32; 3],
    pub fx: f32,
    pub fy: f32,
    pub cx: f32,
    pub cy: f32,
    /// Clamp of x/z in the Jacobian.
    pub lim_x: f32,
    /// Clamp of y/z in the Jacobian.
    pub lim_y: f32,
    pub near_m: f32,
}

/// Why a Gaussian was culled.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Culled {
    NonFinite,
    DegenerateQuaternion,
    BehindNearPlane,
    DegenerateCovariance,
    Transparent,
}

/// One Gaussian's raw parameters.
#[derive(Clone, Copy, Debug)]
pub struct GaussianParams {
    pub mean: [f32; 3],
    pub log_scale: [f32; 3],
    pub rotation: [f32; 4],
    pub opacity_logit: f32,
}

/// Forward intermediates; kept only transiently (recomputed in backward).
#[derive(Clone, Copy, Debug)]
pub struct Projection {
    pub q_hat: [f32; 4],
    pub q_norm: f32,
    pub rot: M3,
    pub scale: [f32; 3],
    /// `R diag(s)`.
    pub m: M3,
    pub cov3: M3,
    pub t_cam: [f32; 3],
    pub ratio_x: f32,
    pub ratio_y: f32,
    pub clamped_x: bool,
    pub clamped_y: bool,
    /// `J W`, 2x3.
    pub t_mat: [[f32; 3]; 2],
    /// Dilated 2D covariance `[xx, xy, yy]`, px^2.
    pub cov2: [f32; 3],
    /// Inverse of `cov2`: `[a, b, c]`, power = -0.5 (a dx^2 + c dy^2) - b dx dy.
    pub conic: [f32; 3],
    pub mean_px: [f32; 2],
    pub opacity: f32,
}

/// Gradients flowing into one Gaussian's projected quantities.
#[derive(Clone, Copy, Debug, Default)]
pub struct ProjectedGrad {
    pub d_mean_px: [f32; 2],
    pub d_conic: [f32; 3],
    pub d_opacity: f32,
    pub d_depth: f32,
}

/// Gradients of one Gaussian's raw parameters.
#[derive(Clone, Copy, Debug, Default)]
pub struct ParamGrad {
    pub d_mean: [f32; 3],
    pub d_log_scale: [f32; 3],
    pub d_rotation: [f32; 4],
    pub d_opacity_logit: f32,
}

impl ParamGrad {
    pub fn is_finite(&self) -> bool {
        self.d_mean
            .iter()
            .chain(&self.d_log_scale)
            .chain(&self.d_rotation)
            .all(|v| v.is_finite())
            && self.d_opacity_logit.is_finite()
    }
}

pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

fn quat_to_mat(q: [f32; 4]) -> M3 {
    let [w, x, y, z] = q;
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

fn all_finite(values: &[f32]) -> bool {
    values.iter().all(|v| v.is_finite())
}

/// Projects one Gaussian. `alpha_threshold` is the smallest alpha that blending keeps:
/// a Gaussian whose opacity is below it can never contribute and is culled.
pub fn project_forward(
    frame: &CameraFrame,
    g: &GaussianParams,
    alpha_threshold: f32,
) -> Result<Projection, Culled> {
    if !(all_finite(&g.mean)
        && all_finite(&g.log_scale)
        && all_finite(&g.rotation)
        && g.opacity_logit.is_finite())
    {
        return Err(Culled::NonFinite);
    }
    let q = g.rotation;
    let q_norm2 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    if q_norm2.is_nan() || q_norm2 < MIN_QUAT_NORM2 || !q_norm2.is_finite() {
        return Err(Culled::DegenerateQuaternion);
    }
    let opacity = sigmoid(g.opacity_logit);
    if opacity.is_nan() || opacity < alpha_threshold {
        return Err(Culled::Transparent);
    }

    let w = &frame.rot_cam_from_world;
    let mut t_cam = [0.0f32; 3];
    for (r, t) in t_cam.iter_mut().enumerate() {
        *t = w[r][0] * g.mean[0] + w[r][1] * g.mean[1] + w[r][2] * g.mean[2] + frame.translation[r];
    }
    if !all_finite(&t_cam) {
        return Err(Culled::NonFinite);
    }
    let z = t_cam[2];
    if z.is_nan() || z < frame.near_m {
        return Err(Culled::BehindNearPlane);
    }

    let q_norm = q_norm2.sqrt();
    let q_hat = [q[0] / q_norm, q[1] / q_norm, q[2] / q_norm, q[3] / q_norm];
    let rot = quat_to_mat(q_hat);
    let scale = [
        g.log_scale[0].exp(),
        g.log_scale[1].exp(),
        g.log_scale[2].exp(),
    ];
    let mut m = [[0.0f32; 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            m[r][c] = rot[r][c] * scale[c];
        }
    }
    let mut cov3 = [[0.0f32; 3]; 3];
    for r in 0..3 {
        for c in 0..3 {
            cov3[r][c] = m[r][0] * m[c][0] + m[r][1] * m[c][1] + m[r][2] * m[c][2];
        }
    }

    let raw_x = t_cam[0] / z;
    let raw_y = t_cam[1] / z;
    let ratio_x = raw_x.clamp(-frame.lim_x, frame.lim_x);
    let ratio_y = raw_y.clamp(-frame.lim_y, frame.lim_y);
    let clamped_x = ratio_x != raw_x;
    let clamped_y = ratio_y != raw_y;
    let inv_z = 1.0 / z;
    let j = [
        [frame.fx * inv_z, 0.0, -frame.fx * ratio_x * inv_z],
        [0.0, frame.fy * inv_z, -frame.fy * ratio_y * inv_z],
    ];
    let mut t_mat = [[0.0f32; 3]; 2];
    for r in 0..2 {
        for c in 0..3 {
            t_mat[r][c] = j[r][0] * w[0][c] + j[r][1] * w[1][c] + j[r][2] * w[2][c];
        }
    }
    // Sigma2 = T cov3 T^T (only the three distinct entries).
    let mut tc = [[0.0f32; 3]; 2];
    for r in 0..2 {
        for c in 0..3 {
            tc[r][c] =
                t_mat[r][0] * cov3[0][c] + t_mat[r][1] * cov3[1][c] + t_mat[r][2] * cov3[2][c];
        }
    }
    let dot3 = |a: &[f32; 3], b: &[f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let cov2 = [
        dot3(&tc[0], &t_mat[0]) + COV2D_DILATION_PX2,
        dot3(&tc[0], &t_mat[1]),
        dot3(&tc[1], &t_mat[1]) + COV2D_DILATION_PX2,
    ];
    let det = cov2[0] * cov2[2] - cov2[1] * cov2[1];
    if det.is_nan() || det <= 0.0 || !det.is_finite() || !all_finite(&cov2) {
        return Err(Culled::DegenerateCovariance);
    }
    let inv_det = 1.0 / det;
    let conic = [cov2[2] * inv_det, -cov2[1] * inv_det, cov2[0] * inv_det];
    let mean_px = [frame.fx * raw_x + frame.cx, frame.fy * raw_y + frame.cy];
    if !all_finite(&conic) || !all_finite(&mean_px) {
        return Err(Culled::DegenerateCovariance);
    }
    Ok(Projection {
        q_hat,
        q_norm,
        rot,
        scale,
        m,
        cov3,
        t_cam,
        ratio_x,
        ratio_y,
        clamped_x,
        clamped_y,
        t_mat,
        cov2,
        conic,
        mean_px,
        opacity,
    })
}

/// Early frustum test: true only when the Gaussian's footprint certainly misses the
/// `width` x `height` image, decided from its centre and largest scale before the
/// covariance is projected. Conservative by construction, so culling what it flags changes
/// no output: the dilated 2D covariance satisfies `Sigma_xx <= (fx/z)^2 (1 + r_x^2)
/// s_max^2 + 0.3` (the Jacobian row has norm `fx/z sqrt(1 + r_x^2)` with the clamped ratio
/// `|r_x| <= lim_x`, the world-to-camera rotation is orthonormal, and `Sigma3 <= s_max^2
/// I`), the pixel rectangle of the blend extends `sqrt(q_max Sigma_xx)` (plus 0.1 % and
/// 0.01 px) around the centre, and this bound is widened by 1 % and a further pixel for
/// rounding. Anything it cannot decide (non-finite values, a centre behind the near
/// plane, an opacity below the threshold) returns false and is left to [`project_forward`].
pub fn footprint_certainly_misses(
    frame: &CameraFrame,
    g: &GaussianParams,
    alpha_threshold: f32,
    width: u32,
    height: u32,
) -> bool {
    let w = &frame.rot_cam_from_world;
    let mut t_cam = [0.0f32; 3];
    for (r, t) in t_cam.iter_mut().enumerate() {
        *t = w[r][0] * g.mean[0] + w[r][1] * g.mean[1] + w[r][2] * g.mean[2] + frame.translation[r];
    }
    let z = t_cam[2];
    let opacity = sigmoid(g.opacity_logit);
    // Written so that NaN anywhere leaves the decision to the full projection.
    if !(all_finite(&t_cam) && z >= frame.near_m && opacity >= alpha_threshold) {
        return false;
    }
    let s_max = g.log_scale[0].max(g.log_scale[1]).max(g.log_scale[2]).exp();
    let q_max = 2.0 * (opacity / alpha_threshold).ln();
    let inv_z = 1.0 / z;
    let raw_x = t_cam[0] * inv_z;
    let raw_y = t_cam[1] * inv_z;
    let rx = raw_x.abs().min(frame.lim_x);
    let ry = raw_y.abs().min(frame.lim_y);
    let fz_x = frame.fx * inv_z * s_max;
    let fz_y = frame.fy * inv_z * s_max;
    let sxx = fz_x * fz_x * (1.0 + rx * rx) + COV2D_DILATION_PX2;
    let syy = fz_y * fz_y * (1.0 + ry * ry) + COV2D_DILATION_PX2;
    let ext_x = (q_max * sxx * 1.02).sqrt() * 1.01 + 1.0;
    let ext_y = (q_max * syy * 1.02).sqrt() * 1.01 + 1.0;
    let mx = frame.fx * (t_cam[0] / z) + frame.cx;
    let my = frame.fy * (t_cam[1] / z) + frame.cy;
    let misses = mx + ext_x < 0.0
        || mx - ext_x > width as f32
        || my + ext_y < 0.0
        || my - ext_y > height as f32;
    // A non-finite bound (huge scales) decides nothing.
    misses && ext_x.is_finite() && ext_y.is_finite() && mx.is_finite() && my.is_finite()
}

/// Chain rule from the projected quantities back to the raw parameters.
pub fn project_backward(frame: &CameraFrame, p: &Projection, d: &ProjectedGrad) -> ParamGrad {
    let [a, b, c] = p.conic;
    let [ga, gb, gc] = d.d_conic;
    // dL/dSigma' = -K G K, G the symmetric matrix gradient of K ([[ga, gb/2], [gb/2, gc]]).
    let hb = 0.5 * gb;
    let kg00 = a * ga + b * hb;
    let kg01 = a * hb + b * gc;
    let kg10 = b * ga + c * hb;
    let kg11 = b * hb + c * gc;
    let s00 = -(kg00 * a + kg01 * b);
    let s01 = -(kg00 * b + kg01 * c);
    let s11 = -(kg10 * b + kg11 * c);
    // Dilation is additive: the same gradient reaches Sigma2.
    let g2 = [[s00, s01], [s01, s11]];

    // dL/dcov3 = T^T G2 T; dL/dT = 2 G2 T cov3.
    let t = &p.t_mat;
    let mut g2t = [[0.0f32; 3]; 2];
    for r in 0..2 {
        for col in 0..3 {
            g2t[r][col] = g2[r][0] * t[0][col] + g2[r][1] * t[1][col];
        }
    }
    let mut d_cov3 = [[0.0f32; 3]; 3];
    for r in 0..3 {
        for col in 0..3 {
            d_cov3[r][col] = t[0][r] * g2t[0][col] + t[1][r] * g2t[1][col];
        }
    }
    let mut d_t = [[0.0f32; 3]; 2];
    for r in 0..2 {
        for col in 0..3 {
            d_t[r][col] = 2.0
                * (g2t[r][0] * p.cov3[0][col]
                    + g2t[r][1] * p.cov3[1][col]
                    + g2t[r][2] * p.cov3[2][col]);
        }
    }
    // T = J W  =>  dL/dJ = dL/dT W^T.
    let w = &frame.rot_cam_from_world;
    let mut d_j = [[0.0f32; 3]; 2];
    for r in 0..2 {
        for col in 0..3 {
            d_j[r][col] = d_t[r][0] * w[col][0] + d_t[r][1] * w[col][1] + d_t[r][2] * w[col][2];
        }
    }

    let [x, y, z] = p.t_cam;
    let inv_z = 1.0 / z;
    let inv_z2 = inv_z * inv_z;
    let (fx, fy) = (frame.fx, frame.fy);
    let mut d_tc = [0.0f32; 3];
    // J00 = fx/z, J11 = fy/z.
    d_tc[2] += -fx * inv_z2 * d_j[0][0] - fy * inv_z2 * d_j[1][1];
    // J02 = -fx * ratio_x / z.
    if p.clamped_x {
        d_tc[2] += fx * p.ratio_x * inv_z2 * d_j[0][2];
    } else {
        d_tc[0] += -fx * inv_z2 * d_j[0][2];
        d_tc[2] += 2.0 * fx * x * inv_z2 * inv_z * d_j[0][2];
    }
    if p.clamped_y {
        d_tc[2] += fy * p.ratio_y * inv_z2 * d_j[1][2];
    } else {
        d_tc[1] += -fy * inv_z2 * d_j[1][2];
        d_tc[2] += 2.0 * fy * y * inv_z2 * inv_z * d_j[1][2];
    }
    // Pixel mean: u = fx x / z + cx, v = fy y / z + cy (never clamped).
    let [du, dv] = d.d_mean_px;
    d_tc[0] += fx * inv_z * du;
    d_tc[1] += fy * inv_z * dv;
    d_tc[2] += -fx * x * inv_z2 * du - fy * y * inv_z2 * dv;
    d_tc[2] += d.d_depth;

    let mut d_mean = [0.0f32; 3];
    for (col, dm) in d_mean.iter_mut().enumerate() {
        *dm = w[0][col] * d_tc[0] + w[1][col] * d_tc[1] + w[2][col] * d_tc[2];
    }

    // cov3 = M M^T  =>  dL/dM = 2 dL/dcov3 M (dL/dcov3 symmetric).
    let mut d_m = [[0.0f32; 3]; 3];
    for r in 0..3 {
        for col in 0..3 {
            d_m[r][col] = 2.0
                * (d_cov3[r][0] * p.m[0][col]
                    + d_cov3[r][1] * p.m[1][col]
                    + d_cov3[r][2] * p.m[2][col]);
        }
    }
    let mut d_log_scale = [0.0f32; 3];
    let mut d_rot = [[0.0f32; 3]; 3];
    for col in 0..3 {
        let mut ds = 0.0;
        for r in 0..3 {
            ds += d_m[r][col] * p.rot[r][col];
            d_rot[r][col] = d_m[r][col] * p.scale[col];
        }
        d_log_scale[col] = ds * p.scale[col];
    }

    let [qw, qx, qy, qz] = p.q_hat;
    let r = &d_rot;
    let g_w = 2.0
        * (-qz * r[0][1] + qy * r[0][2] + qz * r[1][0] - qx * r[1][2] - qy * r[2][0]
            + qx * r[2][1]);
    let g_x = 2.0
        * (qy * r[0][1] + qz * r[0][2] + qy * r[1][0] - 2.0 * qx * r[1][1] - qw * r[1][2]
            + qz * r[2][0]
            + qw * r[2][1]
            - 2.0 * qx * r[2][2]);
    let g_y = 2.0
        * (-2.0 * qy * r[0][0] + qx * r[0][1] + qw * r[0][2] + qx * r[1][0] + qz * r[1][2]
            - qw * r[2][0]
            + qz * r[2][1]
            - 2.0 * qy * r[2][2]);
    let g_z = 2.0
        * (-2.0 * qz * r[0][0] - qw * r[0][1] + qx * r[0][2] + qw * r[1][0] - 2.0 * qz * r[1][1]
            + qy * r[1][2]
            + qx * r[2][0]
            + qy * r[2][1]);
    let g_hat = [g_w, g_x, g_y, g_z];
    let dot = g_hat[0] * qw + g_hat[1] * qx + g_hat[2] * qy + g_hat[3] * qz;
    let mut d_rotation = [0.0f32; 4];
    for k in 0..4 {
        d_rotation[k] = (g_hat[k] - p.q_hat[k] * dot) / p.q_norm;
    }

    ParamGrad {
        d_mean,
        d_log_scale,
        d_rotation,
        d_opacity_logit: d.d_opacity * p.opacity * (1.0 - p.opacity),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame() -> CameraFrame {
        CameraFrame {
            rot_cam_from_world: quat_to_mat([0.9, 0.1, -0.3, 0.2].map(|v| v / 0.969_536_07)),
            translation: [0.1, -0.2, 4.0],
            fx: 120.0,
            fy: 110.0,
            cx: 40.0,
            cy: 30.0,
            lim_x: 1.3 * 40.0 / 120.0,
            lim_y: 1.3 * 30.0 / 110.0,
            near_m: 0.01,
        }
    }

    /// A scalar loss of every projected output, with fixed weights.
    fn loss(p: &Projection) -> f64 {
        let w = [0.7, -1.3, 0.4, 2.1, -0.8, 1.7, 0.9];
        w[0] * p.mean_px[0] as f64
            + w[1] * p.mean_px[1] as f64
            + w[2] * p.conic[0] as f64 * 100.0
            + w[3] * p.conic[1] as f64 * 100.0
            + w[4] * p.conic[2] as f64 * 100.0
            + w[5] * p.opacity as f64
            + w[6] * p.t_cam[2] as f64
    }

    /// Projection backward against central differences, including a Gaussian whose
    /// Jacobian ratio is clamped. Tolerance 2e-2 relative (plus 2e-3 absolute): f32
    /// forward, step 1e-3, losses of order 10 give rounding noise around 1e-3.
    #[test]
    fn projection_gradients_match_finite_differences() {
        let f = frame();
        for g in [
            GaussianParams {
                mean: [0.2, -0.1, 0.3],
                log_scale: [-1.2, -2.0, -1.6],
                rotation: [0.8, 0.3, -0.2, 0.5],
                opacity_logit: 0.3,
            },
            GaussianParams {
                mean: [3.0, 0.5, 0.0],
                log_scale: [-0.5, -1.0, -2.0],
                rotation: [0.2, -0.7, 0.4, 0.1],
                opacity_logit: -1.0,
            },
        ] {
            let p = project_forward(&f, &g, 1.0 / 255.0).unwrap();
            let d = ProjectedGrad {
                d_mean_px: [0.7, -1.3],
                d_conic: [40.0, 210.0, -80.0],
                d_opacity: 1.7,
                d_depth: 0.9,
            };
            let an = project_backward(&f, &p, &d);
            let mut flat_an = Vec::new();
            flat_an.extend(an.d_mean);
            flat_an.extend(an.d_log_scale);
            flat_an.extend(an.d_rotation);
            flat_an.push(an.d_opacity_logit);
            for (k, &a_val) in flat_an.iter().enumerate() {
                let eval = |delta: f32| {
                    let mut gp = g;
                    match k {
                        0..=2 => gp.mean[k] += delta,
                        3..=5 => gp.log_scale[k - 3] += delta,
                        6..=9 => gp.rotation[k - 6] += delta,
                        _ => gp.opacity_logit += delta,
                    }
                    loss(&project_forward(&f, &gp, 1.0 / 255.0).unwrap())
                };
                let h = 1e-3;
                let fd = (eval(h) - eval(-h)) / (2.0 * h as f64);
                let tol = 2e-3 + 2e-2 * fd.abs().max(a_val.abs() as f64);
                assert!(
                    (fd - a_val as f64).abs() < tol,
                    "param {k}: fd {fd} analytic {a_val}"
                );
            }
        }
    }

    #[test]
    fn invalid_inputs_are_culled() {
        let f = frame();
        let good = GaussianParams {
            mean: [0.0; 3],
            log_scale: [-1.0; 3],
            rotation: [1.0, 0.0, 0.0, 0.0],
            opacity_logit: 0.0,
        };
        assert!(project_forward(&f, &good, 1.0 / 255.0).is_ok());
        let mut bad = good;
        bad.mean[1] = f32::NAN;
        assert_eq!(
            project_forward(&f, &bad, 1.0 / 255.0).unwrap_err(),
            Culled::NonFinite
        );
        let mut bad = good;
        bad.rotation = [0.0, 1e-4, 0.0, 0.0];
        assert_eq!(
            project_forward(&f, &bad, 1.0 / 255.0).unwrap_err(),
            Culled::DegenerateQuaternion
        );
        let mut bad = good;
        bad.mean = [0.0, 0.0, -10.0];
        // Camera looks roughly along +z of the rotated frame; put it far behind instead.
        let behind = {
            let w = &f.rot_cam_from_world;
            // world point whose camera z is -1: x_w = W^T (x_c - t).
            let xc = [
                0.0 - f.translation[0],
                0.0 - f.translation[1],
                -1.0 - f.translation[2],
            ];
            [
                w[0][0] * xc[0] + w[1][0] * xc[1] + w[2][0] * xc[2],
                w[0][1] * xc[0] + w[1][1] * xc[1] + w[2][1] * xc[2],
                w[0][2] * xc[0] + w[1][2] * xc[1] + w[2][2] * xc[2],
            ]
        };
        bad.mean = behind;
        assert_eq!(
            project_forward(&f, &bad, 1.0 / 255.0).unwrap_err(),
            Culled::BehindNearPlane
        );
        let mut bad = good;
        bad.opacity_logit = -40.0;
        assert_eq!(
            project_forward(&f, &bad, 1.0 / 255.0).unwrap_err(),
            Culled::Transparent
        );
    }
}
