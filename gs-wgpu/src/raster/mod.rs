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
//! Files: `forward.rs` and `backward.rs` record the passes, `sort.rs` the prefix sum and
//! the radix sort; this one holds the pipelines, the pass state and the uniform layouts.
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

mod backward;
mod forward;
mod sort;

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
use sort::RadixPipelines;
pub(crate) use sort::SortKeys;

/// Most channels the GPU kernels take (the backward's workgroup reduction holds
/// `(7 + channels) * 256` floats in 16 KiB of workgroup memory).
pub const MAX_GPU_CHANNELS: usize = 8;

const COMMON: &str = include_str!("../shaders/common.wgsl");
const PROJECT: &str = include_str!("../shaders/project.wgsl");
const SCAN_BLOCK: &str = include_str!("../shaders/scan_block.wgsl");
const SCAN_ADD: &str = include_str!("../shaders/scan_add.wgsl");
const KEYGEN: &str = include_str!("../shaders/keygen.wgsl");
const RANGES: &str = include_str!("../shaders/ranges.wgsl");
const BLEND: &str = include_str!("../shaders/blend.wgsl");
const BLEND_BACKWARD: &str = include_str!("../shaders/blend_backward.wgsl");
const BLEND_BACKWARD_DIRECT: &str = include_str!("../shaders/blend_backward_direct.wgsl");
const CONTRIB: &str = include_str!("../shaders/contrib.wgsl");
const ACC_F32: &str = include_str!("../shaders/acc_f32.wgsl");
const ACC_CAS: &str = include_str!("../shaders/acc_cas.wgsl");
const ACC_RECORDS: &str = include_str!("../shaders/acc_records.wgsl");
const GATHER: &str = include_str!("../shaders/gather.wgsl");
const PROJECT_BACKWARD: &str = include_str!("../shaders/project_backward.wgsl");

/// Values per Gaussian in the gradient readback: 12 parameter/NDC values, a dropped flag,
/// then the channels.
const OUT_FIXED: usize = 13;
/// Per-Gaussian input stride (mean 3, log-scale 3, quaternion 4, opacity logit 1).
const GSTRIDE: usize = 11;
/// Per-splat stride on the device (see common.wgsl).
pub(super) const SSTRIDE: usize = 12;
/// Splats per batch staged in workgroup memory by the blend kernels (`BATCH` in WGSL).
const BATCH: usize = 128;

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
}

/// Tile edge, pixels (the WGSL `TILE` constant must match).
const _: () = assert!(TILE_PX == 16);
