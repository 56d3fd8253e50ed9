//! The oracle: the light pass alone on known geometry (the initial surface samples made
//! opaque), `V_i` against whether the Sun reaches each Gaussian's centre, over light
//! projections, resolutions, depth biases and receiver extents; and its per-Gaussian CSV.
//!
//! Invariant: the model is the preset's initial surface samples; nothing is trained here.

use super::report::{OracleRow, COS_BUCKETS, ORACLE_BIAS_AND_EXTENT};
use super::scores::{ratio, GaussianAcc};
use crate::experiment::data::{SceneData, ViewData};
use crate::experiment::evaluate::{camera_of, sun_of};
use crate::experiment::preset::Preset;
use crate::experiment::{write_text, ExperimentError};
use crate::raytrace::sunlight::sun_reaches_point;
use crate::raytrace::Scene;
use glam::Vec3;
use gs_core::init::inverse_sigmoid;
use gs_core::model::{GaussianModel, Param};
use gs_core::sunaware::sun_visibility::{sun_visibility_with_margin, RECEIVER_EXTENT_SIGMAS};
use gs_core::sunaware::{LightConfig, LightProjection, SunAwareModel};
use rayon::prelude::*;

/// Step of the ground-truth shadow ray off a Gaussian's centre, metres.
pub(super) fn reach_step_m(scene: &SceneData) -> f32 {
    1e-3 * scene.bounding_radius_m.max(0.1)
}

pub(super) fn reached(rt: &Scene, model: &GaussianModel, i: usize, sun: Vec3, step_m: f32) -> bool {
    let m = model.params.row(Param::Mean, i);
    sun_reaches_point(rt, Vec3::new(m[0], m[1], m[2]), sun, step_m).unwrap_or(false)
}

pub(super) fn opacity(model: &GaussianModel, i: usize) -> f32 {
    let logit = model.params.row(Param::OpacityLogit, i)[0];
    1.0 / (1.0 + (-logit).exp())
}

/// The light pass on the initial surface samples made opaque (see the module header).
pub(super) fn oracle_rows(
    scene: &SceneData,
    rt: &Scene,
    preset: &Preset,
    model: &SunAwareModel,
    views: &[&ViewData],
    out_csv: &std::path::Path,
) -> Result<Vec<OracleRow>, ExperimentError> {
    let mut g = model.gaussians.clone();
    let n = g.len();
    let normals: Vec<Vec3> = scene.surface.iter().take(n).map(|s| s.normal).collect();
    if normals.len() != n {
        return Err(ExperimentError::Invalid(format!(
            "oracle: {n} Gaussians but {} surface samples",
            normals.len()
        )));
    }
    g.params
        .get_mut(Param::OpacityLogit)
        .fill(inverse_sigmoid(0.95));
    let step_m = reach_step_m(scene);
    let truth: Vec<Vec<bool>> = views
        .iter()
        .map(|v| {
            let sun = sun_of(v);
            (0..n)
                .into_par_iter()
                .map(|i| reached(rt, &g, i, sun, step_m))
                .collect()
        })
        .collect();
    if let Some(view) = views.first() {
        write_oracle_csv(scene, model, &g, &normals, &truth[0], view, out_csv)?;
    }
    let mut rows = Vec::new();
    for projection in [LightProjection::Perspective, LightProjection::Orthographic] {
        for resolution_px in [preset.light_resolution_px, 256] {
            for (depth_bias_fraction, extent_sigmas) in ORACLE_BIAS_AND_EXTENT {
                let config = LightConfig {
                    projection,
                    resolution_px,
                    depth_bias_fraction,
                    ..model.config.light
                };
                let mut facing = GaussianAcc::default();
                let mut away = GaussianAcc::default();
                let mut by_cos = [GaussianAcc::default(); COS_BUCKETS.len()];
                for (view, truth) in views.iter().zip(&truth) {
                    let camera = camera_of(&scene.intrinsics, view);
                    let sun = sun_of(view);
                    let v = sun_visibility_with_margin(
                        &g,
                        sun,
                        camera.position(),
                        &model.scene_box,
                        &config,
                        model.config.near_m,
                        extent_sigmas,
                    )?;
                    for i in 0..n {
                        let c = normals[i].dot(sun);
                        if c <= -0.1 {
                            away.add(truth[i], v[i], 1.0);
                        }
                        if let Some(slot) = COS_BUCKETS.iter().position(|&lo| c >= lo) {
                            facing.add(truth[i], v[i], 1.0);
                            by_cos[slot].add(truth[i], v[i], 1.0);
                        }
                    }
                }
                rows.push(OracleRow {
                    projection: format!("{projection:?}").to_lowercase(),
                    resolution_px,
                    depth_bias_fraction,
                    receiver_extent_sigmas: extent_sigmas,
                    facing: facing.scores(),
                    mean_on_facing_away: {
                        let a = away.scores();
                        let n = (a.reached + a.blocked) as f64;
                        let w = |m: f64, k: usize| if k > 0 { m * k as f64 } else { 0.0 };
                        ratio(
                            w(a.mean_on_reached, a.reached) + w(a.mean_on_blocked, a.blocked),
                            n,
                        )
                    },
                    by_cos: by_cos.iter().map(GaussianAcc::scores).collect(),
                });
            }
        }
    }
    Ok(rows)
}

/// Per Gaussian of the oracle model for one view (the model's light settings): position,
/// outward normal, scale, whether the Sun reaches it, V without and with the acne fix.
fn write_oracle_csv(
    scene: &SceneData,
    model: &SunAwareModel,
    g: &GaussianModel,
    normals: &[Vec3],
    truth: &[bool],
    view: &ViewData,
    path: &std::path::Path,
) -> Result<(), ExperimentError> {
    let camera = camera_of(&scene.intrinsics, view);
    let sun = sun_of(view);
    let vis = |extent| {
        sun_visibility_with_margin(
            g,
            sun,
            camera.position(),
            &model.scene_box,
            &model.config.light,
            model.config.near_m,
            extent,
        )
    };
    let (v0, v2) = (vis(0.0)?, vis(RECEIVER_EXTENT_SIGMAS)?);
    let mut text =
        String::from("x_m,y_m,z_m,nx,ny,nz,cos_sun,scale_m,reached,v_fixed_bias,v_extent\n");
    for i in 0..g.len() {
        let m = g.params.row(Param::Mean, i);
        let n = normals[i];
        text += &format!(
            "{:.4},{:.4},{:.4},{:.3},{:.3},{:.3},{:.3},{:.4},{},{:.4},{:.4}\n",
            m[0],
            m[1],
            m[2],
            n.x,
            n.y,
            n.z,
            n.dot(sun),
            g.params.row(Param::LogScale, i)[0].exp(),
            u8::from(truth[i]),
            v0[i],
            v2[i]
        );
    }
    write_text(path, &text)
}
