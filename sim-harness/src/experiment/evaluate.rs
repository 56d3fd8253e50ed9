//! Evaluation of a trained Sun-aware model on a scene's evaluation views, and the conversion of
//! simulator views into gs-core cameras and observations.
//!
//! Metrics: PSNR and SSIM per image on [0, 1] images (gs-core `loss.rs` definitions: renders
//! clamped to [0, 1], SSIM with the loss's 11x11 Gaussian window), averaged over the views.
//! The headline numbers are FULL FRAME on the black background, as the paper's most likely
//! are; masked numbers (target pixels only) are reported beside them, since the background
//! is easy and inflates full-frame PSNR.
//!
//! Invariants: the world frame is the target body frame; a view's camera is exactly the pose
//! its image was rendered with; a non-finite metric is an error, never averaged in.

use super::data::{SceneData, SceneIntrinsics, ViewData};
use crate::raytrace::{FrameRequest, PinholeCamera};
use glam::{Quat, Vec3};
use gs_core::camera::{Camera, Intrinsics};
use gs_core::loss::{psnr, ssim, ImageShape};
use gs_core::sunaware::trainer::{masked_psnr, masked_ssim};
use gs_core::sunaware::{SunAwareError, SunAwareModel};
use serde::{Deserialize, Serialize};

/// gs-core intrinsics of a scene.
pub fn intrinsics(k: &SceneIntrinsics) -> Intrinsics {
    Intrinsics {
        fx: k.fx as f32,
        fy: k.fy as f32,
        cx: k.cx as f32,
        cy: k.cy as f32,
        width: k.width,
        height: k.height,
    }
}

/// The camera a view was rendered with (world = target body frame).
pub fn camera_of(k: &SceneIntrinsics, view: &ViewData) -> Camera {
    let q = view.q_camera_from_target;
    Camera {
        intrinsics: intrinsics(k),
        rotation: Quat::from_xyzw(q.x as f32, q.y as f32, q.z as f32, q.w as f32).normalize(),
        translation: view.t_camera_from_target_m.as_vec3(),
    }
}

/// The view's Sun vector, target body frame, unit length.
pub fn sun_of(view: &ViewData) -> Vec3 {
    view.sun_dir_target.as_vec3().normalize()
}

/// The ray-tracer request of a view's camera, pose and Sun (one sample, no Earth fill): for
/// maps of what each pixel's centre ray hits (`raytrace::material_ids`, the Sun classes), not
/// for re-rendering the view's image.
pub fn frame_request_of(k: &SceneIntrinsics, view: &ViewData) -> FrameRequest {
    let camera = camera_of(k, view);
    let i = camera.intrinsics;
    FrameRequest {
        camera: PinholeCamera {
            fx: i.fx,
            fy: i.fy,
            cx: i.cx,
            cy: i.cy,
            width: i.width,
            height: i.height,
        },
        camera_from_target_rotation: camera.rotation,
        camera_from_target_translation_m: camera.translation,
        sun_dir_target: sun_of(view),
        sun_lit: !view.eclipse,
        earth_albedo: None,
        samples_per_pixel: 1,
        exposure: 1.0,
        seed: 0,
    }
}

/// Scores of one evaluation view.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewMetrics {
    pub index: u32,
    pub psnr_db: f64,
    pub ssim: f64,
    pub masked_psnr_db: f64,
    pub masked_ssim: f64,
}

/// Means over the evaluation set.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalSummary {
    pub views: usize,
    /// Full frame (the headline numbers).
    pub psnr_db: f64,
    pub ssim: f64,
    /// Target pixels only.
    pub masked_psnr_db: f64,
    pub masked_ssim: f64,
    pub per_view: Vec<ViewMetrics>,
}

/// sRGB bytes of a [0, 1] render (clamped, rounded).
pub fn to_rgb8(image: &[f32]) -> Vec<u8> {
    image
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8)
        .collect()
}

/// Scores one render against its view.
pub(crate) fn score_view(
    k: &SceneIntrinsics,
    view: &ViewData,
    render: &[f32],
) -> Result<ViewMetrics, SunAwareError> {
    let shape = ImageShape::new(k.width as usize, k.height as usize, 3);
    let truth = view.rgb_f32();
    let mask = view.mask_f32();
    let full_psnr = psnr(render, &truth, shape)? as f64;
    let full_ssim = ssim(render, &truth, shape)? as f64;
    // A view whose target is off-screen has no masked score: fall back to the full frame.
    let has_target = mask.iter().any(|&m| m > 0.0);
    let (masked_psnr_db, masked_ssim_value) = if has_target {
        (
            masked_psnr(render, &truth, Some(&mask), shape)? as f64,
            masked_ssim(render, &truth, Some(&mask), shape)? as f64,
        )
    } else {
        (full_psnr, full_ssim)
    };
    let metrics = ViewMetrics {
        index: view.index,
        psnr_db: full_psnr,
        ssim: full_ssim,
        masked_psnr_db,
        masked_ssim: masked_ssim_value,
    };
    // A perfect render gives infinite PSNR; anything else non-finite is a bug upstream.
    if [metrics.ssim, metrics.masked_ssim]
        .iter()
        .any(|v| !v.is_finite())
        || metrics.psnr_db.is_nan()
        || metrics.masked_psnr_db.is_nan()
    {
        return Err(SunAwareError::BadObservation(format!(
            "evaluation view {} gave non-finite metrics {metrics:?}",
            view.index
        )));
    }
    Ok(metrics)
}

/// Renders every evaluation view, scores it, and keeps the renders of the first `keep` views
/// (sRGB bytes) for figures.
pub fn evaluate_model(
    model: &SunAwareModel,
    scene: &SceneData,
    keep: usize,
) -> Result<(EvalSummary, Vec<Vec<u8>>), SunAwareError> {
    let views: Vec<&ViewData> = scene.eval.iter().collect();
    evaluate_views(model, &scene.intrinsics, &views, keep)
}

/// Renders and scores `views`, keeping the renders of the first `keep`.
pub fn evaluate_views(
    model: &SunAwareModel,
    k: &SceneIntrinsics,
    views: &[&ViewData],
    keep: usize,
) -> Result<(EvalSummary, Vec<Vec<u8>>), SunAwareError> {
    let mut per_view = Vec::with_capacity(views.len());
    let mut kept = Vec::new();
    for (i, view) in views.iter().enumerate() {
        let image = model.render(&camera_of(k, view), sun_of(view))?.image;
        if !image.iter().all(|v| v.is_finite()) {
            return Err(SunAwareError::BadObservation(format!(
                "render of view {} is not finite",
                view.index
            )));
        }
        per_view.push(score_view(k, view, &image)?);
        if i < keep {
            kept.push(to_rgb8(&image));
        }
    }
    Ok((summarise(per_view), kept))
}

/// Scores of `model` on `views` (no renders kept) and of an all-black render on the same
/// views: one rung of the accuracy ladder.
pub(crate) fn score_with_black(
    model: &SunAwareModel,
    k: &SceneIntrinsics,
    views: &[&ViewData],
) -> Result<(EvalSummary, EvalSummary), SunAwareError> {
    let (scores, _) = evaluate_views(model, k, views, 0)?;
    Ok((scores, black_baseline(k, views.iter().copied())?))
}

/// The smallest angle between `dir` and any of `among`, degrees (infinite when empty).
pub fn nearest_angle_deg(dir: glam::DVec3, among: &[glam::DVec3]) -> f64 {
    among
        .iter()
        .map(|a| a.angle_between(dir).to_degrees())
        .fold(f64::INFINITY, f64::min)
}

/// Scores of an all-black render on `views`: the floor any useful model must beat (the
/// background is black, so this measures how much of the frame the target covers).
pub fn black_baseline<'a>(
    k: &SceneIntrinsics,
    views: impl IntoIterator<Item = &'a ViewData>,
) -> Result<EvalSummary, SunAwareError> {
    let black = vec![0.0f32; 3 * k.width as usize * k.height as usize];
    let per_view = views
        .into_iter()
        .map(|v| score_view(k, v, &black))
        .collect::<Result<_, _>>()?;
    Ok(summarise(per_view))
}

/// Up to `max` lit frames of `frames` (time order), evenly spaced: views the model trained on.
pub fn seen_views<'a>(frames: &[&'a ViewData], max: usize) -> Vec<&'a ViewData> {
    let lit: Vec<&ViewData> = frames.iter().copied().filter(|v| !v.eclipse).collect();
    if lit.len() <= max {
        return lit;
    }
    (0..max).map(|i| lit[i * lit.len() / max]).collect()
}

/// Means of per-view metrics (fixed order). Infinite PSNRs (exact renders) are capped at
/// 100 dB so one perfect view cannot make the mean infinite.
pub(crate) fn summarise(per_view: Vec<ViewMetrics>) -> EvalSummary {
    let n = per_view.len().max(1) as f64;
    let cap = |v: f64| v.min(100.0);
    let mean = |f: fn(&ViewMetrics) -> f64| per_view.iter().map(f).sum::<f64>() / n;
    EvalSummary {
        views: per_view.len(),
        psnr_db: per_view.iter().map(|m| cap(m.psnr_db)).sum::<f64>() / n,
        ssim: mean(|m| m.ssim),
        masked_psnr_db: per_view.iter().map(|m| cap(m.masked_psnr_db)).sum::<f64>() / n,
        masked_ssim: mean(|m| m.masked_ssim),
        per_view,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DQuat, DVec3};

    #[test]
    fn camera_maps_the_target_origin_to_the_principal_point() {
        let k = SceneIntrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 40.0,
            cy: 25.0,
            width: 80,
            height: 50,
        };
        let view = ViewData {
            index: 0,
            time_s: None,
            eclipse: false,
            q_camera_from_target: DQuat::from_rotation_y(0.4) * DQuat::from_rotation_x(-0.2),
            t_camera_from_target_m: DVec3::new(0.0, 0.0, 30.0),
            sun_dir_target: DVec3::new(0.0, 2.0, 0.0),
            rgb8: vec![0; 80 * 50 * 3],
            mask8: vec![0; 80 * 50],
        };
        let cam = camera_of(&k, &view);
        let p = cam.rotation * Vec3::ZERO + cam.translation;
        assert_eq!(p, Vec3::new(0.0, 0.0, 30.0));
        // A body-frame point maps like the double-precision pose.
        let x = DVec3::new(1.0, -2.0, 0.5);
        let expect = view.q_camera_from_target * x + view.t_camera_from_target_m;
        let got = cam.rotation * x.as_vec3() + cam.translation;
        assert!((got.as_dvec3() - expect).length() < 1e-5);
        assert!((sun_of(&view) - Vec3::Y).length() < 1e-7);
        // The view direction points from the target to the camera.
        let eye = -(view.q_camera_from_target.inverse() * view.t_camera_from_target_m);
        assert!((view.view_dir_target() - eye.normalize()).length() < 1e-12);
    }

    #[test]
    fn scores_of_exact_and_wrong_renders() {
        let k = SceneIntrinsics {
            fx: 20.0,
            fy: 20.0,
            cx: 8.0,
            cy: 8.0,
            width: 16,
            height: 16,
        };
        let mut rgb8 = vec![0u8; 16 * 16 * 3];
        let mut mask8 = vec![0u8; 16 * 16];
        for y in 4..12 {
            for x in 4..12 {
                mask8[y * 16 + x] = 255;
                rgb8[3 * (y * 16 + x)..3 * (y * 16 + x) + 3].copy_from_slice(&[200, 150, 100]);
            }
        }
        let view = ViewData {
            index: 3,
            time_s: None,
            eclipse: false,
            q_camera_from_target: DQuat::IDENTITY,
            t_camera_from_target_m: DVec3::new(0.0, 0.0, 10.0),
            sun_dir_target: DVec3::X,
            rgb8,
            mask8,
        };
        let exact = view.rgb_f32();
        let m = score_view(&k, &view, &exact).unwrap();
        assert!(m.psnr_db.is_infinite() && (m.ssim - 1.0).abs() < 1e-6);
        // Off by 0.1 on the target only: masked MSE 0.01 (20 dB), full MSE 0.01 / 4 (26.0 dB).
        let wrong: Vec<f32> = exact
            .iter()
            .enumerate()
            .map(|(i, &v)| if view.mask8[i / 3] > 0 { v - 0.1 } else { v })
            .collect();
        let m = score_view(&k, &view, &wrong).unwrap();
        assert!((m.masked_psnr_db - 20.0).abs() < 1e-3, "{m:?}");
        assert!(
            (m.psnr_db - (20.0 + 10.0 * 4f64.log10())).abs() < 1e-3,
            "{m:?}"
        );
        let s = summarise(vec![m, score_view(&k, &view, &exact).unwrap()]);
        assert!((s.psnr_db - (m.psnr_db + 100.0) / 2.0).abs() < 1e-9);
    }
}
