//! Tile rasterizer for Gaussians: projection, binning, blending, and the backward pass.
//!
//! Two ways in: [`render`] / [`render_with`] do everything in one call; or
//! [`prepare_view`] projects, sorts and bins the geometry alone, [`PreparedView::contributing`]
//! tells which Gaussians the blend will read (an alpha-only walk of the tiles), and
//! [`render_prepared`] blends channels computed afterwards (e.g. by a network, for those
//! Gaussians only) without projecting again. Both give the same bits. The alpha-only walk
//! also compacts the tile lists to the entries that change some pixel of their tile
//! (blended there, or ending a pixel's blend); after it the blend and the backward walk
//! only those (about a fifth of the entries on a dense 100K-Gaussian scene), same bits.
//!
//! Stages (each a reusable function, so a shadow pass from a light camera is an
//! addition): [`project_splats`] (per Gaussian, rayon), depth sort + [`bin::bin_tiles`]
//! (serial radix/counting sorts), [`blend::blend_tile_forward`] (rayon over 16x16 tiles).
//! Backward: [`blend::blend_tile_backward`] per tile writes one gradient record per
//! tile-list entry; records are summed per Gaussian in tile order and pushed through
//! [`project::project_backward`] (rayon over blocks of Gaussians, each Gaussian's sum in
//! one task, so the thread count changes no bit). The forward's tile-major buffers go to
//! the image layout by bands of tile rows (rayon), one tile row per copy.
//!
//! Invariants:
//! - outputs are pixel-major, row-major: `color[(y * W + x) * C + c]`;
//! - `depth` is the alpha-weighted camera z, NOT normalised by alpha (divide by `alpha`
//!   for the mean depth of what was hit); background depth is 0;
//! - culled or invalid Gaussians (non-finite values, `|q|^2 < 1e-6`, z < near, opacity
//!   below the cutoff, no pixel touched) have no effect on the output and get zero
//!   gradients; nothing non-finite reaches the outputs or the gradients (a Gaussian whose
//!   gradient is non-finite gets zeros, counted in `GaussianGrads::dropped_nonfinite`);
//! - results do not depend on the thread count at all: every reduction runs in a fixed
//!   order (tile order per Gaussian), and tiles never share memory.

pub mod bin;
pub mod blend;
pub mod project;

mod backward;
mod forward;
mod prepared;
mod settings;
mod splats;
mod untile;

#[cfg(test)]
mod tests;

use std::time::Instant;

pub use backward::{
    render_backward, render_backward_with, BackwardTimings, GaussianGrads, PixelGrads,
};
pub use forward::{
    render, render_prepared, render_with, ForwardTimings, RasterWorkspace, RenderOutput,
};
pub use prepared::{prepare_view, PreparedView};
pub use settings::{GaussianView, RasterError, RasterSettings, MAX_IMAGE_SIDE_PX};
pub(crate) use splats::splat_rect;
pub use splats::{camera_frame, depth_order, project_splats, project_splats_with, ProjectedSet};

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}
