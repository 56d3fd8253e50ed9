//! A view's geometry before any channel is read ([`PreparedView`]): projection, depth
//! order and tile bins, and the alpha-only walk that finds the contributing Gaussians and
//! compacts the tile lists to the entries that change a pixel.
//!
//! Invariants: the compacted lists keep, per tile, the kept entries in their original
//! order and, per rank, its entries in tile order (as [`bin::bin_tiles`] does), so the
//! blend and the backward over them give the same bits as over the full lists.

use std::sync::OnceLock;
use std::time::Instant;

use rayon::prelude::*;

use super::bin::{self, PixelRect, TileBins, TileGrid};
use super::blend::{self, AlphaMode, Splat};
use super::{
    camera_frame, depth_order, ms_since, project_splats_with, ForwardTimings, GaussianView,
    RasterError, RasterSettings,
};
#[cfg(doc)]
use super::{render_prepared, RenderOutput};
use crate::camera::Camera;

/// The geometry of one view, before any channel is read: projection, depth order and tile
/// bins. [`PreparedView::contributing`] finds the Gaussians the blend will read, so a
/// caller can compute channels (e.g. network outputs) for those alone and hand them to
/// [`render_prepared`], which blends without projecting again.
#[derive(Clone, Debug)]
pub struct PreparedView {
    pub(super) camera: Camera,
    pub(super) settings: RasterSettings,
    pub(super) mode: AlphaMode,
    pub(super) n_gaussians: usize,
    pub(super) grid: TileGrid,
    /// Splats in depth order (rank), and the Gaussian of each rank.
    pub(super) splats: Vec<Splat>,
    pub(super) gaussian_of_rank: Vec<u32>,
    pub(super) bins: TileBins,
    /// Per Gaussian, from the projection (0 when culled).
    pub(super) radii_px: Vec<f32>,
    /// Filled by the first [`PreparedView::contributing`]; the blend then walks these lists.
    pub(super) compact: OnceLock<CompactLists>,
    /// Projection and sort/bin times (`blend_ms` is 0 here).
    pub timings: ForwardTimings,
}

/// The tile lists without the entries that change no pixel of their tile, found by the
/// alpha-only pass ([`blend::tile_contributions`]): an entry is kept when it is blended into
/// a pixel of its tile or ends a pixel's blend there. Every pixel meets the same kept
/// entries in the same order, with the same transmittance before each, so the forward
/// blend over these lists is the same operations as over the full ones, and the backward
/// (which walks a list back to front, changing a pixel only at entries blended into it)
/// writes records that differ only by the records of the dropped entries, which are all
/// zero: the per-Gaussian sums, which start at +0.0, are the same bits without them.
#[derive(Clone, Debug)]
pub(super) struct CompactLists {
    pub(super) bins: TileBins,
    /// Per rank: blended into at least one pixel (the flag [`blend::ENTRY_BLENDS`]).
    blended_rank: Vec<bool>,
}

/// Projection, depth sort and binning of `gaussians` (channels in the view, if any, are
/// only checked for finiteness: a Gaussian with a non-finite channel is culled).
pub(super) fn prepare(
    camera: &Camera,
    gaussians: &GaussianView,
    settings: &RasterSettings,
) -> Result<PreparedView, RasterError> {
    let frame = camera_frame(camera, settings.near_m)?;
    let n = gaussians.check()?;
    let mode = AlphaMode {
        smooth: settings.smooth_cutoff,
    };
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    let grid = TileGrid::new(width, height);
    if let Some(selection) = &settings.blend_tiles {
        if selection.image_size() != (width, height) {
            return Err(RasterError::InvalidSettings(
                "blend_tiles was built for another image size",
            ));
        }
    }

    let t0 = Instant::now();
    let projected = project_splats_with(
        &frame,
        gaussians,
        mode,
        width,
        height,
        settings.cull_outside_frustum,
    );
    let project_ms = ms_since(t0);

    let t1 = Instant::now();
    let gaussian_of_rank = depth_order(&projected.splats);
    let splats: Vec<Splat> = gaussian_of_rank
        .iter()
        .filter_map(|&g| projected.splats[g as usize])
        .collect();
    let rects: Vec<PixelRect> = splats.iter().map(|s| s.rect).collect();
    let total_entries: usize = rects.iter().map(|r| grid.tile_count(r)).sum();
    if total_entries >= u32::MAX as usize {
        return Err(RasterError::TooLarge("more than u32::MAX tile entries"));
    }
    let bins = bin::bin_tiles(&grid, &rects);
    let sort_bin_ms = ms_since(t1);
    Ok(PreparedView {
        camera: *camera,
        settings: settings.clone(),
        mode,
        n_gaussians: n,
        grid,
        splats,
        gaussian_of_rank,
        bins,
        radii_px: projected.radii_px,
        compact: OnceLock::new(),
        timings: ForwardTimings {
            project_ms,
            sort_bin_ms,
            blend_ms: 0.0,
        },
    })
}

/// Projects, depth-sorts and bins the Gaussians of `geometry` for `camera` (its channels
/// are ignored: they come later, to [`render_prepared`]).
pub fn prepare_view(
    camera: &Camera,
    geometry: &GaussianView,
    settings: &RasterSettings,
) -> Result<PreparedView, RasterError> {
    let bare = GaussianView {
        channels: &[],
        n_channels: 0,
        ..*geometry
    };
    prepare(camera, &bare, settings)
}

impl PreparedView {
    pub fn n_gaussians(&self) -> usize {
        self.n_gaussians
    }

    /// Per Gaussian: survived culling and touches the image (the Gaussians a render
    /// projects; [`RenderOutput::visible`] is the same set).
    pub fn survived(&self) -> Vec<bool> {
        let mut out = vec![false; self.n_gaussians];
        for &g in &self.gaussian_of_rank {
            out[g as usize] = true;
        }
        out
    }

    /// Number of (tile, Gaussian) pairs the blend walks.
    pub fn tile_entry_count(&self) -> usize {
        self.bins.tile_ranks.len()
    }

    /// Per Gaussian: blended into at least one pixel, i.e. its alpha passes the cutoff
    /// there before the pixel's transmittance stops (an alpha-only pass over the tiles,
    /// rayon). The blend and its backward read the channels of these Gaussians only:
    /// channels of the others may hold anything finite without changing a single bit of
    /// the image or of any gradient.
    ///
    /// The first call also keeps the compacted tile lists (only the entries that change
    /// some pixel of their tile, see `CompactLists`): [`render_prepared`] then blends those
    /// and the backward walks them, with the same bits as the full lists.
    pub fn contributing(&self) -> Vec<bool> {
        let compact = self.compact.get_or_init(|| self.compact_lists());
        let mut out = vec![false; self.n_gaussians];
        for (&g, &blended) in self.gaussian_of_rank.iter().zip(&compact.blended_rank) {
            out[g as usize] = blended;
        }
        out
    }

    /// The alpha-only pass over every tile (rayon) and the lists without the entries that
    /// change no pixel (serial, in tile order, so each rank's entries stay in tile order
    /// as in [`bin::bin_tiles`]).
    fn compact_lists(&self) -> CompactLists {
        let grid = &self.grid;
        let bins = &self.bins;
        let n_tiles = grid.n_tiles();
        let mut entry_flags = vec![0u8; bins.tile_ranks.len()];
        let mut per_tile: Vec<&mut [u8]> = Vec::with_capacity(n_tiles);
        let mut rest: &mut [u8] = &mut entry_flags;
        for t in 0..n_tiles {
            let (head, tail) = rest.split_at_mut(bins.tile_offsets[t + 1] - bins.tile_offsets[t]);
            per_tile.push(head);
            rest = tail;
        }
        per_tile.into_par_iter().enumerate().for_each(|(t, flags)| {
            let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
            blend::tile_contributions(
                &grid.tile_rect(t),
                list,
                &self.splats,
                self.mode,
                self.settings.early_termination,
                flags,
            );
        });
        let n_ranks = self.splats.len();
        let mut blended_rank = vec![false; n_ranks];
        let mut rank_counts = vec![0usize; n_ranks];
        let mut tile_offsets = Vec::with_capacity(n_tiles + 1);
        let mut tile_ranks = Vec::new();
        tile_offsets.push(0);
        for t in 0..n_tiles {
            let entries = bins.tile_offsets[t]..bins.tile_offsets[t + 1];
            for (&flag, &rank) in entry_flags[entries.clone()]
                .iter()
                .zip(&bins.tile_ranks[entries])
            {
                if flag != 0 {
                    tile_ranks.push(rank);
                    rank_counts[rank as usize] += 1;
                    blended_rank[rank as usize] |= flag & blend::ENTRY_BLENDS != 0;
                }
            }
            tile_offsets.push(tile_ranks.len());
        }
        let mut rank_offsets = Vec::with_capacity(n_ranks + 1);
        let mut sum = 0usize;
        rank_offsets.push(0);
        for &c in &rank_counts {
            sum += c;
            rank_offsets.push(sum);
        }
        let mut cursor = rank_offsets[..n_ranks].to_vec();
        let mut entry_of_rank = vec![0u32; tile_ranks.len()];
        for (entry, &rank) in tile_ranks.iter().enumerate() {
            entry_of_rank[cursor[rank as usize]] = entry as u32;
            cursor[rank as usize] += 1;
        }
        CompactLists {
            bins: TileBins {
                tile_offsets,
                tile_ranks,
                rank_offsets,
                entry_of_rank,
            },
            blended_rank,
        }
    }
}
