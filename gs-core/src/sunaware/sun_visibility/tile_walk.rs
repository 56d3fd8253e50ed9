//! The walk of one light tile in the Sun visibility pass: for every receiver in the tile's
//! depth-ordered list, the sums of its footprint weights and of weight x transmittance of
//! what lies in front of it, with occluders applied once each in depth order.
//!
//! Invariants: the same bits as a per-pixel scan of the whole list (tested), in the plain
//! and the AVX-512F builds alike; pixels are visited in row-major order per receiver. The
//! exponentials are `f32::exp`'s bits whether taken one by one or sixteen at once
//! ([`ExpLanes`]).

use super::exp_lanes::ExpLanes;
use crate::raster::bin::PixelRect;
use crate::raster::blend::{Splat, ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_STOP};

/// The exponent of a splat's footprint at a pixel centre: an occluder's alpha is
/// `o exp(power)`, a receiver's weight `exp(power)`.
#[inline(always)]
pub(super) fn footprint_power(s: &Splat, px: f32, py: f32) -> f32 {
    let dx = s.mean_px[0] - px;
    let dy = s.mean_px[1] - py;
    let [a, b, c] = s.conic;
    -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
}

/// The rasterizer's alpha from an occluder's opacity and footprint exponent:
/// `min(0.99, o exp(power))`, 0 where that is NaN.
#[cfg(test)]
pub(super) fn occluder_alpha(opacity: f32, power: f32) -> f32 {
    alpha_of_footprint(opacity, power.exp())
}

/// [`occluder_alpha`] from the footprint `exp(power)` already taken.
#[inline(always)]
fn alpha_of_footprint(opacity: f32, footprint: f32) -> f32 {
    let raw = opacity * footprint;
    if raw.is_nan() {
        0.0
    } else {
        raw.min(ALPHA_MAX)
    }
}

/// Below this exponent an occluder's alpha is certainly under [`ALPHA_MIN`]:
/// `ln(ALPHA_MIN / o)` less a margin far above the rounding of `exp` and `ln`, so testing it
/// first skips the exponential without changing which occluders count.
pub(super) fn occluder_power_floor(s: &Splat) -> f32 {
    let floor = (ALPHA_MIN / s.opacity).ln() - 1e-3;
    if floor.is_nan() {
        f32::NEG_INFINITY
    } else {
        floor
    }
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
pub(super) struct TileScratch {
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
pub(super) fn tile_visibility(walk: &TileWalk, isa: WalkIsa) -> Vec<[f32; 2]> {
    let mut acc = vec![[0.0f32; 2]; walk.list.len()];
    let mut scratch = TileScratch::default();
    tile_visibility_into(walk, &mut scratch, &mut acc, isa);
    acc
}

/// What the walk of one light tile reads: its list (ranks in depth order), the splats and
/// per-rank limits and exponent floors in rank order, the tile's pixels and the footprint
/// radius. Bundled so the plain and the AVX-512 builds take the same one argument.
pub(super) struct TileWalk<'a> {
    pub(super) list: &'a [u32],
    pub(super) ranked: &'a [Splat],
    pub(super) limit_of_rank: &'a [f32],
    pub(super) power_floor_of_rank: &'a [f32],
    pub(super) rect: PixelRect,
    pub(super) footprint_radius_px: f32,
}

/// [`tile_visibility`] into `acc` (one entry per list entry, zeroed here) with reused
/// buffers, compiled for AVX-512F where the CPU has it (the lane loops below become vector
/// operations: the same separate IEEE operations, and `f32::exp`'s bits sixteen lanes at a
/// time where [`ExpLanes::detect`] allows, so the same bits; tested against the plain
/// build).
pub(super) fn tile_visibility_into(
    walk: &TileWalk,
    scratch: &mut TileScratch,
    acc: &mut [[f32; 2]],
    isa: WalkIsa,
) {
    #[cfg(target_arch = "x86_64")]
    if isa == WalkIsa::Detect && std::arch::is_x86_feature_detected!("avx512f") {
        // SAFETY: the CPU has AVX-512F (checked just above).
        unsafe { tile_visibility_avx512(walk, scratch, acc, ExpLanes::detect()) };
        return;
    }
    let _ = isa;
    tile_visibility_body(walk, scratch, acc, ExpLanes::Scalar);
}

/// Which build of the tile walk runs: the widest the CPU has, or the plain one (tests).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum WalkIsa {
    Detect,
    #[cfg_attr(not(test), allow(dead_code))]
    Plain,
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn tile_visibility_avx512(
    walk: &TileWalk,
    scratch: &mut TileScratch,
    acc: &mut [[f32; 2]],
    exp: ExpLanes,
) {
    tile_visibility_body(walk, scratch, acc, exp);
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
fn tile_visibility_body(
    walk: &TileWalk,
    scratch: &mut TileScratch,
    acc: &mut [[f32; 2]],
    exp: ExpLanes,
) {
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
            apply_occluder(o, floors[next_occluder], rect, trans, &mut saturated, exp);
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
            let weights = exp_lanes(exp, &power, live);
            // Bits in increasing row, then x: the sums run in row-major pixel order.
            while live != 0 {
                let l = live.trailing_zeros() as usize;
                live &= live - 1;
                let weight = weights[l];
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

/// `exp` of the lanes of `power` whose bit is set in `live` (unspecified elsewhere),
/// sixteen at a time.
#[inline(always)]
fn exp_lanes<const N: usize>(exp: ExpLanes, power: &[f32; N], live: u64) -> [f32; N] {
    let mut out = [0.0f32; N];
    for (c, (o, p)) in out
        .chunks_exact_mut(16)
        .zip(power.chunks_exact(16))
        .enumerate()
    {
        let m = (live >> (16 * c)) as u16;
        if m != 0 {
            o.copy_from_slice(&exp.exp16(p.try_into().expect("16 lanes"), m));
        }
    }
    out
}

/// Multiplies the transmittance of every pixel in `live` (bit `l`: pixel `trans[l]`) by
/// `1 - alpha` of its exponent `power[l]` where that alpha reaches the cutoff, and counts
/// the pixels it takes below the stop. Each lane is its own pixel, so the order of the
/// lanes does not matter; the exponentials are `f32::exp`'s bits ([`ExpLanes`]).
#[inline(always)]
fn attenuate_live_pixels<const N: usize>(
    live: u64,
    opacity: f32,
    power: &[f32; N],
    trans: &mut [f32],
    saturated: &mut usize,
    exp: ExpLanes,
) {
    let footprint = exp_lanes(exp, power, live);
    for (c, (t, f)) in trans[..N]
        .chunks_exact_mut(16)
        .zip(footprint.chunks_exact(16))
        .enumerate()
    {
        let m = (live >> (16 * c)) as u16;
        if m == 0 {
            continue;
        }
        let mut stopped = 0u32;
        for l in 0..16 {
            let alpha = alpha_of_footprint(opacity, f[l]);
            let go = (m >> l) & 1 != 0 && alpha >= ALPHA_MIN;
            let attenuated = t[l] * (1.0 - alpha);
            stopped += u32::from(go && attenuated < TRANSMITTANCE_STOP);
            t[l] = if go { attenuated } else { t[l] };
        }
        *saturated += stopped as usize;
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
    exp: ExpLanes,
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
            attenuate_live_pixels(live, o.opacity, &power, &mut trans[base..], saturated, exp);
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
                exp,
            );
            cs += WALK_LANES as u32;
        }
    }
}
