//! The light camera of the Sun visibility pass: on the Sun vector, looking at the scene
//! box's centre (perspective or orthographic, see the parent module), the Gaussians'
//! splats in its image and their standard deviations along its axis.
//!
//! Invariants: the camera is outside the scene box's bounding sphere; a Gaussian with a
//! non-finite parameter gets no splat and a zero axis sigma.

use glam::Vec3;
use rayon::prelude::*;

use crate::camera::{Camera, Intrinsics};
use crate::model::{GaussianModel, Param};
use crate::nn::SceneBox;
use crate::raster::blend::{AlphaMode, Splat, ALPHA_MIN};
use crate::raster::project::COV2D_DILATION_PX2;
use crate::raster::{camera_frame, project_splats, splat_rect, GaussianView};

use crate::sunaware::config::{LightConfig, LightProjection};
use crate::sunaware::error::SunAwareError;

/// Centre and bounding-sphere radius of a scene box, metres.
pub fn box_sphere(scene_box: &SceneBox) -> (Vec3, f32) {
    let lo = Vec3::from_array(scene_box.min_m());
    let hi = Vec3::from_array(scene_box.max_m());
    ((lo + hi) * 0.5, 0.5 * (hi - lo).length())
}

/// Where the light camera is and how it maps the scene to its image.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightCamera {
    /// Pose (and, for perspective, intrinsics) of the light camera.
    pub camera: Camera,
    pub projection: LightProjection,
    /// Orthographic only: pixels per metre in the image plane.
    pub ortho_px_per_m: f32,
    /// Occluder depth bias, metres.
    pub depth_bias_m: f32,
}

/// The light camera for an image taken from `camera_centre` with the Sun along `sun_dir`
/// (unit vector from the target towards the Sun, target body frame).
pub fn light_camera(
    sun_dir: Vec3,
    camera_centre: Vec3,
    scene_box: &SceneBox,
    config: &LightConfig,
) -> Result<LightCamera, SunAwareError> {
    if !(sun_dir.is_finite() && sun_dir.length_squared() > 1e-12) {
        return Err(SunAwareError::BadObservation(format!(
            "Sun vector {sun_dir:?} is not a finite non-zero vector"
        )));
    }
    if !camera_centre.is_finite() {
        return Err(SunAwareError::BadObservation(
            "camera centre is not finite".into(),
        ));
    }
    let sun = sun_dir.normalize();
    let (centre, radius) = box_sphere(scene_box);
    let distance = (camera_centre - centre).length().max(1.5 * radius);
    let eye = centre + sun * distance;
    let up = if sun.z.abs() < 0.9 { Vec3::Z } else { Vec3::X };
    let side = config.resolution_px;
    let extent = radius * config.fov_margin;
    let half_angle = (extent / distance).clamp(1e-6, 0.999).asin();
    let intrinsics = Intrinsics::from_fov_x(2.0 * half_angle, side, side);
    Ok(LightCamera {
        camera: Camera::look_at(intrinsics, eye, centre, up),
        projection: config.projection,
        ortho_px_per_m: 0.5 * side as f32 / extent,
        depth_bias_m: config.depth_bias_fraction * radius,
    })
}

fn quat_to_mat(q: [f32; 4]) -> [[f32; 3]; 3] {
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

/// Orthographic splat of Gaussian `i`, or `None` when culled.
fn ortho_splat(model: &GaussianModel, i: usize, light: &LightCamera, near_m: f32) -> Option<Splat> {
    let p = &model.params;
    let mean = p.row(Param::Mean, i);
    let log_scale = p.row(Param::LogScale, i);
    let q = p.row(Param::Rotation, i);
    let logit = p.row(Param::OpacityLogit, i)[0];
    let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
    if !(finite(mean) && finite(log_scale) && finite(q) && logit.is_finite()) {
        return None;
    }
    let q_norm2 = q.iter().map(|v| v * v).sum::<f32>();
    if !(q_norm2.is_finite() && q_norm2 >= 1e-6) {
        return None;
    }
    let opacity = 1.0 / (1.0 + (-logit).exp());
    if opacity.is_nan() || opacity < ALPHA_MIN {
        return None;
    }
    let cam = &light.camera;
    let t = cam.world_to_camera(Vec3::new(mean[0], mean[1], mean[2]));
    if !(t.is_finite() && t.z >= near_m) {
        return None;
    }
    let qn = q_norm2.sqrt();
    let r = quat_to_mat([q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn]);
    let s = [log_scale[0].exp(), log_scale[1].exp(), log_scale[2].exp()];
    // Rows 0 and 1 of W R S, W the world-to-camera rotation: the image-plane axes.
    let w = glam::Mat3::from_quat(cam.rotation.normalize());
    let mut m = [[0.0f32; 3]; 2];
    for (row, m_row) in m.iter_mut().enumerate() {
        let axis = w.row(row);
        for (c, v) in m_row.iter_mut().enumerate() {
            let col = Vec3::new(r[0][c], r[1][c], r[2][c]);
            *v = axis.dot(col) * s[c];
        }
    }
    let k = light.ortho_px_per_m;
    let k2 = k * k;
    let dot = |a: &[f32; 3], b: &[f32; 3]| a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    let xx = k2 * dot(&m[0], &m[0]) + COV2D_DILATION_PX2;
    let xy = k2 * dot(&m[0], &m[1]);
    let yy = k2 * dot(&m[1], &m[1]) + COV2D_DILATION_PX2;
    let det = xx * yy - xy * xy;
    if !(det.is_finite() && det > 0.0) {
        return None;
    }
    let conic = [yy / det, -xy / det, xx / det];
    let side = cam.intrinsics.width;
    let half = 0.5 * side as f32;
    let mean_px = [k * t.x + half, k * t.y + half];
    let q_max = 2.0 * (opacity / ALPHA_MIN).ln();
    let rect = splat_rect(mean_px, [xx, xy, yy], q_max, side, side);
    if rect.is_empty() || !mean_px.iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(Splat {
        mean_px,
        conic,
        opacity,
        depth: t.z,
        rect,
    })
}

/// Splats of every Gaussian in the light camera (`None`: culled or off the light image).
pub fn light_splats(
    model: &GaussianModel,
    light: &LightCamera,
    near_m: f32,
) -> Result<Vec<Option<Splat>>, SunAwareError> {
    let side = light.camera.intrinsics.width;
    match light.projection {
        LightProjection::Perspective => {
            let frame = camera_frame(&light.camera, near_m)?;
            let view = GaussianView::from_model(model, &[], 0);
            let mode = AlphaMode { smooth: false };
            Ok(project_splats(&frame, &view, mode, side, side).splats)
        }
        LightProjection::Orthographic => Ok((0..model.len())
            .into_par_iter()
            .with_min_len(1024)
            .map(|i| ortho_splat(model, i, light, near_m))
            .collect()),
    }
}

/// Standard deviation of every Gaussian along the light camera's axis, metres (0 where a
/// parameter is not finite: such Gaussians are culled anyway).
pub fn light_axis_sigmas_m(model: &GaussianModel, light: &LightCamera) -> Vec<f32> {
    let axis = glam::Mat3::from_quat(light.camera.rotation.normalize()).row(2);
    let p = &model.params;
    (0..model.len())
        .into_par_iter()
        .with_min_len(4096)
        .map(|i| {
            let log_scale = p.row(Param::LogScale, i);
            let q = p.row(Param::Rotation, i);
            let q_norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            if !(q_norm.is_finite() && q_norm > 1e-3 && log_scale.iter().all(|v| v.is_finite())) {
                return 0.0;
            }
            let r = quat_to_mat([q[0] / q_norm, q[1] / q_norm, q[2] / q_norm, q[3] / q_norm]);
            let var: f32 = (0..3)
                .map(|c| {
                    let along = axis.dot(Vec3::new(r[0][c], r[1][c], r[2][c]));
                    let s = log_scale[c].exp();
                    along * along * s * s
                })
                .sum();
            if var.is_finite() {
                var.sqrt()
            } else {
                0.0
            }
        })
        .collect()
}
