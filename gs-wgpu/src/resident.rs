//! Device-resident training state for the plain 3DGS trainer: parameters, gradients,
//! Adam moments and densification statistics live in device buffers across iterations,
//! and a step's SH colour, rasterizer forward, loss (L1 + SSIM, `super::loss`), loss
//! gradient, rasterizer backward, gradient assembly, statistics and Adam update run as
//! kernels on them ([`ResidentModel::step`]).
//!
//! Layout: every per-Gaussian buffer (parameters, gradients, both moments) is one packed,
//! group-major array in [`Param`] order: group `g` holds its `n * dim(g)` values,
//! row-major, starting at `offsets[g]` (a [`ParamSet`]'s groups laid end to end). The
//! statistics buffer holds `grad_accum`, `visible_count` and `max_radius_px`, `n` each.
//!
//! Per step the host uploads the target image and the pixel weights (into persistent
//! buffers) and a few small uniforms, submits the whole step as one command buffer and
//! waits once, for 20 bytes (refusal flags, rows dropped, SSIM and L1 totals, the entry
//! count). The sort is sized from the previous step's entry count with head room; a step
//! whose count outgrows it is refused by the device (nothing applied) and redone with the
//! exact count (the first step reads the count back before sorting).
//! Parameters, moments and statistics come back only when the caller asks
//! ([`ResidentModel::download`]: densification, checkpoints, the end of a run); after the
//! host edits them, [`ResidentModel::upload`] puts them back (buffers grow with 50% head
//! room, so densification reallocates rarely). The per-step scratch of the rasterizer and
//! the loss (splats, keys, tile ranges, images, accumulators, the sort's uniforms) comes
//! from a pool that keeps each buffer across steps and grows it when needed
//! (`super::Scratch`): a steady-state step allocates no device memory.
//!
//! Invariants:
//! - the same arithmetic as the CPU path: `sh.rs` colour and its backward, `optim.rs`'s
//!   Adam (torch formulation, eps from the host, step sizes and bias corrections computed
//!   in f64 on the host), `densify.rs` statistics; checked in `tests/gpu_resident.rs`;
//! - a step with any non-finite gradient changes nothing (parameters, moments,
//!   statistics, step count), as on the CPU;
//! - the host's Adam step counter mirrors the device's (it is what bias correction reads).

use std::sync::Arc;

use super::loss::{combine, pixel_weights, GpuLoss};
use super::raster::{DeviceInputs, GpuRasterizer};
use super::{
    bytes_f32, bytes_u32, dispatch_1d, f32_bytes, u32_bytes, GpuContext, GpuError, Scratch,
};
use gs_core::camera::Camera;
use gs_core::densify::DensifyStats;
use gs_core::loss::ImageShape;
use gs_core::model::{Param, ParamSet};
use gs_core::optim::{Adam, GroupRates};
use gs_core::raster::RasterSettings;

pub(super) const RESIDENT_COMMON: &str = include_str!("shaders/resident_common.wgsl");
pub(super) const RESIDENT_COLOUR: &str = include_str!("shaders/resident_colour.wgsl");
pub(super) const RESIDENT_PACK: &str = include_str!("shaders/resident_pack.wgsl");
pub(super) const RESIDENT_GRADS: &str = include_str!("shaders/resident_grads.wgsl");
pub(super) const RESIDENT_STATS: &str = include_str!("shaders/resident_stats.wgsl");
pub(super) const ADAM: &str = include_str!("shaders/adam.wgsl");
pub(super) const RESIDENT_OVERFLOW: &str = include_str!("shaders/resident_overflow.wgsl");
/// Refusal bits of `flags[0]`: a non-finite render or gradient; the sort's capacity was
/// too small (the step is redone).
pub(super) const REFUSED_NONFINITE: u32 = 1;
pub(super) const REFUSED_OVERFLOW: u32 = 2;
/// Steps whose entry counts size the sort (a few passes over a training view set).
pub(super) const RECENT_STEPS: usize = 32;

/// Channels of the plain trainer's render (RGB).
const CHANNELS: usize = 3;
/// Floats per rasterizer gradient row with RGB (project_backward.wgsl: 13 + channels).
const OSTRIDE: u32 = 13 + CHANNELS as u32;
/// Floats per rasterizer input row (mean 3, log-scale 3, quaternion 4, opacity logit 1).
pub(super) const GSTRIDE: u64 = 11;

/// Compiled kernels of the resident path.
struct ResidentPipelines {
    pack: wgpu::ComputePipeline,
    grads: wgpu::ComputePipeline,
    stats: wgpu::ComputePipeline,
    adam: wgpu::ComputePipeline,
    overflow: wgpu::ComputePipeline,
    loss: GpuLoss,
}

/// The Gaussians' device state, sized for `capacity` Gaussians: the packed parameters,
/// a gradient of the same layout, both Adam moments and the densification statistics
/// (`grad_accum`, `visible_count`, `max_radius_px`, `n` each: resident_stats.wgsl). The
/// plain and the Sun-aware resident trainers both keep their Gaussians in one.
pub(super) struct GaussianBuffers {
    pub capacity: usize,
    pub params: wgpu::Buffer,
    pub grads: wgpu::Buffer,
    pub m: wgpu::Buffer,
    pub v: wgpu::Buffer,
    pub stats: wgpu::Buffer,
}

impl GaussianBuffers {
    /// Buffers for `capacity` rows of `dims` (labels start with `label`).
    pub(super) fn allocate(
        ctx: &GpuContext,
        label: &str,
        dims: &[usize; Param::COUNT],
        capacity: usize,
    ) -> Result<Self, GpuError> {
        let values = (row_width(dims) * capacity).max(1) as u64 * 4;
        Ok(Self {
            capacity,
            params: ctx.storage(&format!("{label} params"), values)?,
            grads: ctx.storage(&format!("{label} grads"), values)?,
            m: ctx.storage(&format!("{label} adam m"), values)?,
            v: ctx.storage(&format!("{label} adam v"), values)?,
            stats: ctx.storage(
                &format!("{label} densify stats"),
                capacity.max(1) as u64 * 12,
            )?,
        })
    }

    /// Writes the host's parameters, moments and statistics (the caller checked their
    /// shapes against each other and that they fit the capacity).
    pub(super) fn write(
        &self,
        ctx: &GpuContext,
        params: &ParamSet,
        adam: &Adam,
        stats: &DensifyStats,
    ) {
        let q = &ctx.queue;
        q.write_buffer(&self.params, 0, &pad4(f32_bytes(&pack(params))));
        q.write_buffer(&self.m, 0, &pad4(f32_bytes(&pack(&adam.m))));
        q.write_buffer(&self.v, 0, &pad4(f32_bytes(&pack(&adam.v))));
        let mut words: Vec<u32> = stats.grad_accum.iter().map(|v| v.to_bits()).collect();
        words.extend_from_slice(&stats.visible_count);
        words.extend(stats.max_radius_px.iter().map(|v| v.to_bits()));
        q.write_buffer(&self.stats, 0, &pad4(u32_bytes(&words)));
    }

    /// Reads the first `params.len()` rows back into the host's parameters, moments and
    /// statistics (shapes checked by the caller; `adam.step` is the caller's to set).
    pub(super) fn read(
        &self,
        ctx: &GpuContext,
        params: &mut ParamSet,
        adam: &mut Adam,
        stats: &mut DensifyStats,
    ) -> Result<(), GpuError> {
        let n = params.len();
        let values = (row_width(&params.dims()) * n) as u64 * 4;
        let back = ctx.read_back(
            ctx.encoder("resident download"),
            &[
                (&self.params, values),
                (&self.m, values),
                (&self.v, values),
                (&self.stats, n as u64 * 12),
            ],
        )?;
        unpack(&bytes_f32(&back[0]), params);
        unpack(&bytes_f32(&back[1]), &mut adam.m);
        unpack(&bytes_f32(&back[2]), &mut adam.v);
        let words = bytes_u32(&back[3]);
        stats.grad_accum = words[..n].iter().map(|w| f32::from_bits(*w)).collect();
        stats.visible_count = words[n..2 * n].to_vec();
        stats.max_radius_px = words[2 * n..3 * n]
            .iter()
            .map(|w| f32::from_bits(*w))
            .collect();
        Ok(())
    }
}

/// One step's inputs (see [`ResidentModel::step`]).
#[derive(Clone, Copy, Debug)]
pub struct ResidentStepInput<'a> {
    pub camera: &'a Camera,
    pub settings: &'a RasterSettings,
    /// Active SH degree.
    pub degree: u32,
    /// Add this step's screen-space gradients and radii to the densification statistics.
    pub accumulate_stats: bool,
    /// `H * W * 3` RGB.
    pub target: &'a [f32],
    /// Optional `H * W` foreground weights in [0, 1] (loss.rs's mask).
    pub mask: Option<&'a [f32]>,
    pub lambda_dssim: f32,
    pub rates: &'a GroupRates,
}

/// Persistent per-image buffers (reallocated when the image size changes).
struct ImageBuffers {
    pixels: usize,
    target: wgpu::Buffer,
    weights: wgpu::Buffer,
    px_grad: wgpu::Buffer,
}

/// What a resident step did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ResidentStepReport {
    /// The render or a gradient was NaN or infinite: nothing was changed.
    pub refused: bool,
    /// The sort's capacity (from the last step's count) was too small: nothing was
    /// changed. [`ResidentModel::step`] then redoes the step, so its report has `false`
    /// here and `sort_retries == 1`.
    pub sort_overflow: bool,
    /// Steps redone for a sort overflow (0 or 1).
    pub sort_retries: usize,
    /// Gaussians whose rasterizer gradient came out non-finite and was zeroed.
    pub dropped_nonfinite: usize,
    /// `(1 - lambda) l1 + lambda (1 - ssim)`, and its parts (masked means).
    pub loss: f32,
    pub l1: f32,
    pub ssim: f32,
    /// (tile, Gaussian) pairs blended.
    pub tile_entries: usize,
    /// Wall time of recording and, on the first step (no count to size the sort from),
    /// the entry-count readback, ms.
    pub project_ms: f64,
    /// Wall time of the rest (the whole step's device work and the final readback), ms.
    pub rest_ms: f64,
}

/// Parameters, gradients, Adam moments and densification statistics on the device.
pub struct ResidentModel {
    raster: Arc<GpuRasterizer>,
    pipelines: ResidentPipelines,
    dims: [usize; Param::COUNT],
    n: usize,
    buffers: GaussianBuffers,
    /// `[refused, dropped]` counters of the last step.
    flags: wgpu::Buffer,
    images: Option<ImageBuffers>,
    /// Per-step scratch of the rasterizer, the loss and the kernels' uniforms, reused.
    scratch: Scratch,
    /// Entry counts of the last steps (at most [`RECENT_STEPS`]): their maximum sizes the
    /// next step's sort without a readback.
    recent_entries: std::collections::VecDeque<u64>,
    /// Adam steps taken (bias correction), mirrored to the host's `Adam::step`.
    adam_step: u64,
    beta1: f32,
    beta2: f32,
    eps: f32,
}

impl std::fmt::Debug for ResidentModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "ResidentModel({} Gaussians, capacity {}, {} Adam steps)",
            self.n, self.buffers.capacity, self.adam_step
        )
    }
}

fn row_width(dims: &[usize; Param::COUNT]) -> usize {
    dims.iter().sum()
}

/// Start of each group in the packed layout for `n` rows, and the total.
pub(crate) fn offsets(
    dims: &[usize; Param::COUNT],
    n: usize,
) -> Result<[u32; Param::COUNT + 1], GpuError> {
    let mut out = [0u32; Param::COUNT + 1];
    let mut at = 0u64;
    for (g, d) in dims.iter().enumerate() {
        out[g] = u32::try_from(at)
            .map_err(|_| GpuError::TooLarge(format!("{n} Gaussians of {dims:?} values")))?;
        at += (*d as u64) * n as u64;
    }
    out[Param::COUNT] = u32::try_from(at)
        .map_err(|_| GpuError::TooLarge(format!("{n} Gaussians of {dims:?} values")))?;
    Ok(out)
}

/// A [`ParamSet`]'s groups end to end.
pub(crate) fn pack(set: &ParamSet) -> Vec<f32> {
    let mut out = Vec::with_capacity(set.len() * row_width(&set.dims()));
    for p in Param::ALL {
        out.extend_from_slice(set.get(p));
    }
    out
}

/// Packed values back into `set` (same dims and rows).
pub(crate) fn unpack(values: &[f32], set: &mut ParamSet) {
    let mut at = 0;
    for p in Param::ALL {
        let dst = set.get_mut(p);
        let len = dst.len();
        dst.copy_from_slice(&values[at..at + len]);
        at += len;
    }
}

impl ResidentModel {
    /// Compiles the kernels and uploads `params`, the optimiser state and the statistics.
    pub fn new(
        raster: Arc<GpuRasterizer>,
        params: &ParamSet,
        adam: &Adam,
        stats: &DensifyStats,
    ) -> Result<Self, GpuError> {
        let ctx = raster.context();
        let common = format!("{RESIDENT_COMMON}\n");
        let pipelines = ResidentPipelines {
            pack: ctx.pipeline(
                "resident_pack",
                &format!("{common}{RESIDENT_COLOUR}\n{RESIDENT_PACK}"),
            )?,
            grads: ctx.pipeline(
                "resident_grads",
                &format!("{common}{RESIDENT_COLOUR}\n{RESIDENT_GRADS}"),
            )?,
            stats: ctx.pipeline("resident_stats", &format!("{common}{RESIDENT_STATS}"))?,
            adam: ctx.pipeline("adam", ADAM)?,
            overflow: ctx.pipeline("resident_overflow", RESIDENT_OVERFLOW)?,
            loss: GpuLoss::new(ctx, CHANNELS)?,
        };
        let buffers =
            GaussianBuffers::allocate(ctx, "resident", &params.dims(), params.len().max(1))?;
        let flags = ctx.storage("resident step flags", 8)?;
        let mut out = Self {
            raster,
            pipelines,
            dims: params.dims(),
            n: 0,
            buffers,
            flags,
            images: None,
            scratch: Scratch::default(),
            recent_entries: std::collections::VecDeque::new(),
            adam_step: 0,
            beta1: adam.beta1,
            beta2: adam.beta2,
            eps: adam.eps,
        };
        out.upload(params, adam, stats)?;
        Ok(out)
    }

    pub fn len(&self) -> usize {
        self.n
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Gaussians the buffers hold without reallocating.
    pub fn capacity(&self) -> usize {
        self.buffers.capacity
    }

    /// Adam steps taken on the device.
    pub fn adam_step(&self) -> u64 {
        self.adam_step
    }

    fn check_shapes(
        &self,
        params: &ParamSet,
        adam: &Adam,
        stats: &DensifyStats,
    ) -> Result<(), GpuError> {
        let same = |a: &ParamSet| a.dims() == self.dims && a.len() == params.len();
        if params.dims() != self.dims || !same(&adam.m) || !same(&adam.v) {
            return Err(GpuError::Invalid(format!(
                "parameter set ({} rows, widths {:?}) and moments ({} and {} rows) differ \
                 from each other or from the resident layout (widths {:?})",
                params.len(),
                params.dims(),
                adam.m.len(),
                adam.v.len(),
                self.dims
            )));
        }
        if stats.len() != params.len() {
            return Err(GpuError::Invalid(format!(
                "densification statistics have {} rows, the parameters {}",
                stats.len(),
                params.len()
            )));
        }
        Ok(())
    }

    /// Replaces the device state with the host's (after densification, an opacity reset,
    /// a checkpoint load). Grows the buffers, with 50% head room, when they are too small.
    pub fn upload(
        &mut self,
        params: &ParamSet,
        adam: &Adam,
        stats: &DensifyStats,
    ) -> Result<(), GpuError> {
        self.check_shapes(params, adam, stats)?;
        let n = params.len();
        offsets(&self.dims, n)?;
        let ctx = self.raster.context();
        if n > self.buffers.capacity {
            let capacity = n.saturating_add(n / 2);
            self.buffers = GaussianBuffers::allocate(ctx, "resident", &self.dims, capacity)?;
        }
        self.buffers.write(ctx, params, adam, stats);
        self.n = n;
        self.adam_step = adam.step;
        (self.beta1, self.beta2, self.eps) = (adam.beta1, adam.beta2, adam.eps);
        Ok(())
    }

    /// Copies the device state into the host's parameters, optimiser and statistics,
    /// which must have the resident row count and widths.
    pub fn download(
        &self,
        params: &mut ParamSet,
        adam: &mut Adam,
        stats: &mut DensifyStats,
    ) -> Result<(), GpuError> {
        if params.len() != self.n {
            return Err(GpuError::Invalid(format!(
                "host parameter set has {} rows, the device {}",
                params.len(),
                self.n
            )));
        }
        self.check_shapes(params, adam, stats)?;
        self.buffers
            .read(self.raster.context(), params, adam, stats)?;
        adam.step = self.adam_step;
        Ok(())
    }

    /// The gradient buffer as a parameter set (tests, diagnostics).
    pub fn download_grads(&self) -> Result<ParamSet, GpuError> {
        let mut out = ParamSet::new(self.dims);
        out.push_zeros(self.n);
        let values = (row_width(&self.dims) * self.n) as u64 * 4;
        let ctx = self.raster.context();
        let back = ctx.read_back(
            ctx.encoder("resident grads"),
            &[(&self.buffers.grads, values)],
        )?;
        unpack(&bytes_f32(&back[0]), &mut out);
        Ok(out)
    }

    /// Overwrites the gradient buffer (tests of the Adam kernel on its own).
    pub fn upload_grads(&self, grads: &ParamSet) -> Result<(), GpuError> {
        if grads.dims() != self.dims || grads.len() != self.n {
            return Err(GpuError::Invalid(format!(
                "gradient set ({} rows, widths {:?}) differs from the resident layout \
                 ({} rows, widths {:?})",
                grads.len(),
                grads.dims(),
                self.n,
                self.dims
            )));
        }
        self.raster.context().queue.write_buffer(
            &self.buffers.grads,
            0,
            &pad4(f32_bytes(&pack(grads))),
        );
        Ok(())
    }

    /// One Adam step on the gradient buffer as it stands, refused (nothing changes) when
    /// any gradient is non-finite. Returns whether it was applied.
    pub fn adam_step_on_grads(&mut self, rates: &GroupRates) -> Result<bool, GpuError> {
        let ctx = self.raster.context();
        let mut encoder = ctx.encoder("resident adam");
        encoder.clear_buffer(&self.flags, 0, None);
        // The finiteness check of a plain Adam step: the grads kernel's flag, here from
        // the host (the buffer is small next to the kernels' work only in tests).
        let grads_back = ctx.read_back(
            ctx.encoder("resident grads check"),
            &[(
                &self.buffers.grads,
                (row_width(&self.dims) * self.n) as u64 * 4,
            )],
        )?;
        if bytes_f32(&grads_back[0]).iter().any(|g| !g.is_finite()) {
            return Ok(false);
        }
        let keep = self.encode_adam(&mut encoder, rates)?;
        ctx.queue.submit(Some(encoder.finish()));
        drop(keep);
        self.adam_step += 1;
        Ok(true)
    }

    /// Records the Adam kernel for step `adam_step + 1` (guarded by the refused flag).
    fn encode_adam(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        rates: &GroupRates,
    ) -> Result<wgpu::Buffer, GpuError> {
        let words = adam_words(
            &self.dims,
            self.n,
            rates,
            self.adam_step + 1,
            (self.beta1, self.beta2, self.eps),
        )?;
        let ctx = self.raster.context();
        let uniform = self.scratch.uniform(ctx, "adam", &u32_bytes(&words))?;
        let b = &self.buffers;
        let bind = ctx.bind_group(
            &self.pipelines.adam,
            &[&uniform, &b.params, &b.grads, &b.m, &b.v, &self.flags],
        );
        let mut pass = encoder.begin_compute_pass(&Default::default());
        dispatch_1d(&mut pass, &self.pipelines.adam, &bind, words[8] as u64);
        drop(pass);
        Ok(uniform)
    }

    fn step_uniform(&self, camera: &Camera, degree: u32, accumulate_stats: bool) -> Vec<u8> {
        step_words(
            &self.dims,
            self.n,
            Some(degree),
            camera,
            accumulate_stats,
            OSTRIDE,
        )
    }

    /// One training step on the device: SH colour at `degree` from the camera centre,
    /// the rasterizer forward, the loss against `target` (uploaded into a persistent
    /// buffer), its gradient, the rasterizer backward, gradient assembly, statistics (when
    /// `accumulate_stats`) and one Adam step with `rates`, in one submission with one
    /// 20-byte readback (the first step, and a step redone after a sort overflow, also
    /// wait for the entry count before sorting).
    pub fn step(&mut self, input: &ResidentStepInput) -> Result<ResidentStepReport, GpuError> {
        // The sort is sized from the recent steps' largest entry count with a little head
        // room (head room costs key memory, not sort work: the radix sort reads the live
        // count on the device), so the step needs no mid-step readback; a step that
        // outgrows it is redone at the exact count (nothing was applied: the overflow
        // refuses it).
        let capacity = self.recent_entries.iter().max().map(|&e| e + e / 16 + 256);
        let report = self.step_with_capacity(input, capacity)?;
        if report.sort_overflow {
            let mut again = self.step_with_capacity(input, Some(report.tile_entries as u64))?;
            again.sort_retries = 1;
            return Ok(again);
        }
        Ok(report)
    }

    fn step_with_capacity(
        &mut self,
        input: &ResidentStepInput,
        capacity: Option<u64>,
    ) -> Result<ResidentStepReport, GpuError> {
        let ResidentStepInput {
            camera,
            settings,
            degree,
            accumulate_stats,
            target,
            mask,
            lambda_dssim,
            rates,
        } = *input;
        let rest = self.dims[Param::ShRest.index()];
        let stored = match rest / 3 {
            0 => 0,
            3 => 1,
            8 => 2,
            _ => 3,
        };
        if degree > stored || self.dims[Param::ShDc.index()] != 3 {
            return Err(GpuError::Invalid(format!(
                "SH degree {degree} requested; the model stores degree {stored} \
                 (DC width {})",
                self.dims[Param::ShDc.index()]
            )));
        }
        let background = if settings.background.is_empty() {
            vec![0.0; CHANNELS]
        } else if settings.background.len() == CHANNELS
            && settings.background.iter().all(|v| v.is_finite())
        {
            settings.background.clone()
        } else {
            return Err(GpuError::Invalid(
                "background must be 3 finite values".into(),
            ));
        };
        let shape = ImageShape::new(
            camera.intrinsics.width as usize,
            camera.intrinsics.height as usize,
            CHANNELS,
        );
        if target.len() != shape.values() || shape.values() == 0 {
            return Err(GpuError::Invalid(format!(
                "target image: expected {} values (H * W * 3), got {}",
                shape.values(),
                target.len()
            )));
        }
        if !target.iter().all(|v| v.is_finite()) {
            return Err(GpuError::Invalid("target image is not finite".into()));
        }
        let weights = pixel_weights(mask, shape)?;
        self.ensure_image_buffers(shape.pixels())?;
        let t0 = std::time::Instant::now();
        let ctx = self.raster.context();
        let images = self.images.as_ref().expect("allocated above");
        ctx.queue
            .write_buffer(&images.target, 0, &pad4(f32_bytes(target)));
        ctx.queue
            .write_buffer(&images.weights, 0, &pad4(f32_bytes(&weights)));
        let n = self.n;
        let step = self.scratch.uniform(
            ctx,
            "resident step",
            &self.step_uniform(camera, degree, accumulate_stats),
        )?;
        let gauss = self
            .scratch
            .storage(ctx, "gaussians", n as u64 * GSTRIDE * 4)?;
        let chans = self
            .scratch
            .storage(ctx, "channels", (n * CHANNELS) as u64 * 4)?;
        let mut encoder = ctx.encoder("resident forward");
        {
            let bind = ctx.bind_group(
                &self.pipelines.pack,
                &[&step, &self.buffers.params, &gauss, &chans],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.pipelines.pack, &bind, n as u64);
        }
        let inputs = DeviceInputs {
            camera,
            settings,
            n,
            nc: CHANNELS,
            background: &background,
            gauss,
            chans,
        };
        let device = self
            .raster
            .forward_device(inputs, encoder, Some(&self.scratch), capacity)?;
        let project_ms = t0.elapsed().as_secs_f64() * 1e3;
        let t1 = std::time::Instant::now();
        let mut encoder = device.encoder;
        let st = &device.state;
        let b = &self.buffers;
        encoder.clear_buffer(&self.flags, 0, None);
        encoder.clear_buffer(&images.px_grad, 0, None);
        let cap = self.scratch.uniform(
            ctx,
            "sort capacity",
            &u32_bytes(&[n as u32, device.n_sort as u32, 0, 0]),
        )?;
        {
            let bind = ctx.bind_group(
                &self.pipelines.overflow,
                &[&cap, &device.counts, &self.flags],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipelines.overflow);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(1, 1, 1);
        }
        let loss_buffers = self.pipelines.loss.encode(
            ctx,
            &mut encoder,
            shape,
            lambda_dssim,
            &device.color,
            &images.target,
            &images.weights,
            &images.px_grad,
            &self.flags,
            Some(&self.scratch),
        )?;
        let rows = self.raster.encode_backward(
            st,
            device.tile_entries.unwrap_or(device.n_sort as usize),
            &images.px_grad,
            &mut encoder,
            Some(&self.scratch),
        )?;
        {
            let bind = ctx.bind_group(
                &self.pipelines.grads,
                &[&step, &b.params, &rows, &b.grads, &self.flags],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.pipelines.grads, &bind, n as u64);
        }
        {
            let bind = ctx.bind_group(
                &self.pipelines.stats,
                &[&step, &rows, &st.splats, &self.flags, &b.stats],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.pipelines.stats, &bind, n as u64);
        }
        let adam_uniform = self.encode_adam(&mut encoder, rates)?;
        let entry_count = self.scratch.storage(ctx, "entry count", 4)?;
        encoder.copy_buffer_to_buffer(&device.counts, 4 * n as u64, &entry_count, 0, 4);
        let back = ctx.read_back(
            encoder,
            &[
                (&self.flags, 8),
                (&loss_buffers.totals, 8),
                (&entry_count, 4),
            ],
        )?;
        drop((adam_uniform, loss_buffers, cap));
        let flags = bytes_u32(&back[0]);
        let totals = bytes_f32(&back[1]);
        let entries = bytes_u32(&back[2])[0] as u64;
        if self.recent_entries.len() == RECENT_STEPS {
            self.recent_entries.pop_front();
        }
        self.recent_entries.push_back(entries);
        let refused = flags[0] != 0;
        if !refused {
            self.adam_step += 1;
        }
        let loss = combine(totals[0], totals[1], lambda_dssim, Vec::new());
        Ok(ResidentStepReport {
            refused: flags[0] & REFUSED_NONFINITE != 0,
            sort_overflow: flags[0] & REFUSED_OVERFLOW != 0,
            sort_retries: 0,
            dropped_nonfinite: flags[1] as usize,
            loss: loss.loss,
            l1: loss.l1,
            ssim: loss.ssim,
            tile_entries: entries as usize,
            project_ms,
            rest_ms: t1.elapsed().as_secs_f64() * 1e3,
        })
    }

    /// Persistent target, weight and pixel-gradient buffers for `pixels` pixels.
    fn ensure_image_buffers(&mut self, pixels: usize) -> Result<(), GpuError> {
        if self.images.as_ref().is_some_and(|i| i.pixels == pixels) {
            return Ok(());
        }
        let ctx = self.raster.context();
        let p = pixels as u64;
        self.images = Some(ImageBuffers {
            pixels,
            target: ctx.storage("resident target", p * CHANNELS as u64 * 4)?,
            weights: ctx.storage("resident weights", p * 4)?,
            px_grad: ctx.storage("resident pixel grads", p * (CHANNELS as u64 + 2) * 4)?,
        });
        Ok(())
    }
}

/// The Adam kernel's uniform (shaders/adam.wgsl) for Adam step `step` (1-based) over the
/// packed groups of `n` rows of `dims`: step sizes and the bias correction in f64 as
/// optim.rs computes them; groups with rate 0 (or width 0) stay untouched.
pub(super) fn adam_words(
    dims: &[usize; Param::COUNT],
    n: usize,
    rates: &GroupRates,
    step: u64,
    betas_eps: (f32, f32, f32),
) -> Result<[u32; 28], GpuError> {
    let off = offsets(dims, n)?;
    let t = i32::try_from(step).unwrap_or(i32::MAX);
    let (beta1, beta2, eps) = betas_eps;
    let bias1 = 1.0 - (beta1 as f64).powi(t);
    let bias2 = 1.0 - (beta2 as f64).powi(t);
    let mut words = [0u32; 28];
    // The kernel knows the first 8 groups; word 8 ends them (a learned shading normal,
    // which the engine refuses, would stay unstepped).
    words[..9].copy_from_slice(&off[..9]);
    let mut active = 0u32;
    for p in Param::ALL {
        let lr = rates[p.index()];
        if !(lr.is_finite() && lr >= 0.0) {
            return Err(GpuError::Invalid(format!(
                "learning rate of {} is {lr}",
                p.name()
            )));
        }
        if lr != 0.0 && dims[p.index()] != 0 {
            active |= 1 << p.index();
        }
        words[12 + p.index()] = ((lr as f64 / bias1) as f32).to_bits();
    }
    words[20] = active;
    words[21] = beta1.to_bits();
    words[22] = beta2.to_bits();
    words[23] = eps.to_bits();
    words[24] = ((1.0 / bias2.sqrt()) as f32).to_bits();
    Ok(words)
}

/// The `Step` uniform of the resident kernels (shaders/resident_common.wgsl): group
/// offsets, counts and widths, the SH degree (`coeffs` 0 when `degree` is `None`: no SH
/// colour), the camera centre, whether statistics accumulate, and the stride of the
/// rasterizer's gradient rows.
pub(super) fn step_words(
    dims: &[usize; Param::COUNT],
    n: usize,
    degree: Option<u32>,
    camera: &Camera,
    accumulate_stats: bool,
    ostride: u32,
) -> Vec<u8> {
    let off = offsets(dims, n).unwrap_or([0; Param::COUNT + 1]);
    let mut w = [0u32; 20];
    w[..8].copy_from_slice(&off[..8]);
    w[8] = n as u32;
    w[9] = dims[Param::ShRest.index()] as u32;
    w[10] = degree.map_or(0, |d| (d + 1) * (d + 1));
    w[11] = degree.unwrap_or(0);
    let c = camera.position();
    w[12] = c.x.to_bits();
    w[13] = c.y.to_bits();
    w[14] = c.z.to_bits();
    w[16] = accumulate_stats as u32;
    w[17] = ostride;
    w[18] = dims[Param::Feature.index()] as u32;
    w[19] = dims[Param::ShadowLatent.index()] as u32;
    u32_bytes(&w)
}

/// Pads to a multiple of 4 bytes, at least 4 (`write_buffer` needs both).
pub(crate) fn pad4(mut bytes: Vec<u8>) -> Vec<u8> {
    bytes.resize(bytes.len().max(4).next_multiple_of(4), 0);
    bytes
}
