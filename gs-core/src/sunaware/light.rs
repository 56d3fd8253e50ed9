//! The shadow pass: per-Gaussian Sun visibility `V_i` seen from a light camera.
//!
//! The light camera sits on the Sun vector at the image camera's distance from the target
//! centre (at least 1.5 scene radii, so it is outside the box) and looks at the centre:
//! - [`LightProjection::Perspective`]: a pinhole whose field of view just covers the scene
//!   box's bounding sphere (times a margin), as in the paper;
//! - [`LightProjection::Orthographic`]: parallel projection along the Sun vector with the
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

use glam::Vec3;
use rayon::prelude::*;

use crate::camera::{Camera, Intrinsics};
use crate::model::{GaussianModel, Param};
use crate::nn::SceneBox;
use crate::raster::bin::{bin_tiles, PixelRect, TileGrid};
use crate::raster::blend::{AlphaMode, Splat, ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_STOP};
use crate::raster::project::COV2D_DILATION_PX2;
use crate::raster::{camera_frame, depth_order, project_splats, splat_rect, GaussianView};

use super::config::{LightConfig, LightProjection};
use super::error::SunAwareError;

/// Occluders within this many of a receiver's own standard deviations along the light axis
/// (plus the depth bias) do not shadow it (see the module docs).
pub const RECEIVER_EXTENT_SIGMAS: f32 = 2.0;

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

/// The exponent of a splat's footprint at a pixel centre: an occluder's alpha is
/// `o exp(power)`, a receiver's weight `exp(power)`.
#[inline(always)]
fn footprint_power(s: &Splat, px: f32, py: f32) -> f32 {
    let dx = s.mean_px[0] - px;
    let dy = s.mean_px[1] - py;
    let [a, b, c] = s.conic;
    -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
}

/// The rasterizer's alpha from an occluder's opacity and footprint exponent:
/// `min(0.99, o exp(power))`, 0 where that is NaN.
#[inline(always)]
fn occluder_alpha(opacity: f32, power: f32) -> f32 {
    let raw = opacity * power.exp();
    if raw.is_nan() {
        0.0
    } else {
        raw.min(ALPHA_MAX)
    }
}

/// Below this exponent an occluder's alpha is certainly under [`ALPHA_MIN`]:
/// `ln(ALPHA_MIN / o)` less a margin far above the rounding of `exp` and `ln`, so testing it
/// first skips the exponential without changing which occluders count.
fn occluder_power_floor(s: &Splat) -> f32 {
    let floor = (ALPHA_MIN / s.opacity).ln() - 1e-3;
    if floor.is_nan() {
        f32::NEG_INFINITY
    } else {
        floor
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

/// A key whose unsigned order is `f32::total_cmp`'s order.
fn total_order_key(v: f32) -> u32 {
    let b = v.to_bits();
    if b & 0x8000_0000 != 0 {
        !b
    } else {
        b | 0x8000_0000
    }
}

/// Per-thread buffers of [`tile_visibility_into`], reused from tile to tile.
#[derive(Default)]
struct TileScratch {
    /// The tile's splats, limits and power floors in list order (copied out of the
    /// rank-ordered arrays, so the walk reads them from cache instead of all over memory).
    splats: Vec<Splat>,
    limits: Vec<f32>,
    floors: Vec<f32>,
    /// `(total_order_key(limit) << 32) | list position` of the receivers to serve.
    order: Vec<u64>,
    trans: Vec<f32>,
}

/// One light tile's `[sum of footprint weights, sum of weight x transmittance]` per entry
/// of its depth-ordered `list` (ranks into `ranked`).
///
/// Receivers are served in increasing `limit` (ties by list position) while one pointer
/// applies the occluders in depth order to a transmittance image of the tile: before a
/// receiver is served, every occluder nearer than its limit has been applied, so each of its
/// pixels reads the transmittance of exactly what lies in front of it. An occluder only
/// touches the pixels of its own rectangle (outside it its alpha is below the cutoff by
/// construction), and skips the exponential where its exponent is certainly below the
/// cutoff; a pixel stops at `T < 1e-4`. Receivers with no pixel centre of the tile within
/// reach are not served at all (they read nothing; the occluders they would have applied
/// are applied for the next receiver that does). Per receiver the sums run over its pixels
/// in row-major order, so the result is the same bits as a per-pixel scan of the whole list
/// (`tests::tile_walk_matches_the_plain_scan_bit_for_bit`) at the cost of the occluders'
/// footprints instead of pixels x list length.
#[cfg(test)]
fn tile_visibility(walk: &TileWalk, isa: WalkIsa) -> Vec<[f32; 2]> {
    let mut acc = vec![[0.0f32; 2]; walk.list.len()];
    let mut scratch = TileScratch::default();
    tile_visibility_into(walk, &mut scratch, &mut acc, isa);
    acc
}

/// What the walk of one light tile reads: its list (ranks in depth order), the splats and
/// per-rank limits and exponent floors in rank order, the tile's pixels and the footprint
/// radius. Bundled so the plain and the AVX-512 builds take the same one argument.
struct TileWalk<'a> {
    list: &'a [u32],
    ranked: &'a [Splat],
    limit_of_rank: &'a [f32],
    power_floor_of_rank: &'a [f32],
    rect: PixelRect,
    footprint_radius_px: f32,
}

/// [`tile_visibility`] into `acc` (one entry per list entry, zeroed here) with reused
/// buffers, compiled for AVX-512F where the CPU has it (the lane loops below become vector
/// operations: the same separate IEEE operations, and the same scalar `expf` calls, so the
/// same bits; tested against the plain build).
fn tile_visibility_into(
    walk: &TileWalk,
    scratch: &mut TileScratch,
    acc: &mut [[f32; 2]],
    isa: WalkIsa,
) {
    #[cfg(target_arch = "x86_64")]
    if isa == WalkIsa::Detect && std::arch::is_x86_feature_detected!("avx512f") {
        // SAFETY: the CPU has AVX-512F (checked just above).
        unsafe { tile_visibility_avx512(walk, scratch, acc) };
        return;
    }
    let _ = isa;
    tile_visibility_body(walk, scratch, acc);
}

/// Which build of the tile walk runs: the widest the CPU has, or the plain one (tests).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum WalkIsa {
    Detect,
    #[cfg_attr(not(test), allow(dead_code))]
    Plain,
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn tile_visibility_avx512(walk: &TileWalk, scratch: &mut TileScratch, acc: &mut [[f32; 2]]) {
    tile_visibility_body(walk, scratch, acc);
}

/// Pixels of a tile row handled together by the occluder loop (a tile row is 16 pixels).
const WALK_LANES: usize = 16;
/// Tile rows an occluder handles at once (one 64-bit mask of live pixels) in full-width
/// tiles.
const OCCLUDER_BLOCK_ROWS: usize = 4;
/// Pixels of a receiver's window row handled together (the window is `2 reach + 1` = 7
/// pixels wide at the default radius of 2 px).
const RECEIVER_LANES: usize = 8;
/// Receiver windows up to this many pixels on a side (the default radius gives 7) are
/// handled in one piece of `WINDOW_SIDE^2` lanes.
const WINDOW_SIDE: usize = 8;

// `!(a < b)` on floats: NaN goes on to the next test, exactly as in the plain scan.
#[inline(always)]
#[allow(clippy::neg_cmp_op_on_partial_ord)]
fn tile_visibility_body(walk: &TileWalk, scratch: &mut TileScratch, acc: &mut [[f32; 2]]) {
    let TileWalk {
        list,
        ranked,
        limit_of_rank,
        power_floor_of_rank,
        rect,
        footprint_radius_px,
    } = *walk;
    acc.iter_mut().for_each(|a| *a = [0.0; 2]);
    if list.is_empty() || rect.is_empty() {
        return;
    }
    let tile_w = (rect.x1 - rect.x0) as usize;
    let TileScratch {
        splats,
        limits,
        floors,
        order,
        trans,
    } = scratch;
    splats.clear();
    limits.clear();
    floors.clear();
    for (i, &r) in list.iter().enumerate() {
        // The list is in rank order but sparse: fetch a few entries ahead, the copy below
        // would otherwise wait on memory for most of them.
        #[cfg(target_arch = "x86_64")]
        if let Some(&ahead) = list.get(i + 8) {
            let p = ranked.as_ptr().wrapping_add(ahead as usize) as *const i8;
            // SAFETY: a prefetch is only a hint; it never faults, whatever the address.
            unsafe {
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(p);
                std::arch::x86_64::_mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(
                    p.wrapping_add(32),
                );
            }
        }
        let _ = i;
        splats.push(ranked[r as usize]);
        limits.push(limit_of_rank[r as usize]);
        floors.push(power_floor_of_rank[r as usize]);
    }
    // Pixel centres within the footprint radius lie in this range (one pixel wider than
    // needed, so rounding never drops one; the exact test below decides).
    let reach = footprint_radius_px.ceil() as i64 + 1;
    let window = |s: &Splat| {
        let cx = s.mean_px[0].floor() as i64;
        let cy = s.mean_px[1].floor() as i64;
        (
            (cx - reach).max(rect.x0 as i64),
            (cx + reach + 1).min(rect.x1 as i64),
            (cy - reach).max(rect.y0 as i64),
            (cy + reach + 1).min(rect.y1 as i64),
        )
    };
    order.clear();
    for (k, s) in splats.iter().enumerate() {
        if !(s.mean_px[0].is_finite() && s.mean_px[1].is_finite()) {
            continue;
        }
        let (x0, x1, y0, y1) = window(s);
        if x0 < x1 && y0 < y1 {
            order.push(((total_order_key(limits[k]) as u64) << 32) | k as u64);
        }
    }
    // Keys are unique (the position breaks ties), so the unstable sort is the stable one.
    order.sort_unstable();
    // Values past the last pixel, so a lane loop may read a whole chunk or block of rows.
    let pixels = tile_w * (rect.y1 - rect.y0) as usize;
    trans.clear();
    trans.resize(pixels + OCCLUDER_BLOCK_ROWS * WALK_LANES, 1.0);
    let r2 = footprint_radius_px * footprint_radius_px;
    let mut next_occluder = 0;
    let mut saturated = 0usize;
    for &key in order.iter() {
        let k = (key & 0xffff_ffff) as usize;
        let s = &splats[k];
        let limit = limits[k];
        while next_occluder < list.len() && splats[next_occluder].depth < limit {
            if saturated == pixels {
                // Every pixel of the tile is opaque: no occluder can change anything.
                next_occluder = list.len();
                break;
            }
            let o = &splats[next_occluder];
            apply_occluder(o, floors[next_occluder], rect, trans, &mut saturated);
            next_occluder += 1;
        }
        // Inside the tile now: pixel coordinates fit in i32 (exact in f32 either way; i32
        // converts in one vector instruction).
        let (x0, x1, y0, y1) = window(s);
        let (x0, x1, y0, y1) = (x0 as i32, x1 as i32, y0 as i32, y1 as i32);
        if x1 - x0 <= WINDOW_SIDE as i32 && y1 - y0 <= WINDOW_SIDE as i32 {
            // The whole window at once: one mask, one loop over its pixels.
            let mut power = [0.0f32; WINDOW_SIDE * WINDOW_SIDE];
            let mut live = 0u64;
            for (l, p) in power.iter_mut().enumerate() {
                let (c, r) = ((l % WINDOW_SIDE) as i32, (l / WINDOW_SIDE) as i32);
                let fx = (x0 + c) as f32 + 0.5;
                let fy = (y0 + r) as f32 + 0.5;
                let dx = s.mean_px[0] - fx;
                let dy = s.mean_px[1] - fy;
                let inside = !(dx * dx + dy * dy > r2);
                *p = footprint_power(s, fx, fy);
                live |= ((c < x1 - x0 && r < y1 - y0 && inside) as u64) << l;
            }
            // Bits in increasing row, then x: the sums run in row-major pixel order.
            while live != 0 {
                let l = live.trailing_zeros() as usize;
                live &= live - 1;
                let weight = power[l].exp();
                if weight.is_nan() || weight <= 1e-6 {
                    continue;
                }
                let (c, r) = ((l % WINDOW_SIDE) as i32, (l / WINDOW_SIDE) as i32);
                let t = trans[(y0 + r - rect.y0 as i32) as usize * tile_w
                    + (x0 + c - rect.x0 as i32) as usize];
                let seen = if t < TRANSMITTANCE_STOP { 0.0 } else { t };
                acc[k][0] += weight;
                acc[k][1] += weight * seen;
            }
            continue;
        }
        for py in y0..y1 {
            let fy = py as f32 + 0.5;
            let row = (py - rect.y0 as i32) as usize * tile_w;
            let mut cs = x0;
            while cs < x1 {
                let n = ((x1 - cs) as usize).min(RECEIVER_LANES);
                let mut power = [0.0f32; RECEIVER_LANES];
                let mut live = 0u32;
                for (l, p) in power.iter_mut().enumerate() {
                    let fx = (cs + l as i32) as f32 + 0.5;
                    let dx = s.mean_px[0] - fx;
                    let dy = s.mean_px[1] - fy;
                    let inside = !(dx * dx + dy * dy > r2);
                    *p = footprint_power(s, fx, fy);
                    live |= ((l < n && inside) as u32) << l;
                }
                // Lanes in increasing x: the sums run in row-major pixel order.
                while live != 0 {
                    let l = live.trailing_zeros() as usize;
                    live &= live - 1;
                    let weight = power[l].exp();
                    if weight.is_nan() || weight <= 1e-6 {
                        continue;
                    }
                    let t = trans[row + (cs - rect.x0 as i32) as usize + l];
                    let seen = if t < TRANSMITTANCE_STOP { 0.0 } else { t };
                    acc[k][0] += weight;
                    acc[k][1] += weight * seen;
                }
                cs += RECEIVER_LANES as i32;
            }
        }
    }
}

/// Multiplies the transmittance of every pixel in `live` (bit `l`: pixel `trans[l]`) by
/// `1 - alpha` of its exponent `power[l]` where that alpha reaches the cutoff, in pixel
/// order (scalar `exp`: the same bits as the plain scan), and counts the pixels it takes
/// below the stop.
#[inline(always)]
fn attenuate_live_pixels(
    mut live: u64,
    opacity: f32,
    power: &[f32],
    trans: &mut [f32],
    saturated: &mut usize,
) {
    while live != 0 {
        let l = live.trailing_zeros() as usize;
        live &= live - 1;
        let alpha = occluder_alpha(opacity, power[l]);
        if alpha >= ALPHA_MIN {
            let t = &mut trans[l];
            *t *= 1.0 - alpha;
            if *t < TRANSMITTANCE_STOP {
                *saturated += 1;
            }
        }
    }
}

/// Applies occluder `o` to the tile's transmittance: `T *= 1 - alpha` on the pixels of its
/// rectangle inside the tile where `T` has not stopped and its exponent is not certainly
/// below the cutoff (`floor`); counts pixels that stop.
// `!(a < b)` on floats: NaN goes on to the next test, exactly as in the plain scan.
#[inline(always)]
#[allow(clippy::neg_cmp_op_on_partial_ord)]
fn apply_occluder(
    o: &Splat,
    floor: f32,
    rect: PixelRect,
    trans: &mut [f32],
    saturated: &mut usize,
) {
    let tile_w = (rect.x1 - rect.x0) as usize;
    let (x0, x1) = (o.rect.x0.max(rect.x0), o.rect.x1.min(rect.x1));
    let (y0, y1) = (o.rect.y0.max(rect.y0), o.rect.y1.min(rect.y1));
    if x0 >= x1 || y0 >= y1 {
        return;
    }
    if tile_w == WALK_LANES {
        // Blocks of rows at once: in a full-width tile the block's pixels are contiguous,
        // lane `l` is column `x0 + l % 16` of row `py + l / 16` (lanes past the rectangle
        // are masked off, and read the padding past the last pixel at worst).
        const BLOCK: usize = OCCLUDER_BLOCK_ROWS * WALK_LANES;
        let mut py = y0;
        while py < y1 {
            let base = (py - rect.y0) as usize * tile_w + (x0 - rect.x0) as usize;
            let t_lanes: &[f32; BLOCK] =
                trans[base..base + BLOCK].try_into().expect("BLOCK values");
            let mut power = [0.0f32; BLOCK];
            let mut live = 0u64;
            for (l, p) in power.iter_mut().enumerate() {
                let (c, r) = ((l % WALK_LANES) as u32, (l / WALK_LANES) as u32);
                let fx = (x0 + c) as f32 + 0.5;
                let fy = (py + r) as f32 + 0.5;
                *p = footprint_power(o, fx, fy);
                // Most of the rectangle misses the footprint: no exponential there.
                let go = x0 + c < x1
                    && py + r < y1
                    && !(t_lanes[l] < TRANSMITTANCE_STOP)
                    && !(*p < floor);
                live |= (go as u64) << l;
            }
            attenuate_live_pixels(live, o.opacity, &power, &mut trans[base..], saturated);
            py += OCCLUDER_BLOCK_ROWS as u32;
        }
        return;
    }
    for py in y0..y1.max(y0) {
        let fy = py as f32 + 0.5;
        let mut cs = x0;
        while cs < x1 {
            let n = ((x1 - cs) as usize).min(WALK_LANES);
            let base = (py - rect.y0) as usize * tile_w + (cs - rect.x0) as usize;
            let t_lanes: &[f32; WALK_LANES] = trans[base..base + WALK_LANES]
                .try_into()
                .expect("WALK_LANES values");
            let mut power = [0.0f32; WALK_LANES];
            let mut live = 0u32;
            for (l, p) in power.iter_mut().enumerate() {
                let fx = (cs + l as u32) as f32 + 0.5;
                *p = footprint_power(o, fx, fy);
                // Most of the rectangle misses the footprint: no exponential there.
                let go = l < n && !(t_lanes[l] < TRANSMITTANCE_STOP) && !(*p < floor);
                live |= (go as u32) << l;
            }
            attenuate_live_pixels(
                u64::from(live),
                o.opacity,
                &power,
                &mut trans[base..],
                saturated,
            );
            cs += WALK_LANES as u32;
        }
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;

    /// The per-pixel scan over the whole tile list that `tile_visibility` replaces.
    fn plain_scan_tile(
        list: &[u32],
        ranked: &[Splat],
        limit_of_rank: &[f32],
        rect: PixelRect,
        footprint_radius_px: f32,
    ) -> Vec<[f32; 2]> {
        let mut acc = vec![[0.0f32; 2]; list.len()];
        let mut receivers: Vec<usize> = (0..list.len()).collect();
        receivers.sort_by(|&a, &b| {
            limit_of_rank[list[a] as usize]
                .total_cmp(&limit_of_rank[list[b] as usize])
                .then(a.cmp(&b))
        });
        let r2 = footprint_radius_px * footprint_radius_px;
        for py in rect.y0..rect.y1 {
            for px in rect.x0..rect.x1 {
                let (fx, fy) = (px as f32 + 0.5, py as f32 + 0.5);
                let mut trans = 1.0f32;
                let mut next_occluder = 0;
                for &k in &receivers {
                    let s = &ranked[list[k] as usize];
                    let (dx, dy) = (s.mean_px[0] - fx, s.mean_px[1] - fy);
                    if dx * dx + dy * dy > r2 {
                        continue;
                    }
                    let [a, b, c] = s.conic;
                    let weight = (-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy).exp();
                    if weight.is_nan() || weight <= 1e-6 {
                        continue;
                    }
                    let limit = limit_of_rank[list[k] as usize];
                    while next_occluder < list.len()
                        && ranked[list[next_occluder] as usize].depth < limit
                    {
                        if trans >= TRANSMITTANCE_STOP {
                            let o = &ranked[list[next_occluder] as usize];
                            let alpha = occluder_alpha(o.opacity, footprint_power(o, fx, fy));
                            if alpha >= ALPHA_MIN {
                                trans *= 1.0 - alpha;
                            }
                        }
                        next_occluder += 1;
                    }
                    let seen = if trans < TRANSMITTANCE_STOP {
                        0.0
                    } else {
                        trans
                    };
                    acc[k][0] += weight;
                    acc[k][1] += weight * seen;
                }
            }
        }
        acc
    }

    /// The whole pass against the reference it replaced: every tile by the plain per-pixel
    /// scan, then each Gaussian's sums over its tiles in tile order, serially. Same bits,
    /// on 1, 2 and 3 threads. The light image (72 px) ends inside a tile row and column.
    #[test]
    fn visibility_matches_the_serial_plain_scan_on_any_thread_count() {
        let side = 72u32;
        let radius = 2.0f32;
        let bias = 0.01f32;
        let mut rng = SplitMix64::new(21);
        let n = 700;
        let splats: Vec<Option<Splat>> = (0..n)
            .map(|i| {
                let wide = rng.uniform(0.05, 0.8);
                let conic = [wide, rng.uniform_symmetric(0.5 * wide), wide * 1.2];
                let det = conic[0] * conic[2] - conic[1] * conic[1];
                let cov = [conic[2] / det, -conic[1] / det, conic[0] / det];
                let mean_px = [rng.uniform(-4.0, 76.0), rng.uniform(-4.0, 76.0)];
                let opacity = rng.uniform(0.05, 0.99);
                let depth = rng.uniform(1.0, 2.0);
                let rect = splat_rect(mean_px, cov, 2.0 * (opacity / ALPHA_MIN).ln(), side, side);
                (i % 17 != 0 && !rect.is_empty()).then_some(Splat {
                    mean_px,
                    conic,
                    opacity,
                    depth,
                    rect,
                })
            })
            .collect();
        let margin: Vec<f32> = (0..n).map(|_| rng.uniform(0.0, 0.05)).collect();

        let order = depth_order(&splats);
        let ranked: Vec<Splat> = order.iter().filter_map(|&g| splats[g as usize]).collect();
        let limit_of_rank: Vec<f32> = order
            .iter()
            .zip(&ranked)
            .map(|(&g, s)| s.depth - bias - margin[g as usize])
            .collect();
        let grid = TileGrid::new(side, side);
        let rects: Vec<PixelRect> = ranked.iter().map(|s| s.rect).collect();
        let bins = bin_tiles(&grid, &rects);
        let mut sum_w = vec![0.0f64; n];
        let mut sum_wt = vec![0.0f64; n];
        for t in 0..grid.n_tiles() {
            let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
            let acc = plain_scan_tile(list, &ranked, &limit_of_rank, grid.tile_rect(t), radius);
            for (&rank, a) in list.iter().zip(&acc) {
                let g = order[rank as usize] as usize;
                sum_w[g] += a[0] as f64;
                sum_wt[g] += a[1] as f64;
            }
        }
        let want: Vec<u32> = sum_w
            .iter()
            .zip(&sum_wt)
            .map(|(&w, &wt)| {
                let v = if w > 0.0 {
                    ((wt / w) as f32).clamp(0.0, 1.0)
                } else {
                    1.0
                };
                v.to_bits()
            })
            .collect();
        let shadowed = want
            .iter()
            .filter(|&&b| f32::from_bits(b) > 0.0 && f32::from_bits(b) < 0.9)
            .count();
        assert!(shadowed > n / 10, "only {shadowed} partly shadowed");
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let got = pool.install(|| visibility_from_splats(&splats, side, radius, bias, &margin));
            let got: Vec<u32> = got.iter().map(|v| v.to_bits()).collect();
            assert!(got == want, "{threads} threads");
        }
    }

    #[test]
    fn tile_walk_matches_the_plain_scan_bit_for_bit() {
        let rect = PixelRect {
            x0: 16,
            y0: 32,
            x1: 32,
            y1: 48,
        };
        let mut rng = SplitMix64::new(7);
        for (trial, &count) in [0usize, 1, 5, 40, 300].iter().enumerate() {
            for &radius in &[0.5f32, 1.3, 2.0, 3.7] {
                // Centres in and around the tile, some far off and one non-finite; dense,
                // opaque occluders so that pixels saturate; depths with ties.
                // Each splat's rectangle is the rasterizer's bound in a 64 x 64 image.
                let mut ranked: Vec<Splat> = (0..count)
                    .map(|i| {
                        let wide = rng.uniform(0.02, 0.6);
                        let conic = [wide, rng.uniform_symmetric(0.5 * wide), wide * 1.3];
                        let det = conic[0] * conic[2] - conic[1] * conic[1];
                        let cov = [conic[2] / det, -conic[1] / det, conic[0] / det];
                        let mean_px = [rng.uniform(12.0, 36.0), rng.uniform(28.0, 52.0)];
                        let opacity = if i % 7 == 0 {
                            rng.uniform(0.0, 0.01)
                        } else {
                            rng.uniform(0.05, 0.99)
                        };
                        let q_max = 2.0 * (opacity / ALPHA_MIN).ln();
                        let rect = if q_max > 0.0 {
                            splat_rect(mean_px, cov, q_max, 64, 64)
                        } else {
                            PixelRect {
                                x0: 0,
                                y0: 0,
                                x1: 0,
                                y1: 0,
                            }
                        };
                        Splat {
                            mean_px,
                            conic,
                            opacity,
                            depth: (i / 3) as f32 * 0.01,
                            rect,
                        }
                    })
                    .collect();
                if count == 300 {
                    // Four near-opaque walls in front of everything: the whole tile
                    // saturates and the walk can stop.
                    for wall in ranked.iter_mut().take(4) {
                        wall.conic = [1e-4, 0.0, 1e-4];
                        wall.opacity = 0.99;
                        wall.depth = -1.0;
                        wall.rect = PixelRect {
                            x0: 0,
                            y0: 0,
                            x1: 64,
                            y1: 64,
                        };
                    }
                }
                if count > 3 {
                    ranked[2].mean_px[0] = f32::NAN;
                    ranked[3].mean_px = [1e9, -1e9];
                }
                let limit_of_rank: Vec<f32> = ranked
                    .iter()
                    .map(|s| s.depth - rng.uniform(0.0, 0.05))
                    .collect();
                let list: Vec<u32> = (0..count as u32).collect();
                let floors: Vec<f32> = ranked.iter().map(occluder_power_floor).collect();
                let want = plain_scan_tile(&list, &ranked, &limit_of_rank, rect, radius);
                let bits = |v: &[[f32; 2]]| {
                    v.iter()
                        .flat_map(|p| [p[0].to_bits(), p[1].to_bits()])
                        .collect::<Vec<_>>()
                };
                let walk = TileWalk {
                    list: &list,
                    ranked: &ranked,
                    limit_of_rank: &limit_of_rank,
                    power_floor_of_rank: &floors,
                    rect,
                    footprint_radius_px: radius,
                };
                // Both builds of the walk (AVX-512 where the CPU has it, and plain).
                for isa in [WalkIsa::Detect, WalkIsa::Plain] {
                    let got = tile_visibility(&walk, isa);
                    assert_eq!(
                        bits(&got),
                        bits(&want),
                        "trial {trial}, radius {radius} {isa:?}"
                    );
                }
                let got = tile_visibility(&walk, WalkIsa::Detect);
                if count >= 40 {
                    assert!(
                        got.iter().any(|a| a[0] > 0.0 && a[1] < a[0]),
                        "no shadowing"
                    );
                }
            }
        }
    }
}
