//! GPU rasterizer: the CPU rasterizer's forward and backward passes as WGSL kernels.
//!
//! Forward, all on the device: projection (one thread per Gaussian) -> exclusive prefix
//! sum of the per-Gaussian tile counts -> key generation (tile, depth bits, Gaussian) ->
//! stable radix sort of the live keys by (tile, depth) -> per-tile key ranges -> blending
//! (one workgroup per 16x16 tile). The
//! only mid-pass readback is the 4-byte entry count, which sizes the sort; the image, the
//! per-pixel alpha and depth and the per-Gaussian radii come back at the end.
//! Backward: per-tile back-to-front walk with per-key workgroup reductions and atomic
//! accumulation per Gaussian (f32 atomics, or a compare-and-swap loop), then the
//! projection backward per Gaussian; the gradients come back in [`GaussianGrads`].
//!
//! Invariants:
//! - the same conventions and formulas as `gs_core::raster` (see the shaders' headers), so
//!   outputs agree with it to float rounding, except where a rounding difference moves a
//!   pixel across the 1/255 cutoff or the 1e-4 stop (see `tests/gpu_parity.rs`);
//! - keys (tile, depth bits, Gaussian index) are written in Gaussian order and sorted
//!   stably by (tile, depth bits), so each tile's list is the CPU's list in the CPU's
//!   order; the forward is deterministic. The backward's atomic sums are
//!   not (their order, and so the last bits of the gradients, vary from run to run)
//!   unless [`super::GpuOptions::deterministic`] is set;
//! - device buffers of a forward pass live in its [`GpuRenderOutput`] until backward.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use super::{
    bytes_f32, bytes_u32, dispatch_1d, f32_bytes, groups_1d, storage_in, u32_bytes, uniform_in,
    GpuContext, GpuError, Scratch,
};
use gs_core::camera::Camera;
use gs_core::raster::bin::{TileGrid, TILE_PX};
use gs_core::raster::blend::{AlphaMode, REC_CHANNELS};
use gs_core::raster::{
    camera_frame, BackwardTimings, GaussianGrads, GaussianView, PixelGrads, RasterError,
    RasterSettings,
};

/// Most channels the GPU kernels take (the backward's workgroup reduction holds
/// `(7 + channels) * 256` floats in 16 KiB of workgroup memory).
pub const MAX_GPU_CHANNELS: usize = 8;

const COMMON: &str = include_str!("shaders/common.wgsl");
const PROJECT: &str = include_str!("shaders/project.wgsl");
const SCAN_BLOCK: &str = include_str!("shaders/scan_block.wgsl");
const SCAN_ADD: &str = include_str!("shaders/scan_add.wgsl");
const KEYGEN: &str = include_str!("shaders/keygen.wgsl");
const SORT_RADIX_COMMON: &str = include_str!("shaders/sort_radix_common.wgsl");
const SORT_RADIX_COUNT: &str = include_str!("shaders/sort_radix_count.wgsl");
const SORT_RADIX_SCAN: &str = include_str!("shaders/sort_radix_scan.wgsl");
const SORT_RADIX_SCATTER: &str = include_str!("shaders/sort_radix_scatter.wgsl");
const SORT_RADIX_COPY: &str = include_str!("shaders/sort_radix_copy.wgsl");
const RANGES: &str = include_str!("shaders/ranges.wgsl");
const BLEND: &str = include_str!("shaders/blend.wgsl");
const BLEND_BACKWARD: &str = include_str!("shaders/blend_backward.wgsl");
const BLEND_BACKWARD_DIRECT: &str = include_str!("shaders/blend_backward_direct.wgsl");
const CONTRIB: &str = include_str!("shaders/contrib.wgsl");
const ACC_F32: &str = include_str!("shaders/acc_f32.wgsl");
const ACC_CAS: &str = include_str!("shaders/acc_cas.wgsl");
const ACC_RECORDS: &str = include_str!("shaders/acc_records.wgsl");
const GATHER: &str = include_str!("shaders/gather.wgsl");
const PROJECT_BACKWARD: &str = include_str!("shaders/project_backward.wgsl");

/// Values per Gaussian in the gradient readback: 12 parameter/NDC values, a dropped flag,
/// then the channels.
const OUT_FIXED: usize = 13;
/// Per-Gaussian input stride (mean 3, log-scale 3, quaternion 4, opacity logit 1).
const GSTRIDE: usize = 11;
/// Per-splat stride on the device (see common.wgsl).
pub(super) const SSTRIDE: usize = 12;
/// Splats per batch staged in workgroup memory by the blend kernels (`BATCH` in WGSL).
const BATCH: usize = 128;
/// Bits of one radix sort digit (16 bins; `DIGITS` in sort_radix_common.wgsl).
const RADIX_BITS: u32 = 4;
/// Keys per radix sort workgroup (`BLOCK` in sort_radix_common.wgsl: 256 threads of 16).
const RADIX_BLOCK: u64 = 4096;
/// Order bits of a key (word 1: depth, or a receiver's limit), sorted in full.
const ORDER_BITS: u32 = 32;

/// Keys to sort on the device in place: `n_sort` vec4<u32> keys (tile, order bits, tie
/// index, 0) of which the first `min(count[count_word], n_sort)` are live. The live keys
/// end up ordered by (tile, order bits), stably, so keys written in ascending tie index
/// come out ordered by (tile, order bits, tie index); the keys past them stay as they
/// were (padding, see keygen.wgsl).
pub(super) struct SortKeys<'a> {
    pub keys: &'a wgpu::Buffer,
    pub n_sort: u64,
    pub count: &'a wgpu::Buffer,
    pub count_word: u32,
    /// Every live key's tile word is below this: only its bits are sorted.
    pub n_tiles: u32,
    /// Names this sort's uniforms, which must differ between sorts recorded into one
    /// submission from one scratch pool. (The temporary key and histogram buffers are
    /// shared by every sort of a pool: sorts recorded one after the other run in order.)
    pub label: &'a str,
}

/// The radix sort's kernels (sort_radix_*.wgsl, after sort_radix_common.wgsl).
struct RadixPipelines {
    count: wgpu::ComputePipeline,
    scan: wgpu::ComputePipeline,
    scatter: wgpu::ComputePipeline,
    copy: wgpu::ComputePipeline,
}

impl RadixPipelines {
    fn new(ctx: &GpuContext) -> Result<Self, GpuError> {
        let build =
            |label: &str, body: &str| ctx.pipeline(label, &format!("{SORT_RADIX_COMMON}\n{body}"));
        Ok(Self {
            count: build("sort_radix_count", SORT_RADIX_COUNT)?,
            scan: build("sort_radix_scan", SORT_RADIX_SCAN)?,
            scatter: build("sort_radix_scatter", SORT_RADIX_SCATTER)?,
            copy: build("sort_radix_copy", SORT_RADIX_COPY)?,
        })
    }
}

/// The radix passes that sort keys of `n_tiles` tiles: (key word, shift), least
/// significant digit first (the order bits, then the tile bits).
fn radix_digits(n_tiles: u32) -> Vec<(u32, u32)> {
    let tile_bits = u32::BITS - n_tiles.saturating_sub(1).leading_zeros();
    let order = (0..ORDER_BITS / RADIX_BITS).map(|d| (1, d * RADIX_BITS));
    let tile = (0..tile_bits.div_ceil(RADIX_BITS)).map(|d| (0, d * RADIX_BITS));
    order.chain(tile).collect()
}

/// Constants the raster shaders expect before common.wgsl, then common.wgsl.
pub(super) fn prelude(nc: usize) -> String {
    let rec = REC_CHANNELS + nc;
    format!(
        "const NC: u32 = {nc}u;\nconst NCA: u32 = {}u;\nconst REC: u32 = {rec}u;\n\
         const RED_LEN: u32 = {}u;\nconst OSTRIDE: u32 = {}u;\nconst SH_LEN: u32 = {}u;\n{COMMON}\n",
        nc.max(1),
        rec * 256,
        OUT_FIXED + nc,
        BATCH * (7 + nc.max(1)),
    )
}

/// Pipelines whose shaders depend on the channel count.
pub(super) struct ChannelPipelines {
    pub(super) project: wgpu::ComputePipeline,
    pub(super) keygen: wgpu::ComputePipeline,
    pub(super) ranges: wgpu::ComputePipeline,
    blend: wgpu::ComputePipeline,
    blend_backward: wgpu::ComputePipeline,
    /// The alpha-only walk of [`GpuRasterizer::encode_contributing`].
    contrib: wgpu::ComputePipeline,
    project_backward: wgpu::ComputePipeline,
    /// Deterministic mode only: per-Gaussian sums of the per-entry records.
    gather: Option<wgpu::ComputePipeline>,
}

/// The GPU rasterizer: a device and its compiled pipelines (per channel count, built on
/// first use).
pub struct GpuRasterizer {
    pub(super) ctx: GpuContext,
    scan_block: wgpu::ComputePipeline,
    scan_add: wgpu::ComputePipeline,
    radix: RadixPipelines,
    by_channels: Mutex<HashMap<usize, Arc<ChannelPipelines>>>,
}

impl std::fmt::Debug for GpuRasterizer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuRasterizer({})", self.ctx.describe())
    }
}

/// Wall-clock split of a GPU forward pass, milliseconds (each stage waits for the device).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GpuForwardTimings {
    /// Upload, projection, prefix sum and the entry-count readback.
    pub project_scan_ms: f64,
    /// Key generation, sort, tile ranges, blending and the image readback.
    pub sort_blend_ms: f64,
}

/// Device state of one forward pass, for its backward.
pub(super) struct ForwardState {
    pub(super) camera: Camera,
    pub(super) settings: RasterSettings,
    pub(super) n: usize,
    pub(super) nc: usize,
    pub(super) frame: wgpu::Buffer,
    pub(super) gauss: wgpu::Buffer,
    pub(super) chans: wgpu::Buffer,
    pub(super) splats: wgpu::Buffer,
    pub(super) keys: wgpu::Buffer,
    pub(super) ranges: wgpu::Buffer,
    pub(super) px_state: wgpu::Buffer,
    /// `RasterSettings::blend_tiles` as bits (see [`tile_mask_words`]).
    pub(super) tile_mask: wgpu::Buffer,
    pub(super) pipelines: Arc<ChannelPipelines>,
    pub(super) grid: TileGrid,
}

/// Device inputs of a forward pass: the rasterizer rows (`GSTRIDE` floats per Gaussian)
/// and `nc` channels per Gaussian, already on the device.
pub(super) struct DeviceInputs<'a> {
    pub camera: &'a Camera,
    pub settings: &'a RasterSettings,
    pub n: usize,
    pub nc: usize,
    pub background: &'a [f32],
    pub gauss: wgpu::Buffer,
    pub chans: wgpu::Buffer,
}

/// A forward pass recorded on the device (see [`GpuRasterizer::forward_device`]).
pub(super) struct DeviceForward {
    pub state: ForwardState,
    /// `H * W * nc` colour, written by the recorded blend.
    pub color: wgpu::Buffer,
    /// Sort and blend, recorded and not yet submitted.
    pub encoder: wgpu::CommandEncoder,
    /// The entry count, when it was read back (no `capacity`).
    pub tile_entries: Option<usize>,
    /// Keys the sort's buffers hold: the entry count, or the capacity.
    pub n_sort: u64,
    /// Scanned tile counts: `counts[n]` is the entry count.
    pub counts: wgpu::Buffer,
    /// Uniforms the recorded sort reads, held until the caller submits.
    pub _sort_uniforms: Vec<wgpu::Buffer>,
}

/// A forward pass up to its blend (see [`GpuRasterizer::forward_device_prepare`]):
/// projected, sorted and binned, the blend's outputs allocated. `state.chans` is the
/// buffer the projection checked until [`GpuRasterizer::forward_device_blend`] sets the
/// channels it blends.
pub(super) struct DevicePrepared {
    pub state: ForwardState,
    /// `H * W * nc` colour, written by the blend.
    pub color: wgpu::Buffer,
    /// The entry count, when it was read back (no `capacity`).
    pub tile_entries: Option<usize>,
    /// Keys the sort's buffers hold: the entry count, or the capacity.
    pub n_sort: u64,
    /// Scanned tile counts: `counts[n]` is the entry count.
    pub counts: wgpu::Buffer,
    /// Uniforms the recorded sort reads, held until the caller submits.
    pub sort_uniforms: Vec<wgpu::Buffer>,
}

/// A GPU render: the same images and per-Gaussian data as [`gs_core::raster::RenderOutput`].
pub struct GpuRenderOutput {
    pub width: u32,
    pub height: u32,
    pub n_channels: usize,
    /// `H * W * n_channels`, `(y * W + x) * C + c`.
    pub color: Vec<f32>,
    /// `H * W` accumulated opacity `1 - T_final`.
    pub alpha: Vec<f32>,
    /// `H * W` alpha-weighted camera z (not normalised by alpha).
    pub depth: Vec<f32>,
    pub radii_px: Vec<f32>,
    pub visible: Vec<bool>,
    /// Number of (tile, Gaussian) pairs blended.
    pub tile_entries: usize,
    pub timings: GpuForwardTimings,
    state: ForwardState,
}

impl std::fmt::Debug for GpuRenderOutput {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "GpuRenderOutput({}x{}, {} channels, {} tile entries)",
            self.width, self.height, self.n_channels, self.tile_entries
        )
    }
}

/// Alias kept for the module's public surface.
pub type GpuForward = GpuRenderOutput;

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn check_len(what: &str, expected: usize, got: usize) -> Result<(), GpuError> {
    if expected == got {
        Ok(())
    } else {
        Err(GpuError::Invalid(format!(
            "{what}: expected {expected} values, got {got}"
        )))
    }
}

/// A storage buffer holding `data` (from `scratch` when given: written through the queue,
/// so it takes effect at the next submission).
fn storage_data_in(
    ctx: &GpuContext,
    scratch: Option<&Scratch>,
    label: &str,
    data: &[u8],
) -> Result<wgpu::Buffer, GpuError> {
    match scratch {
        Some(s) => {
            let b = s.storage(ctx, label, data.len() as u64)?;
            ctx.queue.write_buffer(&b, 0, data);
            Ok(b)
        }
        None => Ok(ctx.storage_init(label, data)),
    }
}

/// `Frame::n_entries` when the entry count stays on the device (common.wgsl).
const ENTRIES_ON_DEVICE: u32 = u32::MAX;

/// Words of the frame uniform (`Frame` in common.wgsl, 160 bytes).
const FRAME_WORDS: usize = 40;
/// Word of `Frame::stop` (then `tile_masked`).
const FRAME_STOP_WORD: usize = 36;

/// The frame uniform (layout of `Frame` in common.wgsl), with the blend's default
/// switches: early termination on, every tile blended ([`with_blend_switches`] sets
/// others).
#[allow(clippy::too_many_arguments)]
pub(super) fn frame_bytes(
    frame: &gs_core::raster::project::CameraFrame,
    cutoff: f32,
    grid: &TileGrid,
    n: u32,
    smooth: bool,
    n_entries: u32,
    n_sort: u32,
    background: &[f32],
) -> Vec<u8> {
    let mut w = [0u32; FRAME_WORDS];
    for r in 0..3 {
        for c in 0..3 {
            w[4 * r + c] = frame.rot_cam_from_world[r][c].to_bits();
        }
        w[4 * r + 3] = frame.translation[r].to_bits();
    }
    let f = [
        frame.fx,
        frame.fy,
        frame.cx,
        frame.cy,
        frame.lim_x,
        frame.lim_y,
        frame.near_m,
        cutoff,
    ];
    for (k, v) in f.iter().enumerate() {
        w[12 + k] = v.to_bits();
    }
    w[20] = grid.width;
    w[21] = grid.height;
    w[22] = grid.tiles_x;
    w[23] = grid.tiles_y;
    w[24] = n;
    w[25] = smooth as u32;
    w[26] = n_entries;
    w[27] = n_sort;
    for (k, b) in background.iter().enumerate() {
        w[28 + k] = b.to_bits();
    }
    w[FRAME_STOP_WORD] = AlphaMode { smooth }.stop(true).to_bits();
    u32_bytes(&w)
}

/// `frame` (from [`frame_bytes`]) with the blend's switches from `settings`: the stop
/// transmittance (`RasterSettings::early_termination`) and whether the tile mask applies
/// (`RasterSettings::blend_tiles`).
pub(super) fn with_blend_switches(mut frame: Vec<u8>, settings: &RasterSettings) -> Vec<u8> {
    let mode = AlphaMode {
        smooth: settings.smooth_cutoff,
    };
    let stop = mode.stop(settings.early_termination).to_bits();
    let masked = settings.blend_tiles.is_some() as u32;
    let at = 4 * FRAME_STOP_WORD;
    frame[at..at + 4].copy_from_slice(&stop.to_le_bytes());
    frame[at + 4..at + 8].copy_from_slice(&masked.to_le_bytes());
    frame
}

/// The tile mask words of `settings.blend_tiles` for `grid` (bit `t % 32` of word `t / 32`
/// set: tile `t` is blended); one zero word without a selection (the kernels then never
/// read it).
fn tile_mask_words(settings: &RasterSettings, grid: &TileGrid) -> Vec<u32> {
    let Some(selection) = &settings.blend_tiles else {
        return vec![0];
    };
    let n_tiles = grid.n_tiles();
    let mut words = vec![0u32; n_tiles.div_ceil(32).max(1)];
    for t in (0..n_tiles).filter(|&t| selection.is_active(t)) {
        words[t / 32] |= 1 << (t % 32);
    }
    words
}

impl GpuRasterizer {
    /// Compiles the channel-independent pipelines.
    pub fn new(ctx: GpuContext) -> Result<Self, GpuError> {
        Ok(Self {
            scan_block: ctx.pipeline("scan_block", SCAN_BLOCK)?,
            scan_add: ctx.pipeline("scan_add", SCAN_ADD)?,
            radix: RadixPipelines::new(&ctx)?,
            by_channels: Mutex::new(HashMap::new()),
            ctx,
        })
    }

    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    /// WGSL of the atomic accumulator `acc_add` (binding 7): f32 atomics or the CAS loop.
    pub(super) fn atomic_accumulator(&self) -> &'static str {
        if self.ctx.uses_float32_atomics() {
            ACC_F32
        } else {
            ACC_CAS
        }
    }

    pub(super) fn channel_pipelines(&self, nc: usize) -> Result<Arc<ChannelPipelines>, GpuError> {
        let mut map = self
            .by_channels
            .lock()
            .map_err(|_| GpuError::Pipeline("pipeline cache lock poisoned".into()))?;
        if let Some(p) = map.get(&nc) {
            return Ok(p.clone());
        }
        let prelude = prelude(nc);
        let options = self.ctx.options;
        let acc = if options.deterministic {
            ACC_RECORDS
        } else {
            self.atomic_accumulator()
        };
        let blend_backward = if options.workgroup_reduction || options.deterministic {
            BLEND_BACKWARD
        } else {
            BLEND_BACKWARD_DIRECT
        };
        let build = |label: &str, body: &str| self.ctx.pipeline(label, &format!("{prelude}{body}"));
        let p = Arc::new(ChannelPipelines {
            project: build("project", PROJECT)?,
            keygen: build("keygen", KEYGEN)?,
            ranges: build("ranges", RANGES)?,
            blend: build("blend", BLEND)?,
            blend_backward: build("blend_backward", &format!("{acc}\n{blend_backward}"))?,
            contrib: build("contrib", CONTRIB)?,
            project_backward: build("project_backward", PROJECT_BACKWARD)?,
            gather: if options.deterministic {
                Some(build("gather", GATHER)?)
            } else {
                None
            },
        });
        map.insert(nc, p.clone());
        Ok(p)
    }

    /// Exclusive prefix sum of `len` u32 values in `data`, in place (recursive over
    /// block sums). `keep` holds the temporaries until submission.
    pub(super) fn encode_scan(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        len: u64,
        keep: &mut Vec<wgpu::Buffer>,
    ) -> Result<(), GpuError> {
        self.encode_scan_in(encoder, data, len, keep, None, 0)
    }

    /// [`Self::encode_scan`] with its temporaries from `scratch` (one set per recursion
    /// `level`).
    pub(super) fn encode_scan_in(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        len: u64,
        keep: &mut Vec<wgpu::Buffer>,
        scratch: Option<&Scratch>,
        level: u32,
    ) -> Result<(), GpuError> {
        let blocks = len.div_ceil(256).max(1);
        let sums = storage_in(
            &self.ctx,
            scratch,
            &format!("scan sums {level}"),
            blocks * 4,
        )?;
        let params = uniform_in(
            &self.ctx,
            scratch,
            &format!("scan params {level}"),
            &u32_bytes(&[len as u32, blocks as u32, 0, 0]),
        )?;
        {
            let bind = self
                .ctx
                .bind_group(&self.scan_block, &[&params, data, &sums]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.scan_block, &bind, len);
        }
        if blocks > 1 {
            self.encode_scan_in(encoder, &sums, blocks, keep, scratch, level + 1)?;
            let bind = self.ctx.bind_group(&self.scan_add, &[&params, data, &sums]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.scan_add, &bind, len);
        }
        keep.push(sums);
        keep.push(params);
        Ok(())
    }

    /// Stable LSD radix sort of `sort`'s live keys by (tile, order bits), 4 bits per
    /// pass: per-block digit histograms, one prefix sum over them, a stable scatter into
    /// a temporary buffer and back (and a copy of the live keys when the pass count is
    /// odd). Deterministic: the histograms are integer sums and every key's destination
    /// follows from its position. Temporaries from `scratch` ("sort radix ..."), held in
    /// `keep` until submission.
    pub(super) fn encode_sort_in(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        sort: &SortKeys,
        keep: &mut Vec<wgpu::Buffer>,
        scratch: Option<&Scratch>,
    ) -> Result<(), GpuError> {
        let ctx = &self.ctx;
        let n_blocks = sort.n_sort.div_ceil(RADIX_BLOCK);
        if sort.n_sort > u32::MAX as u64 / 2 {
            return Err(GpuError::TooLarge(format!("{} sort keys", sort.n_sort)));
        }
        let temp = storage_in(ctx, scratch, "sort radix keys", sort.n_sort * 16)?;
        let hist = storage_in(
            ctx,
            scratch,
            "sort radix histograms",
            n_blocks * (1 << RADIX_BITS) * 4,
        )?;
        let p = &self.radix;
        let digits = radix_digits(sort.n_tiles);
        let block_groups = groups_1d(n_blocks * 256);
        let mut uniforms = Vec::with_capacity(digits.len());
        for (pass, &(key_word, shift)) in digits.iter().enumerate() {
            let params = uniform_in(
                ctx,
                scratch,
                &format!("sort radix {} pass {pass}", sort.label),
                &u32_bytes(&[
                    key_word,
                    shift,
                    n_blocks as u32,
                    sort.n_sort as u32,
                    sort.count_word,
                    0,
                    0,
                    0,
                ]),
            )?;
            let (src, dst) = if pass % 2 == 0 {
                (sort.keys, &temp)
            } else {
                (&temp, sort.keys)
            };
            let count = ctx.bind_group(&p.count, &[&params, sort.count, src, &hist]);
            let scan = ctx.bind_group_at(&p.scan, &[(0, &params), (2, &hist)]);
            let scatter = ctx.bind_group(&p.scatter, &[&params, sort.count, src, &hist, dst]);
            let mut cpass = encoder.begin_compute_pass(&Default::default());
            cpass.set_pipeline(&p.count);
            cpass.set_bind_group(0, &count, &[]);
            cpass.dispatch_workgroups(block_groups.0, block_groups.1, 1);
            drop(cpass);
            let mut cpass = encoder.begin_compute_pass(&Default::default());
            cpass.set_pipeline(&p.scan);
            cpass.set_bind_group(0, &scan, &[]);
            cpass.dispatch_workgroups(1, 1, 1);
            drop(cpass);
            let mut cpass = encoder.begin_compute_pass(&Default::default());
            cpass.set_pipeline(&p.scatter);
            cpass.set_bind_group(0, &scatter, &[]);
            cpass.dispatch_workgroups(block_groups.0, block_groups.1, 1);
            drop(cpass);
            uniforms.push(params);
        }
        if let (true, Some(params)) = (digits.len() % 2 == 1, uniforms.last()) {
            let bind = ctx.bind_group(&p.copy, &[params, sort.count, &temp, sort.keys]);
            let mut cpass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut cpass, &p.copy, &bind, sort.n_sort);
        }
        keep.extend(uniforms);
        keep.extend([temp, hist]);
        Ok(())
    }

    /// Sorts `keys` on the device as a forward pass sorts its tile keys (see
    /// [`Self::encode_sort_in`]): `keys.len()` is the sort's capacity, `live` (kept
    /// on the device, as a pass without the entry-count readback keeps it) the number of
    /// keys sorted, `n_tiles` a bound on their tile words. Returns the whole buffer: the
    /// live keys sorted by (tile, order bits), stably, then the rest as given. For tests
    /// and benchmarks.
    pub fn sort_keys(
        &self,
        keys: &[[u32; 4]],
        live: usize,
        n_tiles: u32,
    ) -> Result<Vec<[u32; 4]>, GpuError> {
        if live > keys.len() {
            return Err(GpuError::Invalid(format!(
                "{live} live keys in a buffer of {}",
                keys.len()
            )));
        }
        if let Some(k) = keys[..live].iter().find(|k| k[0] >= n_tiles) {
            return Err(GpuError::Invalid(format!(
                "key tile {} not below the tile count {n_tiles}",
                k[0]
            )));
        }
        let ctx = &self.ctx;
        let flat: Vec<u32> = keys.iter().flatten().copied().collect();
        let buf = ctx.storage_init("sort keys", &u32_bytes(&flat));
        let count = ctx.storage_init("sort live count", &u32_bytes(&[live as u32]));
        let mut encoder = ctx.encoder("sort");
        let mut keep = Vec::new();
        let sort = SortKeys {
            keys: &buf,
            n_sort: keys.len() as u64,
            count: &count,
            count_word: 0,
            n_tiles,
            label: "keys",
        };
        self.encode_sort_in(&mut encoder, &sort, &mut keep, None)?;
        // The buffer holds at least one key's bytes, even for no keys.
        let back = ctx.read_back(encoder, &[(&buf, keys.len().max(1) as u64 * 16)])?;
        Ok(bytes_u32(&back[0])
            .chunks_exact(4)
            .take(keys.len())
            .map(|k| [k[0], k[1], k[2], k[3]])
            .collect())
    }

    /// Projection, prefix sum (and the 4-byte entry-count readback), key generation,
    /// sort, tile ranges and blending of `inputs`' device buffers:
    /// [`Self::forward_device_prepare`] then [`Self::forward_device_blend`] with
    /// `inputs.chans`. `encoder` may already hold work that fills them (it is submitted
    /// first). Returns the forward's device state and an encoder with the sort and blend
    /// recorded but not submitted, so the caller appends its own readbacks or kernels.
    pub(super) fn forward_device(
        &self,
        inputs: DeviceInputs,
        encoder: wgpu::CommandEncoder,
        scratch: Option<&Scratch>,
        capacity: Option<u64>,
    ) -> Result<DeviceForward, GpuError> {
        let chans = inputs.chans.clone();
        let (prepared, encoder) =
            self.forward_device_prepare(inputs, encoder, scratch, capacity)?;
        Ok(self.forward_device_blend(prepared, chans, encoder))
    }

    /// The forward up to its blend: projection, prefix sum (and, without `capacity`, the
    /// 4-byte entry-count readback, which submits `encoder` and returns a fresh one), key
    /// generation, sort and tile ranges, recorded into the returned encoder; also
    /// uploads `settings.blend_tiles` and allocates the blend's outputs. `inputs.chans`
    /// only serves the projection's finiteness check (a Gaussian with a non-finite
    /// channel is culled, as on the CPU): a caller whose channels are not computed yet
    /// passes finite placeholders (zeros) and checks the real ones itself. Record
    /// [`Self::encode_contributing`] and then [`Self::forward_device_blend`] after it.
    ///
    /// With `capacity` the entry count is not read back: the sort's buffers hold
    /// `capacity` keys (it sorts the live ones) in the same encoder, and the caller checks the
    /// scanned total (`DevicePrepared::counts[n]`) against `n_sort` after the fact (keys
    /// beyond it were dropped).
    pub(super) fn forward_device_prepare(
        &self,
        inputs: DeviceInputs,
        mut encoder: wgpu::CommandEncoder,
        scratch: Option<&Scratch>,
        capacity: Option<u64>,
    ) -> Result<(DevicePrepared, wgpu::CommandEncoder), GpuError> {
        let DeviceInputs {
            camera,
            settings,
            n,
            nc,
            background,
            gauss,
            chans,
        } = inputs;
        let frame = camera_frame(camera, settings.near_m)?;
        let mode = AlphaMode {
            smooth: settings.smooth_cutoff,
        };
        let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
        let grid = TileGrid::new(width, height);
        if let Some(selection) = &settings.blend_tiles {
            if selection.image_size() != (width, height) {
                return Err(GpuError::Raster(RasterError::InvalidSettings(
                    "blend_tiles was built for another image size",
                )));
            }
        }
        let pipelines = self.channel_pipelines(nc)?;
        let ctx = &self.ctx;
        let tile_mask = storage_data_in(
            ctx,
            scratch,
            "tile mask",
            &u32_bytes(&tile_mask_words(settings, &grid)),
        )?;
        let frame0 = uniform_in(
            ctx,
            scratch,
            "frame (projection)",
            &frame_bytes(
                &frame,
                mode.cutoff(),
                &grid,
                n as u32,
                mode.smooth,
                0,
                0,
                background,
            ),
        )?;
        let splats = storage_in(ctx, scratch, "splats", (n * SSTRIDE * 4) as u64)?;
        // One extra zero at the end: its exclusive prefix sum is the entry count.
        let counts = storage_in(ctx, scratch, "tile counts", (n as u64 + 1) * 4)?;
        let mut keep = Vec::new();
        encoder.clear_buffer(&counts, 0, None);
        {
            let bind = ctx.bind_group(
                &pipelines.project,
                &[&frame0, &gauss, &chans, &splats, &counts],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &pipelines.project, &bind, n as u64);
        }
        self.encode_scan_in(&mut encoder, &counts, n as u64 + 1, &mut keep, scratch, 0)?;
        let (total, n_sort, mut encoder) = match capacity {
            None => {
                // Copy the total to a small buffer so the readback needs no offset.
                let total_buf = storage_in(ctx, scratch, "entry count", 4)?;
                encoder.copy_buffer_to_buffer(&counts, 4 * n as u64, &total_buf, 0, 4);
                let total = bytes_u32(&ctx.read_back(encoder, &[(&total_buf, 4)])?[0])[0] as u64;
                keep.clear();
                (Some(total), total, ctx.encoder("forward: sort and blend"))
            }
            Some(cap) => (None, cap, encoder),
        };
        if n_sort > u32::MAX as u64 / 2 {
            return Err(GpuError::TooLarge(format!("{n_sort} tile entries")));
        }
        let keys = storage_in(ctx, scratch, "keys", n_sort * 16)?;
        let frame = uniform_in(
            ctx,
            scratch,
            "frame",
            &with_blend_switches(
                frame_bytes(
                    &frame,
                    mode.cutoff(),
                    &grid,
                    n as u32,
                    mode.smooth,
                    total.map_or(ENTRIES_ON_DEVICE, |t| t as u32),
                    n_sort as u32,
                    background,
                ),
                settings,
            ),
        )?;
        let ranges = storage_in(ctx, scratch, "tile ranges", grid.n_tiles() as u64 * 8)?;
        let pixels = width as u64 * height as u64;
        let color = storage_in(ctx, scratch, "colour", pixels * nc as u64 * 4)?;
        let px_state = storage_in(ctx, scratch, "pixel state", pixels * 16)?;
        {
            let bind = ctx.bind_group(&pipelines.keygen, &[&frame, &splats, &counts, &keys]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &pipelines.keygen, &bind, n_sort.max(n as u64));
        }
        // The sort's uniforms (and, without a readback, the scan's temporaries) must
        // outlive the submission: the state keeps them.
        let mut sort_uniforms = keep;
        let sort = SortKeys {
            keys: &keys,
            n_sort,
            count: &counts,
            count_word: n as u32,
            n_tiles: grid.n_tiles() as u32,
            label: "tiles",
        };
        self.encode_sort_in(&mut encoder, &sort, &mut sort_uniforms, scratch)?;
        encoder.clear_buffer(&ranges, 0, None);
        {
            let bind = ctx.bind_group(&pipelines.ranges, &[&frame, &keys, &ranges]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &pipelines.ranges, &bind, n_sort);
        }
        let prepared = DevicePrepared {
            state: ForwardState {
                camera: *camera,
                settings: settings.clone(),
                n,
                nc,
                frame,
                gauss,
                chans,
                splats,
                keys,
                ranges,
                px_state,
                tile_mask,
                pipelines,
                grid,
            },
            color,
            tile_entries: total.map(|t| t as usize),
            n_sort,
            counts,
            sort_uniforms,
        };
        Ok((prepared, encoder))
    }

    /// Records the alpha-only walk of every blended tile of `prepared` (the blend's walk,
    /// stop and tile mask, without channels): `out_flags[g]` (u32) becomes 1 for each
    /// Gaussian `g` blended into at least one pixel, 0 for every other `g < n` (the
    /// buffer is cleared first). These are the Gaussians whose channels the blend and its
    /// backward read, as `gs_core::raster::PreparedView::contributing` on the CPU.
    pub(super) fn encode_contributing(
        &self,
        prepared: &DevicePrepared,
        encoder: &mut wgpu::CommandEncoder,
        out_flags: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        let st = &prepared.state;
        if out_flags.size() < st.n as u64 * 4 {
            return Err(GpuError::Invalid(format!(
                "contribution flags: {} bytes for {} Gaussians",
                out_flags.size(),
                st.n
            )));
        }
        encoder.clear_buffer(out_flags, 0, None);
        let p = &st.pipelines;
        let bind = self.ctx.bind_group(
            &p.contrib,
            &[
                &st.frame,
                &st.keys,
                &st.ranges,
                &st.splats,
                &st.tile_mask,
                out_flags,
            ],
        );
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(&p.contrib);
        pass.set_bind_group(0, &bind, &[]);
        pass.dispatch_workgroups(st.grid.tiles_x, st.grid.tiles_y, 1);
        Ok(())
    }

    /// Records the blend of `prepared` with `chans` (`n * nc` f32, the channels the
    /// backward reads too) into `encoder`: the rest of [`Self::forward_device`].
    pub(super) fn forward_device_blend(
        &self,
        prepared: DevicePrepared,
        chans: wgpu::Buffer,
        mut encoder: wgpu::CommandEncoder,
    ) -> DeviceForward {
        let DevicePrepared {
            mut state,
            color,
            tile_entries,
            n_sort,
            counts,
            sort_uniforms,
        } = prepared;
        state.chans = chans;
        {
            let st = &state;
            let bind = self.ctx.bind_group(
                &st.pipelines.blend,
                &[
                    &st.frame,
                    &st.keys,
                    &st.ranges,
                    &st.splats,
                    &st.chans,
                    &color,
                    &st.px_state,
                    &st.tile_mask,
                ],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&st.pipelines.blend);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(st.grid.tiles_x, st.grid.tiles_y, 1);
        }
        DeviceForward {
            state,
            color,
            encoder,
            tile_entries,
            n_sort,
            counts,
            _sort_uniforms: sort_uniforms,
        }
    }

    /// Checks `gaussians` and `settings` as [`gs_core::raster::render`] does and uploads
    /// them: the forward's inputs (with the resolved background).
    fn upload_view<'a>(
        &self,
        camera: &'a Camera,
        gaussians: &GaussianView,
        settings: &'a RasterSettings,
        background: &'a mut Vec<f32>,
    ) -> Result<DeviceInputs<'a>, GpuError> {
        camera_frame(camera, settings.near_m)?;
        let n = gaussians.len();
        let nc = gaussians.n_channels;
        check_len("means (3 per Gaussian)", 3 * n, gaussians.means.len())?;
        check_len(
            "log_scales (3 per Gaussian)",
            3 * n,
            gaussians.log_scales.len(),
        )?;
        check_len(
            "rotations (4 per Gaussian)",
            4 * n,
            gaussians.rotations.len(),
        )?;
        check_len(
            "channels (n_channels per Gaussian)",
            n.saturating_mul(nc),
            gaussians.channels.len(),
        )?;
        if nc > MAX_GPU_CHANNELS {
            return Err(GpuError::TooLarge(format!(
                "{nc} channels (the GPU kernels take at most {MAX_GPU_CHANNELS})"
            )));
        }
        if n >= (u32::MAX as usize) / (GSTRIDE + SSTRIDE) {
            return Err(GpuError::TooLarge(format!("{n} Gaussians")));
        }
        *background = if settings.background.is_empty() {
            vec![0.0; nc]
        } else {
            check_len(
                "background (one value per channel)",
                nc,
                settings.background.len(),
            )?;
            if !settings.background.iter().all(|v| v.is_finite()) {
                return Err(GpuError::Invalid("background is not finite".into()));
            }
            settings.background.clone()
        };
        let mut packed = Vec::with_capacity(n * GSTRIDE);
        for i in 0..n {
            packed.extend_from_slice(&gaussians.means[3 * i..3 * i + 3]);
            packed.extend_from_slice(&gaussians.log_scales[3 * i..3 * i + 3]);
            packed.extend_from_slice(&gaussians.rotations[4 * i..4 * i + 4]);
            packed.push(gaussians.opacity_logits[i]);
        }
        let ctx = &self.ctx;
        Ok(DeviceInputs {
            camera,
            settings,
            n,
            nc,
            background,
            gauss: ctx.storage_init("gaussians", &f32_bytes(&packed)),
            chans: ctx.storage_init("channels", &f32_bytes(gaussians.channels)),
        })
    }

    /// Per Gaussian: blended into at least one pixel of a blended tile (the device's
    /// contribution pass, [`Self::encode_contributing`]); the same list as
    /// [`gs_core::raster::PreparedView::contributing`] of `prepare_view(camera, geometry,
    /// settings)` where no tile is left out. The view's channels are ignored.
    pub fn contributing(
        &self,
        camera: &Camera,
        geometry: &GaussianView,
        settings: &RasterSettings,
    ) -> Result<Vec<bool>, GpuError> {
        let bare = GaussianView {
            channels: &[],
            n_channels: 0,
            ..*geometry
        };
        let bare_settings = RasterSettings {
            background: Vec::new(),
            ..settings.clone()
        };
        let mut background = Vec::new();
        let inputs = self.upload_view(camera, &bare, &bare_settings, &mut background)?;
        let n = inputs.n;
        let ctx = &self.ctx;
        let (prepared, mut encoder) =
            self.forward_device_prepare(inputs, ctx.encoder("contributing"), None, None)?;
        let flags = ctx.storage("contribution flags", n as u64 * 4)?;
        self.encode_contributing(&prepared, &mut encoder, &flags)?;
        let back = ctx.read_back(encoder, &[(&flags, n as u64 * 4)])?;
        Ok(bytes_u32(&back[0]).iter().map(|&f| f != 0).collect())
    }

    /// Renders `gaussians` from `camera` (same inputs, checks and outputs as
    /// [`gs_core::raster::render`]).
    pub fn render(
        &self,
        camera: &Camera,
        gaussians: &GaussianView,
        settings: &RasterSettings,
    ) -> Result<GpuRenderOutput, GpuError> {
        let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
        let ctx = &self.ctx;
        let t0 = Instant::now();
        let mut background = Vec::new();
        let inputs = self.upload_view(camera, gaussians, settings, &mut background)?;
        let (n, nc) = (inputs.n, inputs.nc);
        let fwd = self.forward_device(inputs, ctx.encoder("forward: project"), None, None)?;
        let project_scan_ms = ms_since(t0);
        let t1 = Instant::now();
        let pixels = width as u64 * height as u64;
        let back = ctx.read_back(
            fwd.encoder,
            &[
                (&fwd.color, pixels * nc as u64 * 4),
                (&fwd.state.px_state, pixels * 16),
                (&fwd.state.splats, (n * SSTRIDE * 4) as u64),
            ],
        )?;
        let total = fwd.tile_entries.unwrap_or(0);
        let state = fwd.state;
        let color = bytes_f32(&back[0]);
        let px = bytes_f32(&back[1]);
        let alpha = px.chunks_exact(4).map(|p| p[0]).collect();
        let depth = px.chunks_exact(4).map(|p| p[1]).collect();
        let sp = bytes_f32(&back[2]);
        let mut radii_px = Vec::with_capacity(n);
        let mut visible = Vec::with_capacity(n);
        for s in sp.chunks_exact(SSTRIDE) {
            visible.push(s[7] >= 0.0);
            radii_px.push(s[7].max(0.0));
        }
        let sort_blend_ms = ms_since(t1);
        Ok(GpuRenderOutput {
            width,
            height,
            n_channels: nc,
            color,
            alpha,
            depth,
            radii_px,
            visible,
            tile_entries: total,
            timings: GpuForwardTimings {
                project_scan_ms,
                sort_blend_ms,
            },
            state,
        })
    }

    /// Gradients of a loss with respect to the Gaussians of `forward` (rendered by this
    /// rasterizer), given its pixel gradients. Same layouts as
    /// [`gs_core::raster::render_backward`]; `camera` and `settings` must be the forward's.
    pub fn render_backward(
        &self,
        camera: &Camera,
        settings: &RasterSettings,
        forward: &GpuRenderOutput,
        grads: &PixelGrads,
    ) -> Result<GaussianGrads, GpuError> {
        let st = &forward.state;
        if *camera != st.camera {
            return Err(GpuError::Invalid(
                "backward camera differs from the forward's".into(),
            ));
        }
        if *settings != st.settings {
            return Err(GpuError::Invalid(
                "backward settings differ from the forward's".into(),
            ));
        }
        let (n, nc) = (st.n, st.nc);
        let pixels = forward.width as usize * forward.height as usize;
        let finite = |what: &str, v: &[f32], len: usize| -> Result<(), GpuError> {
            check_len(what, len, v.len())?;
            if v.iter().all(|x| x.is_finite()) {
                Ok(())
            } else {
                Err(GpuError::Invalid(format!("{what} contains NaN or Inf")))
            }
        };
        finite("d_color", grads.d_color, pixels * nc)?;
        if let Some(d) = grads.d_alpha {
            finite("d_alpha", d, pixels)?;
        }
        if let Some(d) = grads.d_depth {
            finite("d_depth", d, pixels)?;
        }
        let t0 = Instant::now();
        let pgs = nc + 2;
        let mut px_grad = vec![0.0f32; pixels * pgs];
        for (p, row) in px_grad.chunks_exact_mut(pgs).enumerate() {
            row[..nc].copy_from_slice(&grads.d_color[p * nc..p * nc + nc]);
            row[nc] = grads.d_alpha.map_or(0.0, |d| d[p]);
            row[nc + 1] = grads.d_depth.map_or(0.0, |d| d[p]);
        }
        let ctx = &self.ctx;
        let px_grad = ctx.storage_init("pixel grads", &f32_bytes(&px_grad));
        let ostride = OUT_FIXED + nc;
        let mut encoder = ctx.encoder("backward");
        let out = self.encode_backward(st, forward.tile_entries, &px_grad, &mut encoder, None)?;
        let back = ctx.read_back(encoder, &[(&out, (n * ostride * 4) as u64)])?;
        let rows = bytes_f32(&back[0]);
        let mut g = GaussianGrads {
            d_means: vec![0.0; 3 * n],
            d_log_scales: vec![0.0; 3 * n],
            d_rotations: vec![0.0; 4 * n],
            d_opacity_logits: vec![0.0; n],
            d_channels: vec![0.0; nc * n],
            mean2d_grad_ndc: vec![0.0; n],
            dropped_nonfinite: 0,
            timings: BackwardTimings::default(),
        };
        for (i, r) in rows.chunks_exact(ostride).enumerate() {
            g.d_means[3 * i..3 * i + 3].copy_from_slice(&r[0..3]);
            g.d_log_scales[3 * i..3 * i + 3].copy_from_slice(&r[3..6]);
            g.d_rotations[4 * i..4 * i + 4].copy_from_slice(&r[6..10]);
            g.d_opacity_logits[i] = r[10];
            g.mean2d_grad_ndc[i] = r[11];
            if r[12] != 0.0 {
                g.dropped_nonfinite += 1;
            }
            g.d_channels[nc * i..nc * i + nc].copy_from_slice(&r[OUT_FIXED..]);
        }
        // Both kernels run in one submission: without timestamp queries the split is not
        // observable, so the whole backward (upload to readback) counts as blending.
        g.timings = BackwardTimings {
            blend_ms: ms_since(t0),
            reduce_project_ms: 0.0,
        };
        Ok(g)
    }

    /// Records the backward of a forward's device state: per-tile blending backward
    /// (and, in deterministic mode, the gather) and the projection backward, reading
    /// per-pixel gradients `[d_color (nc), d_alpha, d_depth]` from `px_grad`. Returns
    /// the per-Gaussian output rows (`13 + nc` floats, see project_backward.wgsl).
    pub(super) fn encode_backward(
        &self,
        st: &ForwardState,
        tile_entries: usize,
        px_grad: &wgpu::Buffer,
        encoder: &mut wgpu::CommandEncoder,
        scratch: Option<&Scratch>,
    ) -> Result<wgpu::Buffer, GpuError> {
        let (n, nc) = (st.n, st.nc);
        let ctx = &self.ctx;
        let rec = REC_CHANNELS + nc;
        let acc = storage_in(ctx, scratch, "grad accumulators", (n * rec * 4) as u64)?;
        let ostride = OUT_FIXED + nc;
        let out = storage_in(ctx, scratch, "gaussian grads", (n * ostride * 4) as u64)?;
        let p = &st.pipelines;
        // Deterministic mode: the blend kernel writes per-entry records, summed into `acc`
        // by the gather kernel.
        let records = match p.gather {
            Some(_) => Some(storage_in(
                ctx,
                scratch,
                "grad records",
                (tile_entries.max(1) * rec * 4) as u64,
            )?),
            None => None,
        };
        encoder.clear_buffer(&acc, 0, None);
        // Rows of culled or dropped Gaussians are left as zeros by the kernel.
        encoder.clear_buffer(&out, 0, None);
        if let Some(r) = &records {
            encoder.clear_buffer(r, 0, None);
        }
        {
            let bind = ctx.bind_group(
                &p.blend_backward,
                &[
                    &st.frame,
                    &st.keys,
                    &st.ranges,
                    &st.splats,
                    &st.chans,
                    &st.px_state,
                    px_grad,
                    records.as_ref().unwrap_or(&acc),
                    &st.tile_mask,
                ],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&p.blend_backward);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(st.grid.tiles_x, st.grid.tiles_y, 1);
        }
        if let (Some(gather), Some(records)) = (&p.gather, &records) {
            let bind = ctx.bind_group(
                gather,
                &[&st.frame, &st.splats, &st.keys, &st.ranges, records, &acc],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, gather, &bind, n as u64);
        }
        {
            let bind = ctx.bind_group(
                &p.project_backward,
                &[&st.frame, &st.gauss, &st.splats, &acc, &out],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &p.project_backward, &bind, n as u64);
        }
        Ok(out)
    }
}

/// Tile edge, pixels (the WGSL `TILE` constant must match).
const _: () = assert!(TILE_PX == 16);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn radix_digits_cover_the_order_bits_then_the_tile_bits() {
        let order: Vec<(u32, u32)> = (0..8).map(|d| (1, 4 * d)).collect();
        assert_eq!(radix_digits(0), order);
        assert_eq!(radix_digits(1), order);
        // (tiles, tile digits): 2..=16 tiles need 1 to 4 bits, 17 need 5.
        for (n_tiles, tile_digits) in [(2, 1), (16, 1), (17, 2), (4096, 3), (4097, 4)] {
            let digits = radix_digits(n_tiles);
            assert_eq!(digits[..8], order[..], "{n_tiles} tiles");
            let tile: Vec<(u32, u32)> = (0..tile_digits).map(|d| (0, 4 * d)).collect();
            assert_eq!(digits[8..], tile[..], "{n_tiles} tiles");
        }
        assert_eq!(radix_digits(u32::MAX).len(), 16);
    }
}
