//! The forward pass: blends the tiles of a prepared view (rayon over 16x16 tiles, into
//! tile-major buffers), copies them to the image layout, and keeps what the backward
//! needs ([`RenderOutput`]'s state). Scratch memory lives in a [`RasterWorkspace`].
//!
//! Invariants: outputs are pixel-major, `color[(y * W + x) * C + c]`; tiles never share
//! memory, so the bits do not depend on the thread count; every reused scratch value is
//! overwritten before it is read.

use std::time::Instant;

use rayon::prelude::*;

use super::bin::{TileBins, TileGrid, TILE_PIXELS};
use super::blend::{self, Splat};
use super::prepared::prepare;
use super::untile::{untile, TileMajor};
use super::{ms_since, GaussianView, PreparedView, RasterError, RasterSettings};
#[cfg(doc)]
use super::{render_backward, render_backward_with};
use crate::camera::Camera;

/// Wall-clock split of one forward pass, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ForwardTimings {
    pub project_ms: f64,
    pub sort_bin_ms: f64,
    pub blend_ms: f64,
}

/// What backward needs from the forward pass.
#[derive(Clone, Debug)]
pub(super) struct ForwardState {
    pub(super) camera: Camera,
    pub(super) settings: RasterSettings,
    pub(super) background: Vec<f32>,
    pub(super) n_gaussians: usize,
    pub(super) grid: TileGrid,
    pub(super) splats: Vec<Splat>,
    pub(super) splat_channels: Vec<f32>,
    pub(super) gaussian_of_rank: Vec<u32>,
    /// The tile lists the forward blended: the compacted ones when the view's
    /// [`PreparedView::contributing`] ran, else the full bins. One gradient record per entry.
    pub(super) bins: TileBins,
    /// Entries of the full bins (before any compaction).
    pub(super) n_tile_entries: usize,
    /// Tile-major final transmittance and last-blended index per pixel.
    pub(super) tile_transmittance: Vec<f32>,
    pub(super) tile_last: Vec<u32>,
}

/// Rendered images and per-Gaussian screen data.
#[derive(Clone, Debug)]
pub struct RenderOutput {
    pub width: u32,
    pub height: u32,
    pub n_channels: usize,
    /// `H * W * n_channels`, `(y * W + x) * C + c`.
    pub color: Vec<f32>,
    /// `H * W` accumulated opacity `1 - T_final`.
    pub alpha: Vec<f32>,
    /// `H * W` alpha-weighted camera z (not normalised by alpha).
    pub depth: Vec<f32>,
    /// Per Gaussian: screen radius in pixels beyond which its alpha is below the cutoff
    /// (`sqrt(2 ln(o / cutoff) * lambda_max)`, at most about 3.3 sigma); 0 when culled.
    pub radii_px: Vec<f32>,
    /// Per Gaussian: survived culling and touched at least one tile.
    pub visible: Vec<bool>,
    pub timings: ForwardTimings,
    pub(super) state: ForwardState,
}

impl RenderOutput {
    /// Number of (tile, Gaussian) pairs binned: the rasterizer's work measure (before any
    /// compaction by [`PreparedView::contributing`]).
    pub fn tile_entry_count(&self) -> usize {
        self.state.n_tile_entries
    }

    /// Number of (tile, Gaussian) pairs the blend and its backward walked: the compacted
    /// lists' entries when the view's [`PreparedView::contributing`] ran, else
    /// [`RenderOutput::tile_entry_count`].
    pub fn blended_entry_count(&self) -> usize {
        self.state.bins.tile_ranks.len()
    }
}

fn resolve_background(settings: &RasterSettings, nc: usize) -> Result<Vec<f32>, RasterError> {
    if settings.background.is_empty() {
        return Ok(vec![0.0; nc]);
    }
    if settings.background.len() != nc {
        return Err(RasterError::Length {
            what: "background (one value per channel)",
            expected: nc,
            got: settings.background.len(),
        });
    }
    if !settings.background.iter().all(|v| v.is_finite()) {
        return Err(RasterError::InvalidSettings("background is not finite"));
    }
    Ok(settings.background.clone())
}

/// Scratch memory that [`render_with`] and [`render_backward_with`] reuse from call to
/// call (tile-major forward buffers, backward gradient records). Every reused
/// value is overwritten before it is read, so results are bit-identical to [`render`] and
/// [`render_backward`]; reuse only saves the allocation and the page faults of fresh
/// memory (about 20 MB per call at 960x600). Buffers only grow.
#[derive(Clone, Debug, Default)]
pub struct RasterWorkspace {
    tile_color: Vec<f32>,
    tile_depth: Vec<f32>,
    pub(super) records: Vec<f32>,
}

impl RasterWorkspace {
    /// Frees the backward's gradient records (the largest buffer: one record per tile
    /// entry), keeping the forward's tile buffers. For callers that hold the
    /// workspace across other memory-hungry work and care more about peak memory than
    /// about the backward's page faults.
    pub fn release_backward_buffers(&mut self) {
        self.records = Vec::new();
    }
}

/// The first `len` values of `buf`, growing it (with zeros) when shorter. Values already
/// there are left as they are: callers overwrite or clear what they read.
pub(super) fn scratch(buf: &mut Vec<f32>, len: usize) -> &mut [f32] {
    if buf.len() < len {
        buf.resize(len, 0.0);
    }
    &mut buf[..len]
}

/// Renders `gaussians` from `camera`.
pub fn render(
    camera: &Camera,
    gaussians: &GaussianView,
    settings: &RasterSettings,
) -> Result<RenderOutput, RasterError> {
    render_with(&mut RasterWorkspace::default(), camera, gaussians, settings)
}

/// [`render`] with scratch memory kept in `workspace` between calls.
pub fn render_with(
    workspace: &mut RasterWorkspace,
    camera: &Camera,
    gaussians: &GaussianView,
    settings: &RasterSettings,
) -> Result<RenderOutput, RasterError> {
    // Projection with the channels in view culls Gaussians whose channels are not finite,
    // so the blend below never meets one.
    let prepared = prepare(camera, gaussians, settings)?;
    render_prepared(
        workspace,
        prepared,
        gaussians.channels,
        gaussians.n_channels,
    )
}

/// Blends a prepared view with `n_channels` channels per Gaussian (`channels`,
/// Gaussian-major, for every Gaussian of the view). Same output, bit for bit, as
/// [`render_with`] on a view with these channels, provided every channel the blend reads
/// is finite; a non-finite channel of a projected Gaussian is an error here (a full
/// render would have culled that Gaussian).
pub fn render_prepared(
    workspace: &mut RasterWorkspace,
    prepared: PreparedView,
    channels: &[f32],
    n_channels: usize,
) -> Result<RenderOutput, RasterError> {
    let PreparedView {
        camera,
        settings,
        mode,
        n_gaussians: n,
        grid,
        splats,
        gaussian_of_rank,
        bins,
        radii_px,
        compact,
        timings,
    } = prepared;
    let nc = n_channels;
    let expected = n
        .checked_mul(nc)
        .ok_or(RasterError::TooLarge("channel count overflows"))?;
    if channels.len() != expected {
        return Err(RasterError::Length {
            what: "channels (n_channels per Gaussian)",
            expected,
            got: channels.len(),
        });
    }
    let background = resolve_background(&settings, nc)?;
    let (width, height) = (grid.width, grid.height);
    let mut splat_channels = Vec::with_capacity(gaussian_of_rank.len() * nc);
    for &g in &gaussian_of_rank {
        let g = g as usize;
        let ch = &channels[g * nc..g * nc + nc];
        if !ch.iter().all(|v| v.is_finite()) {
            return Err(RasterError::NonFiniteChannel { gaussian: g });
        }
        splat_channels.extend_from_slice(ch);
    }
    let ForwardTimings {
        project_ms,
        sort_bin_ms,
        ..
    } = timings;

    // Visibility from the full bins (touched a tile), before they give way to the
    // compacted lists.
    let mut visible = vec![false; n];
    for w in bins.rank_offsets.windows(2).zip(&gaussian_of_rank) {
        let ((start, end), &g) = ((w.0[0], w.0[1]), w.1);
        visible[g as usize] = end > start;
    }
    let n_tile_entries = bins.tile_ranks.len();
    let bins = match compact.into_inner() {
        Some(compact) => compact.bins,
        None => bins,
    };

    let t2 = Instant::now();
    let n_tiles = grid.n_tiles();
    // Tile-major buffers; a colour chunk of at least one float per pixel keeps the chunk
    // size non-zero when there are no channels.
    let color_chunk = TILE_PIXELS * nc.max(1);
    // Every tile's blend clears its own part of these first.
    let tile_color = scratch(&mut workspace.tile_color, n_tiles * color_chunk);
    let tile_depth = scratch(&mut workspace.tile_depth, n_tiles * TILE_PIXELS);
    let mut tile_transmittance = vec![0.0f32; n_tiles * TILE_PIXELS];
    let mut tile_last = vec![0u32; n_tiles * TILE_PIXELS];
    let blend_tiles = settings.blend_tiles.as_ref();
    tile_color
        .par_chunks_mut(color_chunk)
        .zip(tile_depth.par_chunks_mut(TILE_PIXELS))
        .zip(tile_transmittance.par_chunks_mut(TILE_PIXELS))
        .zip(tile_last.par_chunks_mut(TILE_PIXELS))
        .enumerate()
        .for_each(|(t, (((color, depth), trans), last))| {
            if blend_tiles.is_some_and(|sel| !sel.is_active(t)) {
                // A tile left out: nothing blended, the background behind T = 1.
                for px in color[..TILE_PIXELS * nc].chunks_exact_mut(nc.max(1)) {
                    px[..nc].copy_from_slice(&background);
                }
                depth.fill(0.0);
                trans.fill(1.0);
                last.fill(0);
                return;
            }
            let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
            let inputs = blend::TileInputs {
                tile: &grid.tile_rect(t),
                list,
                splats: &splats,
                splat_channels: &splat_channels,
                n_channels: nc,
                background: &background,
                mode,
            };
            blend::blend_tile_forward(
                &inputs,
                settings.early_termination,
                blend::TileForwardOut {
                    color: &mut color[..TILE_PIXELS * nc],
                    depth,
                    transmittance: trans,
                    last,
                },
            );
        });

    let w = width as usize;
    let h = height as usize;
    let mut color = vec![0.0f32; w * h * nc];
    let mut alpha = vec![0.0f32; w * h];
    let mut depth = vec![0.0f32; w * h];
    untile(
        &grid,
        nc,
        TileMajor {
            color: tile_color,
            color_chunk,
            depth: tile_depth,
            transmittance: &tile_transmittance,
        },
        &mut color,
        &mut alpha,
        &mut depth,
    );
    let blend_ms = ms_since(t2);

    let mut radii_px = radii_px;
    for (r, v) in radii_px.iter_mut().zip(&visible) {
        if !v {
            *r = 0.0;
        }
    }

    Ok(RenderOutput {
        width,
        height,
        n_channels: nc,
        color,
        alpha,
        depth,
        radii_px,
        visible,
        timings: ForwardTimings {
            project_ms,
            sort_bin_ms,
            blend_ms,
        },
        state: ForwardState {
            camera,
            settings,
            background,
            n_gaussians: n,
            grid,
            splats,
            splat_channels,
            gaussian_of_rank,
            bins,
            n_tile_entries,
            tile_transmittance,
            tile_last,
        },
    })
}
