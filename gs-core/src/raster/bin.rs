//! Depth sort and 16x16 tile binning.
//!
//! Splats are first sorted by depth (a stable LSD radix sort on the f32 bit pattern,
//! which orders positive floats correctly), then scattered into per-tile lists by a
//! stable counting sort, so each tile's list is front to back and ties keep the
//! Gaussians' original order. The result depends only on the inputs, never on threads.
//!
//! Invariants:
//! - `tile_offsets` has `n_tiles + 1` entries; tile `t` owns `tile_ranks[tile_offsets[t]..tile_offsets[t+1]]`;
//! - a rank's entries are listed in `entry_of_rank[rank_offsets[r]..rank_offsets[r+1]]`
//!   (positions in `tile_ranks`), in tile order;
//! - a [`TileSelection`] built from a pixel mask holds every tile with a pixel within
//!   `reach_px` (Chebyshev distance) of a mask pixel above zero, and no other.

use std::sync::Arc;

/// Tile edge, pixels.
pub const TILE_PX: u32 = 16;
/// Pixels per tile.
pub const TILE_PIXELS: usize = (TILE_PX * TILE_PX) as usize;

/// A pixel rectangle `[x0, x1) x [y0, y1)`, already clamped to the image.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PixelRect {
    pub x0: u32,
    pub y0: u32,
    pub x1: u32,
    pub y1: u32,
}

impl PixelRect {
    pub fn is_empty(&self) -> bool {
        self.x0 >= self.x1 || self.y0 >= self.y1
    }
}

/// The tiles of an image that the blend runs on (the others are left at the background).
/// Built from a foreground mask, so a masked loss's gradient is zero on every tile left
/// out (see `RasterSettings::blend_tiles`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TileSelection {
    width: u32,
    height: u32,
    /// Per tile, row-major over the tile grid: blended.
    active: Arc<[bool]>,
}

/// Why a [`TileSelection`] could not be built.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum TileSelectionError {
    /// The mask does not have one value per pixel.
    Length { expected: usize, got: usize },
    /// Width or height is zero.
    EmptyImage,
}

impl std::fmt::Display for TileSelectionError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TileSelectionError::Length { expected, got } => {
                write!(f, "mask has {got} values, the image has {expected} pixels")
            }
            TileSelectionError::EmptyImage => write!(f, "image has no pixels"),
        }
    }
}

impl std::error::Error for TileSelectionError {}

impl TileSelection {
    /// Every tile with a pixel within `reach_px` (in x and in y) of a pixel whose `mask`
    /// value is above zero (NaN counts as zero). `mask` is `width * height`, row-major. A
    /// loss that reads rendered pixels up to `reach_px` away from the mask (a windowed
    /// SSIM) needs that reach; a loss on the mask pixels alone needs 0.
    pub fn from_mask(
        mask: &[f32],
        width: u32,
        height: u32,
        reach_px: u32,
    ) -> Result<TileSelection, TileSelectionError> {
        if width == 0 || height == 0 {
            return Err(TileSelectionError::EmptyImage);
        }
        let (w, h) = (width as usize, height as usize);
        if mask.len() != w * h {
            return Err(TileSelectionError::Length {
                expected: w * h,
                got: mask.len(),
            });
        }
        let grid = TileGrid::new(width, height);
        let tiles_x = grid.tiles_x as usize;
        let tile = TILE_PX as usize;
        let reach = reach_px as usize;
        let mut active = vec![false; grid.n_tiles()];
        for y in 0..h {
            let row = &mask[y * w..(y + 1) * w];
            if !row.iter().any(|&m| m > 0.0) {
                continue;
            }
            let ty0 = y.saturating_sub(reach) / tile;
            let ty1 = (y + reach).min(h - 1) / tile;
            for (x, &m) in row.iter().enumerate() {
                if m > 0.0 {
                    let tx0 = x.saturating_sub(reach) / tile;
                    let tx1 = (x + reach).min(w - 1) / tile;
                    for ty in ty0..=ty1 {
                        active[ty * tiles_x + tx0..=ty * tiles_x + tx1].fill(true);
                    }
                }
            }
        }
        Ok(TileSelection {
            width,
            height,
            active: active.into(),
        })
    }

    /// Image size the selection was built for, pixels.
    pub fn image_size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Tile `t` (row-major over the tile grid) is blended; false beyond the grid.
    pub fn is_active(&self, tile: usize) -> bool {
        self.active.get(tile).copied().unwrap_or(false)
    }

    /// Number of tiles blended.
    pub fn active_count(&self) -> usize {
        self.active.iter().filter(|&&a| a).count()
    }

    /// Number of tiles of the image.
    pub fn n_tiles(&self) -> usize {
        self.active.len()
    }
}

/// Tile grid of an image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileGrid {
    pub width: u32,
    pub height: u32,
    pub tiles_x: u32,
    pub tiles_y: u32,
}

impl TileGrid {
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            tiles_x: width.div_ceil(TILE_PX),
            tiles_y: height.div_ceil(TILE_PX),
        }
    }

    pub fn n_tiles(&self) -> usize {
        self.tiles_x as usize * self.tiles_y as usize
    }

    /// The tile's pixel rectangle, clipped to the image.
    pub fn tile_rect(&self, tile: usize) -> PixelRect {
        let tx = (tile % self.tiles_x as usize) as u32;
        let ty = (tile / self.tiles_x as usize) as u32;
        PixelRect {
            x0: tx * TILE_PX,
            y0: ty * TILE_PX,
            x1: ((tx + 1) * TILE_PX).min(self.width),
            y1: ((ty + 1) * TILE_PX).min(self.height),
        }
    }

    /// Tiles `[tx0, tx1) x [ty0, ty1)` touched by a non-empty pixel rectangle.
    fn tiles_of(&self, r: &PixelRect) -> (u32, u32, u32, u32) {
        (
            r.x0 / TILE_PX,
            r.y0 / TILE_PX,
            r.x1.div_ceil(TILE_PX),
            r.y1.div_ceil(TILE_PX),
        )
    }

    /// Number of tiles a rectangle touches (0 when empty).
    pub fn tile_count(&self, r: &PixelRect) -> usize {
        if r.is_empty() {
            return 0;
        }
        let (x0, y0, x1, y1) = self.tiles_of(r);
        (x1 - x0) as usize * (y1 - y0) as usize
    }
}

/// Stable ascending sort of `keys` (with `values` moved alongside), LSD radix, 11 bits a pass.
pub fn radix_sort_u32(keys: &mut Vec<u32>, values: &mut Vec<u32>) {
    const BITS: u32 = 11;
    const BUCKETS: usize = 1 << BITS;
    let n = keys.len();
    let mut keys_tmp = vec![0u32; n];
    let mut values_tmp = vec![0u32; n];
    let mut shift = 0;
    while shift < 32 {
        let mut counts = vec![0usize; BUCKETS];
        for &k in keys.iter() {
            counts[((k >> shift) as usize) & (BUCKETS - 1)] += 1;
        }
        // Skip passes where every key falls in one bucket (common for the high bits).
        if counts.contains(&n) {
            shift += BITS;
            continue;
        }
        let mut sum = 0;
        for c in counts.iter_mut() {
            let here = *c;
            *c = sum;
            sum += here;
        }
        for i in 0..n {
            let k = keys[i];
            let b = ((k >> shift) as usize) & (BUCKETS - 1);
            keys_tmp[counts[b]] = k;
            values_tmp[counts[b]] = values[i];
            counts[b] += 1;
        }
        std::mem::swap(keys, &mut keys_tmp);
        std::mem::swap(values, &mut values_tmp);
        shift += BITS;
    }
}

/// Per-tile front-to-back lists of splat ranks.
#[derive(Clone, Debug, Default)]
pub struct TileBins {
    pub tile_offsets: Vec<usize>,
    pub tile_ranks: Vec<u32>,
    pub rank_offsets: Vec<usize>,
    pub entry_of_rank: Vec<u32>,
}

/// Bins splats (given in depth order, by rank) into tiles.
pub fn bin_tiles(grid: &TileGrid, rects_by_rank: &[PixelRect]) -> TileBins {
    let n_tiles = grid.n_tiles();
    let mut tile_counts = vec![0usize; n_tiles + 1];
    let mut rank_offsets = Vec::with_capacity(rects_by_rank.len() + 1);
    rank_offsets.push(0);
    let mut total = 0usize;
    for r in rects_by_rank {
        if !r.is_empty() {
            let (x0, y0, x1, y1) = grid.tiles_of(r);
            for ty in y0..y1 {
                let row = ty as usize * grid.tiles_x as usize;
                for tx in x0..x1 {
                    tile_counts[row + tx as usize] += 1;
                }
            }
            total += grid.tile_count(r);
        }
        rank_offsets.push(total);
    }
    let mut tile_offsets = vec![0usize; n_tiles + 1];
    let mut sum = 0;
    for t in 0..n_tiles {
        tile_offsets[t] = sum;
        sum += tile_counts[t];
    }
    tile_offsets[n_tiles] = sum;
    let mut cursor = tile_offsets[..n_tiles].to_vec();
    let mut tile_ranks = vec![0u32; total];
    let mut entry_of_rank = Vec::with_capacity(total);
    for (rank, r) in rects_by_rank.iter().enumerate() {
        if r.is_empty() {
            continue;
        }
        let (x0, y0, x1, y1) = grid.tiles_of(r);
        for ty in y0..y1 {
            let row = ty as usize * grid.tiles_x as usize;
            for tx in x0..x1 {
                let t = row + tx as usize;
                tile_ranks[cursor[t]] = rank as u32;
                entry_of_rank.push(cursor[t] as u32);
                cursor[t] += 1;
            }
        }
    }
    TileBins {
        tile_offsets,
        tile_ranks,
        rank_offsets,
        entry_of_rank,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radix_sort_is_stable_and_ordered() {
        let mut state = 12345u64;
        let mut keys: Vec<u32> = (0..5000)
            .map(|_| {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((state >> 33) as u32) % 700
            })
            .collect();
        let mut values: Vec<u32> = (0..keys.len() as u32).collect();
        let mut expected: Vec<(u32, u32)> =
            keys.iter().copied().zip(values.iter().copied()).collect();
        expected.sort(); // (key, original index) == stable order
        radix_sort_u32(&mut keys, &mut values);
        let got: Vec<(u32, u32)> = keys.into_iter().zip(values).collect();
        assert_eq!(got, expected);
    }

    #[test]
    fn binning_lists_every_touched_tile_in_rank_order() {
        let grid = TileGrid::new(40, 20); // 3 x 2 tiles, ragged edges
        let rects = [
            PixelRect {
                x0: 0,
                y0: 0,
                x1: 40,
                y1: 20,
            },
            PixelRect {
                x0: 15,
                y0: 15,
                x1: 17,
                y1: 17,
            },
            PixelRect::default(),
            PixelRect {
                x0: 33,
                y0: 0,
                x1: 34,
                y1: 1,
            },
        ];
        let bins = bin_tiles(&grid, &rects);
        let list = |t: usize| &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
        assert_eq!(list(0), &[0, 1]);
        assert_eq!(list(1), &[0, 1]);
        assert_eq!(list(2), &[0, 3]);
        assert_eq!(list(3), &[0, 1]);
        assert_eq!(list(4), &[0, 1]);
        assert_eq!(list(5), &[0]);
        assert_eq!(bins.rank_offsets, vec![0, 6, 10, 10, 11]);
        for (rank, w) in bins.rank_offsets.windows(2).enumerate() {
            for &e in &bins.entry_of_rank[w[0]..w[1]] {
                assert_eq!(bins.tile_ranks[e as usize], rank as u32);
            }
        }
    }

    /// Against the definition, pixel by pixel: a tile is selected iff one of its pixels is
    /// within `reach` (in x and y) of a mask pixel above zero; ragged edge tiles included.
    #[test]
    fn tile_selection_matches_its_definition() {
        let (w, h) = (53u32, 37u32);
        let mut mask = vec![0.0f32; (w * h) as usize];
        for (x, y, v) in [(20, 18, 1.0), (52, 0, 0.5), (3, 36, 0.01), (40, 30, -1.0)] {
            mask[y * w as usize + x] = v;
        }
        mask[5] = f32::NAN;
        let grid = TileGrid::new(w, h);
        for reach in [0u32, 1, 5, 16, 100] {
            let sel = TileSelection::from_mask(&mask, w, h, reach).unwrap();
            assert_eq!(sel.n_tiles(), grid.n_tiles());
            for t in 0..grid.n_tiles() {
                let r = grid.tile_rect(t);
                let mut expected = false;
                for y in r.y0..r.y1 {
                    for x in r.x0..r.x1 {
                        for my in 0..h {
                            for mx in 0..w {
                                let m = mask[(my * w + mx) as usize];
                                if m > 0.0 && x.abs_diff(mx) <= reach && y.abs_diff(my) <= reach {
                                    expected = true;
                                }
                            }
                        }
                    }
                }
                assert_eq!(sel.is_active(t), expected, "reach {reach} tile {t}");
            }
        }
        let sel = TileSelection::from_mask(&mask, w, h, 0).unwrap();
        assert_eq!(sel.active_count(), 3);
        assert!(!sel.is_active(grid.n_tiles()));
        assert_eq!(
            TileSelection::from_mask(&mask, w, h + 1, 0),
            Err(TileSelectionError::Length {
                expected: (w * (h + 1)) as usize,
                got: (w * h) as usize
            })
        );
        assert_eq!(
            TileSelection::from_mask(&[], 0, 4, 0),
            Err(TileSelectionError::EmptyImage)
        );
    }
}
