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
//! The tile loops (forward, the alpha-only pass [`tile_contributions`], backward) work on
//! whole tile rows: per list entry, the exponentials of every row the splat meets
//! (`entry_rows`), then per row the 16 lanes' alpha, the masks of the lanes that pass
//! the cutoff, stop and blend, and masked updates of the pixel state. One generic source
//! over `lanes::RowOps`, built for AVX-512 (intrinsics, chosen at run time where the CPU
//! has AVX-512F/BW/VL/DQ), AVX2 and portable (plain arrays). The scalar and 8-lane loops
//! these replaced stay in `reference.rs` (tests only).
//!
//! Invariants:
//! - forward, the alpha-only pass and backward evaluate alpha with the same functions
//!   (`row_exp` and `alpha_row`: [`fast_exp`] and [`alpha_of`] lane by lane), so they
//!   agree bit for bit on which Gaussians each pixel kept;
//! - every build gives the same bits, and the same bits as the replaced loops: each
//!   lane is the scalar formula operation for operation (no fused multiply-adds; the
//!   backward's per-splat sums keep their 8-lane order), checked on random tiles;
//! - a splat is only evaluated inside its rectangle (a conservative bound of where its
//!   alpha reaches the cutoff), so binning never changes the image.
//! - in smooth mode (test-only) the 1/255 step is a C1 ramp `alpha * smoothstep` over
//!   `[0.5/255, 1.5/255]` and the early stop is off, so the image is C1 in the parameters
//!   wherever `o exp(power) < 0.99`.

use super::bin::{PixelRect, TILE_PX};

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

/// Lanes of the backward's per-splat sums (their fixed summation order, [`lane_sum`],
/// dates from 8-lane groups and is kept so that records stay the same bits).
const LANE_GROUP: usize = 8;

/// Pixels of one tile row, one lane each: the unit the tile loops work in (one AVX-512
/// register).
const ROW: usize = TILE_PX as usize;
type Row = [f32; ROW];

mod lanes;
use lanes::RowOps;

/// `exp(power)` of splat `sp` at the pixel centres of row `py`, lane `i` at pixel
/// `x_origin + i`: `power = -0.5 a dx^2 - b dy dx - 0.5 c dy^2`, evaluated in this
/// order for every lane.
#[inline(always)]
fn row_exp<S: RowOps>(ops: S, sp: &Splat, py: f32, x_origin: u32) -> S::F {
    let dy = sp.mean_px[1] - py;
    let [a, b, c] = sp.conic;
    let dx0 = sp.mean_px[0] - (x_origin as f32 + 0.5);
    let base = -0.5 * c * dy * dy;
    let bdy = b * dy;
    let dx = ops.sub(ops.splat(dx0), ops.iota());
    let quad = ops.mul(ops.mul(ops.splat(-0.5 * a), dx), dx);
    let power = ops.add(ops.sub(quad, ops.mul(ops.splat(bdy), dx)), ops.splat(base));
    ops.exp(power)
}

/// `exp(power)` of splat `sp` on the tile rows of `r` (into `gauss[ly]`, tile-local row
/// `ly`), and per row the lanes of `live(ly)` where `o exp(power)` reaches `cutoff` (0
/// for rows without live lanes, which are not evaluated and whose `gauss` is left as it
/// was). Every row's exponential is computed before any row is blended: they are
/// independent, so the core overlaps their long dependency chains instead of waiting on
/// each row's branches.
#[inline(always)]
fn entry_rows<S: RowOps>(
    ops: S,
    sp: &Splat,
    tile: &PixelRect,
    r: &PixelRect,
    cutoff: f32,
    live: impl Fn(usize) -> u16,
    gauss: &mut [S::F; ROW],
) -> [u16; ROW] {
    let mut kept = [0u16; ROW];
    for y in r.y0..r.y1 {
        let ly = (y - tile.y0) as usize;
        let live = live(ly);
        if live == 0 {
            continue;
        }
        let g = row_exp(ops, sp, y as f32 + 0.5, tile.x0);
        kept[ly] = live & ops.ge(ops.mul(ops.splat(sp.opacity), g), ops.splat(cutoff));
        gauss[ly] = g;
    }
    kept
}

#[inline(always)]
fn row_mut(plane: &mut [f32], p0: usize) -> &mut Row {
    (&mut plane[p0..p0 + ROW])
        .try_into()
        .expect("a row lies inside its tile")
}

#[inline(always)]
fn row_ref(plane: &[f32], p0: usize) -> &Row {
    plane[p0..p0 + ROW]
        .try_into()
        .expect("a row lies inside its tile")
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

/// Which build of the tile loops runs. The loops are one source, generic over
/// [`RowOps`]; every build rounds identically and gives the same bits (tests compare them
/// on random tiles).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Isa {
    /// AVX-512 intrinsics, one register per tile row.
    #[cfg(target_arch = "x86_64")]
    Avx512(lanes::Avx512),
    /// The portable rows compiled for AVX2.
    #[cfg(target_arch = "x86_64")]
    Avx2,
    Portable,
}

impl Isa {
    /// The widest build this CPU runs.
    fn best() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            if let Some(ops) = lanes::Avx512::detect() {
                return Isa::Avx512(ops);
            }
            if avx2_build_supported() {
                return Isa::Avx2;
            }
        }
        Isa::Portable
    }
}

/// The CPU has every feature the AVX2 build of the tile loops enables.
#[cfg(target_arch = "x86_64")]
fn avx2_build_supported() -> bool {
    std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
        && std::arch::is_x86_feature_detected!("bmi1")
        && std::arch::is_x86_feature_detected!("bmi2")
        && std::arch::is_x86_feature_detected!("popcnt")
}

/// Instantiates `$body` (an expression over the parameters and `$ops`, a [`RowOps`])
/// once per [`Isa`] and calls the build `$isa` names.
macro_rules! multiversion {
    ($isa:expr, $ops:ident, ($($arg:ident: $ty:ty),*) => $body:expr) => {{
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512dq,avx2,fma,bmi1,bmi2,popcnt")]
        unsafe fn avx512($ops: lanes::Avx512, $($arg: $ty),*) {
            $body
        }
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2,fma,bmi1,bmi2,popcnt")]
        unsafe fn avx2($ops: Portable, $($arg: $ty),*) {
            $body
        }
        fn portable($ops: Portable, $($arg: $ty),*) {
            $body
        }
        match $isa {
            // SAFETY: an `Avx512` exists only where the CPU has those features.
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512(ops) => unsafe { avx512(ops, $($arg),*) },
            // SAFETY: `Isa::Avx2` is only chosen where the CPU has those features
            // (`avx2_build_supported`).
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { avx2(Portable, $($arg),*) },
            Isa::Portable => portable(Portable, $($arg),*),
        }
    }};
}

/// One list entry on one tile row, for the `kept` pixels: its alpha, the transmittance
/// before it, and the pixels it stops (the new transmittance would fall below `stop`) and
/// blends into, whose transmittance it updates in `t_row`. The forward and the alpha-only
/// pass both take this step, so they agree bit for bit on every pixel's sequence. No
/// branches on the masks (an empty mask changes nothing): they are hard to predict, and a
/// miss would stall the rows in flight.
struct RowStep<F> {
    alpha: F,
    t: F,
    stops: u16,
    blends: u16,
}

#[inline(always)]
fn row_step<S: RowOps, const SMOOTH: bool>(
    ops: S,
    opacity: f32,
    gauss: S::F,
    t_row: &mut Row,
    kept: u16,
    stop: f32,
) -> RowStep<S::F> {
    let raw = ops.mul(ops.splat(opacity), gauss);
    let t = ops.load(t_row);
    let alpha = alpha_row::<S, SMOOTH>(ops, raw).0;
    let t_next = ops.mul(t, ops.sub(ops.splat(1.0), alpha));
    let stops = kept & ops.lt(t_next, ops.splat(stop));
    let blends = kept & !stops;
    ops.store_masked(t_row, blends, t_next);
    RowStep {
        alpha,
        t,
        stops,
        blends,
    }
}

/// [`alpha_of`] on a row, for lanes already known to pass the cutoff: `(alpha, d alpha /
/// d (o gauss))`, the same operations, selects instead of branches.
#[inline(always)]
fn alpha_row<S: RowOps, const SMOOTH: bool>(ops: S, raw: S::F) -> (S::F, S::F) {
    let clamped = ops.gt(raw, ops.splat(ALPHA_MAX));
    let alpha_c = ops.select(clamped, ops.splat(ALPHA_MAX), raw);
    let one = ops.splat(1.0);
    let zero = ops.splat(0.0);
    if SMOOTH {
        let ramped = ops.lt(alpha_c, ops.splat(SMOOTH_HI));
        let width = ops.splat(SMOOTH_HI - SMOOTH_LO);
        let u = ops.div(ops.sub(alpha_c, ops.splat(SMOOTH_LO)), width);
        let ramp = ops.mul(
            ops.mul(u, u),
            ops.sub(ops.splat(3.0), ops.mul(ops.splat(2.0), u)),
        );
        let d_ramp = ops.div(ops.mul(ops.mul(ops.splat(6.0), u), ops.sub(one, u)), width);
        let alpha = ops.select(ramped, ops.mul(alpha_c, ramp), alpha_c);
        let d_alpha = ops.select(ramped, ops.add(ramp, ops.mul(alpha_c, d_ramp)), one);
        (alpha, ops.select(clamped, zero, d_alpha))
    } else {
        (alpha_c, ops.select(clamped, zero, one))
    }
}

/// One tile's blending inputs, the same for its forward and its backward
/// ([`blend_tile_forward`], [`blend_tile_backward`]), bundled so that the caller and the
/// multiversioning layers below (`*_with` -> `*_dispatch` -> `*_rows`) each pass one
/// reference.
#[derive(Clone, Copy)]
pub struct TileInputs<'a> {
    pub tile: &'a PixelRect,
    /// Splat ranks in depth order.
    pub list: &'a [u32],
    pub splats: &'a [Splat],
    /// `n_channels` values per splat.
    pub splat_channels: &'a [f32],
    pub n_channels: usize,
    /// `n_channels` values behind the splats.
    pub background: &'a [f32],
    pub mode: AlphaMode,
}
/// Per tile row, the columns inside the tile (all rows of a partial tile's rectangle).
#[inline(always)]
fn full_rows(tile: &PixelRect) -> [u16; ROW] {
    let full = column_mask(
        &PixelRect {
            x0: tile.x0,
            y0: 0,
            x1: tile.x1,
            y1: 0,
        },
        tile,
    );
    let mut rows = [0u16; ROW];
    for m in rows.iter_mut().take((tile.y1 - tile.y0) as usize) {
        *m = full;
    }
    rows
}

type Lanes = [f32; LANE_GROUP];

/// Fixed-order sum of the lanes.
#[inline(always)]
fn lane_sum(v: &Lanes) -> f32 {
    ((v[0] + v[1]) + (v[2] + v[3])) + ((v[4] + v[5]) + (v[6] + v[7]))
}

mod backward;
mod contributions;
mod forward;

pub use backward::{blend_tile_backward, PixelGradsView, TileForwardState};
pub use contributions::{tile_contributions, ENTRY_BLENDS, ENTRY_STOPS};
pub use forward::{blend_tile_forward, TileForwardOut};

#[cfg(test)]
mod reference;

#[cfg(test)]
mod tests;
