//! The Sun-aware resident step's kernels and their uniforms: the compiled pipelines
//! ([`Pipelines`]), the `Step`, Adam and count uniforms, and the optimiser's kernels
//! (the finiteness check and the Gaussians' Adam, [`OptimKernels`]), which [`GpuAdam`]
//! also runs on their own from the host for the kernel tests.
//!
//! Invariants: the Adam uniform holds the step sizes and bias correction computed in f64
//! on the host exactly as `gs_core::optim` computes them; a non-zero `flags[0]` (refusal)
//! makes Adam change nothing, moments included; a uniform in a pool is keyed by its label,
//! so each label is written once per submission.

use super::super::loss::GpuLoss;
use super::super::packed::{offsets, pack, pad4, GaussianBuffers};
use super::super::{bytes_u32, dispatch_1d, f32_bytes, u32_bytes, GpuContext, GpuError, Scratch};
use gs_core::camera::Camera;
use gs_core::densify::DensifyStats;
use gs_core::model::{Param, ParamSet};
use gs_core::optim::{Adam, GroupRates};

const SA_COMMON: &str = include_str!("../shaders/sa_common.wgsl");
const SA_SURVIVE: &str = include_str!("../shaders/sa_survive.wgsl");
const SA_LIST: &str = include_str!("../shaders/sa_list.wgsl");
const SA_COMPOSE: &str = include_str!("../shaders/sa_compose.wgsl");
const SA_COMPOSE_BACKWARD: &str = include_str!("../shaders/sa_compose_backward.wgsl");
const SA_GRADS: &str = include_str!("../shaders/sa_grads.wgsl");
const SA_FINITE: &str = include_str!("../shaders/sa_finite.wgsl");

const RESIDENT_COMMON: &str = include_str!("../shaders/resident_common.wgsl");
const RESIDENT_COLOUR: &str = include_str!("../shaders/resident_colour.wgsl");
const RESIDENT_PACK: &str = include_str!("../shaders/resident_pack.wgsl");
const RESIDENT_GRADS: &str = include_str!("../shaders/resident_grads.wgsl");
const RESIDENT_STATS: &str = include_str!("../shaders/resident_stats.wgsl");
const ADAM: &str = include_str!("../shaders/adam.wgsl");
const RESIDENT_OVERFLOW: &str = include_str!("../shaders/resident_overflow.wgsl");
/// Refusal bits of `flags[0]`: a non-finite render or gradient; the sort's capacity was
/// too small (the step is redone).
pub(super) const REFUSED_NONFINITE: u32 = 1;
pub(super) const REFUSED_OVERFLOW: u32 = 2;
/// Steps whose entry counts size the sort (a few passes over a training view set).
pub(super) const RECENT_STEPS: usize = 32;

/// Floats of the rasterizer's gradient row ahead of the channels (project_backward.wgsl).
pub(super) const OUT_FIXED: u32 = 13;
/// Floats per rasterizer input row (mean 3, log-scale 3, quaternion 4, opacity logit 1).
pub(super) const GSTRIDE: u64 = 11;

/// The step's kernels (the SH colour ones are those of configuration (a)).
pub(super) struct Pipelines {
    pub pack: wgpu::ComputePipeline,
    pub survive: wgpu::ComputePipeline,
    pub list: wgpu::ComputePipeline,
    pub compose: wgpu::ComputePipeline,
    pub compose_backward: wgpu::ComputePipeline,
    pub grads: wgpu::ComputePipeline,
    pub sh_grads: wgpu::ComputePipeline,
    pub stats: wgpu::ComputePipeline,
    pub overflow: wgpu::ComputePipeline,
    pub optim: OptimKernels,
    pub loss: GpuLoss,
}

impl Pipelines {
    /// Compiles every kernel of the step on `ctx`.
    pub(super) fn new(ctx: &GpuContext) -> Result<Self, GpuError> {
        let common = format!("{RESIDENT_COMMON}\n");
        Ok(Self {
            pack: ctx.pipeline(
                "sa pack",
                &format!("{common}{RESIDENT_COLOUR}\n{RESIDENT_PACK}"),
            )?,
            survive: ctx.pipeline("sa survive", &format!("{SA_COMMON}\n{SA_SURVIVE}"))?,
            list: ctx.pipeline("sa list", &format!("{SA_COMMON}\n{SA_LIST}"))?,
            compose: ctx.pipeline("sa compose", &format!("{SA_COMMON}\n{SA_COMPOSE}"))?,
            compose_backward: ctx.pipeline(
                "sa compose backward",
                &format!("{SA_COMMON}\n{SA_COMPOSE_BACKWARD}"),
            )?,
            grads: ctx.pipeline("sa grads", &format!("{common}{SA_GRADS}"))?,
            sh_grads: ctx.pipeline(
                "sa sh grads",
                &format!("{common}{RESIDENT_COLOUR}\n{RESIDENT_GRADS}"),
            )?,
            stats: ctx.pipeline("sa stats", &format!("{common}{RESIDENT_STATS}"))?,
            overflow: ctx.pipeline("sa overflow", RESIDENT_OVERFLOW)?,
            optim: OptimKernels::new(ctx)?,
            loss: GpuLoss::new(ctx, 3)?,
        })
    }
}

/// A one-word-count uniform (`struct { n, pad, pad, pad }` in the kernels).
pub(super) fn count_words(n: usize) -> Vec<u8> {
    u32_bytes(&[n as u32, 0, 0, 0])
}

/// Where a step's kernels record: the device, the pool of their uniforms and the step's
/// refusal flags.
#[derive(Clone, Copy)]
pub(super) struct StepSink<'a> {
    pub ctx: &'a GpuContext,
    pub pool: &'a Scratch,
    pub flags: &'a wgpu::Buffer,
}

/// The optimiser's kernels: the finiteness check (`sa_finite`) and Adam (`adam.wgsl`).
pub(super) struct OptimKernels {
    finite: wgpu::ComputePipeline,
    adam: wgpu::ComputePipeline,
}

impl OptimKernels {
    fn new(ctx: &GpuContext) -> Result<Self, GpuError> {
        let common = format!("{RESIDENT_COMMON}\n");
        Ok(Self {
            finite: ctx.pipeline("sa finite", &format!("{common}{SA_COMMON}\n{SA_FINITE}"))?,
            adam: ctx.pipeline("sa adam", ADAM)?,
        })
    }

    /// Records the finiteness check of the first `len` values of `data`: any NaN or
    /// infinity sets the refusal bit of `sink.flags`.
    pub(super) fn encode_finite(
        &self,
        sink: StepSink,
        encoder: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        len: usize,
        what: &str,
    ) -> Result<(), GpuError> {
        if len == 0 {
            return Ok(());
        }
        let u = sink
            .pool
            .uniform(sink.ctx, &format!("sa finite {what}"), &count_words(len))?;
        let bind = sink.ctx.bind_group(&self.finite, &[&u, data, sink.flags]);
        let mut pass = encoder.begin_compute_pass(&Default::default());
        dispatch_1d(&mut pass, &self.finite, &bind, len as u64);
        Ok(())
    }

    /// Records Adam on the Gaussians' packed buffers with the uniform `words`
    /// ([`adam_words`]), guarded by the refusal flag.
    pub(super) fn encode_adam(
        &self,
        sink: StepSink,
        encoder: &mut wgpu::CommandEncoder,
        b: &GaussianBuffers,
        words: &[u32; ADAM_WORDS],
    ) -> Result<(), GpuError> {
        let adam_u = sink.pool.uniform(sink.ctx, "sa adam", &u32_bytes(words))?;
        let bind = sink.ctx.bind_group(
            &self.adam,
            &[&adam_u, &b.params, &b.grads, &b.m, &b.v, sink.flags],
        );
        let mut pass = encoder.begin_compute_pass(&Default::default());
        dispatch_1d(&mut pass, &self.adam, &bind, words[Param::COUNT] as u64);
        Ok(())
    }
}

/// The Gaussians' optimiser kernels of the resident step on their own, run from the host:
/// the finiteness check of the gradients, then Adam, recorded as
/// [`super::SunAwareResident::step`] records them (same kernels, uniforms and refusal
/// flag). For the kernel tests against `gs_core::optim` (`tests/gpu_resident.rs`).
pub struct GpuAdam {
    ctx: GpuContext,
    kernels: OptimKernels,
    pool: Scratch,
}

impl std::fmt::Debug for GpuAdam {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuAdam({})", self.ctx.adapter_name())
    }
}

impl GpuAdam {
    /// Compiles the kernels on `ctx`.
    pub fn new(ctx: &GpuContext) -> Result<Self, GpuError> {
        Ok(Self {
            ctx: ctx.clone(),
            kernels: OptimKernels::new(ctx)?,
            pool: Scratch::default(),
        })
    }

    /// One Adam step of `params` with `grads` at `rates` on the device: uploads the
    /// parameters, both moments and the gradients, records the check and Adam step
    /// `adam.step + 1`, and reads the parameters and moments back. A non-finite gradient
    /// refuses the step on the device (what comes back is what went up; `adam.step` is
    /// not counted). Returns whether the step applied.
    pub fn step(
        &self,
        params: &mut ParamSet,
        adam: &mut Adam,
        grads: &ParamSet,
        rates: &GroupRates,
    ) -> Result<bool, GpuError> {
        let n = params.len();
        let dims = params.dims();
        let same = |set: &ParamSet| set.dims() == dims && set.len() == n;
        if !same(&adam.m) || !same(&adam.v) || !same(grads) {
            return Err(GpuError::Invalid(format!(
                "parameters ({n} rows, widths {dims:?}), moments ({} and {} rows) and \
                 gradients ({} rows, widths {:?}) differ",
                adam.m.len(),
                adam.v.len(),
                grads.len(),
                grads.dims()
            )));
        }
        let off = offsets(&dims, n)?;
        let ctx = &self.ctx;
        let buffers = GaussianBuffers::allocate(ctx, "adam", &dims, n.max(1))?;
        let mut stats = DensifyStats::new(n);
        buffers.write(ctx, params, adam, &stats);
        ctx.queue
            .write_buffer(&buffers.grads, 0, &pad4(f32_bytes(&pack(grads))));
        let flags = ctx.storage("adam flags", 16)?;
        let words = adam_words(
            &dims,
            n,
            rates,
            adam.step + 1,
            (adam.beta1, adam.beta2, adam.eps),
        )?;
        let mut encoder = ctx.encoder("adam");
        encoder.clear_buffer(&flags, 0, None);
        let sink = StepSink {
            ctx,
            pool: &self.pool,
            flags: &flags,
        };
        let total = off[Param::COUNT] as usize;
        self.kernels
            .encode_finite(sink, &mut encoder, &buffers.grads, total, "gradients")?;
        self.kernels
            .encode_adam(sink, &mut encoder, &buffers, &words)?;
        let back = ctx.read_back(encoder, &[(&flags, 4)])?;
        buffers.read(ctx, params, adam, &mut stats)?;
        let applied = bytes_u32(&back[0])[0] == 0;
        if applied {
            adam.step += 1;
        }
        Ok(applied)
    }
}

/// Words of the Adam kernel's uniform (shaders/adam.wgsl).
pub(super) const ADAM_WORDS: usize = 32;

/// The Adam kernel's uniform (shaders/adam.wgsl) for Adam step `step` (1-based) over the
/// packed groups of `n` rows of `dims` (all nine, the learned shading normal included):
/// step sizes and the bias correction in f64 as optim.rs computes them; groups with rate
/// 0 (or width 0) stay untouched.
pub(super) fn adam_words(
    dims: &[usize; Param::COUNT],
    n: usize,
    rates: &GroupRates,
    step: u64,
    betas_eps: (f32, f32, f32),
) -> Result<[u32; ADAM_WORDS], GpuError> {
    let off = offsets(dims, n)?;
    let t = i32::try_from(step).unwrap_or(i32::MAX);
    let (beta1, beta2, eps) = betas_eps;
    let bias1 = 1.0 - (beta1 as f64).powi(t);
    let bias2 = 1.0 - (beta2 as f64).powi(t);
    let mut words = [0u32; ADAM_WORDS];
    // Group starts, then the total (word 9).
    words[..Param::COUNT + 1].copy_from_slice(&off);
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
        // Groups 0..7 in words 12..19, the Normal group in word 28.
        let at = if p.index() < 8 { 12 + p.index() } else { 28 };
        words[at] = ((lr as f64 / bias1) as f32).to_bits();
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
