//! The projection stage: the camera frame, every Gaussian projected to a screen-space
//! splat (rayon, one task per block of Gaussians), and the depth order of the splats.
//!
//! Invariants: a Gaussian with a non-finite channel or parameter, behind the near plane,
//! below the opacity cutoff or touching no pixel gets no splat (`None`, radius 0); the
//! result does not depend on the thread count or on the early frustum cull.

use rayon::prelude::*;

use super::bin::{self, PixelRect};
use super::blend::{AlphaMode, Splat};
use super::project::{self, CameraFrame, JACOBIAN_CLAMP_FACTOR};
#[cfg(doc)]
use super::RasterSettings;
use super::{GaussianView, RasterError, MAX_IMAGE_SIDE_PX};
use crate::camera::Camera;

/// Validates the camera and builds the projection frame.
pub fn camera_frame(camera: &Camera, near_m: f32) -> Result<CameraFrame, RasterError> {
    let k = &camera.intrinsics;
    if k.width == 0 || k.height == 0 {
        return Err(RasterError::EmptyImage {
            width: k.width,
            height: k.height,
        });
    }
    if k.width > MAX_IMAGE_SIDE_PX || k.height > MAX_IMAGE_SIDE_PX {
        return Err(RasterError::TooLarge("image side above 32768 pixels"));
    }
    if !(k.fx.is_finite() && k.fy.is_finite() && k.fx > 0.0 && k.fy > 0.0) {
        return Err(RasterError::InvalidCamera(
            "focal lengths must be finite and positive",
        ));
    }
    if !(k.cx.is_finite() && k.cy.is_finite()) {
        return Err(RasterError::InvalidCamera("principal point is not finite"));
    }
    let q = camera.rotation;
    if !(q.is_finite() && camera.translation.is_finite()) {
        return Err(RasterError::InvalidCamera("pose is not finite"));
    }
    if q.length_squared() <= 1e-6 {
        return Err(RasterError::InvalidCamera("rotation quaternion is zero"));
    }
    if !(near_m.is_finite() && near_m > 0.0) {
        return Err(RasterError::InvalidSettings(
            "near plane must be finite and positive",
        ));
    }
    let m = glam::Mat3::from_quat(q.normalize());
    let mut rot = [[0.0f32; 3]; 3];
    for (r, row) in rot.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = m.col(c)[r];
        }
    }
    let half_w = k.cx.max(k.width as f32 - k.cx).max(0.5 * k.width as f32);
    let half_h = k.cy.max(k.height as f32 - k.cy).max(0.5 * k.height as f32);
    Ok(CameraFrame {
        rot_cam_from_world: rot,
        translation: camera.translation.to_array(),
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        lim_x: JACOBIAN_CLAMP_FACTOR * half_w / k.fx,
        lim_y: JACOBIAN_CLAMP_FACTOR * half_h / k.fy,
        near_m,
    })
}

/// Splats of the Gaussians that survived projection, with their original index.
#[derive(Clone, Debug, Default)]
pub struct ProjectedSet {
    /// Per Gaussian: `Some(splat)` when it survived culling and touches the image.
    pub splats: Vec<Option<Splat>>,
    pub radii_px: Vec<f32>,
}

/// Pixel rectangle outside which `o exp(power) < cutoff` for certain (also the light
/// pass's bound, `sunaware::sun_visibility`).
pub(crate) fn splat_rect(
    mean_px: [f32; 2],
    cov2: [f32; 3],
    q_max: f32,
    width: u32,
    height: u32,
) -> PixelRect {
    // Extent of the ellipse d^T K d <= q_max along x is sqrt(q_max * Sigma_xx); the margin
    // covers rounding in the conic and in exp.
    let ext_x = (q_max * cov2[0]).sqrt() * 1.001 + 0.01;
    let ext_y = (q_max * cov2[2]).sqrt() * 1.001 + 0.01;
    let to_px = |v: f32, hi: u32| v.clamp(0.0, hi as f32) as u32;
    // Pixel x is inside when |mean - (x + 0.5)| <= ext.
    PixelRect {
        x0: to_px((mean_px[0] - ext_x - 0.5).floor(), width),
        y0: to_px((mean_px[1] - ext_y - 0.5).floor(), height),
        x1: to_px((mean_px[0] + ext_x - 0.5).floor() + 1.0, width),
        y1: to_px((mean_px[1] + ext_y - 0.5).floor() + 1.0, height),
    }
}

/// Projects every Gaussian (rayon); culled ones and those touching no pixel are `None`.
/// Same as [`project_splats_with`] with the early frustum cull on.
pub fn project_splats(
    frame: &CameraFrame,
    gaussians: &GaussianView,
    mode: AlphaMode,
    width: u32,
    height: u32,
) -> ProjectedSet {
    project_splats_with(frame, gaussians, mode, width, height, true)
}

/// [`project_splats`] with the early frustum cull switchable
/// ([`RasterSettings::cull_outside_frustum`]): the result is the same either way.
pub fn project_splats_with(
    frame: &CameraFrame,
    gaussians: &GaussianView,
    mode: AlphaMode,
    width: u32,
    height: u32,
    cull_outside_frustum: bool,
) -> ProjectedSet {
    let nc = gaussians.n_channels;
    let cutoff = mode.cutoff();
    let results: Vec<(Option<Splat>, f32)> = (0..gaussians.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            if !gaussians.channels[i * nc..i * nc + nc]
                .iter()
                .all(|v| v.is_finite())
            {
                return (None, 0.0);
            }
            let params = gaussians.params(i);
            if cull_outside_frustum
                && project::footprint_certainly_misses(frame, &params, cutoff, width, height)
            {
                return (None, 0.0);
            }
            let Ok(p) = project::project_forward(frame, &params, cutoff) else {
                return (None, 0.0);
            };
            let q_max = 2.0 * (p.opacity / cutoff).ln();
            let [xx, xy, yy] = p.cov2;
            let mid = 0.5 * (xx + yy);
            let lambda_max = mid + (mid * mid - (xx * yy - xy * xy)).max(0.0).sqrt();
            let radius = (q_max * lambda_max).sqrt();
            let rect = splat_rect(p.mean_px, p.cov2, q_max, width, height);
            if rect.is_empty() || !radius.is_finite() {
                return (None, 0.0);
            }
            let splat = Splat {
                mean_px: p.mean_px,
                conic: p.conic,
                opacity: p.opacity,
                depth: p.t_cam[2],
                rect,
            };
            (Some(splat), radius)
        })
        .collect();
    let (splats, radii_px) = results.into_iter().unzip();
    ProjectedSet { splats, radii_px }
}

/// Depth-sorts the visible splats: returns the Gaussian index of each rank.
pub fn depth_order(splats: &[Option<Splat>]) -> Vec<u32> {
    let mut keys = Vec::new();
    let mut values = Vec::new();
    for (i, s) in splats.iter().enumerate() {
        if let Some(s) = s {
            // Depths are >= near > 0, so the bit pattern orders like the value.
            keys.push(s.depth.to_bits());
            values.push(i as u32);
        }
    }
    bin::radix_sort_u32(&mut keys, &mut values);
    values
}
