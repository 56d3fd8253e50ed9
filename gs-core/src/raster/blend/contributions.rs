//! The alpha-only walk of one tile ([`tile_contributions`]): which list entries blend
//! into or stop some pixel, for the compacted tile lists.
//!
//! Invariant: the walk, the alpha and the transmittance are those of the forward blend
//! operation for operation, so an entry without [`ENTRY_BLENDS`] has its channels read by
//! neither pass, and dropping the zero-flag entries changes no pixel's sequence.

#[cfg(doc)]
use super::blend_tile_forward;
use super::lanes::{self, Portable, RowOps};
use super::{
    column_mask, entry_rows, full_rows, overlap, prefetch_splat, row_mut, row_step, AlphaMode, Isa,
    RowStep, Splat, TileInputs, PREFETCH_AHEAD, ROW,
};
use crate::raster::bin::{PixelRect, TILE_PIXELS};

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
pub(super) fn contributions_with(
    isa: Isa,
    inp: &TileInputs,
    early_termination: bool,
    flags: &mut [u8],
) {
    multiversion!(isa, ops, (inp: &TileInputs, early_termination: bool, flags: &mut [u8]) => {
        if inp.mode.smooth {
            contributions_rows::<_, true>(ops, inp, early_termination, flags);
        } else {
            contributions_rows::<_, false>(ops, inp, early_termination, flags);
        }
    });
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
