//! The initialisation ablation (the paper's Fig. 7, plus a visual hull): configuration d
//! trained online on each target from (1) points sampled on the true surface (the paper),
//! (2) random points in the bounding sphere, (3) a visual hull carved from the first
//! keyframes' masks and known poses (no ground-truth model needed); written to `init.csv`,
//! `init.md`, `init_curves.csv`, `runs.json` and `init.png` (PSNR bars per target, Gaussian
//! count over rounds); `hull.png` shows each target's surface samples beside its hull.
//!
//! The hull's views are the first K keyframes the online trainer's window would take (the
//! first K lit frames each at least `min_view_angle_deg` from the previous keyframe): what the
//! component holds when its window first fills and training starts, so the hull uses no
//! frame the trainer has not seen by then. K defaults to the window size W. The carving box
//! is the cube around the target's bounding sphere (a size prior, not the model); colours are
//! sampled from the keyframe images (the view that sees each point most frontally), or grey.
//! Variants (`hull` with suffixes `-grey`, `-volume`, `-recarve`, `-silhouette`, `-photo`):
//! points filling the hull's voxels rather than its surface; points inside the hull that
//! project onto the foreground in every keyframe (`-silhouette`, preset key
//! `hull_silhouette`), optionally drawn favouring those whose colour the keyframes agree on
//! (`-photo`, `gs_core::hull::carve_photo_consistent`, preset key `hull_photo`); and [`HullPruner`],
//! which carves a persistent volume with every keyframe as the window takes it and prunes
//! the Gaussians whose centres fall outside it (more than one voxel from any occupied
//! voxel). All use only the images, masks and poses of frames the trainer has been offered
//! by then, never an evaluation view.
//!
//! Invariants: every number written comes from a run in this process; runs go one after
//! another, targets in order, initialisations in the order asked; the CSV and Markdown are
//! rewritten after every run; `cpu_s` is this process's CPU time (all threads) over the run,
//! the steadier cost measure on a shared machine.

use super::data::{load_or_render_scene, SceneData};
use super::evaluate::camera_of;
use super::figure::draw_text;
use super::preset::{InitKind, Preset};
use super::runner::{run_config, RunOutcome};
use super::table::target_label;
use super::write_text;
use super::ExperimentError;
use crate::dataset::files;
use crate::dataset::plots::{Canvas, Rgb};
use crate::scenario::Scenario;
use glam::Vec3;
use gs_core::hull::{
    carve, carve_photo_consistent, carve_silhouette_consistent, sample_colours, CarvedVolume,
    ColourView, HullGrid, HullOptions, HullSampling, HullView, PhotoOptions,
    SILHOUETTE_SAMPLES_PER_VOXEL,
};
use gs_core::model::Param;
use gs_core::sunaware::Variant;
use gs_online::keyframe::{Keyframe, KeyframeWindow, ViewDirection, WindowConfig};
use gs_online::online::OnlineTrainer;
use gs_online::online::{Initialisation, OnlineError};
use serde::Serialize;
use std::fmt::Write as _;
use std::path::PathBuf;
use std::time::Instant;

/// Grey for hull points no keyframe colours (and for `hull_grey_colours`).
pub const GREY: [f32; 3] = [0.5; 3];

/// What carving produced, for the report.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct HullReport {
    /// Sequence indices of the keyframes carved from.
    pub frames: Vec<u32>,
    pub voxel_m: f32,
    pub occupied_voxels: usize,
    pub surface_voxels: usize,
    pub points: usize,
    /// Points no keyframe saw on the target (grey).
    pub uncoloured_points: usize,
    /// Mean distance from each hull point to the nearest true surface sample, metres (a
    /// diagnostic only: the hull itself never reads the model).
    pub mean_distance_to_surface_m: f64,
    /// Fraction of the points farther than [`far_distance_m`] from the true surface.
    pub far_fraction: f64,
    /// Fraction of the true surface samples farther than [`far_distance_m`] from every hull
    /// point: the parts of the target the start leaves without a point (diagnostic only).
    pub surface_uncovered_fraction: f64,
    pub carve_s: f64,
    /// `-photo`: candidates drawn, dropped as off the silhouette, and scored by fewer than
    /// two views; the median colour spread (0 for the other hulls).
    pub photo_candidates: usize,
    pub photo_off_silhouette: usize,
    pub photo_unscored: usize,
    pub photo_median_spread: f32,
}

/// Sequence indices of the first `count` keyframes the online window would take: lit frames
/// (not in eclipse) each at least `min_view_angle_deg` from the previous one, in time order.
/// Fewer when the sequence runs out.
pub fn first_keyframes(
    scene: &SceneData,
    count: usize,
    min_view_angle_deg: f64,
) -> Result<Vec<usize>, OnlineError> {
    let capacity = count.max(2);
    let mut window = KeyframeWindow::new(WindowConfig {
        capacity,
        min_view_angle_deg,
    })?;
    for (i, view) in scene.frames.iter().enumerate() {
        if window.len() >= count {
            break;
        }
        if view.eclipse {
            continue;
        }
        let direction = ViewDirection::new(view.view_dir_target())?;
        // No eviction before the window is full: the window holds the first keyframes.
        window.offer(Keyframe {
            id: i as u64,
            view: direction,
            payload: (),
        });
    }
    let mut frames: Vec<usize> = window.ids().into_iter().map(|id| id as usize).collect();
    frames.sort_unstable();
    frames.truncate(count);
    Ok(frames)
}

/// The hull initialisation of `scene` under `preset` (K = `hull_views`, or W when 0).
pub fn hull_initialisation(
    scene: &SceneData,
    preset: &Preset,
) -> Result<(Initialisation, HullReport), OnlineError> {
    let started = Instant::now();
    let k = if preset.hull_views == 0 {
        preset.window
    } else {
        preset.hull_views
    };
    let frames = first_keyframes(scene, k, preset.min_view_angle_deg)?;
    if frames.is_empty() {
        return Err(OnlineError::Config(format!(
            "visual hull of {}: no lit frame to carve from",
            scene.name
        )));
    }
    let cameras: Vec<_> = frames
        .iter()
        .map(|&i| camera_of(&scene.intrinsics, &scene.frames[i]))
        .collect();
    let views: Vec<HullView> = frames
        .iter()
        .zip(&cameras)
        .map(|(&i, &camera)| HullView {
            camera,
            mask: &scene.frames[i].mask8,
        })
        .collect();
    let radius_m = scene.bounding_radius_m.max(0.1);
    let grid = HullGrid::around_sphere(Vec3::ZERO, radius_m, preset.hull_resolution);
    let options = HullOptions {
        point_count: preset.init_points as usize,
        margin_px: 1,
        min_views: 1,
        seed: preset.seed ^ 0x4855_4C4C,
        sampling: if preset.hull_volume {
            HullSampling::Volume
        } else {
            HullSampling::Shell
        },
    };
    let images: Vec<Vec<f32>> = frames.iter().map(|&i| scene.frames[i].rgb_f32()).collect();
    let colour_views: Vec<ColourView> = frames
        .iter()
        .zip(&cameras)
        .zip(&images)
        .map(|((&i, &camera), rgb)| ColourView {
            camera,
            rgb,
            mask: &scene.frames[i].mask8,
        })
        .collect();
    let (hull, photo) = if preset.hull_photo {
        let photo_options = PhotoOptions {
            samples_per_voxel: preset.hull_photo_samples,
            spread_width: preset.hull_photo_spread_width,
        };
        let (hull, stats) = carve_photo_consistent(&colour_views, grid, options, photo_options)
            .map_err(|e| OnlineError::Config(format!("{}: {e}", scene.name)))?;
        (hull, Some(stats))
    } else if preset.hull_silhouette {
        let (hull, stats) =
            carve_silhouette_consistent(&views, grid, options, SILHOUETTE_SAMPLES_PER_VOXEL)
                .map_err(|e| OnlineError::Config(format!("{}: {e}", scene.name)))?;
        (hull, Some(stats))
    } else {
        let hull = carve(&views, grid, options)
            .map_err(|e| OnlineError::Config(format!("{}: {e}", scene.name)))?;
        (hull, None)
    };
    let (colours, uncoloured) = if preset.hull_grey_colours {
        (vec![GREY; hull.points.len()], 0)
    } else {
        sample_colours(&hull.points, &hull.normals, &colour_views, GREY)
    };
    let far_m = far_distance_m(scene, preset);
    let (mean_distance_to_surface_m, far_fraction) = distance_summary(&hull.points, scene, far_m);
    let surface_uncovered_fraction = uncovered_fraction(&hull.points, scene, far_m);
    let report = HullReport {
        frames: frames.iter().map(|&i| scene.frames[i].index).collect(),
        voxel_m: hull.voxel_m,
        occupied_voxels: hull.occupied,
        surface_voxels: hull.surface,
        points: hull.points.len(),
        uncoloured_points: uncoloured,
        mean_distance_to_surface_m,
        far_fraction,
        surface_uncovered_fraction,
        carve_s: started.elapsed().as_secs_f64(),
        photo_candidates: photo.map_or(0, |p| p.candidates),
        photo_off_silhouette: photo.map_or(0, |p| p.off_silhouette),
        photo_unscored: photo.map_or(0, |p| p.unscored),
        photo_median_spread: photo.map_or(0.0, |p| p.median_spread),
    };
    // Normals are left out, as for the surface samples, so the two differ only in where
    // the points are and what colour they start with.
    let init = Initialisation::SurfaceSamples {
        points: hull.points,
        normals: None,
        colours: Some(colours),
    };
    Ok((init, report))
}

/// Mean over `points` of the distance to the nearest surface sample (brute force over a
/// few thousand samples; diagnostic only).
pub fn mean_nearest_distance(points: &[Vec3], scene: &SceneData) -> f64 {
    let distances = nearest_distances(points, scene);
    if distances.is_empty() {
        return f64::NAN;
    }
    distances.iter().sum::<f64>() / distances.len() as f64
}

/// Distance from each point to the nearest surface sample, metres, in point order (brute
/// force; empty when there are no points or no samples; diagnostic only).
pub fn nearest_distances(points: &[Vec3], scene: &SceneData) -> Vec<f64> {
    use rayon::prelude::*;
    if scene.surface.is_empty() {
        return Vec::new();
    }
    points
        .par_iter()
        .map(|p| {
            scene
                .surface
                .iter()
                .map(|s| (s.position_m - *p).length_squared())
                .fold(f32::INFINITY, f32::min)
                .sqrt() as f64
        })
        .collect()
}

/// The "far from the surface" distance for the diagnostics: two voxels of the hull grid
/// (`2 * 2R / hull_resolution`), the same for every start of a target.
pub fn far_distance_m(scene: &SceneData, preset: &Preset) -> f64 {
    4.0 * scene.bounding_radius_m.max(0.1) as f64 / preset.hull_resolution.max(1) as f64
}

/// Mean nearest-sample distance and the fraction farther than `far_m` (NaN, NaN when empty).
pub fn distance_summary(points: &[Vec3], scene: &SceneData, far_m: f64) -> (f64, f64) {
    let d = nearest_distances(points, scene);
    if d.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let n = d.len() as f64;
    let far = d.iter().filter(|&&x| x > far_m).count() as f64;
    (d.iter().sum::<f64>() / n, far / n)
}

/// Fraction of the scene's surface samples farther than `far_m` from every point of
/// `points` (brute force; NaN when there are no samples, 1 when there are no points;
/// diagnostic only).
pub fn uncovered_fraction(points: &[Vec3], scene: &SceneData, far_m: f64) -> f64 {
    use rayon::prelude::*;
    if scene.surface.is_empty() {
        return f64::NAN;
    }
    let far_squared = (far_m * far_m) as f32;
    let uncovered = scene
        .surface
        .par_iter()
        .filter(|s| {
            points
                .iter()
                .all(|p| (s.position_m - *p).length_squared() > far_squared)
        })
        .count();
    uncovered as f64 / scene.surface.len() as f64
}

/// The initialisation's name in files.
pub fn init_name(kind: InitKind, grey: bool) -> &'static str {
    match (kind, grey) {
        (InitKind::Surface, _) => "surface",
        (InitKind::Random, _) => "random",
        (InitKind::Hull, false) => "hull",
        (InitKind::Hull, true) => "hull-grey",
    }
}

/// A hull start's options beyond the kind (each a `hull` name suffix).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HullVariant {
    /// `-grey`: grey initial colours.
    pub grey: bool,
    /// `-volume`: points fill the hull's voxels.
    pub volume: bool,
    /// `-recarve`: carve with every keyframe and prune Gaussians outside ([`HullPruner`]).
    pub recarve: bool,
    /// `-photo`: points inside the hull where the keyframes agree on the colour.
    pub photo: bool,
    /// `-silhouette`: points inside the hull on the foreground in every keyframe.
    pub silhouette: bool,
}

/// Parses `surface`, `random`, or `hull` followed by any of `-grey`, `-volume`, `-recarve`,
/// `-photo`, `-silhouette` (each at most once, any order; `-photo` overrides `-silhouette`,
/// both override `-volume`).
pub fn parse_init_variant(name: &str) -> Result<(InitKind, HullVariant), ExperimentError> {
    let unknown = || {
        ExperimentError::Invalid(format!(
            "unknown initialisation {name:?} (surface, random, or hull with any of the \
             suffixes -grey, -volume, -recarve, -photo, -silhouette)"
        ))
    };
    match name {
        "surface" => return Ok((InitKind::Surface, HullVariant::default())),
        "random" => return Ok((InitKind::Random, HullVariant::default())),
        _ => {}
    }
    let rest = name.strip_prefix("hull").ok_or_else(unknown)?;
    let mut variant = HullVariant::default();
    if rest.is_empty() {
        return Ok((InitKind::Hull, variant));
    }
    let suffixes = rest.strip_prefix('-').ok_or_else(unknown)?;
    for suffix in suffixes.split('-') {
        let flag = match suffix {
            "grey" => &mut variant.grey,
            "volume" => &mut variant.volume,
            "recarve" => &mut variant.recarve,
            "photo" => &mut variant.photo,
            "silhouette" => &mut variant.silhouette,
            _ => return Err(unknown()),
        };
        if *flag {
            return Err(unknown());
        }
        *flag = true;
    }
    Ok((InitKind::Hull, variant))
}

/// Parses an initialisation name (see [`parse_init_variant`]) into its kind and whether
/// its colours are grey.
pub fn parse_init(name: &str) -> Result<(InitKind, bool), ExperimentError> {
    parse_init_variant(name).map(|(kind, v)| (kind, v.grey))
}

/// Online re-carving for a hull start: a persistent [`CarvedVolume`] over the same grid as
/// the initial hull, carved with each keyframe's mask and pose as the window takes it; after
/// each carve the Gaussians whose centres lie more than one voxel from every occupied voxel
/// are pruned (with their optimiser moments and densification statistics). It never reads
/// a frame the trainer has not been offered, nor an evaluation view.
pub struct HullPruner {
    volume: CarvedVolume,
    /// Keyframes carved with.
    pub keyframes: usize,
    /// Gaussians pruned so far.
    pub pruned: usize,
    /// Prunes refused because they would have left no Gaussian.
    pub refused: usize,
}

impl HullPruner {
    /// Voxels of slack around the occupied ones before a Gaussian counts as outside.
    pub const DILATE_VOXELS: u32 = 1;

    /// `Some` when `preset` starts from a hull and asks for re-carving.
    pub fn for_preset(scene: &SceneData, preset: &Preset) -> Result<Option<Self>, OnlineError> {
        if preset.init != InitKind::Hull || !preset.hull_recarve {
            return Ok(None);
        }
        let radius_m = scene.bounding_radius_m.max(0.1);
        let grid = HullGrid::around_sphere(Vec3::ZERO, radius_m, preset.hull_resolution);
        let volume = CarvedVolume::new(grid)
            .map_err(|e| OnlineError::Config(format!("{}: {e}", scene.name)))?;
        Ok(Some(HullPruner {
            volume,
            keyframes: 0,
            pruned: 0,
            refused: 0,
        }))
    }

    /// Occupied voxels now.
    pub fn occupied_voxels(&self) -> usize {
        self.volume.occupied()
    }

    /// The carved volume so far.
    pub fn volume(&self) -> &CarvedVolume {
        &self.volume
    }

    /// Carves with sequence frame `frame` of `scene` (just taken into the window) and
    /// prunes the trainer's Gaussians outside the hull; returns how many it pruned.
    pub fn keyframe_added(
        &mut self,
        trainer: &mut OnlineTrainer,
        scene: &SceneData,
        frame: usize,
    ) -> Result<usize, OnlineError> {
        let view = scene.frames.get(frame).ok_or_else(|| {
            OnlineError::Config(format!("{}: no frame {frame} to carve", scene.name))
        })?;
        let camera = camera_of(&scene.intrinsics, view);
        self.volume
            .carve(
                &HullView {
                    camera,
                    mask: &view.mask8,
                },
                1,
            )
            .map_err(|e| OnlineError::Config(format!("{}: {e}", scene.name)))?;
        self.keyframes += 1;
        let t = trainer.trainer_mut();
        let params = &t.model.gaussians.params;
        let keep: Vec<bool> = (0..params.len())
            .map(|i| {
                let m = params.row(Param::Mean, i);
                self.volume
                    .contains(Vec3::new(m[0], m[1], m[2]), Self::DILATE_VOXELS)
            })
            .collect();
        let kept = keep.iter().filter(|&&k| k).count();
        let pruned = keep.len() - kept;
        if pruned == 0 {
            return Ok(0);
        }
        if kept == 0 {
            self.refused += 1;
            return Ok(0);
        }
        let model_error = |e: gs_core::model::ModelError| {
            OnlineError::Config(format!("{}: hull pruning: {e:?}", scene.name))
        };
        t.model
            .gaussians
            .params
            .retain(&keep)
            .map_err(model_error)?;
        t.adam.m.retain(&keep).map_err(model_error)?;
        t.adam.v.retain(&keep).map_err(model_error)?;
        let stats = &mut t.densify_stats;
        if stats.len() == keep.len() {
            retain_by(&mut stats.grad_accum, &keep);
            retain_by(&mut stats.visible_count, &keep);
            retain_by(&mut stats.max_radius_px, &keep);
        } else {
            *stats = gs_core::densify::DensifyStats::new(kept);
        }
        self.pruned += pruned;
        Ok(pruned)
    }
}

fn retain_by<T: Copy>(values: &mut Vec<T>, keep: &[bool]) {
    let mut k = keep.iter();
    values.retain(|_| *k.next().unwrap_or(&true));
}

/// One run of the ablation.
#[derive(Clone, Debug, Serialize)]
pub struct InitRun {
    pub init: String,
    pub initial_gaussians: usize,
    /// Process CPU time over the whole run (initialisation, training, evaluation), seconds.
    pub cpu_s: f64,
    /// Wall time over the whole run, seconds.
    pub wall_s: f64,
    pub hull: Option<HullReport>,
    /// The final Gaussians' centres: mean distance to the nearest true surface sample, m.
    pub final_mean_distance_m: f64,
    /// ... and the fraction farther than [`far_distance_m`] (phantom Gaussians).
    pub final_far_fraction: f64,
    pub run: RunOutcome,
}

/// What the job needs.
#[derive(Clone, Debug)]
pub struct InitAblationJob {
    /// Its `configs` are ignored: the ablation trains configuration d.
    pub preset: Preset,
    pub scenarios: Vec<Scenario>,
    /// Initialisations in order, as `parse_init` names them.
    pub inits: Vec<String>,
    pub out_dir: PathBuf,
}

/// What the job produced.
#[derive(Clone, Debug)]
pub struct InitAblationResult {
    pub runs: Vec<InitRun>,
    pub render_s: f64,
    pub total_s: f64,
    pub total_cpu_s: f64,
}

/// CSV header of `init.csv`.
pub const CSV_HEADER: &str = "target,init,psnr,ssim,masked_psnr,masked_ssim,seen_psnr,black_psnr,initial_gaussians,final_gaussians,rounds,steps,train_s,step_ms,run_wall_s,run_cpu_s,hull_frames,hull_points,hull_voxel_m,hull_mean_dist_m,hull_carve_s,hull_far_fraction,final_mean_dist_m,final_far_fraction";

/// One line per run.
pub fn to_csv(runs: &[InitRun]) -> String {
    let mut out = format!("{CSV_HEADER}\n");
    for r in runs {
        let o = &r.run;
        let hull = match &r.hull {
            Some(h) => format!(
                "{},{},{:.4},{:.4},{:.2}",
                h.frames.len(),
                h.points,
                h.voxel_m,
                h.mean_distance_to_surface_m,
                h.carve_s
            ),
            None => ",,,,".into(),
        };
        let hull_far = r
            .hull
            .as_ref()
            .map_or(String::new(), |h| format!("{:.4}", h.far_fraction));
        let _ = writeln!(
            out,
            "{},{},{:.2},{:.4},{:.2},{:.4},{:.2},{:.2},{},{},{},{},{:.1},{:.1},{:.1},{:.1},{},{},{:.4},{:.4}",
            o.target,
            r.init,
            o.eval.psnr_db,
            o.eval.ssim,
            o.eval.masked_psnr_db,
            o.eval.masked_ssim,
            o.seen.psnr_db,
            o.black_eval.psnr_db,
            r.initial_gaussians,
            o.gaussians,
            o.rounds,
            o.steps,
            o.train_s,
            o.step_ms,
            r.wall_s,
            r.cpu_s,
            hull,
            hull_far,
            r.final_mean_distance_m,
            r.final_far_fraction
        );
    }
    out
}

/// The Markdown report: metrics per target and initialisation, the gap to surface samples,
/// the evaluation curve and the hull's facts.
pub fn to_markdown(runs: &[InitRun]) -> String {
    let mut out = String::from(
        "Configuration (d), evaluation views, full frame (masked = target pixels only).\n\n\
         | Target | Init. | PSNR↑ | SSIM↑ | masked PSNR | seen PSNR | Δ PSNR vs surface | \\|G\\| start → end | train s | run CPU s |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for r in runs {
        let o = &r.run;
        let surface = runs
            .iter()
            .find(|s| s.init == "surface" && s.run.target == o.target);
        let delta = match surface {
            Some(s) if s.init != r.init => {
                format!("{:+.2} dB", o.eval.psnr_db - s.run.eval.psnr_db)
            }
            _ => "-".into(),
        };
        let _ = writeln!(
            out,
            "| {} | {} | {:.2} | {:.4} | {:.2} | {:.2} | {} | {} → {} | {:.1} | {:.1} |",
            target_label(&o.target),
            r.init,
            o.eval.psnr_db,
            o.eval.ssim,
            o.eval.masked_psnr_db,
            o.seen.psnr_db,
            delta,
            r.initial_gaussians,
            o.gaussians,
            o.train_s,
            r.cpu_s
        );
    }
    let with_curve: Vec<&InitRun> = runs
        .iter()
        .filter(|r| !r.run.eval_curve.is_empty())
        .collect();
    if let Some(first) = with_curve.first() {
        out.push_str("\nEvaluation PSNR (dB) during training, by round:\n\n| Target | Init. |");
        for p in &first.run.eval_curve {
            let _ = write!(out, " {} |", p.round);
        }
        out.push_str("\n|---|---|");
        out.push_str(&"---:|".repeat(first.run.eval_curve.len()));
        out.push('\n');
        for r in &with_curve {
            let _ = write!(out, "| {} | {} |", target_label(&r.run.target), r.init);
            for p in &r.run.eval_curve {
                let _ = write!(out, " {:.2} |", p.psnr_db);
            }
            out.push('\n');
        }
    }
    out.push_str(
        "\nThe final Gaussians' centres against the true surface (nearest surface sample; far: \
         more than two hull voxels away):\n\n\
         | Target | Init. | mean dist. m | far |\n|---|---|---:|---:|\n",
    );
    for r in runs {
        let _ = writeln!(
            out,
            "| {} | {} | {:.3} | {:.1} % |",
            target_label(&r.run.target),
            r.init,
            r.final_mean_distance_m,
            100.0 * r.final_far_fraction
        );
    }
    let hulls: Vec<&InitRun> = runs.iter().filter(|r| r.hull.is_some()).collect();
    if !hulls.is_empty() {
        out.push_str(
            "\nVisual hulls (carved from the first keyframes' masks and poses):\n\n\
             | Target | Init. | frames | voxel m | occupied voxels | surface voxels | points | uncoloured | mean dist. to true surface m | far | carve s |\n\
             |---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
        );
        for r in hulls {
            let Some(h) = &r.hull else { continue };
            let frames: Vec<String> = h.frames.iter().map(|f| f.to_string()).collect();
            let _ = writeln!(
                out,
                "| {} | {} | {} | {:.3} | {} | {} | {} | {} | {:.3} | {:.1} % | {:.2} |",
                target_label(&r.run.target),
                r.init,
                frames.join(" "),
                h.voxel_m,
                h.occupied_voxels,
                h.surface_voxels,
                h.points,
                h.uncoloured_points,
                h.mean_distance_to_surface_m,
                100.0 * h.far_fraction,
                h.carve_s
            );
        }
    }
    out
}

/// Per-round curves: Gaussian count, mean loss and training seconds.
pub fn curves_csv(runs: &[InitRun]) -> String {
    let mut out = String::from("target,init,round,frame_index,gaussians,mean_loss,train_s\n");
    for r in runs {
        for p in &r.run.curve {
            let _ = writeln!(
                out,
                "{},{},{},{},{},{:.6},{:.3}",
                r.run.target, r.init, p.round, p.frame_index, p.gaussians, p.mean_loss, p.train_s
            );
        }
    }
    out
}

const PALETTE: [Rgb; 4] = [[30, 80, 200], [210, 40, 40], [30, 150, 60], [150, 90, 20]];
const AXIS: Rgb = [60, 60, 60];
const PANEL_W: f64 = 360.0;
const PANEL_H: f64 = 260.0;

/// init.png: top, evaluation PSNR per target as grouped bars (one colour per
/// initialisation, the all-black image's PSNR as a grey tick); below, one panel per target
/// with the Gaussian count over rounds.
pub fn plot(runs: &[InitRun], inits: &[String]) -> Canvas {
    let mut targets: Vec<String> = Vec::new();
    for r in runs {
        if !targets.contains(&r.run.target) {
            targets.push(r.run.target.clone());
        }
    }
    let columns = targets.len().max(1) as f64;
    let width = (40.0 + columns * (PANEL_W + 30.0)) as u32;
    let height = (70.0 + 2.0 * (PANEL_H + 60.0)) as u32;
    let mut canvas = Canvas::new(width, height, [255, 255, 255]);
    // Legend.
    let mut x = 20i64;
    for (i, name) in inits.iter().enumerate() {
        let colour = PALETTE[i % PALETTE.len()];
        canvas.fill_rect(x, 14, 16, 10, colour);
        draw_text(&mut canvas, x + 22, 14, &name.to_uppercase(), 2, AXIS);
        x += 22 + (name.len() as i64 * 8) + 30;
    }
    draw_text(
        &mut canvas,
        x + 10,
        14,
        "GREY TICK: ALL-BLACK IMAGE",
        2,
        [150, 150, 150],
    );
    for (t, target) in targets.iter().enumerate() {
        let left = 50.0 + t as f64 * (PANEL_W + 30.0);
        let top = 60.0;
        let of_target: Vec<&InitRun> = runs.iter().filter(|r| &r.run.target == target).collect();
        bar_panel(&mut canvas, left, top, target, &of_target, inits);
        gaussian_panel(
            &mut canvas,
            left,
            top + PANEL_H + 60.0,
            target,
            &of_target,
            inits,
        );
    }
    canvas
}

fn colour_of(init: &str, inits: &[String]) -> Rgb {
    let i = inits.iter().position(|n| n == init).unwrap_or(0);
    PALETTE[i % PALETTE.len()]
}

fn frame(canvas: &mut Canvas, left: f64, top: f64, title: &str) {
    canvas.line((left, top), (left, top + PANEL_H), 1, AXIS);
    canvas.line(
        (left, top + PANEL_H),
        (left + PANEL_W, top + PANEL_H),
        1,
        AXIS,
    );
    draw_text(canvas, left as i64, top as i64 - 20, title, 2, AXIS);
}

fn bar_panel(
    canvas: &mut Canvas,
    left: f64,
    top: f64,
    target: &str,
    runs: &[&InitRun],
    inits: &[String],
) {
    frame(
        canvas,
        left,
        top,
        &format!("{} PSNR DB", target_label(target).to_uppercase()),
    );
    let values: Vec<f64> = runs
        .iter()
        .map(|r| r.run.eval.psnr_db)
        .chain(runs.first().map(|r| r.run.black_eval.psnr_db))
        .filter(|v| v.is_finite())
        .collect();
    if values.is_empty() {
        return;
    }
    // Bars start 2 dB below the lowest value so differences of tenths stay visible.
    let lo = (values.iter().cloned().fold(f64::INFINITY, f64::min) - 2.0).floor();
    let hi = values.iter().cloned().fold(f64::NEG_INFINITY, f64::max) + 0.5;
    let y_of = |v: f64| top + PANEL_H * (1.0 - (v - lo) / (hi - lo));
    draw_text(
        canvas,
        left as i64 - 44,
        top as i64 + PANEL_H as i64 - 10,
        &format!("{lo:.0}"),
        2,
        AXIS,
    );
    let slot = PANEL_W / runs.len().max(1) as f64;
    for (i, r) in runs.iter().enumerate() {
        let v = r.run.eval.psnr_db;
        if !v.is_finite() {
            continue;
        }
        let x0 = left + i as f64 * slot + 0.15 * slot;
        let y0 = y_of(v);
        canvas.fill_rect(
            x0 as i64,
            y0 as i64,
            (0.7 * slot) as i64,
            (top + PANEL_H - y0) as i64,
            colour_of(&r.init, inits),
        );
        draw_text(
            canvas,
            x0 as i64,
            y0 as i64 - 14,
            &format!("{v:.2}"),
            2,
            AXIS,
        );
    }
    if let Some(black) = runs.first().map(|r| r.run.black_eval.psnr_db) {
        if black.is_finite() {
            let y = y_of(black);
            canvas.line((left, y), (left + PANEL_W, y), 2, [150, 150, 150]);
        }
    }
}

fn gaussian_panel(
    canvas: &mut Canvas,
    left: f64,
    top: f64,
    target: &str,
    runs: &[&InitRun],
    inits: &[String],
) {
    frame(
        canvas,
        left,
        top,
        &format!(
            "{} GAUSSIANS PER ROUND",
            target_label(target).to_uppercase()
        ),
    );
    let max_round = runs
        .iter()
        .flat_map(|r| r.run.curve.iter().map(|p| p.round))
        .max()
        .unwrap_or(1)
        .max(1) as f64;
    let max_g = runs
        .iter()
        .flat_map(|r| r.run.curve.iter().map(|p| p.gaussians))
        .chain(runs.iter().map(|r| r.initial_gaussians))
        .max()
        .unwrap_or(1)
        .max(1) as f64;
    let x_of = |round: f64| left + PANEL_W * round / max_round;
    let y_of = |g: f64| top + PANEL_H * (1.0 - g / max_g);
    draw_text(
        canvas,
        left as i64 - 44,
        top as i64,
        &format!("{}", max_g as u64),
        2,
        AXIS,
    );
    draw_text(
        canvas,
        left as i64 - 14,
        (top + PANEL_H) as i64 - 10,
        "0",
        2,
        AXIS,
    );
    draw_text(
        canvas,
        (left + PANEL_W) as i64 - 30,
        (top + PANEL_H) as i64 + 8,
        &format!("{}", max_round as u64),
        2,
        AXIS,
    );
    draw_text(
        canvas,
        left as i64,
        (top + PANEL_H) as i64 + 8,
        "ROUND",
        2,
        AXIS,
    );
    for r in runs {
        let colour = colour_of(&r.init, inits);
        let mut previous = (0.0, r.initial_gaussians as f64);
        for p in &r.run.curve {
            let next = (p.round as f64, p.gaussians as f64);
            canvas.line(
                (x_of(previous.0), y_of(previous.1)),
                (x_of(next.0), y_of(next.1)),
                2,
                colour,
            );
            previous = next;
        }
    }
}

/// Points of one cloud with their sRGB colours in [0, 1].
pub struct Cloud<'a> {
    pub label: String,
    pub points: &'a [Vec3],
    pub colours: &'a [[f32; 3]],
}

const CLOUD_PANEL_PX: f64 = 220.0;
const CLOUD_BACKGROUND: Rgb = [35, 35, 45];

/// hull.png: one row per target, the clouds side by side, each seen along the body z axis
/// (x right, y up) and along the body y axis (x right, z up), at one scale per row so the
/// clouds compare directly. Points are 2x2 pixel squares in their colours.
pub fn cloud_figure(rows: &[(String, Vec<Cloud>)]) -> Canvas {
    let columns = rows.iter().map(|(_, c)| 2 * c.len()).max().unwrap_or(1) as f64;
    let width = (20.0 + columns * (CLOUD_PANEL_PX + 10.0)) as u32;
    let row_h = CLOUD_PANEL_PX + 40.0;
    let height = (20.0 + rows.len() as f64 * row_h) as u32;
    let mut canvas = Canvas::new(width, height, [255, 255, 255]);
    for (r, (target, clouds)) in rows.iter().enumerate() {
        let top = 30.0 + r as f64 * row_h;
        let half_extent = clouds
            .iter()
            .flat_map(|c| c.points.iter())
            .map(|p| p.abs().max_element() as f64)
            .filter(|v| v.is_finite())
            .fold(1e-3f64, f64::max);
        let scale = 0.5 * (CLOUD_PANEL_PX - 10.0) / half_extent;
        for (c, cloud) in clouds.iter().enumerate() {
            for (view, (axis_u, axis_v, name)) in [(0usize, 1usize, "XY"), (0, 2, "XZ")]
                .into_iter()
                .enumerate()
            {
                let left = 10.0 + (2 * c + view) as f64 * (CLOUD_PANEL_PX + 10.0);
                let label = format!(
                    "{} {} {}",
                    target_label(target).to_uppercase(),
                    cloud.label,
                    name
                );
                draw_text(&mut canvas, left as i64, top as i64 - 18, &label, 2, AXIS);
                canvas.fill_rect(
                    left as i64,
                    top as i64,
                    CLOUD_PANEL_PX as i64,
                    CLOUD_PANEL_PX as i64,
                    CLOUD_BACKGROUND,
                );
                let centre = (left + 0.5 * CLOUD_PANEL_PX, top + 0.5 * CLOUD_PANEL_PX);
                for (p, colour) in cloud.points.iter().zip(cloud.colours) {
                    let x = centre.0 + scale * p[axis_u] as f64;
                    let y = centre.1 - scale * p[axis_v] as f64;
                    if !(x.is_finite() && y.is_finite()) {
                        continue;
                    }
                    let rgb = colour.map(|v| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8);
                    canvas.fill_rect(x as i64, y as i64, 2, 2, rgb);
                }
            }
        }
    }
    canvas
}

/// The surface samples (material colours) and the hull (its initial colours) of a scene.
struct FigureRow {
    name: String,
    surface: Vec<Vec3>,
    surface_colours: Vec<[f32; 3]>,
    hull: Vec<Vec3>,
    hull_colours: Vec<[f32; 3]>,
}

fn hull_figure_row(scene: &SceneData, preset: &Preset) -> Result<FigureRow, ExperimentError> {
    let n = (preset.init_points as usize).min(scene.surface.len());
    let surface = scene.surface[..n].iter().map(|s| s.position_m).collect();
    let surface_colours = scene.surface[..n]
        .iter()
        .map(|s| {
            s.albedo_rgb
                .map(|c| crate::raytrace::linear_to_srgb8(c) as f32 / 255.0)
        })
        .collect();
    let (init, _) = hull_initialisation(scene, preset)?;
    let Initialisation::SurfaceSamples {
        points, colours, ..
    } = init
    else {
        return Err(ExperimentError::Invalid(
            "a hull initialises from points".into(),
        ));
    };
    let hull_colours = colours.unwrap_or_else(|| vec![GREY; points.len()]);
    Ok(FigureRow {
        name: scene.name.clone(),
        surface,
        surface_colours,
        hull: points,
        hull_colours,
    })
}

/// Writes `OUT/hull.png` (true surface samples beside the hull of each scenario) without
/// training; returns the hull reports. The hull is drawn as the first hull start in
/// `job.inits` makes it (surface or volume points; plain `hull` when there is none).
pub fn write_hull_figure(
    job: &InitAblationJob,
    progress: &mut dyn FnMut(&str),
) -> Result<Vec<(String, HullReport)>, ExperimentError> {
    let out = &job.out_dir;
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::io(out, e))?;
    let mut variant = HullVariant::default();
    for name in &job.inits {
        if let (InitKind::Hull, v) = parse_init_variant(name)? {
            variant = v;
            break;
        }
    }
    let preset = Preset {
        init: InitKind::Hull,
        hull_grey_colours: job.preset.hull_grey_colours || variant.grey,
        hull_volume: job.preset.hull_volume || variant.volume,
        hull_photo: job.preset.hull_photo || variant.photo,
        hull_silhouette: job.preset.hull_silhouette || variant.silhouette,
        ..job.preset.clone()
    };
    let mut data = Vec::new();
    let mut reports = Vec::new();
    for scenario in &job.scenarios {
        let scenario = preset.apply(scenario)?;
        let scene = load_or_render_scene(
            &scenario,
            preset.init_points as usize,
            &out.join("cache"),
            progress,
        )?;
        let (_, report) = hull_initialisation(&scene, &preset)?;
        progress(&format!(
            "{}: hull from frames {:?}, {} points ({} occupied, {} surface voxels of {:.3} m), mean {:.3} m from the true surface, {:.1} % farther than {:.2} m; {:.1} % of the surface samples that far from every point",
            scene.name,
            report.frames,
            report.points,
            report.occupied_voxels,
            report.surface_voxels,
            report.voxel_m,
            report.mean_distance_to_surface_m,
            100.0 * report.far_fraction,
            far_distance_m(&scene, &preset),
            100.0 * report.surface_uncovered_fraction
        ));
        if report.photo_candidates > 0 {
            progress(&format!(
                "{}: photo-consistency: {} candidates, {} off the silhouette, {} seen by fewer than two views, median colour spread {:.4}",
                scene.name,
                report.photo_candidates,
                report.photo_off_silhouette,
                report.photo_unscored,
                report.photo_median_spread
            ));
        }
        reports.push((scene.name.clone(), report));
        data.push(hull_figure_row(&scene, &preset)?);
    }
    let rows: Vec<(String, Vec<Cloud>)> = data
        .iter()
        .map(|row| {
            (
                row.name.clone(),
                vec![
                    Cloud {
                        label: "MODEL".into(),
                        points: &row.surface,
                        colours: &row.surface_colours,
                    },
                    Cloud {
                        label: "HULL".into(),
                        points: &row.hull,
                        colours: &row.hull_colours,
                    },
                ],
            )
        })
        .collect();
    let canvas = cloud_figure(&rows);
    files::write_png_rgb(
        &out.join("hull.png"),
        canvas.width,
        canvas.height,
        &canvas.rgb8,
    )?;
    Ok(reports)
}

/// Runs the job, reporting progress lines.
pub fn run_init_ablation(
    job: &InitAblationJob,
    progress: &mut dyn FnMut(&str),
) -> Result<InitAblationResult, ExperimentError> {
    let started = Instant::now();
    let cpu_started = gs_core::machine::process_cpu_s();
    let out = &job.out_dir;
    std::fs::create_dir_all(out).map_err(|e| ExperimentError::io(out, e))?;
    let inits: Vec<(InitKind, HullVariant)> = job
        .inits
        .iter()
        .map(|n| parse_init_variant(n))
        .collect::<Result<_, _>>()?;
    if inits.is_empty() {
        return Err(ExperimentError::Invalid(
            "no initialisation to compare".into(),
        ));
    }
    let names: Vec<String> = job.inits.clone();
    let mut runs = Vec::new();
    let mut render_s = 0.0;
    for scenario in &job.scenarios {
        let scenario = job.preset.apply(scenario)?;
        let scene = load_or_render_scene(
            &scenario,
            job.preset.init_points as usize,
            &out.join("cache"),
            progress,
        )?;
        render_s += scene.render_s;
        for (&(kind, variant), name) in inits.iter().zip(&names) {
            let run_started = Instant::now();
            let cpu_before = gs_core::machine::process_cpu_s();
            let preset = Preset {
                init: kind,
                hull_grey_colours: variant.grey,
                hull_volume: variant.volume,
                hull_recarve: variant.recarve,
                hull_photo: variant.photo,
                hull_silhouette: variant.silhouette,
                configs: vec!["d".into()],
                ..job.preset.clone()
            };
            let hull = if kind == InitKind::Hull {
                let (_, report) = hull_initialisation(&scene, &preset)?;
                progress(&format!(
                    "{}/{name}: hull from frames {:?}: {} occupied voxels of {:.3} m, {} points, mean {:.3} m from the true surface, {:.2} s",
                    scene.name,
                    report.frames,
                    report.occupied_voxels,
                    report.voxel_m,
                    report.points,
                    report.mean_distance_to_surface_m,
                    report.carve_s
                ));
                Some(report)
            } else {
                None
            };
            let (run, trainer) = run_config(&scene, &preset, Variant::D, 0, progress)?;
            let params = &trainer.trainer().model.gaussians.params;
            let centres: Vec<Vec3> = (0..params.len())
                .map(|i| Vec3::from_slice(params.row(Param::Mean, i)))
                .collect();
            let far_m = far_distance_m(&scene, &preset);
            let (final_mean_distance_m, final_far_fraction) =
                distance_summary(&centres, &scene, far_m);
            progress(&format!(
                "{}/{name}: final Gaussians {:.3} m from the true surface on average, {:.1} % farther than {:.2} m",
                scene.name,
                final_mean_distance_m,
                100.0 * final_far_fraction,
                far_m
            ));
            let initial_gaussians = match (&hull, kind) {
                (Some(h), _) => h.points,
                (None, InitKind::Surface) => scene.surface.len().min(preset.init_points as usize),
                (None, _) => preset.init_points as usize,
            };
            let cpu_s = match (cpu_before, gs_core::machine::process_cpu_s()) {
                (Some(a), Some(b)) => b - a,
                _ => f64::NAN,
            };
            runs.push(InitRun {
                init: name.clone(),
                initial_gaussians,
                cpu_s,
                wall_s: run_started.elapsed().as_secs_f64(),
                hull,
                final_mean_distance_m,
                final_far_fraction,
                run,
            });
            write_text(&out.join("init.csv"), &to_csv(&runs))?;
            write_text(&out.join("init.md"), &to_markdown(&runs))?;
            write_text(&out.join("init_curves.csv"), &curves_csv(&runs))?;
            write_text(
                &out.join("runs.json"),
                &serde_json::to_string_pretty(&runs).map_err(|e| ExperimentError::io(out, e))?,
            )?;
            progress(&format!(
                "{} of {} runs done, {:.0} s elapsed",
                runs.len(),
                inits.len() * job.scenarios.len(),
                started.elapsed().as_secs_f64()
            ));
        }
    }
    let canvas = plot(&runs, &names);
    files::write_png_rgb(
        &out.join("init.png"),
        canvas.width,
        canvas.height,
        &canvas.rgb8,
    )?;
    let total_cpu_s = match (cpu_started, gs_core::machine::process_cpu_s()) {
        (Some(a), Some(b)) => b - a,
        _ => f64::NAN,
    };
    Ok(InitAblationResult {
        runs,
        render_s,
        total_s: started.elapsed().as_secs_f64(),
        total_cpu_s,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::experiment::data::render_scene;
    use crate::experiment::runner::{online_config, scene_box};
    use gs_core::rng::SplitMix64;
    use std::path::Path;

    #[test]
    fn hull_names_parse_with_their_suffixes_once_each() {
        assert_eq!(
            parse_init_variant("surface").unwrap(),
            (InitKind::Surface, HullVariant::default())
        );
        let (kind, v) = parse_init_variant("hull-recarve-volume").unwrap();
        assert_eq!(kind, InitKind::Hull);
        assert!(v.recarve && v.volume && !v.grey);
        assert_eq!(parse_init("hull-grey").unwrap(), (InitKind::Hull, true));
        let (kind, v) = parse_init_variant("hull-photo").unwrap();
        assert_eq!(kind, InitKind::Hull);
        assert!(v.photo && !v.volume && !v.recarve && !v.grey && !v.silhouette);
        let (_, v) = parse_init_variant("hull-silhouette").unwrap();
        assert!(v.silhouette && !v.photo && !v.volume);
        for bad in [
            "hull-",
            "hull-grey-grey",
            "hull-photo-photo",
            "hull-silhouette-silhouette",
            "hullgrey",
            "hull-shell",
            "random-grey",
            "",
        ] {
            let e = parse_init_variant(bad).unwrap_err().to_string();
            assert!(e.contains(&format!("{bad:?}")), "{bad}: {e}");
        }
    }

    #[test]
    fn the_photo_preset_keys_parse_and_bad_values_are_errors() {
        let p = Preset::from_toml_str(
            "init = \"hull\"\nhull_photo = true\nhull_silhouette = true\nhull_photo_spread_width = 0.25\nhull_photo_samples = 8\n",
            "t.toml",
        )
        .unwrap();
        assert!(p.hull_photo && p.hull_silhouette);
        assert_eq!(p.hull_photo_spread_width, 0.25);
        assert_eq!(p.hull_photo_samples, 8);
        assert!(!Preset::default().hull_photo);
        for bad in [
            "hull_photo_spread_width = 0.0",
            "hull_photo_spread_width = -1.0",
            "hull_photo_spread_width = nan",
            "hull_photo_samples = 0",
            "hull_photo_samples = 65",
        ] {
            let e = Preset::from_toml_str(bad, "t.toml")
                .unwrap_err()
                .to_string();
            let key = bad.split(' ').next().unwrap();
            assert!(e.contains(key), "{bad}: {e}");
        }
    }

    /// On a small rendered target from its first keyframes, the photo-consistent and the
    /// silhouette starts lie closer to the true surface than the volume start (the
    /// carving's margin shell is dropped), report their candidates, and are reproducible.
    #[test]
    fn the_photo_and_silhouette_starts_lie_closer_to_the_surface_than_the_volume_start() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
        let preset = Preset {
            name: "tiny".into(),
            downsample: 10,
            cadence_s: 30.0,
            frames: Some(8),
            eval_views: 1,
            figure_views: 1,
            samples_per_pixel: 1,
            window: 4,
            init_points: 400,
            hull_resolution: 48,
            init: InitKind::Hull,
            hull_volume: true,
            ..Preset::default()
        };
        let scenario = preset.apply(&Scenario::load(&path).unwrap()).unwrap();
        let scene = render_scene(&scenario, 2000, &mut |_| {}).unwrap();
        let (_, volume) = hull_initialisation(&scene, &preset).unwrap();
        let photo_preset = Preset {
            hull_photo: true,
            ..preset.clone()
        };
        let (init, photo) = hull_initialisation(&scene, &photo_preset).unwrap();
        assert_eq!(photo.frames, volume.frames);
        assert_eq!(photo.occupied_voxels, volume.occupied_voxels);
        assert_eq!(photo.points, 400);
        assert_eq!(
            photo.photo_candidates,
            preset.hull_photo_samples as usize * volume.occupied_voxels
        );
        assert!(photo.photo_off_silhouette > 0);
        assert_eq!(volume.photo_candidates, 0);
        assert!(
            photo.mean_distance_to_surface_m < 0.8 * volume.mean_distance_to_surface_m,
            "photo {} m, volume {} m",
            photo.mean_distance_to_surface_m,
            volume.mean_distance_to_surface_m
        );
        assert!(photo.far_fraction < volume.far_fraction);
        let (again, _) = hull_initialisation(&scene, &photo_preset).unwrap();
        assert_eq!(init, again);
        let silhouette_preset = Preset {
            hull_silhouette: true,
            ..preset.clone()
        };
        let (_, silhouette) = hull_initialisation(&scene, &silhouette_preset).unwrap();
        assert_eq!(silhouette.points, 400);
        assert_eq!(
            silhouette.photo_off_silhouette, photo.photo_off_silhouette,
            "the same candidates, the same test"
        );
        assert_eq!(silhouette.photo_median_spread, 0.0);
        assert!(
            silhouette.mean_distance_to_surface_m < 0.8 * volume.mean_distance_to_surface_m,
            "silhouette {} m, volume {} m",
            silhouette.mean_distance_to_surface_m,
            volume.mean_distance_to_surface_m
        );
    }

    /// Gaussians on the true surface and Gaussians spread through the bounding ball: carving
    /// with the frames as they arrive removes exactly the ones outside the (dilated) hull,
    /// never one on the surface, and keeps every kept row's moments and statistics.
    #[test]
    fn the_pruner_removes_exactly_the_gaussians_outside_the_hull() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../config/scenarios/quick.toml");
        let preset = Preset {
            name: "tiny".into(),
            downsample: 20,
            cadence_s: 10.0,
            frames: Some(6),
            eval_views: 1,
            figure_views: 1,
            samples_per_pixel: 1,
            window: 3,
            init_points: 300,
            max_gaussians: 1000,
            light_resolution_px: 32,
            hull_resolution: 40,
            init: InitKind::Hull,
            hull_recarve: true,
            ..Preset::default()
        };
        let scenario = preset.apply(&Scenario::load(&path).unwrap()).unwrap();
        let scene = render_scene(&scenario, 300, &mut |_| {}).unwrap();
        let surface: Vec<Vec3> = scene.surface.iter().map(|s| s.position_m).collect();
        let radius = scene.bounding_radius_m;
        let mut rng = SplitMix64::new(3);
        let mut ball = Vec::new();
        while ball.len() < 300 {
            let p = Vec3::new(
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
                rng.uniform(-1.0, 1.0),
            );
            if p.length() <= 1.0 {
                ball.push(p * radius);
            }
        }
        let points: Vec<Vec3> = surface.iter().chain(&ball).copied().collect();
        let init = Initialisation::SurfaceSamples {
            points: points.clone(),
            normals: None,
            colours: None,
        };
        let mut trainer = OnlineTrainer::new(
            online_config(&preset, Variant::D),
            &init,
            scene_box(&scene).unwrap(),
        )
        .unwrap();
        // Tag each row's moments and statistics with its index, to follow them.
        {
            let t = trainer.trainer_mut();
            for i in 0..points.len() {
                t.adam.m.row_mut(Param::Mean, i)[0] = i as f32;
                t.adam.v.row_mut(Param::Mean, i)[0] = i as f32;
            }
            t.densify_stats.visible_count = (0..points.len() as u32).collect();
        }
        let mut pruner = HullPruner::for_preset(&scene, &preset).unwrap().unwrap();
        let mut total = 0;
        for frame in 0..scene.frames.len() {
            total += pruner.keyframe_added(&mut trainer, &scene, frame).unwrap();
        }
        assert_eq!(pruner.keyframes, scene.frames.len());
        assert_eq!(pruner.pruned, total);
        let volume = pruner.volume();
        let expected: Vec<usize> = (0..points.len())
            .filter(|&i| volume.contains(points[i], HullPruner::DILATE_VOXELS))
            .collect();
        // Every surface sample survives (carving is conservative); many ball points go.
        assert!(expected[..surface.len()]
            .iter()
            .enumerate()
            .all(|(k, &i)| k == i));
        assert!(total > 100, "only {total} of 300 ball points pruned");
        assert_eq!(points.len() - expected.len(), total);
        let t = trainer.trainer();
        let params = &t.model.gaussians.params;
        assert_eq!(params.len(), expected.len());
        assert_eq!(t.adam.m.len(), expected.len());
        assert_eq!(t.densify_stats.len(), expected.len());
        for (row, &i) in expected.iter().enumerate() {
            assert_eq!(Vec3::from_slice(params.row(Param::Mean, row)), points[i]);
            assert_eq!(t.adam.m.row(Param::Mean, row)[0], i as f32);
            assert_eq!(t.adam.v.row(Param::Mean, row)[0], i as f32);
            assert_eq!(t.densify_stats.visible_count[row], i as u32);
        }
        // A preset without re-carving gives no pruner.
        let plain = Preset {
            hull_recarve: false,
            ..preset
        };
        assert!(HullPruner::for_preset(&scene, &plain).unwrap().is_none());
    }
}
