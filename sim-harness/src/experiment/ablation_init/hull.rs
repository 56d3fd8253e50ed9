//! The hull start of the ablation: the first keyframes the online window would take, the
//! visual hull carved from them ([`hull_initialisation`]), the online re-carving
//! ([`HullPruner`]) and the distance diagnostics against the true surface samples.
//!
//! Invariant: the hull uses only the images, masks and poses of frames the trainer has
//! been offered by then, never an evaluation view.

use crate::experiment::data::SceneData;
use crate::experiment::evaluate::camera_of;
use crate::experiment::preset::{InitKind, Preset};
use glam::Vec3;
use gs_core::hull::{
    carve, carve_photo_consistent, carve_silhouette_consistent, sample_colours, CarvedVolume,
    ColourView, HullGrid, HullOptions, HullSampling, HullView, PhotoOptions,
    SILHOUETTE_SAMPLES_PER_VOXEL,
};
use gs_core::model::Param;
use gs_online::keyframe::{Keyframe, KeyframeWindow, ViewDirection, WindowConfig};
use gs_online::online::OnlineTrainer;
use gs_online::online::{Initialisation, OnlineError};
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Grey for hull points no keyframe colours (and for `hull_grey_colours`).
pub const GREY: [f32; 3] = [0.5; 3];

/// What carving produced, for the report.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
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
    pub(crate) const DILATE_VOXELS: u32 = 1;

    /// `Some` when `preset` starts from a hull and asks for re-carving.
    pub(crate) fn for_preset(
        scene: &SceneData,
        preset: &Preset,
    ) -> Result<Option<Self>, OnlineError> {
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
    pub(crate) fn occupied_voxels(&self) -> usize {
        self.volume.occupied()
    }

    /// The carved volume so far.
    pub fn volume(&self) -> &CarvedVolume {
        &self.volume
    }

    /// Carves with sequence frame `frame` of `scene` (just taken into the window) and
    /// prunes the trainer's Gaussians outside the hull; returns how many it pruned.
    pub(crate) fn keyframe_added(
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
