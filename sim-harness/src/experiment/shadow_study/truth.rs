//! The ray-traced ground truth: the frame request and Sun classes of each view, the pooled
//! shadow fractions, how the evaluation views' Sun directions relate to the training ones
//! ([`sun_coverage`]) and the evaluation views' distance from their re-render without cast
//! shadows ([`shadow_headroom`]).
//!
//! Invariant: the ground truth uses the exact geometry, pose and Sun each image was
//! rendered with.

use super::report::{quantiles, ShadowHeadroom, SunCoverage};
use crate::dataset::{eval, eval_seed, frame_request, target_size};
use crate::experiment::data::{SceneData, SceneIntrinsics, ViewData};
use crate::experiment::evaluate::{frame_request_of, sun_of};
use crate::experiment::ExperimentError;
use crate::raytrace::sunlight::{render_sunlight, SunClass, SunlightMap};
use crate::raytrace::{try_render_frame_with, Scene};
use crate::scenario::Scenario;
use glam::Vec3;
use gs_core::loss::{psnr, psnr_db_from_mse, ImageShape};
use rayon::prelude::*;

pub(super) fn sunlight_of(
    rt: &Scene,
    k: &SceneIntrinsics,
    view: &ViewData,
) -> Result<SunlightMap, ExperimentError> {
    render_sunlight(rt, &frame_request_of(k, view))
        .map_err(|e| ExperimentError::Invalid(format!("ground-truth Sun map: {e}")))
}

pub(super) fn pooled_fractions(maps: &[SunlightMap]) -> [f64; 3] {
    let mut n = [0usize; 3];
    for m in maps {
        for c in &m.class {
            match c {
                SunClass::Lit => n[0] += 1,
                SunClass::CastShadow => n[1] += 1,
                SunClass::FacingAway => n[2] += 1,
                SunClass::Background => {}
            }
        }
    }
    let total = n.iter().sum::<usize>().max(1) as f64;
    n.map(|c| c as f64 / total)
}

fn angle_deg(a: Vec3, b: Vec3) -> f64 {
    (a.normalize().dot(b.normalize()).clamp(-1.0, 1.0) as f64)
        .acos()
        .to_degrees()
}

pub(super) fn sun_coverage(scene: &SceneData) -> SunCoverage {
    let lit: Vec<&ViewData> = scene.frames.iter().filter(|v| !v.eclipse).collect();
    let train_sun: Vec<Vec3> = lit.iter().map(|v| sun_of(v)).collect();
    let train_view: Vec<Vec3> = lit.iter().map(|v| v.view_dir_target().as_vec3()).collect();
    let mean = train_sun.iter().fold(Vec3::ZERO, |a, &b| a + b);
    let spread = train_sun
        .iter()
        .map(|&s| angle_deg(s, mean.normalize_or(Vec3::Z)))
        .collect();
    let mut nearest_sun = Vec::new();
    let mut nearest_both = Vec::new();
    for e in &scene.eval {
        let (s, v) = (sun_of(e), e.view_dir_target().as_vec3());
        let mut best_sun = f64::INFINITY;
        let mut best_both = f64::INFINITY;
        for (ts, tv) in train_sun.iter().zip(&train_view) {
            let a = angle_deg(s, *ts);
            best_sun = best_sun.min(a);
            best_both = best_both.min(a.max(angle_deg(v, *tv)));
        }
        nearest_sun.push(best_sun);
        nearest_both.push(best_both);
    }
    SunCoverage {
        train_sun_spread_deg: quantiles(spread),
        eval_to_nearest_train_sun_deg: quantiles(nearest_sun),
        eval_to_nearest_train_sun_and_view_deg: quantiles(nearest_both),
    }
}

/// The evaluation views re-rendered with and without cast shadows from the exact requests
/// `data::render_scene` makes (same geometry, seeds, Earth fill); the first must reproduce
/// the stored image byte for byte, or the comparison is refused.
pub(super) fn shadow_headroom(
    scenario: &Scenario,
    rt: &Scene,
    scene: &SceneData,
) -> Result<ShadowHeadroom, ExperimentError> {
    let geometry = scenario.geometry(target_size(scenario, rt.mesh()))?;
    let ranges = eval::scenario_range_m(scenario, &geometry);
    let k = &scene.intrinsics;
    let shape = ImageShape::new(k.width as usize, k.height as usize, 3);
    let per_view: Vec<(f64, f64)> = scene
        .eval
        .par_iter()
        .map(|view| {
            let g = eval::eval_view(scenario, &geometry, view.index, ranges);
            let request = frame_request(scenario, &g, eval_seed(scenario, view.index));
            let render = |cast| {
                try_render_frame_with(rt, &request, cast)
                    .map_err(|e| ExperimentError::Invalid(format!("headroom render: {e}")))
            };
            if render(true)?.rgb8 != view.rgb8 {
                return Err(ExperimentError::Invalid(format!(
                    "evaluation view {} does not re-render to its stored image",
                    view.index
                )));
            }
            let unshadowed: Vec<f32> = render(false)?
                .rgb8
                .iter()
                .map(|&v| v as f32 / 255.0)
                .collect();
            let truth = view.rgb_f32();
            let mse = truth
                .iter()
                .zip(&unshadowed)
                .map(|(a, b)| ((a - b) as f64).powi(2))
                .sum::<f64>()
                / truth.len() as f64;
            let p = psnr(&unshadowed, &truth, shape)
                .map_err(|e| ExperimentError::Invalid(format!("PSNR: {e}")))?
                as f64;
            Ok((p.min(100.0), mse))
        })
        .collect::<Result<_, ExperimentError>>()?;
    let n = per_view.len().max(1) as f64;
    let pooled_mse = per_view.iter().map(|v| v.1).sum::<f64>() / n;
    Ok(ShadowHeadroom {
        mean_psnr_db: per_view.iter().map(|v| v.0).sum::<f64>() / n,
        pooled_psnr_db: psnr_db_from_mse(pooled_mse).min(100.0),
        pooled_mse,
        per_view_psnr_db: per_view.iter().map(|v| v.0).collect(),
    })
}
