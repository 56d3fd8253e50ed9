//! The forward blend of one tile ([`blend_tile_forward`]): front to back over the tile's
//! list, whole tile rows at a time, on the widest build of the row loops the CPU runs.
//!
//! Invariants: per pixel, the operations of the scalar formulas in list order (the same
//! bits on every build); a pixel stops before a splat that would take its transmittance
//! below the stop, and records one past the last list index it blended.

use super::lanes::{self, Portable, RowOps};
use super::{
    column_mask, entry_rows, full_rows, overlap, prefetch_splat, row_mut, row_step, AlphaMode, Isa,
    TileInputs, PREFETCH_AHEAD, ROW,
};
use crate::raster::bin::TILE_PIXELS;

/// One tile's forward outputs, tile-local pixel index `ly * 16 + lx`.
pub struct TileForwardOut<'a> {
    pub color: &'a mut [f32],
    pub depth: &'a mut [f32],
    pub transmittance: &'a mut [f32],
    /// One past the list index of the last splat blended into each pixel.
    pub last: &'a mut [u32],
}

/// Blends one tile front to back. `list` holds splat ranks in depth order.
///
/// Runs the widest build of the tile loops the CPU supports (AVX-512, AVX2, portable):
/// the same bits on each.
pub fn blend_tile_forward(inp: &TileInputs, early_termination: bool, out: TileForwardOut) {
    forward_with(Isa::best(), inp, early_termination, out);
}

/// [`blend_tile_forward`] on the build `isa` (one the CPU supports).
pub(super) fn forward_with(
    isa: Isa,
    inp: &TileInputs,
    early_termination: bool,
    out: TileForwardOut,
) {
    multiversion!(isa, ops, (inp: &TileInputs, early_termination: bool, out: TileForwardOut) => {
        forward_dispatch(ops, inp, early_termination, out);
    });
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
