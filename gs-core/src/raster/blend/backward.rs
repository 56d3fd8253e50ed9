//! The backward blend of one tile ([`blend_tile_backward`]): walks the list back to
//! front, rebuilding each pixel's transmittance from the final one, and writes one
//! gradient record (`REC_CHANNELS + n_channels` values) per list entry.
//!
//! Invariants: each tile writes only its own records (every value of them), so tiles
//! never share memory; per-pixel quantities are the scalar formulas' operations and the
//! per-splat sums keep their 8-lane order, so every build gives the same bits.

use super::lanes::{self, Portable, RowOps};
use super::{
    alpha_row, column_mask, entry_rows, lane_sum, overlap, prefetch_splat, row_mut, row_ref,
    AlphaMode, Isa, TileInputs, PREFETCH_AHEAD, REC_CHANNELS, REC_CONIC, REC_DEPTH, REC_MEAN_X,
    REC_MEAN_Y, REC_OPACITY, ROW,
};
use crate::raster::bin::TILE_PIXELS;

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
pub(super) struct BackwardPass<'a> {
    pub(super) state: TileForwardState<'a>,
    pub(super) grads: &'a PixelGradsView<'a>,
    pub(super) records: &'a mut [f32],
    /// False evaluates every lane group the splat's rectangle meets (the reference the
    /// tests compare the skip with).
    pub(super) skip_unreached: bool,
}

/// Backward of one tile: writes one gradient record (`REC_CHANNELS + n_channels` values)
/// per list entry into `records` (which holds exactly this tile's entries).
pub fn blend_tile_backward(
    inp: &TileInputs,
    state: TileForwardState,
    grads: &PixelGradsView,
    records: &mut [f32],
) {
    backward_entry(
        inp,
        BackwardPass {
            state,
            grads,
            records,
            skip_unreached: true,
        },
    );
}

/// [`blend_tile_backward`] with the skip of unreached rows selectable, on the widest build.
pub(super) fn backward_entry(inp: &TileInputs, pass: BackwardPass) {
    backward_with(Isa::best(), inp, pass);
}

/// The backward on the build `isa` (one the CPU supports).
pub(super) fn backward_with(isa: Isa, inp: &TileInputs, pass: BackwardPass) {
    multiversion!(isa, ops, (inp: &TileInputs, pass: BackwardPass) => {
        backward_dispatch(ops, inp, pass);
    });
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
