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

/// Lanes of the backward's per-splat sums (their fixed summation order, [`lane_sum`],
/// dates from 8-lane groups and is kept so that records stay the same bits).
const LANE_GROUP: usize = 8;

/// Pixels of one tile row, one lane each: the unit the tile loops work in (one AVX-512
/// register).
const ROW: usize = TILE_PX as usize;
type Row = [f32; ROW];

mod lanes;
use lanes::{Portable, RowOps};

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

/// One tile's blending inputs, bundled so that the multiversioning layers below
/// (`*_with` -> `*_dispatch` -> `*_rows`) each forward one reference.
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
/// Runs the widest build of the tile loops the CPU supports (AVX-512, AVX2, portable):
/// the same bits on each.
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
    forward_with(Isa::best(), &inp, early_termination, out);
}

/// [`blend_tile_forward`] on the build `isa` (one the CPU supports).
fn forward_with(isa: Isa, inp: &TileInputs, early_termination: bool, out: TileForwardOut) {
    multiversion!(isa, ops, (inp: &TileInputs, early_termination: bool, out: TileForwardOut) => {
        forward_dispatch(ops, inp, early_termination, out)
    })
}

/// Picks a build with the channel count fixed at compile time for the common counts,
/// and the alpha mode.
#[inline(always)]
fn forward_dispatch<S: RowOps>(
    ops: S,
    inp: &TileInputs,
    early_termination: bool,
    out: TileForwardOut,
) {
    macro_rules! go {
        ($n:literal) => {
            if inp.mode.smooth {
                forward_rows::<S, $n, true>(ops, inp, early_termination, out)
            } else {
                forward_rows::<S, $n, false>(ops, inp, early_termination, out)
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

/// Forward over whole tile rows: per list entry and row, the 16 lanes' alphas, the lanes
/// that pass the cutoff, those that stop there and those that blend, then the blend
/// itself with selects so that other lanes keep their values. Per pixel these are the
/// operations of the scalar formulas in list order. `FIXED > 0`: the channel count is
/// `FIXED` (loops unroll); 0: `n_channels`.
#[inline(always)]
fn forward_rows<S: RowOps, const FIXED: usize, const SMOOTH: bool>(
    ops: S,
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
        mode: _,
    } = *inp;
    let mode = AlphaMode { smooth: SMOOTH };
    let nc = if FIXED > 0 { FIXED } else { n_channels };
    // Channel planes (channel k at k * TILE_PIXELS), interleaved into `out.color` at the end.
    let mut color = vec![0.0f32; TILE_PIXELS * nc];
    out.depth.fill(0.0);
    out.transmittance.fill(1.0);
    out.last.fill(0);
    let mut row_active = full_rows(tile);
    let mut n_active = ((tile.x1 - tile.x0) * (tile.y1 - tile.y0)) as usize;
    let stop = mode.stop(early_termination);
    let cutoff = mode.cutoff();
    let mut gauss = [ops.splat(0.0); ROW];
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
        let o = s.opacity;
        let entry_end = j as u32 + 1;
        let kept_rows = entry_rows(
            ops,
            s,
            tile,
            &r,
            cutoff,
            |ly| row_active[ly] & cols,
            &mut gauss,
        );
        for y in r.y0..r.y1 {
            let ly = (y - tile.y0) as usize;
            let kept = kept_rows[ly];
            if kept == 0 {
                continue;
            }
            let p0 = ly * ROW;
            let t_row = row_mut(out.transmittance, p0);
            let step = row_step::<S, SMOOTH>(ops, o, gauss[ly], t_row, kept, stop);
            let (alpha, t, stops, blends) = (step.alpha, step.t, step.stops, step.blends);
            row_active[ly] &= !stops;
            n_active -= stops.count_ones() as usize;
            let w = ops.mul(alpha, t);
            for (k, &c) in ch.iter().enumerate() {
                let acc = row_mut(&mut color, k * TILE_PIXELS + p0);
                let sum = ops.add(ops.load(acc), ops.mul(w, ops.splat(c)));
                ops.store_masked(acc, blends, sum);
            }
            let d = row_mut(out.depth, p0);
            let sum = ops.add(ops.load(d), ops.mul(w, ops.splat(s.depth)));
            ops.store_masked(d, blends, sum);
            let last: &mut [u32; ROW] = (&mut out.last[p0..p0 + ROW])
                .try_into()
                .expect("a row lies inside its tile");
            ops.store_u32_masked(last, blends, entry_end);
        }
    }
    let with_background = background.iter().any(|&b| b != 0.0);
    for p in 0..TILE_PIXELS {
        let t = out.transmittance[p];
        for k in 0..nc {
            let c = color[k * TILE_PIXELS + p];
            out.color[p * nc + k] = if with_background {
                c + t * background[k]
            } else {
                c
            };
        }
    }
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
    contributions_with(Isa::best(), &inp, early_termination, flags);
}

/// [`tile_contributions`] on the build `isa` (one the CPU supports).
fn contributions_with(isa: Isa, inp: &TileInputs, early_termination: bool, flags: &mut [u8]) {
    multiversion!(isa, ops, (inp: &TileInputs, early_termination: bool, flags: &mut [u8]) => {
        if inp.mode.smooth {
            contributions_rows::<_, true>(ops, inp, early_termination, flags)
        } else {
            contributions_rows::<_, false>(ops, inp, early_termination, flags)
        }
    })
}

/// [`forward_rows`] without channels or depth: only the transmittance and the flags.
#[inline(always)]
fn contributions_rows<S: RowOps, const SMOOTH: bool>(
    ops: S,
    inp: &TileInputs,
    early_termination: bool,
    flags: &mut [u8],
) {
    let TileInputs {
        tile,
        list,
        splats,
        mode: _,
        ..
    } = *inp;
    let mode = AlphaMode { smooth: SMOOTH };
    flags.fill(0);
    let mut transmittance = [1.0f32; TILE_PIXELS];
    let mut row_active = full_rows(tile);
    let mut n_active = ((tile.x1 - tile.x0) * (tile.y1 - tile.y0)) as usize;
    let stop = mode.stop(early_termination);
    let cutoff = mode.cutoff();
    let mut gauss = [ops.splat(0.0); ROW];
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
        let o = s.opacity;
        let mut flag = 0u8;
        let kept_rows = entry_rows(
            ops,
            s,
            tile,
            &r,
            cutoff,
            |ly| row_active[ly] & cols,
            &mut gauss,
        );
        for y in r.y0..r.y1 {
            let ly = (y - tile.y0) as usize;
            let kept = kept_rows[ly];
            if kept == 0 {
                continue;
            }
            let t_row = row_mut(&mut transmittance, ly * ROW);
            let RowStep { stops, blends, .. } =
                row_step::<S, SMOOTH>(ops, o, gauss[ly], t_row, kept, stop);
            row_active[ly] &= !stops;
            n_active -= stops.count_ones() as usize;
            flag |= (u8::from(stops != 0) * ENTRY_STOPS) | (u8::from(blends != 0) * ENTRY_BLENDS);
        }
        flags[j] = flag;
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

/// [`blend_tile_backward`] with the skip of unreached rows selectable, on the widest build.
fn backward_entry(inp: &TileInputs, pass: BackwardPass) {
    backward_with(Isa::best(), inp, pass);
}

/// The backward on the build `isa` (one the CPU supports).
fn backward_with(isa: Isa, inp: &TileInputs, pass: BackwardPass) {
    multiversion!(isa, ops, (inp: &TileInputs, pass: BackwardPass) => {
        backward_dispatch(ops, inp, pass)
    })
}

/// Picks a build with the channel count fixed at compile time for the common counts,
/// and the alpha mode.
#[inline(always)]
fn backward_dispatch<S: RowOps>(ops: S, inp: &TileInputs, pass: BackwardPass) {
    macro_rules! go {
        ($n:literal) => {
            if inp.mode.smooth {
                backward_rows::<S, $n, true>(ops, inp, pass)
            } else {
                backward_rows::<S, $n, false>(ops, inp, pass)
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

type Lanes = [f32; LANE_GROUP];

/// Fixed-order sum of the lanes.
#[inline(always)]
fn lane_sum(v: &Lanes) -> f32 {
    ((v[0] + v[1]) + (v[2] + v[3])) + ((v[4] + v[5]) + (v[6] + v[7]))
}

/// Backward over whole tile rows: every lane of a row that holds a kept pixel is computed
/// together, with selects so that the other lanes change nothing. Per-pixel quantities are
/// the same operations as the scalar formulas; per-splat sums are kept in 8 lanes
/// (`RowOps::fold`: lane `i` adds pixel `i`, then pixel `i + 8`, the order of the 8-lane
/// groups this replaced) and added in a fixed order at the end of each list entry. A
/// lane that kept nothing adds zeros, which leave the sums' bits as they are (the sums
/// start at +0.0 and round to nearest, so they are never -0.0).
#[inline(always)]
fn backward_rows<S: RowOps, const FIXED: usize, const SMOOTH: bool>(
    ops: S,
    inp: &TileInputs,
    pass: BackwardPass,
) {
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
    let mut row_max_last = [0u32; ROW];
    for y in tile.y0..tile.y1 {
        let ly = (y - tile.y0) as usize;
        for x in tile.x0..tile.x1 {
            let p = ly * ROW + (x - tile.x0) as usize;
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
    let mut acc_ch = vec![ops.half_zero(); nc];
    let cutoff = mode.cutoff();
    let mut gauss = [ops.splat(0.0); ROW];
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
        let mut acc = [ops.half_zero(); REC_CHANNELS];
        acc_ch.fill(ops.half_zero());
        let [ca, cb, cc] = s.conic;
        let o = s.opacity;
        let z = s.depth;
        let dx0 = s.mean_px[0] - (tile.x0 as f32 + 0.5);
        let j_u32 = j as u32;
        // Only the pixels that blended something at or behind this entry can have
        // blended it: a row without one changes nothing (every lane would add a zero),
        // so it is not evaluated at all.
        let mut reach_rows = [0u16; ROW];
        for y in r.y0..r.y1 {
            let ly = (y - tile.y0) as usize;
            if j_u32 < row_max_last[ly] {
                let p0 = ly * ROW;
                let last_row: &[u32; ROW] = last[p0..p0 + ROW].try_into().expect("one tile row");
                reach_rows[ly] = ops.lt_u32(j_u32, last_row);
            }
        }
        let live = |ly: usize| match reach_rows[ly] {
            0 => 0,
            reach if skip_unreached => cols & reach,
            _ => cols,
        };
        let kept_rows = entry_rows(ops, s, tile, &r, cutoff, live, &mut gauss);
        for y in r.y0..r.y1 {
            let ly = (y - tile.y0) as usize;
            let on = kept_rows[ly] & reach_rows[ly];
            if on == 0 {
                continue;
            }
            let p0 = ly * ROW;
            let py = y as f32 + 0.5;
            let g = gauss[ly];
            let raw = ops.mul(ops.splat(o), g);
            let dy = s.mean_px[1] - py;
            let (alpha, d_alpha_d_raw) = alpha_row::<S, SMOOTH>(ops, raw);
            let one = ops.splat(1.0);
            let zero = ops.splat(0.0);
            let tr = row_mut(&mut trans, p0);
            let inv = ops.div(one, ops.sub(one, alpha));
            let t = ops.mul(ops.load(tr), inv);
            ops.store_masked(tr, on, t);
            let w = ops.mul(alpha, t);
            let mut d_alpha = zero;
            for (k, &c) in ch.iter().enumerate() {
                let dc = ops.load(row_ref(&d_color, k * TP + p0));
                let bh_row = row_mut(&mut behind, k * TP + p0);
                let bh = ops.load(bh_row);
                ops.fold(&mut acc_ch[k], ops.select(on, ops.mul(w, dc), zero));
                let c = ops.splat(c);
                let d = ops.mul(dc, ops.sub(ops.mul(t, c), ops.mul(bh, inv)));
                d_alpha = ops.add(d_alpha, d);
                ops.store_masked(bh_row, on, ops.add(bh, ops.mul(w, c)));
            }
            {
                let gd = ops.load(row_ref(&d_depth_px, p0));
                let bh_row = row_mut(&mut behind, nc * TP + p0);
                let bh = ops.load(bh_row);
                ops.fold(&mut acc[REC_DEPTH], ops.select(on, ops.mul(w, gd), zero));
                let z = ops.splat(z);
                let d = ops.mul(gd, ops.sub(ops.mul(t, z), ops.mul(bh, inv)));
                d_alpha = ops.add(d_alpha, d);
                ops.store_masked(bh_row, on, ops.add(bh, ops.mul(w, z)));
            }
            let da_final = ops.load(row_ref(&d_alpha_final, p0));
            let d_a = ops.add(d_alpha, ops.mul(da_final, inv));
            let d_raw = ops.select(on, ops.mul(d_a, d_alpha_d_raw), zero);
            let d_power = ops.mul(ops.mul(d_raw, ops.splat(o)), g);
            let dx = ops.sub(ops.splat(dx0), ops.iota());
            let half_d_power = ops.mul(d_power, ops.splat(0.5));
            ops.fold(&mut acc[REC_OPACITY], ops.mul(d_raw, g));
            let mx = ops.add(ops.mul(ops.splat(ca), dx), ops.splat(cb * dy));
            ops.fold(&mut acc[REC_MEAN_X], ops.mul(d_power, mx));
            let my = ops.add(ops.mul(ops.splat(cb), dx), ops.splat(cc * dy));
            ops.fold(&mut acc[REC_MEAN_Y], ops.mul(d_power, my));
            ops.fold(&mut acc[REC_CONIC], ops.mul(ops.mul(half_d_power, dx), dx));
            let dy_v = ops.splat(dy);
            ops.fold(&mut acc[REC_CONIC + 1], ops.mul(ops.mul(d_power, dx), dy_v));
            ops.fold(
                &mut acc[REC_CONIC + 2],
                ops.mul(ops.mul(half_d_power, dy_v), dy_v),
            );
        }
        // The power derivatives enter the mean and conic gradients with a minus sign.
        rec[REC_MEAN_X] = -lane_sum(&ops.half_lanes(acc[REC_MEAN_X]));
        rec[REC_MEAN_Y] = -lane_sum(&ops.half_lanes(acc[REC_MEAN_Y]));
        for k in 0..3 {
            rec[REC_CONIC + k] = -lane_sum(&ops.half_lanes(acc[REC_CONIC + k]));
        }
        rec[REC_OPACITY] = lane_sum(&ops.half_lanes(acc[REC_OPACITY]));
        rec[REC_DEPTH] = lane_sum(&ops.half_lanes(acc[REC_DEPTH]));
        for (dst, a) in rec[REC_CHANNELS..].iter_mut().zip(&acc_ch) {
            *dst = lane_sum(&ops.half_lanes(*a));
        }
    }
}

#[cfg(test)]
mod reference;

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

    /// The backward's skip of rows no pixel of which blended anything at or behind an
    /// entry writes the same records, bit for bit, as evaluating every row the splat's
    /// rectangle meets (random tiles: clipped, tiny, faint and near-opaque splats; early
    /// termination on and off, smooth mode, a partial tile).
    #[test]
    fn skipping_unreached_rows_writes_the_same_records() {
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

    /// The builds of the tile loops this CPU runs (the portable one always).
    fn builds() -> Vec<Isa> {
        let mut isas = vec![Isa::Portable];
        #[cfg(target_arch = "x86_64")]
        {
            if avx2_build_supported() {
                isas.push(Isa::Avx2);
            }
            if let Some(ops) = lanes::Avx512::detect() {
                isas.push(Isa::Avx512(ops));
            }
        }
        isas
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// Every build of the 16-lane row loops (AVX-512, AVX2, portable) against the scalar
    /// and 8-lane loops they replaced (`reference`), bit for bit: forward colour, depth,
    /// transmittance and last entry, the alpha-only pass's flags, and the backward's
    /// records with the skip of unreached rows on and off. Random tiles (clipped, tiny,
    /// faint and near-opaque splats in random depth order), 0 to 5 channels (the fixed
    /// counts 1, 3, 4 and the general loop), hard mode with early termination on and off,
    /// smooth mode, a full and a partial tile, a background, compacted lists.
    #[test]
    fn row_loops_match_the_reference_bit_for_bit_on_every_build() {
        let mut partial = tile();
        partial.x1 = partial.x0 + 11;
        partial.y1 = partial.y0 + 5;
        let isas = builds();
        assert!(isas.contains(&Isa::best()));
        let mut stopped = 0usize;
        let mut compacted = 0usize;
        for seed in 0..10u64 {
            for nc in 0..=5usize {
                let count = 15 + 29 * ((seed as usize + nc) % 5);
                let (splats, channels) = random_splats(seed * 131 + nc as u64, count, nc);
                let background: Vec<f32> = (0..nc).map(|k| 0.2 * k as f32).collect();
                let mut rng = crate::rng::SplitMix64::new(seed + 1000);
                let n_px = 48 * 48;
                let d_color: Vec<f32> = (0..n_px * nc).map(|_| rng.uniform(-1.0, 1.0)).collect();
                let d_alpha: Vec<f32> = (0..n_px).map(|_| rng.uniform(-1.0, 1.0)).collect();
                let d_depth: Vec<f32> = (0..n_px).map(|_| rng.uniform(-1.0, 1.0)).collect();
                for (smooth, early_termination) in [(false, true), (false, false), (true, false)] {
                    let mode = AlphaMode { smooth };
                    for t in [tile(), partial] {
                        let full: Vec<u32> = (0..count as u32).collect();
                        let inp_full = TileInputs {
                            tile: &t,
                            list: &full,
                            splats: &splats,
                            splat_channels: &channels,
                            n_channels: nc,
                            background: &background,
                            mode,
                        };
                        let mut flags_ref = vec![0u8; count];
                        reference::contributions(&inp_full, early_termination, &mut flags_ref);
                        for &isa in &isas {
                            let mut flags = vec![7u8; count];
                            contributions_with(isa, &inp_full, early_termination, &mut flags);
                            assert_eq!(flags, flags_ref, "{isa:?} seed {seed} nc {nc}");
                        }
                        stopped += flags_ref.iter().filter(|&&f| f & ENTRY_STOPS != 0).count();
                        let kept: Vec<u32> = full
                            .iter()
                            .copied()
                            .filter(|&j| flags_ref[j as usize] != 0)
                            .collect();
                        compacted += count - kept.len();
                        for list in [&full, &kept] {
                            let inp = TileInputs { list, ..inp_full };
                            let run_forward = |isa: Option<Isa>| {
                                let mut color = vec![f32::NAN; TILE_PIXELS * nc];
                                let mut depth = vec![f32::NAN; TILE_PIXELS];
                                let mut trans = vec![f32::NAN; TILE_PIXELS];
                                let mut last = vec![u32::MAX; TILE_PIXELS];
                                let out = TileForwardOut {
                                    color: &mut color,
                                    depth: &mut depth,
                                    transmittance: &mut trans,
                                    last: &mut last,
                                };
                                match isa {
                                    Some(isa) => forward_with(isa, &inp, early_termination, out),
                                    None => reference::forward::<0>(&inp, early_termination, out),
                                }
                                (color, depth, trans, last)
                            };
                            let (c_ref, d_ref, t_ref, l_ref) = run_forward(None);
                            for &isa in &isas {
                                let (c, d, tr, l) = run_forward(Some(isa));
                                let what = format!("{isa:?} seed {seed} nc {nc} mode {mode:?}");
                                assert_eq!(bits(&c), bits(&c_ref), "{what}: colour");
                                assert_eq!(bits(&d), bits(&d_ref), "{what}: depth");
                                assert_eq!(bits(&tr), bits(&t_ref), "{what}: transmittance");
                                assert_eq!(l, l_ref, "{what}: last");
                            }
                            let grads = PixelGradsView {
                                width: 48,
                                d_color: &d_color,
                                d_alpha: Some(&d_alpha),
                                d_depth: Some(&d_depth),
                            };
                            let run_backward = |isa: Option<Isa>, skip: bool| {
                                let mut records = vec![f32::NAN; list.len() * (REC_CHANNELS + nc)];
                                let pass = BackwardPass {
                                    state: TileForwardState {
                                        transmittance: &t_ref,
                                        last: &l_ref,
                                    },
                                    grads: &grads,
                                    records: &mut records,
                                    skip_unreached: skip,
                                };
                                match (isa, smooth) {
                                    (Some(isa), _) => backward_with(isa, &inp, pass),
                                    (None, true) => reference::backward::<0, true>(&inp, pass),
                                    (None, false) => reference::backward::<0, false>(&inp, pass),
                                }
                                bits(&records)
                            };
                            let r_ref = run_backward(None, true);
                            assert_eq!(run_backward(None, false), r_ref);
                            for &isa in &isas {
                                for skip in [true, false] {
                                    assert_eq!(
                                        run_backward(Some(isa), skip),
                                        r_ref,
                                        "{isa:?} seed {seed} nc {nc} mode {mode:?} skip {skip}"
                                    );
                                }
                            }
                        }
                    }
                }
            }
        }
        // The random tiles do stop pixels early and do drop entries from the lists.
        assert!(stopped > 50 && compacted > 50, "{stopped} {compacted}");
    }
}
