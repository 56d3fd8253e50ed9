//! Front-to-back alpha blending of one tile, and its backward pass.
//!
//! Forward, per pixel: `alpha = min(0.99, o exp(power))`, skipped when below 1/255,
//! and blending stops before a Gaussian that would take the transmittance below 1e-4
//! (early termination; switched off, below [`TRANSMITTANCE_FLOOR`] instead, 1.2e-38).
//! Colour = sum_i c_i alpha_i T_i + T_final * background, depth = sum_i z_i alpha_i T_i
//! (not normalised by alpha), alpha = 1 - T_final.
//!
//! Backward walks the tile's list back to front, dividing the final transmittance by
//! `1 - alpha_i` to rebuild `T_i`, and keeps per pixel the unnormalised colour of what
//! lies behind (`S`), so `dC/dalpha_i = c_i T_i - S / (1 - alpha_i)`: no per-pixel lists.
//! Per-Gaussian sums are written to one record per list entry (each entry belongs to
//! exactly one tile, so tiles never write the same memory: no atomics, no races).
//! The backward needs no knowledge of where the forward stopped beyond each pixel's
//! final transmittance and last blended entry, so it is the exact gradient of the forward
//! that ran with early termination on or off.
//!
//! Invariants:
//! - forward and backward evaluate alpha with the same functions (`row_gauss`, [`alpha_of`]),
//!   so they agree bit for bit on which Gaussians each pixel kept;
//! - a splat is only evaluated inside its rectangle (a conservative bound of where its
//!   alpha reaches the cutoff), so binning never changes the image.
//! - in smooth mode (test-only) the 1/255 step is a C1 ramp `alpha * smoothstep` over
//!   `[0.5/255, 1.5/255]` and the early stop is off, so the image is C1 in the parameters
//!   wherever `o exp(power) < 0.99`.

use super::bin::{PixelRect, TILE_PIXELS, TILE_PX};

pub const ALPHA_MAX: f32 = 0.99;
pub const ALPHA_MIN: f32 = 1.0 / 255.0;
pub const TRANSMITTANCE_STOP: f32 = 1e-4;
/// With early termination off a pixel still stops before a Gaussian that would take its
/// transmittance below the smallest normal f32 (1.2e-38): the backward rebuilds each
/// `T_i` by dividing the final transmittance by `1 - alpha`, which needs that value to
/// keep its full precision (a subnormal or zero `T_final` would lose the gradients of
/// everything in front). What is left behind weighs less than 1.2e-38 per unit of
/// colour, far below what an f32 image resolves.
pub const TRANSMITTANCE_FLOOR: f32 = f32::MIN_POSITIVE;
/// Smooth-mode ramp: zero below `SMOOTH_LO`, the identity above `SMOOTH_HI`.
pub const SMOOTH_LO: f32 = 0.5 / 255.0;
pub const SMOOTH_HI: f32 = 1.5 / 255.0;

/// Gradient record layout: `[d_mean_x, d_mean_y, d_conic_a, d_conic_b, d_conic_c,
/// d_opacity, d_depth, d_channel_0, ...]`.
pub const REC_MEAN_X: usize = 0;
pub const REC_MEAN_Y: usize = 1;
pub const REC_CONIC: usize = 2;
pub const REC_OPACITY: usize = 5;
pub const REC_DEPTH: usize = 6;
pub const REC_CHANNELS: usize = 7;

/// A projected Gaussian, in depth order, as blending reads it.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C)]
pub struct Splat {
    pub mean_px: [f32; 2],
    pub conic: [f32; 3],
    pub opacity: f32,
    pub depth: f32,
    /// Pixels outside this rectangle are certain to get alpha below the cutoff.
    pub rect: PixelRect,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct AlphaMode {
    pub smooth: bool,
}

impl AlphaMode {
    /// Smallest alpha (before the smooth ramp) that a pixel keeps.
    pub fn cutoff(&self) -> f32 {
        if self.smooth {
            SMOOTH_LO
        } else {
            ALPHA_MIN
        }
    }

    /// Transmittance below which a pixel stops blending. Smooth mode (test-only) never
    /// stops; `early_termination` off stops only where the transmittance would leave the
    /// normal range of f32 (see [`TRANSMITTANCE_FLOOR`]).
    pub fn stop(&self, early_termination: bool) -> f32 {
        if self.smooth {
            0.0
        } else if early_termination {
            TRANSMITTANCE_STOP
        } else {
            TRANSMITTANCE_FLOOR
        }
    }
}

/// `exp(x)` to about 2 ulp for `x` in [-87, 88] (clamped outside; NaN gives `exp(-87)`).
/// Branch-free arithmetic, so a fixed-width loop of it vectorises; forward and backward
/// both call it, so they agree bit for bit.
#[inline(always)]
pub fn fast_exp(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Not `clamp`: f32::max returns the non-NaN operand, so NaN maps to the lower bound.
    #[allow(clippy::manual_clamp)]
    let x = x.max(-87.0).min(88.0);
    // Round to nearest with the 1.5 * 2^23 trick (SSE2 has no round instruction).
    const MAGIC: f32 = 12_582_912.0;
    let shifted = x * LOG2E + MAGIC;
    let n = shifted - MAGIC;
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = ((((1.987_569_1e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
        + 1.666_666_5e-1)
        * r
        + 0.5;
    let e = p * r * r + r + 1.0;
    // The low mantissa bits of `shifted` hold n as an integer (|n| <= 127 < 2^22): build
    // 2^n from them without a float-to-int conversion (saturating `as` is slow).
    let n_int = shifted.to_bits().wrapping_sub(MAGIC.to_bits());
    let scale = f32::from_bits(n_int.wrapping_add(127) << 23);
    e * scale
}

/// Lanes evaluated together by [`row_gauss`]: one AVX register, two SSE registers.
const LANE_GROUP: usize = 8;

/// `exp(power)` of splat `s` at the pixel centres of row `py`, lanes `i` (pixel
/// `x_origin + i`) for every 8-lane group that meets the columns `cols`, and the mask of
/// those lanes where `o exp(power)` reaches `cutoff` (exactly where [`alpha_of`] is
/// `Some`). Fixed-width and branch-free inside a group so it vectorises; other lanes of
/// `out` are left untouched and never in the mask.
#[inline(always)]
fn row_gauss(
    s: &Splat,
    py: f32,
    x_origin: u32,
    cutoff: f32,
    cols: u16,
    out: &mut [f32; TILE_PX as usize],
) -> u16 {
    let dy = s.mean_px[1] - py;
    let [a, b, c] = s.conic;
    let dx0 = s.mean_px[0] - (x_origin as f32 + 0.5);
    let base = -0.5 * c * dy * dy;
    let bdy = b * dy;
    let mut mask = 0u16;
    for (gi, group) in out.chunks_exact_mut(LANE_GROUP).enumerate() {
        let group_bits = ((1u32 << LANE_GROUP) - 1) << (gi * LANE_GROUP);
        if u32::from(cols) & group_bits == 0 {
            continue;
        }
        let first = (gi * LANE_GROUP) as f32;
        for (i, o) in group.iter_mut().enumerate() {
            let dx = dx0 - (first + i as f32);
            let power = -0.5 * a * dx * dx - bdy * dx + base;
            *o = fast_exp(power);
        }
        // A plain comparison per lane: compiles to one compare and a move-mask.
        let mut m = 0u32;
        for (i, &g) in group.iter().enumerate() {
            m |= u32::from(s.opacity * g >= cutoff) << i;
        }
        let m = m as u16;
        mask |= m << (gi * LANE_GROUP);
    }
    mask
}

/// Alpha of a splat of opacity `o` where its Gaussian is `gauss`, with d alpha /
/// d (o gauss) (zero where the 0.99 clamp is active), or `None` when it is skipped.
#[inline(always)]
pub fn alpha_of(o: f32, gauss: f32, mode: AlphaMode) -> Option<(f32, f32)> {
    let raw = o * gauss;
    let clamped = raw > ALPHA_MAX;
    let alpha_c = if clamped { ALPHA_MAX } else { raw };
    // Written so that a NaN alpha is skipped too.
    if alpha_c.is_nan() || alpha_c < mode.cutoff() {
        return None;
    }
    let (alpha, d_alpha) = if mode.smooth && alpha_c < SMOOTH_HI {
        let u = (alpha_c - SMOOTH_LO) / (SMOOTH_HI - SMOOTH_LO);
        let ramp = u * u * (3.0 - 2.0 * u);
        let d_ramp = 6.0 * u * (1.0 - u) / (SMOOTH_HI - SMOOTH_LO);
        (alpha_c * ramp, ramp + alpha_c * d_ramp)
    } else {
        (alpha_c, 1.0)
    };
    Some((alpha, if clamped { 0.0 } else { d_alpha }))
}

/// One pixel's evaluation of one splat.
#[derive(Clone, Copy, Debug)]
pub struct AlphaEval {
    pub alpha: f32,
    /// d alpha / d (o exp(power)); zero where the 0.99 clamp is active.
    pub d_alpha_d_raw: f32,
    pub gauss: f32,
    pub dx: f32,
    pub dy: f32,
}

/// Alpha of splat `s` at the pixel centre `(px, py)`, or `None` when it is skipped.
/// Same arithmetic as the tile loops (`fast_exp`, [`alpha_of`]); it ignores `s.rect`.
#[inline(always)]
pub fn eval_alpha(s: &Splat, px: f32, py: f32, mode: AlphaMode) -> Option<AlphaEval> {
    let dx = s.mean_px[0] - px;
    let dy = s.mean_px[1] - py;
    let [a, b, c] = s.conic;
    let power = -0.5 * a * dx * dx - b * dy * dx + -0.5 * c * dy * dy;
    let gauss = fast_exp(power);
    let (alpha, d_alpha_d_raw) = alpha_of(s.opacity, gauss, mode)?;
    Some(AlphaEval {
        alpha,
        d_alpha_d_raw,
        gauss,
        dx,
        dy,
    })
}

/// Hints the cache to fetch the splat a few list entries ahead: tile lists visit splats in
/// rank order but sparsely, and that load was the single hottest instruction.
#[inline(always)]
fn prefetch_splat(splats: &[Splat], list: &[u32], at: usize) {
    #[cfg(target_arch = "x86_64")]
    if let Some(&r) = list.get(at) {
        if let Some(s) = splats.get(r as usize) {
            use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
            // SAFETY: SSE is part of the x86_64 baseline, and a prefetch is only a hint:
            // it never faults and the pointer comes from a live reference.
            unsafe { _mm_prefetch::<_MM_HINT_T0>((s as *const Splat).cast::<i8>()) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (splats, list, at);
}

const PREFETCH_AHEAD: usize = 6;

/// One tile's forward outputs, tile-local pixel index `ly * 16 + lx`.
pub struct TileForwardOut<'a> {
    pub color: &'a mut [f32],
    pub depth: &'a mut [f32],
    pub transmittance: &'a mut [f32],
    /// One past the list index of the last splat blended into each pixel.
    pub last: &'a mut [u32],
}

fn overlap(a: &PixelRect, b: &PixelRect) -> PixelRect {
    PixelRect {
        x0: a.x0.max(b.x0),
        y0: a.y0.max(b.y0),
        x1: a.x1.min(b.x1),
        y1: a.y1.min(b.y1),
    }
}

/// Bit `lx` set for the tile columns `x0 - tile.x0 .. x1 - tile.x0`.
fn column_mask(r: &PixelRect, tile: &PixelRect) -> u16 {
    let lo = r.x0 - tile.x0;
    let hi = r.x1 - tile.x0;
    (((1u32 << hi) - 1) & !((1u32 << lo) - 1)) as u16
}

/// One tile's blending inputs, bundled so that the multiversioning layers below
/// (`*_avx2` -> `*_dispatch` -> `*_body`) each forward one reference.
#[derive(Clone, Copy)]
struct TileInputs<'a> {
    tile: &'a PixelRect,
    list: &'a [u32],
    splats: &'a [Splat],
    splat_channels: &'a [f32],
    n_channels: usize,
    background: &'a [f32],
    mode: AlphaMode,
}

/// Blends one tile front to back. `list` holds splat ranks in depth order.
///
/// On x86_64 with AVX2 the same code is compiled for 8-wide registers. Rust never fuses
/// multiplies and adds on its own, so both builds round identically: same results.
#[allow(clippy::too_many_arguments)]
pub fn blend_tile_forward(
    tile: &PixelRect,
    list: &[u32],
    splats: &[Splat],
    splat_channels: &[f32],
    n_channels: usize,
    background: &[f32],
    mode: AlphaMode,
    early_termination: bool,
    out: TileForwardOut,
) {
    let inp = TileInputs {
        tile,
        list,
        splats,
        splat_channels,
        n_channels,
        background,
        mode,
    };
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { forward_avx2(&inp, early_termination, out) };
        return;
    }
    forward_dispatch(&inp, early_termination, out);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn forward_avx2(inp: &TileInputs, early_termination: bool, out: TileForwardOut) {
    forward_dispatch(inp, early_termination, out);
}

/// Picks a build with the channel count fixed at compile time for the common counts.
#[inline(always)]
fn forward_dispatch(inp: &TileInputs, early_termination: bool, out: TileForwardOut) {
    match inp.n_channels {
        1 => forward_body::<1>(inp, early_termination, out),
        3 => forward_body::<3>(inp, early_termination, out),
        4 => forward_body::<4>(inp, early_termination, out),
        _ => forward_body::<0>(inp, early_termination, out),
    }
}

/// `FIXED > 0`: the channel count is `FIXED` (loops unroll); 0: `n_channels`.
#[inline(always)]
fn forward_body<const FIXED: usize>(
    inp: &TileInputs,
    early_termination: bool,
    out: TileForwardOut,
) {
    let TileInputs {
        tile,
        list,
        splats,
        splat_channels,
        n_channels,
        background,
        mode,
    } = *inp;
    let nc = if FIXED > 0 { FIXED } else { n_channels };
    out.color.fill(0.0);
    out.depth.fill(0.0);
    out.transmittance.fill(1.0);
    out.last.fill(0);
    let full = column_mask(
        &PixelRect {
            x0: tile.x0,
            y0: 0,
            x1: tile.x1,
            y1: 0,
        },
        tile,
    );
    // Per tile row, the columns still blending.
    let mut row_active = [0u16; TILE_PX as usize];
    for m in row_active.iter_mut().take((tile.y1 - tile.y0) as usize) {
        *m = full;
    }
    let mut n_active = ((tile.x1 - tile.x0) * (tile.y1 - tile.y0)) as usize;
    let stop = mode.stop(early_termination);
    let cutoff = mode.cutoff();
    let mut gauss = [0.0f32; TILE_PX as usize];
    for (j, &rank) in list.iter().enumerate() {
        if n_active == 0 {
            break;
        }
        prefetch_splat(splats, list, j + PREFETCH_AHEAD);
        let s = &splats[rank as usize];
        let ch = &splat_channels[rank as usize * nc..rank as usize * nc + nc];
        let r = overlap(&s.rect, tile);
        if r.is_empty() {
            continue;
        }
        let cols = column_mask(&r, tile);
        for y in r.y0..r.y1 {
            let ly = (y - tile.y0) as usize;
            let live = row_active[ly] & cols;
            if live == 0 {
                continue;
            }
            let mut bits = live & row_gauss(s, y as f32 + 0.5, tile.x0, cutoff, live, &mut gauss);
            while bits != 0 {
                let lx = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let Some((alpha, _)) = alpha_of(s.opacity, gauss[lx], mode) else {
                    continue;
                };
                let p = ly * TILE_PX as usize + lx;
                let t = out.transmittance[p];
                let t_next = t * (1.0 - alpha);
                if t_next < stop {
                    row_active[ly] &= !(1u16 << lx);
                    n_active -= 1;
                    continue;
                }
                let w = alpha * t;
                for (acc, &c) in out.color[p * nc..p * nc + nc].iter_mut().zip(ch) {
                    *acc += w * c;
                }
                out.depth[p] += w * s.depth;
                out.transmittance[p] = t_next;
                out.last[p] = j as u32 + 1;
            }
        }
    }
    if background.iter().any(|&b| b != 0.0) {
        for p in 0..TILE_PIXELS {
            let t = out.transmittance[p];
            for (acc, &b) in out.color[p * nc..p * nc + nc].iter_mut().zip(background) {
                *acc += t * b;
            }
        }
    }
}

/// `tile_contributions` flag: the entry is blended into at least one pixel of its tile.
pub const ENTRY_BLENDS: u8 = 1;
/// `tile_contributions` flag: the entry stops at least one pixel of its tile (its alpha
/// passes the cutoff there but would take the transmittance below the stop), without
/// necessarily being blended anywhere.
pub const ENTRY_STOPS: u8 = 2;

/// What each entry of one tile's list does in the forward blend: `flags[j]` has
/// [`ENTRY_BLENDS`] when splat `list[j]` is blended into at least one pixel of the tile
/// (its alpha passes the cutoff there before the pixel's transmittance stops) and
/// [`ENTRY_STOPS`] when it ends the blend of at least one pixel; 0 when it changes no pixel
/// of the tile at all. The walk, the alpha and the transmittance are those of
/// [`blend_tile_forward`] operation for operation, so the forward and backward passes
/// never read the channels of an entry without [`ENTRY_BLENDS`], and blending the list
/// without its zero-flag entries gives every pixel the same sequence of operations.
pub fn tile_contributions(
    tile: &PixelRect,
    list: &[u32],
    splats: &[Splat],
    mode: AlphaMode,
    early_termination: bool,
    flags: &mut [u8],
) {
    // The alpha-only walk reads no channels and no background.
    let inp = TileInputs {
        tile,
        list,
        splats,
        splat_channels: &[],
        n_channels: 0,
        background: &[],
        mode,
    };
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { contributions_avx2(&inp, early_termination, flags) };
        return;
    }
    contributions_body(&inp, early_termination, flags);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn contributions_avx2(inp: &TileInputs, early_termination: bool, flags: &mut [u8]) {
    contributions_body(inp, early_termination, flags);
}

/// [`forward_body`] without channels or depth: only the transmittance and the flags.
#[inline(always)]
fn contributions_body(inp: &TileInputs, early_termination: bool, flags: &mut [u8]) {
    let TileInputs {
        tile,
        list,
        splats,
        mode,
        ..
    } = *inp;
    flags.fill(0);
    let mut transmittance = [1.0f32; TILE_PIXELS];
    let full = column_mask(
        &PixelRect {
            x0: tile.x0,
            y0: 0,
            x1: tile.x1,
            y1: 0,
        },
        tile,
    );
    let mut row_active = [0u16; TILE_PX as usize];
    for m in row_active.iter_mut().take((tile.y1 - tile.y0) as usize) {
        *m = full;
    }
    let mut n_active = ((tile.x1 - tile.x0) * (tile.y1 - tile.y0)) as usize;
    let stop = mode.stop(early_termination);
    let cutoff = mode.cutoff();
    let mut gauss = [0.0f32; TILE_PX as usize];
    for (j, &rank) in list.iter().enumerate() {
        if n_active == 0 {
            break;
        }
        prefetch_splat(splats, list, j + PREFETCH_AHEAD);
        let s = &splats[rank as usize];
        let r = overlap(&s.rect, tile);
        if r.is_empty() {
            continue;
        }
        let cols = column_mask(&r, tile);
        for y in r.y0..r.y1 {
            let ly = (y - tile.y0) as usize;
            let live = row_active[ly] & cols;
            if live == 0 {
                continue;
            }
            let mut bits = live & row_gauss(s, y as f32 + 0.5, tile.x0, cutoff, live, &mut gauss);
            while bits != 0 {
                let lx = bits.trailing_zeros() as usize;
                bits &= bits - 1;
                let Some((alpha, _)) = alpha_of(s.opacity, gauss[lx], mode) else {
                    continue;
                };
                let p = ly * TILE_PX as usize + lx;
                let t_next = transmittance[p] * (1.0 - alpha);
                if t_next < stop {
                    row_active[ly] &= !(1u16 << lx);
                    n_active -= 1;
                    flags[j] |= ENTRY_STOPS;
                    continue;
                }
                transmittance[p] = t_next;
                flags[j] |= ENTRY_BLENDS;
            }
        }
    }
}

/// Pixel gradients for one tile, read from image-layout buffers.
pub struct PixelGradsView<'a> {
    pub width: usize,
    pub d_color: &'a [f32],
    pub d_alpha: Option<&'a [f32]>,
    pub d_depth: Option<&'a [f32]>,
}

/// Forward state of one tile that backward needs.
pub struct TileForwardState<'a> {
    pub transmittance: &'a [f32],
    pub last: &'a [u32],
}

/// The backward pass's own inputs and output, beside the shared [`TileInputs`].
struct BackwardPass<'a> {
    state: TileForwardState<'a>,
    grads: &'a PixelGradsView<'a>,
    records: &'a mut [f32],
    /// False evaluates every lane group the splat's rectangle meets (the reference the
    /// tests compare the skip with).
    skip_unreached: bool,
}

/// Backward of one tile: writes one gradient record (`REC_CHANNELS + n_channels` values)
/// per list entry into `records` (which holds exactly this tile's entries).
#[allow(clippy::too_many_arguments)]
pub fn blend_tile_backward(
    tile: &PixelRect,
    list: &[u32],
    splats: &[Splat],
    splat_channels: &[f32],
    n_channels: usize,
    background: &[f32],
    mode: AlphaMode,
    state: TileForwardState,
    grads: &PixelGradsView,
    records: &mut [f32],
) {
    let inp = TileInputs {
        tile,
        list,
        splats,
        splat_channels,
        n_channels,
        background,
        mode,
    };
    backward_entry(
        &inp,
        BackwardPass {
            state,
            grads,
            records,
            skip_unreached: true,
        },
    );
}

/// [`blend_tile_backward`] with the lane-group skip selectable.
fn backward_entry(inp: &TileInputs, pass: BackwardPass) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { backward_avx2(inp, pass) };
        return;
    }
    backward_dispatch(inp, pass);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn backward_avx2(inp: &TileInputs, pass: BackwardPass) {
    backward_dispatch(inp, pass);
}

/// Picks a build with the channel count fixed at compile time for the common counts,
/// and the alpha mode.
#[inline(always)]
fn backward_dispatch(inp: &TileInputs, pass: BackwardPass) {
    macro_rules! go {
        ($n:literal) => {
            if inp.mode.smooth {
                backward_lanes::<$n, true>(inp, pass)
            } else {
                backward_lanes::<$n, false>(inp, pass)
            }
        };
    }
    match inp.n_channels {
        1 => go!(1),
        3 => go!(3),
        4 => go!(4),
        _ => go!(0),
    }
}

/// [`alpha_of`] for a lane already known to pass the cutoff: the same operations, no
/// branch on the lane, so eight lanes evaluate together.
#[inline(always)]
fn alpha_lane<const SMOOTH: bool>(o: f32, gauss: f32) -> (f32, f32) {
    let raw = o * gauss;
    let clamped = raw > ALPHA_MAX;
    let alpha_c = if clamped { ALPHA_MAX } else { raw };
    let (alpha, d_alpha) = if SMOOTH && alpha_c < SMOOTH_HI {
        let u = (alpha_c - SMOOTH_LO) / (SMOOTH_HI - SMOOTH_LO);
        let ramp = u * u * (3.0 - 2.0 * u);
        let d_ramp = 6.0 * u * (1.0 - u) / (SMOOTH_HI - SMOOTH_LO);
        (alpha_c * ramp, ramp + alpha_c * d_ramp)
    } else {
        (alpha_c, 1.0)
    };
    (alpha, if clamped { 0.0 } else { d_alpha })
}

type Lanes = [f32; LANE_GROUP];

/// The 8 lanes of a tile-local plane starting at pixel `p0`.
#[inline(always)]
fn lanes(plane: &[f32], p0: usize) -> &Lanes {
    plane[p0..p0 + LANE_GROUP]
        .try_into()
        .expect("a lane group lies inside its tile")
}

#[inline(always)]
fn lanes_mut(plane: &mut [f32], p0: usize) -> &mut Lanes {
    (&mut plane[p0..p0 + LANE_GROUP])
        .try_into()
        .expect("a lane group lies inside its tile")
}

/// Fixed-order sum of the lanes (both the SSE and the AVX2 build add in this order).
#[inline(always)]
fn lane_sum(v: &Lanes) -> f32 {
    ((v[0] + v[1]) + (v[2] + v[3])) + ((v[4] + v[5]) + (v[6] + v[7]))
}

/// Backward over 8-lane groups: every lane of a group that holds a kept pixel is computed
/// together, with selects so that the other lanes change nothing. Per-pixel quantities are
/// the same operations as the scalar formulas; per-splat sums are kept per lane and added
/// in a fixed order at the end of each list entry.
#[inline(always)]
fn backward_lanes<const FIXED: usize, const SMOOTH: bool>(inp: &TileInputs, pass: BackwardPass) {
    // `mode` is rebuilt from `SMOOTH` so the alpha branch is resolved at compile time.
    let TileInputs {
        tile,
        list,
        splats,
        splat_channels,
        n_channels,
        background,
        mode: _,
    } = *inp;
    let BackwardPass {
        state,
        grads,
        records,
        skip_unreached,
    } = pass;
    const T: usize = TILE_PX as usize;
    const TP: usize = TILE_PIXELS;
    let mode = AlphaMode { smooth: SMOOTH };
    let nc = if FIXED > 0 { FIXED } else { n_channels };
    let stride = REC_CHANNELS + nc;
    // Planes of TILE_PIXELS values: behind-colour S per channel then depth; d_color per
    // channel.
    let mut behind = vec![0.0f32; TP * (nc + 1)];
    let mut trans = [0.0f32; TP];
    let mut d_color = vec![0.0f32; TP * nc];
    // d_alpha of a pixel times its final transmittance.
    let mut d_alpha_final = [0.0f32; TP];
    let mut d_depth_px = [0.0f32; TP];
    let mut last = [0u32; TP];
    let mut row_max_last = [0u32; T];
    for y in tile.y0..tile.y1 {
        let ly = (y - tile.y0) as usize;
        for x in tile.x0..tile.x1 {
            let p = ly * T + (x - tile.x0) as usize;
            let pix = y as usize * grads.width + x as usize;
            let t_final = state.transmittance[p];
            trans[p] = t_final;
            for k in 0..nc {
                behind[k * TP + p] = t_final * background[k];
                d_color[k * TP + p] = grads.d_color[pix * nc + k];
            }
            if let Some(da) = grads.d_alpha {
                d_alpha_final[p] = da[pix] * t_final;
            }
            if let Some(dd) = grads.d_depth {
                d_depth_px[p] = dd[pix];
            }
            last[p] = state.last[p];
            row_max_last[ly] = row_max_last[ly].max(state.last[p]);
        }
    }
    let max_last = row_max_last.iter().copied().max().unwrap_or(0) as usize;
    records[max_last * stride..].fill(0.0);
    let mut acc_ch = vec![[0.0f32; LANE_GROUP]; nc];
    let mut gauss = [0.0f32; T];
    let cutoff = mode.cutoff();
    for j in (0..max_last).rev() {
        let rank = list[j] as usize;
        if let Some(ahead) = j.checked_sub(PREFETCH_AHEAD) {
            prefetch_splat(splats, list, ahead);
        }
        let s = &splats[rank];
        let ch = &splat_channels[rank * nc..rank * nc + nc];
        let rec = &mut records[j * stride..(j + 1) * stride];
        let r = overlap(&s.rect, tile);
        if r.is_empty() {
            rec.fill(0.0);
            continue;
        }
        let cols = column_mask(&r, tile);
        // Per-lane sums: mean x, mean y, conic a, b, c, opacity, depth; then channels.
        let mut acc = [[0.0f32; LANE_GROUP]; REC_CHANNELS];
        acc_ch.fill([0.0; LANE_GROUP]);
        let [ca, cb, cc] = s.conic;
        let o = s.opacity;
        let dx0 = s.mean_px[0] - (tile.x0 as f32 + 0.5);
        let j_u32 = j as u32;
        for y in r.y0..r.y1 {
            let ly = (y - tile.y0) as usize;
            if j_u32 >= row_max_last[ly] {
                continue;
            }
            // Only the pixels that blended something at or behind this entry can have
            // blended it: a lane group without one changes nothing (every lane would add
            // a zero), so it is not evaluated at all.
            let last_row: &[u32; T] = last[ly * T..(ly + 1) * T].try_into().expect("one tile row");
            let mut reach = 0u32;
            for (lx, &l) in last_row.iter().enumerate() {
                reach |= u32::from(j_u32 < l) << lx;
            }
            let live = if skip_unreached {
                cols & reach as u16
            } else {
                cols
            };
            if live == 0 {
                continue;
            }
            let py = y as f32 + 0.5;
            let bits = live & row_gauss(s, py, tile.x0, cutoff, live, &mut gauss);
            let dy = s.mean_px[1] - py;
            for gi in 0..T / LANE_GROUP {
                let group_bits = (bits >> (gi * LANE_GROUP)) & 0xff;
                if group_bits == 0 {
                    continue;
                }
                let p0 = ly * T + gi * LANE_GROUP;
                let g: &Lanes = gauss[gi * LANE_GROUP..(gi + 1) * LANE_GROUP]
                    .try_into()
                    .expect("two groups per row");
                let last_l = &last[p0..p0 + LANE_GROUP];
                let mut on = [false; LANE_GROUP];
                for i in 0..LANE_GROUP {
                    on[i] = (group_bits >> i) & 1 != 0 && j_u32 < last_l[i];
                }
                let mut alpha = [0.0f32; LANE_GROUP];
                let mut d_alpha_d_raw = [0.0f32; LANE_GROUP];
                for i in 0..LANE_GROUP {
                    (alpha[i], d_alpha_d_raw[i]) = alpha_lane::<SMOOTH>(o, g[i]);
                }
                let mut inv = [0.0f32; LANE_GROUP];
                let mut t = [0.0f32; LANE_GROUP];
                let mut w = [0.0f32; LANE_GROUP];
                {
                    let tr = lanes_mut(&mut trans, p0);
                    for i in 0..LANE_GROUP {
                        inv[i] = 1.0 / (1.0 - alpha[i]);
                        t[i] = tr[i] * inv[i];
                        tr[i] = if on[i] { t[i] } else { tr[i] };
                        w[i] = alpha[i] * t[i];
                    }
                }
                let mut d_alpha = [0.0f32; LANE_GROUP];
                for k in 0..nc {
                    let c = ch[k];
                    let dc = lanes(&d_color, k * TP + p0);
                    let a = &mut acc_ch[k];
                    let bh = lanes_mut(&mut behind, k * TP + p0);
                    for i in 0..LANE_GROUP {
                        a[i] += if on[i] { w[i] * dc[i] } else { 0.0 };
                        d_alpha[i] += dc[i] * (t[i] * c - bh[i] * inv[i]);
                        bh[i] = if on[i] { bh[i] + w[i] * c } else { bh[i] };
                    }
                }
                {
                    let gd = lanes(&d_depth_px, p0);
                    let bh = lanes_mut(&mut behind, nc * TP + p0);
                    let z = s.depth;
                    for i in 0..LANE_GROUP {
                        acc[REC_DEPTH][i] += if on[i] { w[i] * gd[i] } else { 0.0 };
                        d_alpha[i] += gd[i] * (t[i] * z - bh[i] * inv[i]);
                        bh[i] = if on[i] { bh[i] + w[i] * z } else { bh[i] };
                    }
                }
                let da_final = lanes(&d_alpha_final, p0);
                for i in 0..LANE_GROUP {
                    let d_a = d_alpha[i] + da_final[i] * inv[i];
                    let d_raw = if on[i] { d_a * d_alpha_d_raw[i] } else { 0.0 };
                    let d_power = d_raw * o * g[i];
                    let dx = dx0 - (gi * LANE_GROUP + i) as f32;
                    acc[REC_OPACITY][i] += d_raw * g[i];
                    acc[REC_MEAN_X][i] += d_power * (ca * dx + cb * dy);
                    acc[REC_MEAN_Y][i] += d_power * (cb * dx + cc * dy);
                    acc[REC_CONIC][i] += d_power * 0.5 * dx * dx;
                    acc[REC_CONIC + 1][i] += d_power * dx * dy;
                    acc[REC_CONIC + 2][i] += d_power * 0.5 * dy * dy;
                }
            }
        }
        // The power derivatives enter the mean and conic gradients with a minus sign.
        rec[REC_MEAN_X] = -lane_sum(&acc[REC_MEAN_X]);
        rec[REC_MEAN_Y] = -lane_sum(&acc[REC_MEAN_Y]);
        for k in 0..3 {
            rec[REC_CONIC + k] = -lane_sum(&acc[REC_CONIC + k]);
        }
        rec[REC_OPACITY] = lane_sum(&acc[REC_OPACITY]);
        rec[REC_DEPTH] = lane_sum(&acc[REC_DEPTH]);
        for (dst, a) in rec[REC_CHANNELS..].iter_mut().zip(&acc_ch) {
            *dst = lane_sum(a);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const NC: usize = 2;

    /// Perturbs one splat quantity (splats, channels, step).
    type Bump<'a> = &'a dyn Fn(&mut [Splat], &mut [f32], f32);

    fn tile() -> PixelRect {
        PixelRect {
            x0: 16,
            y0: 32,
            x1: 32,
            y1: 48,
        }
    }

    /// Five wide splats, each clipped by its rectangle to a few pixels where its alpha is
    /// far above 1/255, stacked so that the central pixels stop early (hard mode):
    /// T = 0.05, 2.5e-3, 1.25e-4 after three, and the fourth (raw alpha 0.9) would take
    /// it to 1.25e-5 < 1e-4.
    fn splats() -> (Vec<Splat>, Vec<f32>) {
        let rect = |x0, y0, x1, y1| PixelRect { x0, y0, x1, y1 };
        let s = |mx: f32, my: f32, o: f32, z: f32, r: PixelRect| Splat {
            mean_px: [mx, my],
            conic: [0.004, 0.001, 0.006],
            opacity: o,
            depth: z,
            rect: r,
        };
        let splats = vec![
            s(20.0, 36.0, 0.96, 1.0, rect(18, 34, 24, 40)),
            s(22.0, 37.0, 0.96, 1.5, rect(20, 35, 26, 41)),
            s(21.0, 38.0, 0.96, 2.0, rect(19, 36, 25, 42)),
            s(23.0, 36.5, 0.9, 2.5, rect(17, 33, 27, 43)),
            s(20.5, 39.0, 0.6, 3.0, rect(16, 32, 30, 46)),
        ];
        let channels = vec![0.9, 0.1, 0.2, 0.7, 0.5, 0.5, 0.3, 0.8, 0.6, 0.4];
        (splats, channels)
    }

    type TileImages = (Vec<f32>, Vec<f32>, Vec<f32>, Vec<u32>);

    /// Blends `list` over tile `t` (background `[0.25, 0.75]`).
    fn forward_on(
        t: &PixelRect,
        list: &[u32],
        splats: &[Splat],
        channels: &[f32],
        mode: AlphaMode,
        early_termination: bool,
    ) -> TileImages {
        let mut color = vec![0.0; TILE_PIXELS * NC];
        let mut depth = vec![0.0; TILE_PIXELS];
        let mut trans = vec![0.0; TILE_PIXELS];
        let mut last = vec![0; TILE_PIXELS];
        blend_tile_forward(
            t,
            list,
            splats,
            channels,
            NC,
            &[0.25, 0.75],
            mode,
            early_termination,
            TileForwardOut {
                color: &mut color,
                depth: &mut depth,
                transmittance: &mut trans,
                last: &mut last,
            },
        );
        (color, depth, trans, last)
    }

    fn render_tile(splats: &[Splat], channels: &[f32], early_termination: bool) -> TileImages {
        let list: Vec<u32> = (0..splats.len() as u32).collect();
        let hard = AlphaMode { smooth: false };
        forward_on(&tile(), &list, splats, channels, hard, early_termination)
    }

    /// Loss weights in image layout for an image 48 wide, 48 high (the tile is inside).
    fn weights() -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let mut state = 99u32;
        let mut next = || {
            state = state.wrapping_mul(1664525).wrapping_add(1013904223);
            (state >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        let n = 48 * 48;
        let c: Vec<f32> = (0..n * NC).map(|_| next()).collect();
        let a: Vec<f32> = (0..n).map(|_| next()).collect();
        let d: Vec<f32> = (0..n).map(|_| next()).collect();
        (c, a, d)
    }

    fn loss(splats: &[Splat], channels: &[f32], early_termination: bool) -> f64 {
        let (wc, wa, wd) = weights();
        let (color, depth, trans, _) = render_tile(splats, channels, early_termination);
        let t = tile();
        let mut sum = 0.0f64;
        for y in t.y0..t.y1 {
            for x in t.x0..t.x1 {
                let p = ((y - t.y0) * TILE_PX + (x - t.x0)) as usize;
                let pix = (y * 48 + x) as usize;
                for k in 0..NC {
                    sum += (wc[pix * NC + k] * color[p * NC + k]) as f64;
                }
                sum += (wa[pix] * (1.0 - trans[p])) as f64 + (wd[pix] * depth[p]) as f64;
            }
        }
        sum
    }

    #[test]
    fn fast_exp_is_accurate_and_safe() {
        let mut worst = 0.0f64;
        let mut x = -87.0f32;
        while x < 10.0 {
            let exact = (x as f64).exp();
            worst = worst.max(((fast_exp(x) as f64) - exact).abs() / exact);
            x += 0.0013;
        }
        assert!(worst < 3e-7, "relative error {worst}");
        assert_eq!(fast_exp(0.0), 1.0);
        assert!(fast_exp(-1e30) > 0.0 && fast_exp(-1e30) < 1e-37);
        assert!(fast_exp(f32::NAN).is_finite());
        assert!(fast_exp(f32::NEG_INFINITY) < 1e-37);
        assert!(fast_exp(1e30).is_finite());
    }

    /// Hard mode, early termination on and off: backward matches central differences of
    /// every splat quantity (on: the stopped splats get exactly zero; off: the stack is
    /// blended past T = 1e-4 and the same check holds). The rectangles keep every kept
    /// alpha far from 1/255 and the stop margins are large, so steps of 1e-3 (relative)
    /// never change which splats a pixel keeps. Tolerance 1e-2 relative plus 1e-3 absolute
    /// covers f32 noise of the ~1e-6 loss rounding over 2h.
    fn check_backward_against_finite_differences(
        splats: &[Splat],
        channels: &[f32],
        early_termination: bool,
    ) {
        let n = splats.len();
        let list: Vec<u32> = (0..n as u32).collect();
        let (_, _, trans, last) = render_tile(splats, channels, early_termination);
        let (wc, wa, wd) = weights();
        let mut records = vec![f32::NAN; n * (REC_CHANNELS + NC)];
        blend_tile_backward(
            &tile(),
            &list,
            splats,
            channels,
            NC,
            &[0.25, 0.75],
            AlphaMode { smooth: false },
            TileForwardState {
                transmittance: &trans,
                last: &last,
            },
            &PixelGradsView {
                width: 48,
                d_color: &wc,
                d_alpha: Some(&wa),
                d_depth: Some(&wd),
            },
            &mut records,
        );
        let stride = REC_CHANNELS + NC;
        for i in 0..n {
            let rec = &records[i * stride..(i + 1) * stride];
            let check = |name: &str, an: f32, bump: Bump| {
                let h = 1e-3f32;
                let (mut sp, mut ch) = (splats.to_vec(), channels.to_vec());
                bump(&mut sp, &mut ch, h);
                let plus = loss(&sp, &ch, early_termination);
                let (mut sp, mut ch) = (splats.to_vec(), channels.to_vec());
                bump(&mut sp, &mut ch, -h);
                let minus = loss(&sp, &ch, early_termination);
                let fd = (plus - minus) / (2.0 * h as f64);
                let tol = 1e-3 + 1e-2 * fd.abs().max(an.abs() as f64);
                assert!(
                    (fd - an as f64).abs() < tol,
                    "early {early_termination} splat {i} {name}: fd {fd} analytic {an}"
                );
            };
            check("mean x", rec[REC_MEAN_X], &|s, _, h| s[i].mean_px[0] += h);
            check("mean y", rec[REC_MEAN_Y], &|s, _, h| s[i].mean_px[1] += h);
            // Conic entries are ~5e-3: perturb them relatively.
            for k in 0..3 {
                let an = rec[REC_CONIC + k] * 1e-3;
                check("conic", an, &|s, _, h| s[i].conic[k] += h * 1e-3);
            }
            check("opacity", rec[REC_OPACITY], &|s, _, h| s[i].opacity += h);
            check("depth", rec[REC_DEPTH], &|s, _, h| s[i].depth += h);
            for k in 0..NC {
                check("channel", rec[REC_CHANNELS + k], &|_, c, h| {
                    c[i * NC + k] += h
                });
            }
        }
    }

    #[test]
    fn hard_mode_backward_matches_finite_differences_with_early_stop() {
        let (splats, channels) = splats();
        let (_, _, trans, last) = render_tile(&splats, &channels, true);
        // The stack really stops early in some pixels and not in others.
        assert!(trans.iter().any(|&t| t < 2e-4 && t > 1e-4));
        assert!(last.contains(&5));
        check_backward_against_finite_differences(&splats, &channels, true);
    }

    /// Early termination off: the pixels that stopped above now blend the fourth splat
    /// (T down to ~1.25e-5), and the backward is still the exact gradient.
    #[test]
    fn hard_mode_backward_matches_finite_differences_without_early_stop() {
        let (splats, channels) = splats();
        let (color_on, _, trans_on, _) = render_tile(&splats, &channels, true);
        let (color_off, _, trans_off, _) = render_tile(&splats, &channels, false);
        assert!(trans_off.iter().all(|&t| t >= TRANSMITTANCE_FLOOR));
        assert!(trans_off.iter().any(|&t| t < TRANSMITTANCE_STOP));
        assert!(trans_on.iter().all(|&t| t >= TRANSMITTANCE_STOP));
        // The difference per pixel is bounded by the residual transmittance of the stopped
        // pixel times the largest |channel - background| (here 0.75 - 0.1 = 0.65).
        let mut differ = 0;
        for p in 0..TILE_PIXELS {
            for k in 0..NC {
                let d = (color_on[p * NC + k] - color_off[p * NC + k]).abs();
                assert!(d <= trans_on[p] * 0.65 + 1e-6, "pixel {p}: {d}");
                differ += usize::from(d > 0.0);
            }
        }
        assert!(differ > 0);
        check_backward_against_finite_differences(&splats, &channels, false);
    }

    /// A stack of 40 near-opaque splats: with early termination off the transmittance
    /// stops at the normal-float floor instead of underflowing, so the backward's rebuilt
    /// `T_i` keep full precision and the front splats' gradients still match.
    #[test]
    fn deep_stack_without_early_stop_keeps_exact_gradients() {
        let rect = PixelRect {
            x0: 18,
            y0: 34,
            x1: 22,
            y1: 38,
        };
        let splats: Vec<Splat> = (0..40)
            .map(|i| Splat {
                mean_px: [20.0 + 0.05 * i as f32, 36.0 - 0.03 * i as f32],
                conic: [0.004, 0.001, 0.006],
                opacity: 0.97,
                depth: 1.0 + 0.1 * i as f32,
                rect,
            })
            .collect();
        let channels: Vec<f32> = (0..40 * NC).map(|i| 0.1 + 0.02 * (i % 37) as f32).collect();
        let (_, _, trans, last) = render_tile(&splats, &channels, false);
        let inside = ((36 - 32) * TILE_PX + (20 - 16)) as usize;
        assert!(trans[inside] >= TRANSMITTANCE_FLOOR && trans[inside] < 1e-30);
        assert!(last[inside] > 20 && last[inside] < 40);
        check_backward_against_finite_differences(&splats, &channels, false);
    }

    /// Renders `list` (a subset of the splats' indices, in order) over the test tile.
    fn render_list(list: &[u32], splats: &[Splat], channels: &[f32]) -> TileImages {
        forward_on(
            &tile(),
            list,
            splats,
            channels,
            AlphaMode { smooth: false },
            true,
        )
    }

    /// Four tile-wide layers: raw alpha 0.99, 0.98 (T = 2e-4), 0.9 (would take every pixel
    /// to 2e-5 < 1e-4: it stops them all and is blended nowhere), 0.3; and a faint splat
    /// below the cutoff everywhere. The flags name the stopper, the list without the
    /// zero-flag entries renders the same bits, and without the stopper too the last
    /// layer would be blended (so stoppers must stay in a compacted list).
    #[test]
    fn contribution_flags_keep_stoppers_and_drop_only_silent_entries() {
        let wide = |o: f32, z: f32| Splat {
            mean_px: [24.0, 40.0],
            conic: [1e-6, 0.0, 1e-6],
            opacity: o,
            depth: z,
            rect: tile(),
        };
        let splats = vec![
            wide(1.0, 1.0),
            wide(0.003, 1.5),
            wide(0.98, 2.0),
            wide(0.9, 3.0),
            wide(0.3, 4.0),
        ];
        let channels: Vec<f32> = (0..splats.len() * NC).map(|i| 0.1 * i as f32).collect();
        let all: Vec<u32> = (0..splats.len() as u32).collect();
        let mut flags = vec![0u8; all.len()];
        tile_contributions(
            &tile(),
            &all,
            &splats,
            AlphaMode { smooth: false },
            true,
            &mut flags,
        );
        assert_eq!(flags, [ENTRY_BLENDS, 0, ENTRY_BLENDS, ENTRY_STOPS, 0]);
        let kept: Vec<u32> = all
            .iter()
            .copied()
            .filter(|&j| flags[j as usize] != 0)
            .collect();
        let (c_all, d_all, t_all, l_all) = render_list(&all, &splats, &channels);
        let (c_kept, d_kept, t_kept, l_kept) = render_list(&kept, &splats, &channels);
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&c_all), bits(&c_kept));
        assert_eq!(bits(&d_all), bits(&d_kept));
        assert_eq!(bits(&t_all), bits(&t_kept));
        // `last` counts list positions: entry 2 of the full list is entry 1 of the kept one.
        assert!(l_all.iter().all(|&l| l == 3));
        assert!(l_kept.iter().all(|&l| l == 2));
        let blenders: Vec<u32> = vec![0, 2, 4];
        let (c_wrong, ..) = render_list(&blenders, &splats, &channels);
        assert_ne!(bits(&c_all), bits(&c_wrong));
    }
    /// Random splats over the test tile (some clipped by the tile's edge, some tiny,
    /// faint or near-opaque), in a random depth order.
    fn random_splats(seed: u64, count: usize, nc: usize) -> (Vec<Splat>, Vec<f32>) {
        let mut rng = crate::rng::SplitMix64::new(seed);
        let t = tile();
        let splats: Vec<Splat> = (0..count)
            .map(|_| {
                let mx = rng.uniform(t.x0 as f32 - 6.0, t.x1 as f32 + 6.0);
                let my = rng.uniform(t.y0 as f32 - 6.0, t.y1 as f32 + 6.0);
                let sx = rng.uniform(0.3, 8.0);
                let sy = rng.uniform(0.3, 8.0);
                let rho = rng.uniform(-0.8, 0.8);
                // Conic of a covariance with these sigmas and correlation.
                let det = sx * sx * sy * sy * (1.0 - rho * rho);
                let conic = [sy * sy / det, -rho * sx * sy / det, sx * sx / det];
                let ext_x = 3.5 * sx;
                let ext_y = 3.5 * sy;
                let clip = |v: f32| v.clamp(0.0, 64.0) as u32;
                let opacity = match rng.uniform(0.0, 1.0) {
                    u if u < 0.15 => rng.uniform(0.002, 0.01),
                    u if u < 0.4 => rng.uniform(0.95, 1.0),
                    _ => rng.uniform(0.05, 0.95),
                };
                Splat {
                    mean_px: [mx, my],
                    conic,
                    opacity,
                    depth: rng.uniform(0.5, 9.0),
                    rect: PixelRect {
                        x0: clip((mx - ext_x).floor()),
                        y0: clip((my - ext_y).floor()),
                        x1: clip((mx + ext_x).ceil() + 1.0),
                        y1: clip((my + ext_y).ceil() + 1.0),
                    },
                }
            })
            .collect();
        let channels = (0..count * nc).map(|_| rng.uniform(-0.5, 1.5)).collect();
        (splats, channels)
    }

    /// The backward's skip of lane groups no pixel of which blended anything at or behind
    /// an entry writes the same records, bit for bit, as evaluating every group the
    /// splat's rectangle meets (random tiles: clipped, tiny, faint and near-opaque splats;
    /// early termination on and off, smooth mode, a partial tile).
    #[test]
    fn skipping_unreached_lane_groups_writes_the_same_records() {
        let mut partial = tile();
        partial.x1 = partial.x0 + 11;
        partial.y1 = partial.y0 + 5;
        let (wc, wa, wd) = weights();
        let mut skipped_somewhere = false;
        for seed in 0..12u64 {
            for (smooth, early_termination) in [(false, true), (false, false), (true, true)] {
                for t in [tile(), partial] {
                    let count = 20 + 37 * (seed as usize % 4);
                    let (splats, channels) = random_splats(seed * 31 + 7, count, NC);
                    let list: Vec<u32> = (0..count as u32).collect();
                    let mode = AlphaMode { smooth };
                    let (_, _, trans, last) =
                        forward_on(&t, &list, &splats, &channels, mode, early_termination);
                    let grads = PixelGradsView {
                        width: 48,
                        d_color: &wc,
                        d_alpha: Some(&wa),
                        d_depth: Some(&wd),
                    };
                    let run = |skip: bool| {
                        let mut records = vec![f32::NAN; count * (REC_CHANNELS + NC)];
                        backward_entry(
                            &TileInputs {
                                tile: &t,
                                list: &list,
                                splats: &splats,
                                splat_channels: &channels,
                                n_channels: NC,
                                background: &[0.25, 0.75],
                                mode,
                            },
                            BackwardPass {
                                state: TileForwardState {
                                    transmittance: &trans,
                                    last: &last,
                                },
                                grads: &grads,
                                records: &mut records,
                                skip_unreached: skip,
                            },
                        );
                        records.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                    };
                    assert_eq!(run(true), run(false), "seed {seed}, smooth {smooth}");
                    // Some pixel stopped in front of a splat that still reaches it.
                    skipped_somewhere |= last.iter().any(|&l| l > 0 && (l as usize) < count / 2);
                }
            }
        }
        assert!(skipped_somewhere);
    }
}
