//! The component's starting model: the `[model]` settings, and the visual-hull start.
//!
//! With `init = "hull"` the Sun-aware learner starts from random points (so it can render
//! from the first frame) and, when its keyframe window first fills, before the first
//! round, carves a visual hull from those keyframes' masks and poses
//! (`gs_core::hull::carve_silhouette_consistent`: points inside the hull that project onto
//! the foreground in every keyframe, the start that met the 0.5 dB goal in
//! docs/initialisation.md), colours the points from the keyframes, and restarts the model
//! from them with a scene box fitted to the hull. The carving box is the cube of half-side
//! `target_radius_m` around the target's body origin (a size prior, not a model); a voxel
//! survives only when at least `MIN_HULL_VIEWS` keyframes see it, all on the target.
//! With fewer than `MIN_HULL_VIEWS` masked keyframes, or when carving fails, the random
//! start stays, and the component says which with an event.
//!
//! Invariants: the result depends only on the keyframes and the settings (carving and
//! colouring are independent of the thread count); a scene box is finite with positive
//! extent on every axis.

use crate::config::ConfigError;
use glam::Vec3;
use gs_core::hull::{
    carve_silhouette_consistent, sample_colours, ColourView, HullError, HullGrid, HullOptions,
    HullPoints, HullSampling, HullView, SILHOUETTE_SAMPLES_PER_VOXEL,
};
use gs_core::nn::SceneBox;
use gs_online::online::Frame;
use serde::{Deserialize, Serialize};

/// Masked keyframes needed to carve (one view only bounds a cone).
pub(crate) const MIN_HULL_VIEWS: usize = 2;
/// Colour of hull points no keyframe sees on the target.
pub const GREY: [f32; 3] = [0.5; 3];
/// Largest `model.hull_resolution` (the hull module's voxel limit is 320^3).
pub(crate) const MAX_HULL_RESOLUTION: u32 = 320;

/// `[model]`: how the model starts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelSettings {
    /// "hull" (carve a visual hull from the first keyframes; random points until then, and
    /// as the fallback) or "random" (random points in the target ball, never replaced).
    pub init: String,
    /// Gaussians of the start (random points, or points drawn from the hull).
    pub initial_gaussians: usize,
    /// The target lies within this distance of its body origin, metres: the random start's
    /// ball, the hull's carving cube, and the random start's scene box.
    pub target_radius_m: f32,
    /// Voxels along the carving cube's side.
    pub hull_resolution: u32,
    /// Seeds the random start and the hull's point draw.
    pub seed: u64,
}

impl Default for ModelSettings {
    fn default() -> Self {
        Self {
            init: "hull".to_string(),
            initial_gaussians: 2000,
            target_radius_m: 5.0,
            hull_resolution: 96,
            seed: 0,
        }
    }
}

/// How the model starts.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InitKind {
    Hull,
    Random,
}

impl ModelSettings {
    /// Checks every key; the error names it.
    pub fn validate(&self) -> Result<InitKind, ConfigError> {
        let invalid = |key: &'static str, problem: String| ConfigError::Invalid { key, problem };
        let kind = match self.init.as_str() {
            "hull" => InitKind::Hull,
            "random" => InitKind::Random,
            other => {
                return Err(invalid(
                    "model.init",
                    format!("{other:?} is not \"hull\" or \"random\""),
                ))
            }
        };
        if self.initial_gaussians == 0 {
            return Err(invalid(
                "model.initial_gaussians",
                "must be at least 1".into(),
            ));
        }
        if !(self.target_radius_m.is_finite() && self.target_radius_m > 0.0) {
            return Err(invalid(
                "model.target_radius_m",
                format!("{} is not a finite positive radius", self.target_radius_m),
            ));
        }
        if !(8..=MAX_HULL_RESOLUTION).contains(&self.hull_resolution) {
            return Err(invalid(
                "model.hull_resolution",
                format!(
                    "{} is outside 8..={MAX_HULL_RESOLUTION}",
                    self.hull_resolution
                ),
            ));
        }
        Ok(kind)
    }

    /// The random start's scene box: the cube around the target ball.
    pub fn ball_scene_box(&self) -> Result<SceneBox, String> {
        let r = self.target_radius_m;
        SceneBox::new([-r; 3], [r; 3]).map_err(|e| e.to_string())
    }
}

/// A carved start: points with colours and the scene box fitted to the hull.
#[derive(Clone, Debug)]
pub struct HullStart {
    pub points: Vec<Vec3>,
    pub colours: Vec<[f32; 3]>,
    pub scene_box: SceneBox,
    pub views: usize,
}

/// Why there is no hull start.
#[derive(Clone, Debug, PartialEq)]
pub enum HullStartError {
    /// Fewer than `MIN_HULL_VIEWS` keyframes carry a mask.
    TooFewMasks {
        masked: usize,
    },
    Carve(HullError),
    SceneBox(String),
}

impl std::fmt::Display for HullStartError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::TooFewMasks { masked } => write!(
                f,
                "{masked} keyframes carry a mask, a hull needs at least {MIN_HULL_VIEWS}"
            ),
            Self::Carve(e) => write!(f, "{e}"),
            Self::SceneBox(e) => write!(f, "scene box of the hull: {e}"),
        }
    }
}

/// Foreground bytes for carving from the frame's mask weights (>= 0.5 is foreground).
fn mask_u8(mask: &[f32]) -> Vec<u8> {
    mask.iter()
        .map(|&v| if v >= 0.5 { 255 } else { 0 })
        .collect()
}

/// Carves the start from `keyframes` (those with masks), in the order given.
pub fn carve(keyframes: &[&Frame], settings: &ModelSettings) -> Result<HullStart, HullStartError> {
    let masked: Vec<(&Frame, Vec<u8>)> = keyframes
        .iter()
        .filter_map(|f| f.mask.as_deref().map(|m| (*f, mask_u8(m))))
        .collect();
    if masked.len() < MIN_HULL_VIEWS {
        return Err(HullStartError::TooFewMasks {
            masked: masked.len(),
        });
    }
    let views: Vec<HullView> = masked
        .iter()
        .map(|(f, m)| HullView {
            camera: f.camera,
            mask: m,
        })
        .collect();
    let grid = HullGrid::around_sphere(
        Vec3::ZERO,
        settings.target_radius_m,
        settings.hull_resolution,
    );
    let options = HullOptions {
        point_count: settings.initial_gaussians,
        margin_px: 1,
        // A voxel only one keyframe sees (the others look past it) would survive on that
        // one vote, out to the prior's edge along its line of sight.
        min_views: MIN_HULL_VIEWS as u32,
        seed: settings.seed ^ 0x4855_4C4C,
        sampling: HullSampling::Silhouette,
    };
    let (hull, _) =
        carve_silhouette_consistent(&views, grid, options, SILHOUETTE_SAMPLES_PER_VOXEL)
            .map_err(HullStartError::Carve)?;
    let colour_views: Vec<ColourView> = masked
        .iter()
        .map(|(f, m)| ColourView {
            camera: f.camera,
            rgb: &f.image,
            mask: m,
        })
        .collect();
    let (colours, _) = sample_colours(&hull.points, &hull.normals, &colour_views, GREY);
    let scene_box = hull_scene_box(&hull, grid).map_err(HullStartError::SceneBox)?;
    Ok(HullStart {
        points: hull.points,
        colours,
        scene_box,
        views: views.len(),
    })
}

/// The bounds of the occupied voxels, grown by 5 % of the extent (at least one voxel) on
/// each side: the hull contains the target, so this box does too, tighter than the prior.
fn hull_scene_box(hull: &HullPoints, grid: HullGrid) -> Result<SceneBox, String> {
    let [nx, ny, _] = hull.dims;
    let (mut lo, mut hi) = ([usize::MAX; 3], [0usize; 3]);
    for (i, _) in hull.occupancy.iter().enumerate().filter(|(_, &o)| o != 0) {
        let index = [i % nx, (i / nx) % ny, i / (nx * ny)];
        for axis in 0..3 {
            lo[axis] = lo[axis].min(index[axis]);
            hi[axis] = hi[axis].max(index[axis] + 1);
        }
    }
    if lo[0] == usize::MAX {
        return Err("no occupied voxel".into());
    }
    let mut min_m = [0.0f32; 3];
    let mut max_m = [0.0f32; 3];
    for axis in 0..3 {
        let a = grid.min_m[axis] + lo[axis] as f32 * hull.voxel_m;
        let b = grid.min_m[axis] + hi[axis] as f32 * hull.voxel_m;
        let pad = (0.05 * (b - a)).max(hull.voxel_m);
        min_m[axis] = a - pad;
        max_m[axis] = b + pad;
    }
    SceneBox::new(min_m, max_m).map_err(|e| e.to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_validate_and_name_the_key() {
        assert_eq!(ModelSettings::default().validate().unwrap(), InitKind::Hull);
        let key = |s: ModelSettings| match s.validate() {
            Err(ConfigError::Invalid { key, .. }) => key,
            other => panic!("{other:?}"),
        };
        let base = ModelSettings::default;
        assert_eq!(
            key(ModelSettings {
                init: "surface".into(),
                ..base()
            }),
            "model.init"
        );
        assert_eq!(
            key(ModelSettings {
                initial_gaussians: 0,
                ..base()
            }),
            "model.initial_gaussians"
        );
        assert_eq!(
            key(ModelSettings {
                target_radius_m: f32::NAN,
                ..base()
            }),
            "model.target_radius_m"
        );
        assert_eq!(
            key(ModelSettings {
                hull_resolution: 4,
                ..base()
            }),
            "model.hull_resolution"
        );
    }
}
