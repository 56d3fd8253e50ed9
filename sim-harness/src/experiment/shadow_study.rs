//! The shadow study: does shadow splatting (configuration c) see the shadows the ray tracer
//! casts? `sim-harness shadow-study` measures, on one target:
//! 1. how much of the target is in cast shadow at all (ground truth from
//!    [`crate::raytrace::sunlight`]), on the training frames and on the evaluation views;
//! 2. how the evaluation views' Sun directions relate to the training ones (target frame),
//!    and how far the evaluation views are from their own re-render without cast shadows
//!    (the most shadow splatting can add);
//! 3. the light pass alone on known geometry ("oracle"): the initial surface-sample Gaussians
//!    made opaque, `V_i` against whether the Sun reaches each Gaussian's centre, for both
//!    light projections, two light-image resolutions, depth biases and receiver extents
//!    (the acne fix; 0 = off), split by the angle between surface normal and Sun;
//! 4. configuration c before and (unless `train` is off) after online training: per view the
//!    shadow image S, the per-Gaussian `V_i` splatted from the camera ("V image") and `V'_i`
//!    against the ground truth: IoU and accuracy of `value < 0.5` against cast shadow over the
//!    target's pixels that face the Sun, mean values on lit / cast-shadow / facing-away pixels,
//!    and the same per Gaussian (opacity-weighted).
//!
//! Writes `shadow_study.json` (everything), `shadow_study.md` (the summary tables),
//! `oracle_gaussians.csv` (the oracle's Gaussians on the first view) and
//! `before.png` / `after.png` (per view: truth, ground-truth Sun classes, V image, S, the
//! colour before the shadow product and the render).
//!
//! Invariants: the ground truth uses the exact geometry, pose and Sun each image was rendered
//! with; the model sees nothing the table's runs would not (the training is
//! [`super::runner::run_config`]); every number comes from this run.

mod oracle;
mod report;
mod scores;
mod truth;

pub use report::{
    to_markdown, AngleQuantiles, OracleRow, ShadowHeadroom, ShadowStudyReport, StageReport,
    SunCoverage, ViewShadowReport, COS_BUCKETS, ORACLE_BIAS_AND_EXTENT,
};
pub use scores::{GaussianScores, PixelScores};

use super::data::{load_or_render_scene, SceneData, ViewData};
use super::evaluate::{camera_of, sun_of, to_rgb8};
use super::figure::{grid_figure, Cell};
use super::preset::Preset;
use super::runner::{initialisation, online_config, run_config, scene_box};
use super::{write_text, ExperimentError};
use crate::dataset::{files, load_target};
use crate::raytrace::sunlight::{SunClass, SunlightMap};
use crate::raytrace::Scene;
use crate::scenario::Scenario;
use gs_core::loss::{psnr, ImageShape};
use gs_core::raster::{render, GaussianView, RasterSettings};
use gs_core::sunaware::{SunAwareModel, Variant};
use gs_online::online::OnlineTrainer;
use oracle::{opacity, oracle_rows, reach_step_m, reached};
use rayon::prelude::*;
use scores::{GaussianAcc, PixelAcc};
use std::path::PathBuf;
use std::time::Instant;
use truth::{pooled_fractions, shadow_headroom, sun_coverage, sunlight_of};

/// What the study needs.
#[derive(Clone, Debug)]
pub struct ShadowStudyJob {
    pub preset: Preset,
    /// The scenario before the preset is applied.
    pub scenario: Scenario,
    pub out_dir: PathBuf,
    /// Rendered scenes are cached here (a table's `OUT/cache` can be reused).
    pub cache_dir: PathBuf,
    /// Evaluation views and training frames shown and scored per stage (each).
    pub views: usize,
    /// Train configuration c (else only the ground truth, the Sun coverage and the oracle).
    pub train: bool,
}

fn grey8(values: &[f32]) -> Vec<u8> {
    values
        .iter()
        .flat_map(|&v| [(v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8; 3])
        .collect()
}

fn class_rgb8(map: &SunlightMap) -> Vec<u8> {
    map.class
        .iter()
        .flat_map(|c| match c {
            SunClass::Background => [0, 0, 0],
            SunClass::Lit => [235, 235, 235],
            SunClass::CastShadow => [220, 40, 40],
            SunClass::FacingAway => [40, 70, 210],
        })
        .collect()
}

/// One view's report, its pixel accumulators (S, V image), its Gaussian accumulators
/// (V, V') and its figure cells.
type ViewStudy = (ViewShadowReport, [PixelAcc; 2], [GaussianAcc; 2], Vec<Cell>);

/// Scores and figure cells of one view for one model.
fn study_view(
    model: &SunAwareModel,
    rt: &Scene,
    scene: &SceneData,
    view: &ViewData,
    label: String,
    step_m: f32,
) -> Result<ViewStudy, ExperimentError> {
    let k = &scene.intrinsics;
    let camera = camera_of(k, view);
    let sun = sun_of(view);
    let settings = model.raster_settings(false);
    let degree = model.gaussians.layout().sh_degree;
    let pass = model.forward(&camera, sun, degree, &settings, None)?;
    if pass.shadow_image.is_empty() {
        return Err(ExperimentError::Invalid(
            "shadow study needs a configuration with shadow splatting (c or d)".into(),
        ));
    }
    let truth = sunlight_of(rt, k, view)?;
    let v_view = GaussianView::from_model(&model.gaussians, &pass.visibility, 1);
    let v_settings = RasterSettings {
        near_m: settings.near_m,
        background: vec![1.0],
        smooth_cutoff: false,
        ..RasterSettings::default()
    };
    let v_image = render(&camera, &v_view, &v_settings)
        .map_err(|e| ExperimentError::Invalid(format!("V image: {e}")))?
        .color;
    let mut pixel = [PixelAcc::default(); 2];
    for (px, &class) in truth.class.iter().enumerate() {
        pixel[0].add(class, pass.shadow_image[px]);
        pixel[1].add(class, v_image[px]);
    }
    let mut gauss = [GaussianAcc::default(); 2];
    let g = &model.gaussians;
    let reach: Vec<bool> = pass
        .visible_list
        .par_iter()
        .map(|&i| reached(rt, g, i as usize, sun, step_m))
        .collect();
    for (&i, &r) in pass.visible_list.iter().zip(&reach) {
        let i = i as usize;
        let w = opacity(g, i);
        gauss[0].add(r, pass.visibility[i], w);
        gauss[1].add(r, pass.refined_visibility[i], w);
    }
    let shape = ImageShape::new(k.width as usize, k.height as usize, 3);
    let psnr_db = psnr(&pass.image, &view.rgb_f32(), shape)
        .map_err(|e| ExperimentError::Invalid(format!("PSNR: {e}")))? as f64;
    let report = ViewShadowReport {
        view: label,
        psnr_db,
        truth_fractions: truth.fractions(),
        shadow_image: pixel[0].scores(),
        visibility_image: pixel[1].scores(),
        visibility: gauss[0].scores(),
        refined_visibility: gauss[1].scores(),
    };
    let cell = |rgb8: Vec<u8>, caption: String| Cell {
        rgb8: Some(rgb8),
        caption,
    };
    let cells = vec![
        cell(view.rgb8.clone(), report.view.clone()),
        cell(
            class_rgb8(&truth),
            format!("cast {:.0}%", 100.0 * report.truth_fractions[1]),
        ),
        cell(
            grey8(&v_image),
            format!("iou {:.2}", report.visibility_image.iou_dark),
        ),
        cell(
            grey8(&pass.shadow_image),
            format!("iou {:.2}", report.shadow_image.iou_dark),
        ),
        cell(to_rgb8(&pass.rgb), String::new()),
        cell(to_rgb8(&pass.image), format!("{psnr_db:.1} db")),
    ];
    Ok((report, pixel, gauss, cells))
}

/// Every selected view for one model: the stage report and its figure.
fn study_stage(
    stage: &str,
    model: &SunAwareModel,
    rt: &Scene,
    scene: &SceneData,
    views: &[(String, &ViewData)],
) -> Result<(StageReport, crate::dataset::plots::Canvas), ExperimentError> {
    let step_m = reach_step_m(scene);
    let mut reports = Vec::new();
    let mut pixel = [PixelAcc::default(); 2];
    let mut gauss = [GaussianAcc::default(); 2];
    let mut rows = Vec::new();
    for (label, view) in views {
        let (r, p, g, cells) = study_view(model, rt, scene, view, label.clone(), step_m)?;
        for k in 0..2 {
            pixel[k].merge(&p[k]);
            gauss[k].merge(&g[k]);
        }
        reports.push(r);
        rows.push(cells);
    }
    let labels = ["truth", "sun gt", "v image", "s", "rgb", "rgb x s"].map(String::from);
    let figure = grid_figure(
        scene.intrinsics.width,
        scene.intrinsics.height,
        &labels,
        &[],
        &rows,
        240,
    );
    Ok((
        StageReport {
            stage: stage.to_string(),
            gaussians: model.len(),
            views: reports,
            shadow_image: pixel[0].scores(),
            visibility_image: pixel[1].scores(),
            visibility: gauss[0].scores(),
            refined_visibility: gauss[1].scores(),
        },
        figure,
    ))
}

/// Up to `n` lit training frames, evenly spaced in time.
fn spaced_frames(scene: &SceneData, n: usize) -> Vec<&ViewData> {
    let lit: Vec<&ViewData> = scene.frames.iter().filter(|v| !v.eclipse).collect();
    if lit.len() <= n {
        return lit;
    }
    (0..n)
        .map(|i| lit[(2 * i + 1) * lit.len() / (2 * n)])
        .collect()
}

/// Runs the study (see the module header).
pub fn run_shadow_study(
    job: &ShadowStudyJob,
    progress: &mut dyn FnMut(&str),
) -> Result<ShadowStudyReport, ExperimentError> {
    let started = Instant::now();
    let out = &job.out_dir;
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::Io {
        path: out.clone(),
        message: e.to_string(),
    })?;
    let scenario = job.preset.apply(&job.scenario)?;
    let scene = load_or_render_scene(
        &scenario,
        job.preset.init_points as usize,
        &job.cache_dir,
        progress,
    )?;
    let rt = Scene::new(load_target(&scenario)?);
    let k = scene.intrinsics;

    let train_maps: Vec<SunlightMap> = scene
        .frames
        .iter()
        .filter(|v| !v.eclipse)
        .map(|v| sunlight_of(&rt, &k, v))
        .collect::<Result<_, _>>()?;
    let eval_maps: Vec<SunlightMap> = scene
        .eval
        .iter()
        .map(|v| sunlight_of(&rt, &k, v))
        .collect::<Result<_, _>>()?;
    let truth_fractions_train = pooled_fractions(&train_maps);
    let truth_fractions_eval = pooled_fractions(&eval_maps);
    progress(&format!(
        "{}: target pixels lit / cast shadow / facing away: training {:.3} / {:.3} / {:.3}, evaluation {:.3} / {:.3} / {:.3}",
        scene.name,
        truth_fractions_train[0],
        truth_fractions_train[1],
        truth_fractions_train[2],
        truth_fractions_eval[0],
        truth_fractions_eval[1],
        truth_fractions_eval[2]
    ));
    let eval_cast_fraction = eval_maps.iter().map(|m| m.fractions()[1]).collect();
    let no_cast_shadow_psnr = shadow_headroom(&scenario, &rt, &scene)?;
    progress(&format!(
        "{}: evaluation views without cast shadows: PSNR {:.2} dB (pooled {:.2} dB)",
        scene.name, no_cast_shadow_psnr.mean_psnr_db, no_cast_shadow_psnr.pooled_psnr_db
    ));
    let sun_coverage = sun_coverage(&scene);

    let variant = Variant::C;
    let fresh = OnlineTrainer::new(
        online_config(&job.preset, variant)?,
        &initialisation(&scene, &job.preset),
        scene_box(&scene)?,
    )?;
    let fresh_model = &fresh.trainer().model;
    let eval_views: Vec<&ViewData> = scene.eval.iter().take(job.views).collect();
    let train_views = spaced_frames(&scene, job.views);
    let mut selected: Vec<(String, &ViewData)> = eval_views
        .iter()
        .map(|v| (format!("eval {}", v.index), *v))
        .collect();
    selected.extend(
        train_views
            .iter()
            .map(|v| (format!("frame {}", v.index), *v)),
    );
    let oracle_views: Vec<&ViewData> = selected.iter().map(|(_, v)| *v).collect();
    let oracle = oracle_rows(
        &scene,
        &rt,
        &job.preset,
        fresh_model,
        &oracle_views,
        &out.join("oracle_gaussians.csv"),
    )?;
    progress(&format!(
        "{}: oracle light pass done ({} settings)",
        scene.name,
        oracle.len()
    ));
    let (before, figure) = study_stage("before", fresh_model, &rt, &scene, &selected)?;
    write_png(&out.join("before.png"), &figure)?;

    let (mut after, mut eval_psnr_db, mut eval_psnr_per_view_db) = (None, None, Vec::new());
    if job.train {
        let (outcome, trainer) = run_config(&scene, &job.preset, variant, 0, progress)?;
        let (stage, figure) =
            study_stage("after", &trainer.trainer().model, &rt, &scene, &selected)?;
        write_png(&out.join("after.png"), &figure)?;
        after = Some(stage);
        eval_psnr_db = Some(outcome.eval.psnr_db);
        eval_psnr_per_view_db = outcome.eval.per_view.iter().map(|m| m.psnr_db).collect();
    }
    let report = ShadowStudyReport {
        target: scene.name.clone(),
        width: k.width,
        height: k.height,
        truth_fractions_train,
        truth_fractions_eval,
        eval_cast_fraction,
        sun_coverage,
        no_cast_shadow_psnr,
        oracle,
        before,
        after,
        eval_psnr_db,
        eval_psnr_per_view_db,
        total_s: started.elapsed().as_secs_f64(),
    };
    let json = serde_json::to_string_pretty(&report)
        .map_err(|e| ExperimentError::Invalid(format!("shadow study JSON: {e}")))?;
    write_text(&out.join("shadow_study.json"), &json)?;
    write_text(&out.join("shadow_study.md"), &to_markdown(&report))?;
    Ok(report)
}

fn write_png(
    path: &std::path::Path,
    canvas: &crate::dataset::plots::Canvas,
) -> Result<(), ExperimentError> {
    files::write_png_rgb(path, canvas.width, canvas.height, &canvas.rgb8)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use report::quantiles;

    #[test]
    fn pixel_scores_count_cast_shadow_against_lit_only() {
        let mut acc = PixelAcc::default();
        acc.add(SunClass::Lit, 0.9); // tn
        acc.add(SunClass::Lit, 0.2); // fp
        acc.add(SunClass::CastShadow, 0.1); // tp
        acc.add(SunClass::CastShadow, 0.7); // fn
        acc.add(SunClass::FacingAway, 0.0); // not in IoU
        acc.add(SunClass::Background, 0.0); // ignored
        let s = acc.scores();
        assert_eq!((s.lit_px, s.cast_px, s.away_px), (2, 2, 1));
        assert!((s.iou_dark - 1.0 / 3.0).abs() < 1e-12);
        assert!((s.accuracy - 0.5).abs() < 1e-12);
        assert!((s.mean_on_lit - 0.55).abs() < 1e-6);
        assert!((s.mean_on_cast - 0.4).abs() < 1e-6);
        assert_eq!(s.mean_on_away, 0.0);
    }

    #[test]
    fn gaussian_scores_are_opacity_weighted() {
        let mut acc = GaussianAcc::default();
        acc.add(true, 1.0, 3.0);
        acc.add(true, 0.0, 1.0);
        acc.add(false, 0.2, 1.0);
        let s = acc.scores();
        assert_eq!((s.reached, s.blocked), (2, 1));
        assert!((s.mean_on_reached - 0.75).abs() < 1e-12);
        assert!((s.mean_on_blocked - 0.2).abs() < 1e-6);
        assert!((s.accuracy - 0.8).abs() < 1e-12);
        assert!(GaussianAcc::default().scores().accuracy.is_nan());
    }

    #[test]
    fn quantiles_of_a_list() {
        let q = quantiles((0..=100).map(f64::from).rev().collect());
        assert_eq!(
            (q.min, q.p25, q.median, q.p75, q.max),
            (0.0, 25.0, 50.0, 75.0, 100.0)
        );
    }
}
