//! Tile-major forward buffers to the image layout: one band of tile rows per rayon task,
//! one tile row (up to 16 pixels) per copy.
//!
//! Invariant: only copies (and `alpha = 1 - T`), so the bits do not depend on the split.

use rayon::prelude::*;

use super::bin::{TileGrid, TILE_PIXELS, TILE_PX};

/// Tile-major forward buffers (`TILE_PIXELS` pixels per tile, row-major in the tile).
pub(super) struct TileMajor<'a> {
    pub(super) color: &'a [f32],
    /// Values per tile in `color` (at least `TILE_PIXELS * nc`).
    pub(super) color_chunk: usize,
    pub(super) depth: &'a [f32],
    pub(super) transmittance: &'a [f32],
}

/// Copies the tile-major buffers into the image layout (`alpha = 1 - T`), one band of
/// tile rows per rayon task, one tile row (up to 16 pixels) per copy. Only copies: the
/// bits do not depend on the split.
pub(super) fn untile(
    grid: &TileGrid,
    nc: usize,
    tiles: TileMajor,
    color: &mut [f32],
    alpha: &mut [f32],
    depth: &mut [f32],
) {
    let w = grid.width as usize;
    let tile_px = TILE_PX as usize;
    let tiles_x = grid.tiles_x as usize;
    let band = tile_px * w;
    // Empty colour bands when there are no channels (a chunk size of zero is not allowed).
    let color_bands: Vec<&mut [f32]> = if nc > 0 {
        color.chunks_mut(band * nc).collect()
    } else {
        (0..grid.tiles_y).map(|_| <&mut [f32]>::default()).collect()
    };
    let bands: Vec<_> = color_bands
        .into_iter()
        .zip(alpha.chunks_mut(band).zip(depth.chunks_mut(band)))
        .collect();
    bands
        .into_par_iter()
        .enumerate()
        .for_each(|(ty, (color_band, (alpha_band, depth_band)))| {
            let rows = alpha_band.len() / w;
            for tx in 0..tiles_x {
                let t = ty * tiles_x + tx;
                let x0 = tx * tile_px;
                let cols = tile_px.min(w - x0);
                for ly in 0..rows {
                    let src = t * TILE_PIXELS + ly * tile_px;
                    let dst = ly * w + x0;
                    for (a, &tr) in alpha_band[dst..dst + cols]
                        .iter_mut()
                        .zip(&tiles.transmittance[src..src + cols])
                    {
                        *a = 1.0 - tr;
                    }
                    depth_band[dst..dst + cols].copy_from_slice(&tiles.depth[src..src + cols]);
                    if nc > 0 {
                        let c_src = t * tiles.color_chunk + ly * tile_px * nc;
                        color_band[dst * nc..(dst + cols) * nc]
                            .copy_from_slice(&tiles.color[c_src..c_src + cols * nc]);
                    }
                }
            }
        });
}
