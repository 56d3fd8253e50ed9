//! The backward pass: the backward blend of every tile writes one gradient record per
//! tile-list entry (rayon over tiles); the records are summed per Gaussian in tile order
//! and pushed through [`project::project_backward`] (rayon over blocks of Gaussians).
//!
//! Invariants: each Gaussian's sum runs in one task in a fixed order (tile order, from
//! +0.0), so the thread count changes no bit; culled Gaussians get zero gradients, and a
//! Gaussian whose gradient is not finite gets zeros and is counted in
//! [`GaussianGrads::dropped_nonfinite`]; inputs that differ from the forward's are a
//! [`RasterError::ForwardMismatch`].

use std::time::Instant;

use rayon::prelude::*;

use super::bin::TILE_PIXELS;
use super::blend::{self, AlphaMode, REC_CHANNELS, REC_CONIC, REC_DEPTH, REC_OPACITY};
use super::forward::{scratch, ForwardState};
use super::project::{self, CameraFrame, ProjectedGrad};
use super::{
    camera_frame, ms_since, GaussianView, RasterError, RasterSettings, RasterWorkspace,
    RenderOutput,
};
use crate::camera::Camera;

/// Wall-clock split of one backward pass, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BackwardTimings {
    pub blend_ms: f64,
    pub reduce_project_ms: f64,
}

/// Loss gradients with respect to the rendered images (same layouts as [`RenderOutput`]).
#[derive(Clone, Copy, Debug)]
pub struct PixelGrads<'a> {
    pub d_color: &'a [f32],
    pub d_alpha: Option<&'a [f32]>,
    pub d_depth: Option<&'a [f32]>,
}

/// Gradients of the loss with respect to the Gaussians (same layouts as [`GaussianView`]).
#[derive(Clone, Debug, Default)]
pub struct GaussianGrads {
    pub d_means: Vec<f32>,
    pub d_log_scales: Vec<f32>,
    pub d_rotations: Vec<f32>,
    pub d_opacity_logits: Vec<f32>,
    pub d_channels: Vec<f32>,
    /// Per Gaussian `|dL/d(mean2d)|` in NDC units (pixel gradient times W/2, H/2).
    pub mean2d_grad_ndc: Vec<f32>,
    /// Gaussians whose gradient came out non-finite and was replaced by zeros.
    pub dropped_nonfinite: usize,
    pub timings: BackwardTimings,
}

/// Hints the cache to fetch the line holding `value` (never faults; no effect elsewhere).
#[inline(always)]
fn prefetch<T>(value: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: SSE is part of the x86_64 baseline, and a prefetch is only a hint: it
        // never faults and the pointer comes from a live reference.
        unsafe { _mm_prefetch::<_MM_HINT_T0>((value as *const T).cast::<i8>()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = value;
}

/// The backward blend of every tile (rayon): one gradient record of
/// `REC_CHANNELS + n_channels` values per entry of `st.bins` into `records` (every value
/// written).
pub(super) fn write_records(
    st: &ForwardState,
    mode: AlphaMode,
    nc: usize,
    pixel_view: &blend::PixelGradsView,
    records: &mut [f32],
) {
    let grid = st.grid;
    let bins = &st.bins;
    let stride = REC_CHANNELS + nc;
    let mut per_tile: Vec<&mut [f32]> = Vec::with_capacity(grid.n_tiles());
    let mut rest: &mut [f32] = &mut *records;
    for t in 0..grid.n_tiles() {
        let len = (bins.tile_offsets[t + 1] - bins.tile_offsets[t]) * stride;
        let (head, tail) = rest.split_at_mut(len);
        per_tile.push(head);
        rest = tail;
    }
    let blend_tiles = st.settings.blend_tiles.as_ref();
    per_tile
        .into_par_iter()
        .enumerate()
        .for_each(|(t, tile_records)| {
            if blend_tiles.is_some_and(|sel| !sel.is_active(t)) {
                // Not blended in the forward: no gradient reaches its entries.
                tile_records.fill(0.0);
                return;
            }
            let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
            let px = t * TILE_PIXELS..(t + 1) * TILE_PIXELS;
            let inputs = blend::TileInputs {
                tile: &grid.tile_rect(t),
                list,
                splats: &st.splats,
                splat_channels: &st.splat_channels,
                n_channels: nc,
                background: &st.background,
                mode,
            };
            blend::blend_tile_backward(
                &inputs,
                blend::TileForwardState {
                    transmittance: &st.tile_transmittance[px.clone()],
                    last: &st.tile_last[px],
                },
                pixel_view,
                tile_records,
            );
        });
}

/// Gaussians per block of the backward reduction (one rayon task each).
pub(super) const REDUCE_BLOCK: usize = 256;

/// How far ahead (in Gaussians) the reduction fetches what it will read: a rank's
/// offsets and splat first, then its list of entries, then the entries' records, each
/// step reading only what the previous one fetched.
const PREFETCH_RANK_AHEAD: usize = 12;
const PREFETCH_ENTRIES_AHEAD: usize = 8;
const PREFETCH_RECORDS_AHEAD: usize = 4;

/// Marks a Gaussian without a rank (culled) in [`rank_of_gaussian`].
const NO_RANK: u32 = u32::MAX;

/// Inverse of `gaussian_of_rank` over `n` Gaussians; [`NO_RANK`] for the culled ones.
fn rank_of_gaussian(gaussian_of_rank: &[u32], n: usize) -> Vec<u32> {
    let mut out = vec![NO_RANK; n];
    for (rank, &g) in gaussian_of_rank.iter().enumerate() {
        out[g as usize] = rank as u32;
    }
    out
}

/// What the per-Gaussian reduction of the backward reads.
struct ReduceInputs<'a> {
    frame: &'a CameraFrame,
    mode: AlphaMode,
    /// Half the image width and height, pixels (pixel to NDC gradient scale).
    half_px: [f32; 2],
    gaussians: &'a GaussianView<'a>,
    state: &'a ForwardState,
    rank_of_gaussian: &'a [u32],
    /// One record of `stride` values per entry of `state.bins`.
    records: &'a [f32],
    stride: usize,
}

/// The output rows of Gaussians `first..first + d_opacity_logits.len()`.
struct GradBlock<'a> {
    first: usize,
    d_means: &'a mut [f32],
    d_log_scales: &'a mut [f32],
    d_rotations: &'a mut [f32],
    d_opacity_logits: &'a mut [f32],
    d_channels: &'a mut [f32],
    mean2d_grad_ndc: &'a mut [f32],
}

/// `out` cut into blocks of [`REDUCE_BLOCK`] Gaussians (any channel count, zero too).
fn gaussian_blocks(out: &mut GaussianGrads, nc: usize) -> Vec<GradBlock<'_>> {
    let n = out.d_opacity_logits.len();
    let mut blocks = Vec::with_capacity(n.div_ceil(REDUCE_BLOCK));
    let mut means = &mut out.d_means[..];
    let mut log_scales = &mut out.d_log_scales[..];
    let mut rotations = &mut out.d_rotations[..];
    let mut opacity = &mut out.d_opacity_logits[..];
    let mut channels = &mut out.d_channels[..];
    let mut ndc = &mut out.mean2d_grad_ndc[..];
    let mut first = 0;
    while first < n {
        let len = REDUCE_BLOCK.min(n - first);
        let (m, m_rest) = std::mem::take(&mut means).split_at_mut(3 * len);
        let (s, s_rest) = std::mem::take(&mut log_scales).split_at_mut(3 * len);
        let (r, r_rest) = std::mem::take(&mut rotations).split_at_mut(4 * len);
        let (o, o_rest) = std::mem::take(&mut opacity).split_at_mut(len);
        let (c, c_rest) = std::mem::take(&mut channels).split_at_mut(nc * len);
        let (d, d_rest) = std::mem::take(&mut ndc).split_at_mut(len);
        blocks.push(GradBlock {
            first,
            d_means: m,
            d_log_scales: s,
            d_rotations: r,
            d_opacity_logits: o,
            d_channels: c,
            mean2d_grad_ndc: d,
        });
        (means, log_scales, rotations, opacity, channels, ndc) =
            (m_rest, s_rest, r_rest, o_rest, c_rest, d_rest);
        first += len;
    }
    blocks
}

/// Sums the records of each Gaussian of `block` (in tile order, from +0.0: the order of
/// `entry_of_rank`, whatever the thread count) and pushes them through the projection
/// backward into the block's rows. Rows of culled Gaussians stay zero, as do those of a
/// Gaussian whose gradient is not finite (counted). Returns (dropped, mismatch): mismatch
/// when a Gaussian's parameters or channels no longer give the forward's splat.
fn reduce_block(inputs: &ReduceInputs, block: GradBlock) -> (usize, bool) {
    let ReduceInputs {
        frame,
        mode,
        half_px: [half_w, half_h],
        gaussians,
        state: st,
        rank_of_gaussian,
        records,
        stride,
    } = *inputs;
    let nc = gaussians.n_channels;
    let bins = &st.bins;
    let n = rank_of_gaussian.len();
    let rank_ahead = |g: usize, ahead: usize| {
        rank_of_gaussian
            .get(g + ahead)
            .copied()
            .filter(|&r| r != NO_RANK)
            .map(|r| r as usize)
    };
    let mut dropped = 0;
    for i in 0..block.d_opacity_logits.len() {
        let g = block.first + i;
        // Ranks lie scattered in Gaussian order: fetch what a Gaussian a few steps ahead
        // will read while this one is summed.
        if let Some(r) = rank_ahead(g, PREFETCH_RANK_AHEAD) {
            prefetch(&bins.rank_offsets[r]);
            prefetch(&st.splats[r]);
            if nc > 0 {
                prefetch(&st.splat_channels[r * nc]);
            }
        }
        if let Some(r) = rank_ahead(g, PREFETCH_ENTRIES_AHEAD) {
            if let Some(e) = bins.entry_of_rank.get(bins.rank_offsets[r]) {
                prefetch(e);
            }
        }
        if let Some(r) = rank_ahead(g, PREFETCH_RECORDS_AHEAD) {
            for &e in &bins.entry_of_rank[bins.rank_offsets[r]..bins.rank_offsets[r + 1]] {
                prefetch(&records[e as usize * stride]);
            }
        }
        debug_assert!(g < n);
        let rank = rank_of_gaussian[g];
        if rank == NO_RANK {
            continue;
        }
        let rank = rank as usize;
        // The geometry part of the sum here, the channel part in the output row (which
        // starts at +0.0 like the sum).
        let mut sum = [0.0f32; REC_CHANNELS];
        let d_ch = &mut block.d_channels[i * nc..(i + 1) * nc];
        for &e in &bins.entry_of_rank[bins.rank_offsets[rank]..bins.rank_offsets[rank + 1]] {
            let rec = &records[e as usize * stride..(e as usize + 1) * stride];
            let (rec_geo, rec_ch) = rec.split_at(REC_CHANNELS);
            for (s, r) in sum.iter_mut().zip(rec_geo) {
                *s += r;
            }
            for (s, r) in d_ch.iter_mut().zip(rec_ch) {
                *s += r;
            }
        }
        let splat = &st.splats[rank];
        let Ok(p) = project::project_forward(frame, &gaussians.params(g), mode.cutoff()) else {
            return (dropped, true);
        };
        if p.mean_px != splat.mean_px
            || p.conic != splat.conic
            || p.opacity != splat.opacity
            || p.t_cam[2] != splat.depth
            || gaussians.channels[g * nc..g * nc + nc]
                != st.splat_channels[rank * nc..rank * nc + nc]
        {
            return (dropped, true);
        }
        let d = ProjectedGrad {
            d_mean_px: [sum[0], sum[1]],
            d_conic: [sum[REC_CONIC], sum[REC_CONIC + 1], sum[REC_CONIC + 2]],
            d_opacity: sum[REC_OPACITY],
            d_depth: sum[REC_DEPTH],
        };
        let pg = project::project_backward(frame, &p, &d);
        let ndc = (sum[0] * half_w).hypot(sum[1] * half_h);
        if !(pg.is_finite() && d_ch.iter().all(|v| v.is_finite()) && ndc.is_finite()) {
            d_ch.fill(0.0);
            dropped += 1;
            continue;
        }
        block.d_means[3 * i..3 * i + 3].copy_from_slice(&pg.d_mean);
        block.d_log_scales[3 * i..3 * i + 3].copy_from_slice(&pg.d_log_scale);
        block.d_rotations[4 * i..4 * i + 4].copy_from_slice(&pg.d_rotation);
        block.d_opacity_logits[i] = pg.d_opacity_logit;
        block.mean2d_grad_ndc[i] = ndc;
    }
    (dropped, false)
}

fn check_grad_slice(what: &'static str, slice: &[f32], expected: usize) -> Result<(), RasterError> {
    if slice.len() != expected {
        return Err(RasterError::Length {
            what,
            expected,
            got: slice.len(),
        });
    }
    if !slice.iter().all(|v| v.is_finite()) {
        return Err(RasterError::NonFiniteGradient(what));
    }
    Ok(())
}

/// Gradients of a loss with respect to the Gaussians, given its pixel gradients.
/// `camera`, `gaussians` and `settings` must be those `forward` was rendered with.
pub fn render_backward(
    camera: &Camera,
    gaussians: &GaussianView,
    settings: &RasterSettings,
    forward: &RenderOutput,
    grads: &PixelGrads,
) -> Result<GaussianGrads, RasterError> {
    render_backward_with(
        &mut RasterWorkspace::default(),
        camera,
        gaussians,
        settings,
        forward,
        grads,
    )
}

/// [`render_backward`] with scratch memory kept in `workspace` between calls.
pub fn render_backward_with(
    workspace: &mut RasterWorkspace,
    camera: &Camera,
    gaussians: &GaussianView,
    settings: &RasterSettings,
    forward: &RenderOutput,
    grads: &PixelGrads,
) -> Result<GaussianGrads, RasterError> {
    let st = &forward.state;
    let frame = camera_frame(camera, settings.near_m)?;
    let n = gaussians.check()?;
    let nc = gaussians.n_channels;
    if *camera != st.camera {
        return Err(RasterError::ForwardMismatch("camera differs"));
    }
    if *settings != st.settings {
        return Err(RasterError::ForwardMismatch("settings differ"));
    }
    if n != st.n_gaussians || nc != forward.n_channels {
        return Err(RasterError::ForwardMismatch(
            "number of Gaussians or channels differs",
        ));
    }
    let pixels = forward.width as usize * forward.height as usize;
    check_grad_slice("d_color", grads.d_color, pixels * nc)?;
    if let Some(d) = grads.d_alpha {
        check_grad_slice("d_alpha", d, pixels)?;
    }
    if let Some(d) = grads.d_depth {
        check_grad_slice("d_depth", d, pixels)?;
    }
    let mode = AlphaMode {
        smooth: settings.smooth_cutoff,
    };
    let bins = &st.bins;
    let stride = REC_CHANNELS + nc;

    let t0 = Instant::now();
    let n_entries = bins.tile_ranks.len();
    // Each tile writes every value of its records (see `blend_tile_backward`).
    let records = scratch(&mut workspace.records, n_entries * stride);
    let pixel_view = blend::PixelGradsView {
        width: forward.width as usize,
        d_color: grads.d_color,
        d_alpha: grads.d_alpha,
        d_depth: grads.d_depth,
    };
    write_records(st, mode, nc, &pixel_view, records);
    let blend_ms = ms_since(t0);

    let t1 = Instant::now();
    let mut out = GaussianGrads {
        d_means: vec![0.0; 3 * n],
        d_log_scales: vec![0.0; 3 * n],
        d_rotations: vec![0.0; 4 * n],
        d_opacity_logits: vec![0.0; n],
        d_channels: vec![0.0; nc * n],
        mean2d_grad_ndc: vec![0.0; n],
        dropped_nonfinite: 0,
        timings: BackwardTimings::default(),
    };
    let reduce = ReduceInputs {
        frame: &frame,
        mode,
        half_px: [0.5 * forward.width as f32, 0.5 * forward.height as f32],
        gaussians,
        state: st,
        rank_of_gaussian: &rank_of_gaussian(&st.gaussian_of_rank, n),
        records,
        stride,
    };
    let (dropped, mismatch) = gaussian_blocks(&mut out, nc)
        .into_par_iter()
        .map(|block| reduce_block(&reduce, block))
        .reduce(|| (0, false), |a, b| (a.0 + b.0, a.1 || b.1));
    if mismatch {
        return Err(RasterError::ForwardMismatch(
            "Gaussian parameters changed since the forward pass",
        ));
    }
    out.dropped_nonfinite = dropped;
    out.timings = BackwardTimings {
        blend_ms,
        reduce_project_ms: ms_since(t1),
    };
    Ok(out)
}
