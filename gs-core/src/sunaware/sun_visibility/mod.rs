//! The Sun visibility pass: per-Gaussian Sun visibility `V_i` seen from a light camera.
//!
//! The light camera sits on the Sun vector at the image camera's distance from the target
//! centre (at least 1.5 scene radii, so it is outside the box) and looks at the centre:
//! - [`LightProjection::Perspective`](crate::sunaware::LightProjection::Perspective): a pinhole whose field of view just covers the scene
//!   box's bounding sphere (times a margin), as in the paper;
//! - [`LightProjection::Orthographic`](crate::sunaware::LightProjection::Orthographic): parallel projection along the Sun vector with the
//!   same image extent, the exact model of a directional source. The 2D covariance is the
//!   camera-frame covariance's x/y block times the pixel scale squared (plus the
//!   rasterizer's 0.3 px^2 dilation).
//!
//! Splats are depth-sorted and binned into 16x16 tiles (the rasterizer's own
//! [`crate::raster::project_splats`], [`crate::raster::depth_order`] and
//! [`crate::raster::bin::bin_tiles`]). For each pixel, the tile list is walked front to back;
//! each Gaussian `i` whose projected centre lies within `footprint_radius_px` of the pixel
//! centre reads the transmittance of everything nearer than
//! `depth_i - bias - RECEIVER_EXTENT_SIGMAS * sigma_i` and accumulates it weighted by its own
//! footprint `exp(power_i)` there. `V_i = sum(w T) / sum(w)`, or 1 when no pixel saw it
//! (culled or outside the light image: nothing is known to block the Sun). Alphas and
//! cutoffs are the rasterizer's (`min(0.99, o exp(power))`, skip below 1/255, `T < 1e-4`
//! counts as 0).
//!
//! `sigma_i` is Gaussian `i`'s standard deviation along the light camera's axis
//! (`sqrt(a^T Sigma_i a)`). Without it, neighbours on the same surface shadow each other
//! wherever the Sun is not face-on ("shadow acne"): on a tilted surface each neighbour's
//! centre is nearer the light by up to the spacing times the tilt's tangent, far more than a
//! fixed bias, and the splats overlap. Measured with the ray tracer's ground truth on the
//! three targets' surfaces made opaque (docs/shadows.md), a lit Gaussian had a mean `V` of
//! only 0.31-0.57 with the fixed bias alone. What lies within `i`'s own extent along the
//! light ray is beside it, not in front of it; flat Gaussians tilted towards the light get a
//! large `sigma_i`, face-on ones a small one, so this is the splatting form of a
//! slope-scaled depth bias.
//!
//! Invariants: `V_i` in [0, 1]; no gradient (it is data for Psi); deterministic for any
//! thread count (tiles are independent, the per-Gaussian sums run in tile order).
//!
//! Files: [`light_camera`](mod@light_camera) (where the light camera sits, the Gaussians' splats in its image
//! and their extents along its axis), `tile_walk` (the per-tile walk that accumulates the
//! weights and transmittances), `exp_lanes` (`f32::exp` sixteen lanes at a time, same
//! bits), this file (the pass from splats to `V_i`).

use glam::Vec3;
use rayon::prelude::*;

use crate::model::GaussianModel;
use crate::nn::SceneBox;
use crate::raster::bin::{bin_tiles, PixelRect, TileGrid};
use crate::raster::blend::Splat;
use crate::raster::depth_order;

use super::config::LightConfig;
use super::error::SunAwareError;

mod exp_lanes;
pub mod light_camera;
#[cfg(test)]
mod tests;
mod tile_walk;

pub use light_camera::{box_sphere, light_axis_sigmas_m, light_camera, light_splats, LightCamera};
use tile_walk::{occluder_power_floor, tile_visibility_into, TileScratch, TileWalk, WalkIsa};

/// Occluders within this many of a receiver's own standard deviations along the light axis
/// (plus the depth bias) do not shadow it (see the module docs).
pub const RECEIVER_EXTENT_SIGMAS: f32 = 2.0;

/// A splat that covers no pixel (a placeholder that is never walked).
const NO_SPLAT: Splat = Splat {
    mean_px: [f32::NAN; 2],
    conic: [0.0; 3],
    opacity: 0.0,
    depth: f32::INFINITY,
    rect: PixelRect {
        x0: 0,
        y0: 0,
        x1: 0,
        y1: 0,
    },
};

/// `V_i` for every Gaussian from its splats in the light image (see the module docs).
/// `receiver_margin_m[i]` (empty: all zero) is added to the depth bias for receiver `i`.
pub fn visibility_from_splats(
    splats: &[Option<Splat>],
    side_px: u32,
    footprint_radius_px: f32,
    depth_bias_m: f32,
    receiver_margin_m: &[f32],
) -> Vec<f32> {
    let n = splats.len();
    let order = depth_order(splats);
    // Element-wise maps, in parallel (each value depends on its own inputs only).
    // `depth_order` lists only the splats that exist, so the map is indexed (rayon collects
    // it straight into place) and the fallback is never taken.
    let ranked: Vec<Splat> = order
        .par_iter()
        .with_min_len(4096)
        .map(|&g| splats[g as usize].unwrap_or(NO_SPLAT))
        .collect();
    // Occluders must end before this depth to shadow the receiver of that rank.
    let limit_of_rank: Vec<f32> = order
        .par_iter()
        .zip(&ranked)
        .map(|(&g, s)| {
            let margin = receiver_margin_m.get(g as usize).copied().unwrap_or(0.0);
            s.depth - depth_bias_m - margin.max(0.0)
        })
        .collect();
    let power_floor_of_rank: Vec<f32> = ranked.par_iter().map(occluder_power_floor).collect();
    let grid = TileGrid::new(side_px, side_px);
    let rects: Vec<PixelRect> = ranked.par_iter().map(|s| s.rect).collect();
    let bins = bin_tiles(&grid, &rects);
    // One accumulator per tile-list entry, filled tile by tile in parallel (each tile's
    // entries are its own slice).
    let mut per_entry = vec![[0.0f32; 2]; bins.tile_ranks.len()];
    let mut tiles: Vec<(usize, &mut [[f32; 2]])> = Vec::with_capacity(grid.n_tiles());
    let mut rest = per_entry.as_mut_slice();
    for t in 0..grid.n_tiles() {
        let (mine, after) = rest.split_at_mut(bins.tile_offsets[t + 1] - bins.tile_offsets[t]);
        tiles.push((t, mine));
        rest = after;
    }
    tiles
        .into_par_iter()
        .for_each_init(TileScratch::default, |scratch, (t, acc)| {
            let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
            let walk = TileWalk {
                list,
                ranked: &ranked,
                limit_of_rank: &limit_of_rank,
                power_floor_of_rank: &power_floor_of_rank,
                rect: grid.tile_rect(t),
                footprint_radius_px,
            };
            tile_visibility_into(&walk, scratch, acc, WalkIsa::Detect);
        });
    // Per rank, its entries' sums in tile order (`entry_of_rank` lists them so): the same
    // additions in the same order as a pass over the tiles, in parallel over ranks.
    let v_of_rank: Vec<f32> = (0..ranked.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|rank| {
            let (mut w, mut wt) = (0.0f64, 0.0f64);
            let entries = &bins.entry_of_rank[bins.rank_offsets[rank]..bins.rank_offsets[rank + 1]];
            for &e in entries {
                let a = per_entry[e as usize];
                w += a[0] as f64;
                wt += a[1] as f64;
            }
            if w > 0.0 {
                ((wt / w) as f32).clamp(0.0, 1.0)
            } else {
                1.0
            }
        })
        .collect();
    // Culled Gaussians (no rank) saw no pixel: nothing is known to block the Sun.
    let mut visibility = vec![1.0f32; n];
    for (&g, &v) in order.iter().zip(&v_of_rank) {
        visibility[g as usize] = v;
    }
    visibility
}

/// `V_i` of every Gaussian for one image: light camera, splats, visibility.
pub fn sun_visibility(
    model: &GaussianModel,
    sun_dir: Vec3,
    camera_centre: Vec3,
    scene_box: &SceneBox,
    config: &LightConfig,
    near_m: f32,
) -> Result<Vec<f32>, SunAwareError> {
    sun_visibility_with_margin(
        model,
        sun_dir,
        camera_centre,
        scene_box,
        config,
        near_m,
        RECEIVER_EXTENT_SIGMAS,
    )
}

/// [`sun_visibility`] with `extent_sigmas` instead of [`RECEIVER_EXTENT_SIGMAS`] (0: the
/// fixed depth bias alone), for studies of the shadow pass.
pub fn sun_visibility_with_margin(
    model: &GaussianModel,
    sun_dir: Vec3,
    camera_centre: Vec3,
    scene_box: &SceneBox,
    config: &LightConfig,
    near_m: f32,
    extent_sigmas: f32,
) -> Result<Vec<f32>, SunAwareError> {
    if !(extent_sigmas.is_finite() && extent_sigmas >= 0.0) {
        return Err(SunAwareError::Config(format!(
            "receiver extent must be a finite number of sigmas >= 0, got {extent_sigmas}"
        )));
    }
    let light = light_camera(sun_dir, camera_centre, scene_box, config)?;
    let splats = light_splats(model, &light, near_m)?;
    let margin: Vec<f32> = if extent_sigmas > 0.0 {
        light_axis_sigmas_m(model, &light)
            .iter()
            .map(|s| s * extent_sigmas)
            .collect()
    } else {
        Vec::new()
    };
    Ok(visibility_from_splats(
        &splats,
        config.resolution_px,
        config.footprint_radius_px,
        light.depth_bias_m,
        &margin,
    ))
}
