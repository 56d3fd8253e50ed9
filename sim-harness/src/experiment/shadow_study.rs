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

use super::data::{load_or_render_scene, SceneData, SceneIntrinsics, ViewData};
use super::evaluate::{camera_of, sun_of, to_rgb8};
use super::figure::{grid_figure, Cell};
use super::preset::Preset;
use super::runner::{initialisation, online_config, run_config, scene_box};
use super::write_text;
use super::ExperimentError;
use crate::dataset::{eval, files, frame_request, framing_radius_m, load_target};
use crate::raytrace::sunlight::{render_sunlight, sun_reaches_point, SunClass, SunlightMap};
use crate::raytrace::{try_render_frame_with, FrameRequest, PinholeCamera, Scene};
use crate::scenario::{Scenario, TargetSize};
use glam::Vec3;
use gs_core::init::inverse_sigmoid;
use gs_core::loss::{psnr, psnr_db_from_mse, ImageShape};
use gs_core::model::{GaussianModel, Param};
use gs_core::raster::{render, GaussianView, RasterSettings};
use gs_core::rng::mix64;
use gs_core::sunaware::light::{sun_visibility_with_margin, RECEIVER_EXTENT_SIGMAS};
use gs_core::sunaware::{LightConfig, LightProjection, SunAwareModel, Variant};
use gs_online::online::OnlineTrainer;
use rayon::prelude::*;
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

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

/// Pixel scores of a map in [0, 1] (S or the V image) against the ground truth: "predicted
/// dark" is `value < 0.5`, "truly dark" is cast shadow; IoU and accuracy count only pixels
/// that face the Sun (lit or cast shadow), since facing-away pixels are dark whatever S says.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct PixelScores {
    pub lit_px: usize,
    pub cast_px: usize,
    pub away_px: usize,
    pub mean_on_lit: f64,
    pub mean_on_cast: f64,
    pub mean_on_away: f64,
    pub iou_dark: f64,
    pub accuracy: f64,
}

#[derive(Clone, Copy, Debug, Default)]
struct PixelAcc {
    n: [usize; 3],
    sum: [f64; 3],
    tp: usize,
    fp: usize,
    fn_: usize,
    tn: usize,
}

impl PixelAcc {
    fn add(&mut self, class: SunClass, value: f32) {
        let slot = match class {
            SunClass::Lit => 0,
            SunClass::CastShadow => 1,
            SunClass::FacingAway => 2,
            SunClass::Background => return,
        };
        self.n[slot] += 1;
        self.sum[slot] += value as f64;
        let dark = value < 0.5;
        match (slot, dark) {
            (1, true) => self.tp += 1,
            (1, false) => self.fn_ += 1,
            (0, true) => self.fp += 1,
            (0, false) => self.tn += 1,
            _ => {}
        }
    }

    fn merge(&mut self, o: &PixelAcc) {
        for k in 0..3 {
            self.n[k] += o.n[k];
            self.sum[k] += o.sum[k];
        }
        self.tp += o.tp;
        self.fp += o.fp;
        self.fn_ += o.fn_;
        self.tn += o.tn;
    }

    fn scores(&self) -> PixelScores {
        let mean = |k: usize| ratio(self.sum[k], self.n[k] as f64);
        PixelScores {
            lit_px: self.n[0],
            cast_px: self.n[1],
            away_px: self.n[2],
            mean_on_lit: mean(0),
            mean_on_cast: mean(1),
            mean_on_away: mean(2),
            iou_dark: ratio(self.tp as f64, (self.tp + self.fp + self.fn_) as f64),
            accuracy: ratio(
                (self.tp + self.tn) as f64,
                (self.tp + self.tn + self.fp + self.fn_) as f64,
            ),
        }
    }
}

/// NaN for an empty denominator (written as null in the JSON).
fn ratio(a: f64, b: f64) -> f64 {
    if b > 0.0 {
        a / b
    } else {
        f64::NAN
    }
}

/// Per-Gaussian scores of a visibility (`V_i` or `V'_i`) against whether the Sun reaches the
/// Gaussian's centre, weighted by opacity: mean value on reached / blocked Gaussians and the
/// accuracy of `value >= 0.5` meaning "reached".
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct GaussianScores {
    pub reached: usize,
    pub blocked: usize,
    pub mean_on_reached: f64,
    pub mean_on_blocked: f64,
    pub accuracy: f64,
}

#[derive(Clone, Copy, Debug, Default)]
struct GaussianAcc {
    n: [usize; 2],
    w: [f64; 2],
    sum: [f64; 2],
    correct_w: f64,
}

impl GaussianAcc {
    fn add(&mut self, reached: bool, value: f32, weight: f32) {
        let k = usize::from(!reached);
        self.n[k] += 1;
        self.w[k] += weight as f64;
        self.sum[k] += (weight * value) as f64;
        if (value >= 0.5) == reached {
            self.correct_w += weight as f64;
        }
    }

    fn merge(&mut self, o: &GaussianAcc) {
        for k in 0..2 {
            self.n[k] += o.n[k];
            self.w[k] += o.w[k];
            self.sum[k] += o.sum[k];
        }
        self.correct_w += o.correct_w;
    }

    fn scores(&self) -> GaussianScores {
        GaussianScores {
            reached: self.n[0],
            blocked: self.n[1],
            mean_on_reached: ratio(self.sum[0], self.w[0]),
            mean_on_blocked: ratio(self.sum[1], self.w[1]),
            accuracy: ratio(self.correct_w, self.w[0] + self.w[1]),
        }
    }
}

/// Scores of one view at one stage.
#[derive(Clone, Debug, Serialize)]
pub struct ViewShadowReport {
    /// `eval K` or `frame K`.
    pub view: String,
    pub psnr_db: f64,
    /// Fractions of the target's pixels lit / in cast shadow / facing away.
    pub truth_fractions: [f64; 3],
    pub shadow_image: PixelScores,
    pub visibility_image: PixelScores,
    pub visibility: GaussianScores,
    pub refined_visibility: GaussianScores,
}

/// One stage (before or after training), per view and pooled.
#[derive(Clone, Debug, Serialize)]
pub struct StageReport {
    pub stage: String,
    pub gaussians: usize,
    pub views: Vec<ViewShadowReport>,
    pub shadow_image: PixelScores,
    pub visibility_image: PixelScores,
    pub visibility: GaussianScores,
    pub refined_visibility: GaussianScores,
}

/// The light pass on opaque surface samples for one light setting, pooled over the views.
#[derive(Clone, Debug, Serialize)]
pub struct OracleRow {
    pub projection: String,
    pub resolution_px: u32,
    pub depth_bias_fraction: f32,
    /// Receivers ignore occluders within this many of their own sigmas along the light
    /// axis (0: the fixed bias alone, the shadow pass before the acne fix).
    pub receiver_extent_sigmas: f32,
    /// Gaussians whose surface faces the Sun (cos(outward normal, Sun) >= 0.1): reached =
    /// lit, blocked = in cast shadow. This is what shadow splatting has to tell apart.
    pub facing: GaussianScores,
    /// Mean V of Gaussians on surfaces facing away (cos <= -0.1): dark by shading whatever V
    /// says; back faces of thin bodies sit within the front face's extent and stay V ~ 1.
    pub mean_on_facing_away: f64,
    /// Facing Gaussians by cos(normal, Sun) in [`COS_BUCKETS`] (face-on first): neighbours on
    /// a tilted surface are nearer the light than each other, so false self-shadowing
    /// ("acne") grows as the Sun grazes the surface.
    pub by_cos: Vec<GaussianScores>,
}

/// (depth bias fraction, receiver extent in sigmas) settings of the oracle sweep.
pub const ORACLE_BIAS_AND_EXTENT: [(f32, f32); 8] = [
    (0.005, 0.0),
    (0.02, 0.0),
    (0.05, 0.0),
    (0.02, 1.0),
    (0.02, 2.0),
    (0.02, 3.0),
    (0.005, 2.0),
    (0.05, 2.0),
];

/// Lower bounds of the |cos(normal, Sun)| buckets of [`OracleRow::by_cos`].
pub const COS_BUCKETS: [f32; 4] = [0.9, 0.7, 0.4, 0.1];

/// Quantiles (min, 25 %, median, 75 %, max) of a list of angles, degrees.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct AngleQuantiles {
    pub min: f64,
    pub p25: f64,
    pub median: f64,
    pub p75: f64,
    pub max: f64,
}

fn quantiles(mut v: Vec<f64>) -> AngleQuantiles {
    if v.is_empty() {
        return AngleQuantiles::default();
    }
    v.sort_by(f64::total_cmp);
    let q = |p: f64| v[((v.len() - 1) as f64 * p).round() as usize];
    AngleQuantiles {
        min: q(0.0),
        p25: q(0.25),
        median: q(0.5),
        p75: q(0.75),
        max: q(1.0),
    }
}

/// How the evaluation views' Sun directions relate to the training frames' (target frame).
#[derive(Clone, Debug, Serialize)]
pub struct SunCoverage {
    /// Angle between the training frames' Sun directions and their mean direction.
    pub train_sun_spread_deg: AngleQuantiles,
    /// Per evaluation view: angle to the nearest training Sun direction.
    pub eval_to_nearest_train_sun_deg: AngleQuantiles,
    /// Per evaluation view: over training frames, the smallest max(Sun angle, view angle):
    /// how far the nearest training frame with both a similar Sun and a similar viewpoint is.
    pub eval_to_nearest_train_sun_and_view_deg: AngleQuantiles,
}

/// PSNR of the evaluation views rendered without cast shadows against the true views.
#[derive(Clone, Debug, Serialize)]
pub struct ShadowHeadroom {
    /// Mean over views of the full-frame PSNR (capped at 100 dB per view), dB.
    pub mean_psnr_db: f64,
    /// Full-frame PSNR of the pooled squared error over all views, dB.
    pub pooled_psnr_db: f64,
    /// Mean squared error per pixel and channel on [0, 1] images, pooled.
    pub pooled_mse: f64,
    pub per_view_psnr_db: Vec<f64>,
}

/// Everything the study measured.
#[derive(Clone, Debug, Serialize)]
pub struct ShadowStudyReport {
    pub target: String,
    pub width: u32,
    pub height: u32,
    /// Pooled fractions of target pixels lit / cast shadow / facing away.
    pub truth_fractions_train: [f64; 3],
    pub truth_fractions_eval: [f64; 3],
    /// Per evaluation view (all of them): cast-shadow fraction of the target's pixels.
    pub eval_cast_fraction: Vec<f64>,
    pub sun_coverage: SunCoverage,
    /// The evaluation views re-rendered without cast shadows (same request otherwise), PSNR
    /// against the true views: the error of a model perfect in every other respect that
    /// ignores self-shadowing; the ceiling of what shadow splatting can add.
    pub no_cast_shadow_psnr: ShadowHeadroom,
    pub oracle: Vec<OracleRow>,
    pub before: StageReport,
    pub after: Option<StageReport>,
    /// Configuration c after training on all evaluation views (mean PSNR, dB).
    pub eval_psnr_db: Option<f64>,
    pub eval_psnr_per_view_db: Vec<f64>,
    pub total_s: f64,
}

fn frame_request_of(k: &SceneIntrinsics, view: &ViewData) -> FrameRequest {
    let q = view.q_camera_from_target;
    FrameRequest {
        camera: PinholeCamera {
            fx: k.fx as f32,
            fy: k.fy as f32,
            cx: k.cx as f32,
            cy: k.cy as f32,
            width: k.width,
            height: k.height,
        },
        camera_from_target_rotation: glam::Quat::from_xyzw(
            q.x as f32, q.y as f32, q.z as f32, q.w as f32,
        )
        .normalize(),
        camera_from_target_translation_m: view.t_camera_from_target_m.as_vec3(),
        sun_dir_target: sun_of(view),
        sun_lit: !view.eclipse,
        earth_albedo: None,
        samples_per_pixel: 1,
        exposure: 1.0,
        seed: 0,
    }
}

fn sunlight_of(
    rt: &Scene,
    k: &SceneIntrinsics,
    view: &ViewData,
) -> Result<SunlightMap, ExperimentError> {
    render_sunlight(rt, &frame_request_of(k, view))
        .map_err(|e| ExperimentError::Invalid(format!("ground-truth Sun map: {e}")))
}

fn pooled_fractions(maps: &[SunlightMap]) -> [f64; 3] {
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

fn sun_coverage(scene: &SceneData) -> SunCoverage {
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
fn shadow_headroom(
    scenario: &Scenario,
    rt: &Scene,
    scene: &SceneData,
) -> Result<ShadowHeadroom, ExperimentError> {
    let mesh = load_target(scenario)?;
    let radius_m = mesh.bounding_radius_m();
    let point_seed = mix64(scenario.seed ^ 0x706F_696E_7473);
    let framing = mesh.sample_surface(scenario.target.surface_points as usize, point_seed);
    let target_size = TargetSize {
        bounding_radius_m: radius_m as f64,
        framing_radius_m: framing_radius_m(&framing).unwrap_or(radius_m as f64),
    };
    let geometry = scenario.geometry(target_size)?;
    let ranges = eval::scenario_range_m(scenario, &geometry);
    let k = &scene.intrinsics;
    let shape = ImageShape::new(k.width as usize, k.height as usize, 3);
    let per_view: Vec<(f64, f64)> = scene
        .eval
        .par_iter()
        .map(|view| {
            let g = eval::eval_view(scenario, &geometry, view.index, ranges);
            let request = frame_request(
                scenario,
                &g,
                mix64(scenario.seed ^ 0x6576_616C ^ mix64(view.index as u64)),
            );
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

/// Step of the ground-truth shadow ray off a Gaussian's centre, metres.
fn reach_step_m(scene: &SceneData) -> f32 {
    1e-3 * scene.bounding_radius_m.max(0.1)
}

fn reached(rt: &Scene, model: &GaussianModel, i: usize, sun: Vec3, step_m: f32) -> bool {
    let m = model.params.row(Param::Mean, i);
    sun_reaches_point(rt, Vec3::new(m[0], m[1], m[2]), sun, step_m).unwrap_or(false)
}

fn opacity(model: &GaussianModel, i: usize) -> f32 {
    let logit = model.params.row(Param::OpacityLogit, i)[0];
    1.0 / (1.0 + (-logit).exp())
}

/// The light pass on the initial surface samples made opaque (see the module header).
fn oracle_rows(
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
        online_config(&job.preset, variant),
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

fn pct(v: f64) -> String {
    format!("{:.1} %", 100.0 * v)
}

fn f3(v: f64) -> String {
    if v.is_finite() {
        format!("{v:.3}")
    } else {
        "-".into()
    }
}

fn stage_rows(s: &StageReport) -> String {
    let mut t = String::new();
    let p = |name: &str, x: &PixelScores| {
        format!(
            "| {} {name} | {} | {} | {} | {} | {} |\n",
            s.stage,
            f3(x.iou_dark),
            f3(x.accuracy),
            f3(x.mean_on_lit),
            f3(x.mean_on_cast),
            f3(x.mean_on_away)
        )
    };
    t += &p("S (pixels)", &s.shadow_image);
    t += &p("V image (pixels)", &s.visibility_image);
    let g = |name: &str, x: &GaussianScores| {
        format!(
            "| {} {name} | | {} | {} | {} | |\n",
            s.stage,
            f3(x.accuracy),
            f3(x.mean_on_reached),
            f3(x.mean_on_blocked)
        )
    };
    t += &g("V_i (Gaussians)", &s.visibility);
    t += &g("V'_i (Gaussians)", &s.refined_visibility);
    t
}

/// The summary tables of a report.
pub fn to_markdown(r: &ShadowStudyReport) -> String {
    let mut t = format!(
        "# Shadow study: {} ({}x{})\n\n## Ground truth\n\nTarget pixels lit / in cast shadow / facing away from the Sun: training frames {} / {} / {}, evaluation views {} / {} / {}.\n\n",
        r.target,
        r.width,
        r.height,
        pct(r.truth_fractions_train[0]),
        pct(r.truth_fractions_train[1]),
        pct(r.truth_fractions_train[2]),
        pct(r.truth_fractions_eval[0]),
        pct(r.truth_fractions_eval[1]),
        pct(r.truth_fractions_eval[2]),
    );
    let h = &r.no_cast_shadow_psnr;
    t += &format!(
        "Evaluation views rendered without cast shadows, against the true views: PSNR {:.2} dB (mean over views; pooled MSE {:.2e} = {:.2} dB). A model that ignores self-shadowing cannot score above this even if perfect otherwise.\n\n",
        h.mean_psnr_db, h.pooled_mse, h.pooled_psnr_db
    );
    let q = |a: &AngleQuantiles| {
        format!(
            "{:.1} / {:.1} / {:.1} / {:.1} / {:.1}",
            a.min, a.p25, a.median, a.p75, a.max
        )
    };
    let c = &r.sun_coverage;
    t += "## Sun directions (target frame), degrees: min / 25 % / median / 75 % / max\n\n";
    t += &format!(
        "- training Sun around its mean: {}\n- evaluation Sun to the nearest training Sun: {}\n- evaluation (Sun, view) to the nearest training frame with both close (max of the two angles): {}\n\n",
        q(&c.train_sun_spread_deg),
        q(&c.eval_to_nearest_train_sun_deg),
        q(&c.eval_to_nearest_train_sun_and_view_deg)
    );
    t += "## Light pass on opaque surface samples (oracle geometry)\n\n";
    t += "Gaussians on surfaces facing the Sun (cos(outward normal, Sun) >= 0.1): accuracy of V >= 0.5 as \"the Sun reaches the centre\" (lit) against blocked (cast shadow), mean V on lit / cast-shadow Gaussians, mean V on lit Gaussians by cos(normal, Sun) (their count in brackets); mean V of Gaussians on surfaces facing away (cos <= -0.1).\n\n";
    t += "| projection | light px | bias | extent sigmas | accuracy | V lit | V cast | V facing away |";
    for lo in COS_BUCKETS {
        t += &format!(" V lit, cos >= {lo} |");
    }
    t += "\n|---|---:|---:|---:|---:|---:|---:|---:|";
    t += &"---:|".repeat(COS_BUCKETS.len());
    t += "\n";
    for o in &r.oracle {
        t += &format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} |",
            o.projection,
            o.resolution_px,
            o.depth_bias_fraction,
            o.receiver_extent_sigmas,
            f3(o.facing.accuracy),
            f3(o.facing.mean_on_reached),
            f3(o.facing.mean_on_blocked),
            f3(o.mean_on_facing_away),
        );
        for bucket in &o.by_cos {
            t += &format!(" {} ({}) |", f3(bucket.mean_on_reached), bucket.reached);
        }
        t += "\n";
    }
    t +=
        "\n## Configuration c: shadow image S, V image and V_i / V'_i against the ground truth\n\n";
    t += "Pixels: IoU and accuracy of value < 0.5 against cast shadow (pixels facing the Sun), mean value on lit / cast / facing-away pixels. Gaussians (opacity-weighted, those in view): accuracy, mean on reached / blocked.\n\n";
    t += "| stage, quantity | IoU | accuracy | mean lit / reached | mean cast / blocked | mean facing away |\n|---|---:|---:|---:|---:|---:|\n";
    t += &stage_rows(&r.before);
    if let Some(a) = &r.after {
        t += &stage_rows(a);
    }
    if let Some(p) = r.eval_psnr_db {
        t += &format!(
            "\nConfiguration c after training: evaluation PSNR {p:.2} dB over {} views.\n",
            r.eval_psnr_per_view_db.len()
        );
    }
    t += &format!("\nTotal {:.0} s.\n", r.total_s);
    t
}

#[cfg(test)]
mod tests {
    use super::*;

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
