//! The photometric loss on the device: `(1 - lambda) L1 + lambda (1 - SSIM)` with
//! per-pixel weights (the mask), its gradient with respect to the rendered image written
//! straight into the rasterizer backward's pixel-gradient rows, and the two totals
//! (weighted SSIM and L1 sums) as the only values meant to come back ([`GpuLoss`]).
//!
//! Six kernels (shaders/loss_*.wgsl), the same passes as loss.rs `weighted_ssim`: moments
//! filtered along rows; along columns into the SSIM map and its derivatives; those along
//! rows; along columns and combined with the L1 sign into `dL/dx`; and a two-stage,
//! fixed-order sum of the per-pixel weighted values (partial sums over chunks of at least
//! 4,096 pixels, at most 1,024 of them, then one workgroup over the partials).
//!
//! Invariants:
//! - the weights are loss.rs's `m_p / (C sum m)` (1 / (C N) without a mask), computed on
//!   the host in f64 as there ([`pixel_weights`]);
//! - a non-finite rendered value or gradient sets the step's refusal flag (`flags[0]`),
//!   which the gradient assembly, statistics and Adam kernels honour;
//! - the same formulas as loss.rs in f32; sums in a different (fixed) order, so totals and
//!   gradients agree with the CPU to rounding (`tests/gpu_resident.rs`).

use super::{
    bytes_f32, dispatch_1d, f32_bytes, storage_in, u32_bytes, uniform_in, GpuContext, GpuError,
    Scratch,
};
use gs_core::loss::{ssim_window, ImageShape, LossOutput, SSIM_C1, SSIM_C2};

const LOSS_COMMON: &str = include_str!("shaders/loss_common.wgsl");
const LOSS_MOMENTS: &str = include_str!("shaders/loss_moments.wgsl");
const LOSS_MAP: &str = include_str!("shaders/loss_map.wgsl");
const LOSS_GRAD_H: &str = include_str!("shaders/loss_grad_h.wgsl");
const LOSS_GRAD: &str = include_str!("shaders/loss_grad.wgsl");
const LOSS_PARTIAL: &str = include_str!("shaders/loss_partial.wgsl");
const LOSS_SUM: &str = include_str!("shaders/loss_sum.wgsl");
/// Pixels per workgroup of the totals' first stage (at most 1024 workgroups).
const SUM_CHUNK_MIN: usize = 4096;

/// Compiled loss kernels for one channel count.
pub struct GpuLoss {
    channels: usize,
    moments: wgpu::ComputePipeline,
    map: wgpu::ComputePipeline,
    grad_h: wgpu::ComputePipeline,
    grad: wgpu::ComputePipeline,
    partial: wgpu::ComputePipeline,
    sum: wgpu::ComputePipeline,
}

impl std::fmt::Debug for GpuLoss {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuLoss({} channels)", self.channels)
    }
}

/// Device buffers of one recorded loss evaluation; the caller keeps them until the
/// submission and reads `totals` (`[ssim, l1]`) back.
pub struct LossBuffers {
    pub totals: wgpu::Buffer,
    _temporaries: Vec<wgpu::Buffer>,
}

/// Per-pixel weights `m_p / (C sum m)` (`1 / (C N)` without a mask), as loss.rs computes
/// them; the mask is checked as there.
pub fn pixel_weights(mask: Option<&[f32]>, shape: ImageShape) -> Result<Vec<f32>, GpuError> {
    let n = shape.pixels();
    match mask {
        None => Ok(vec![(1.0 / (n * shape.channels) as f64) as f32; n]),
        Some(m) => {
            if m.len() != n {
                return Err(GpuError::Invalid(format!(
                    "mask: expected {n} values, got {}",
                    m.len()
                )));
            }
            if let Some(i) = m.iter().position(|v| !(0.0..=1.0).contains(v)) {
                return Err(GpuError::Invalid(format!(
                    "mask value {i} ({}) is not in [0, 1]",
                    m[i]
                )));
            }
            let sum: f64 = m.iter().map(|&v| v as f64).sum();
            if sum <= 0.0 {
                return Err(GpuError::Invalid("mask is zero everywhere".into()));
            }
            let norm = 1.0 / (sum * shape.channels as f64);
            Ok(m.iter().map(|&v| (v as f64 * norm) as f32).collect())
        }
    }
}

/// The device images of one loss evaluation: `rendered` and `target` (`H * W * C`), the
/// pixel weights (`H * W`, [`pixel_weights`]) and the pixel-gradient rows the loss's
/// gradient goes into (`H * W * (C + 2)`: the colour slots of each row; the caller zeroes
/// the rest).
#[derive(Clone, Copy, Debug)]
pub(super) struct LossImages<'a> {
    pub shape: ImageShape,
    pub rendered: &'a wgpu::Buffer,
    pub target: &'a wgpu::Buffer,
    pub weights: &'a wgpu::Buffer,
    pub px_grad: &'a wgpu::Buffer,
}

impl GpuLoss {
    /// Compiles the kernels for `channels` channels.
    pub fn new(ctx: &GpuContext, channels: usize) -> Result<Self, GpuError> {
        if channels == 0 {
            return Err(GpuError::Invalid(
                "the loss needs at least one channel".into(),
            ));
        }
        let prelude = format!("const NC: u32 = {channels}u;\n{LOSS_COMMON}\n");
        let build = |label: &str, body: &str| ctx.pipeline(label, &format!("{prelude}{body}"));
        Ok(Self {
            channels,
            moments: build("loss_moments", LOSS_MOMENTS)?,
            map: build("loss_map", LOSS_MAP)?,
            grad_h: build("loss_grad_h", LOSS_GRAD_H)?,
            grad: build("loss_grad", LOSS_GRAD)?,
            partial: build("loss_partial", LOSS_PARTIAL)?,
            sum: build("loss_sum", LOSS_SUM)?,
        })
    }

    pub fn channels(&self) -> usize {
        self.channels
    }

    /// Records the loss of `images.rendered` against `images.target` with
    /// `images.weights` (see [`LossImages`]): the gradient goes into the colour slots of
    /// `images.px_grad`, refusals into `flags[0]`.
    pub(super) fn encode(
        &self,
        ctx: &GpuContext,
        encoder: &mut wgpu::CommandEncoder,
        lambda_dssim: f32,
        LossImages {
            shape,
            rendered,
            target,
            weights,
            px_grad,
        }: LossImages,
        flags: &wgpu::Buffer,
        scratch: Option<&Scratch>,
    ) -> Result<LossBuffers, GpuError> {
        if shape.channels != self.channels {
            return Err(GpuError::Invalid(format!(
                "loss kernels built for {} channels, image has {}",
                self.channels, shape.channels
            )));
        }
        if !(0.0..=1.0).contains(&lambda_dssim) {
            return Err(GpuError::Invalid(format!(
                "lambda_dssim {lambda_dssim} is not in [0, 1]"
            )));
        }
        let (w, h, nc) = (shape.width, shape.height, shape.channels);
        let n = (w * h) as u64;
        let taps = ssim_window();
        let chunk = (w * h).div_ceil(1024).max(SUM_CHUNK_MIN);
        let groups = (w * h).div_ceil(chunk).max(1);
        let mut words = [0u32; 20];
        words[5] = groups as u32;
        words[6] = chunk as u32;
        words[0] = w as u32;
        words[1] = h as u32;
        words[2] = lambda_dssim.to_bits();
        words[3] = (SSIM_C1 as f32).to_bits();
        words[4] = (SSIM_C2 as f32).to_bits();
        for (k, t) in taps.iter().enumerate() {
            words[8 + k] = (*t as f32).to_bits();
        }
        let uniform = uniform_in(ctx, scratch, "loss", &u32_bytes(&words))?;
        let values = n * nc as u64;
        let moments = storage_in(ctx, scratch, "loss moments", values * 5 * 4)?;
        let grads = storage_in(ctx, scratch, "loss ssim derivatives", values * 3 * 4)?;
        let grads_h = storage_in(ctx, scratch, "loss ssim derivatives (rows)", values * 3 * 4)?;
        let maps = storage_in(ctx, scratch, "loss weighted maps", values * 2 * 4)?;
        let partials = storage_in(
            ctx,
            scratch,
            "loss partial sums",
            (groups * 2 * nc * 4) as u64,
        )?;
        let totals = storage_in(ctx, scratch, "loss totals", 8)?;
        let mut run = |pipeline: &wgpu::ComputePipeline, buffers: &[&wgpu::Buffer]| {
            let bind = ctx.bind_group(pipeline, buffers);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, pipeline, &bind, values);
        };
        run(&self.moments, &[&uniform, rendered, target, &moments]);
        run(
            &self.map,
            &[
                &uniform, rendered, target, weights, &moments, &grads, &maps, flags,
            ],
        );
        run(&self.grad_h, &[&uniform, &grads, &grads_h]);
        run(
            &self.grad,
            &[
                &uniform, rendered, target, weights, &grads_h, px_grad, flags,
            ],
        );
        {
            let bind = ctx.bind_group(&self.partial, &[&uniform, &maps, &partials]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.partial);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(groups as u32, 1, 1);
        }
        {
            let bind = ctx.bind_group(&self.sum, &[&uniform, &partials, &totals]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.sum);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(1, 1, 1);
        }
        Ok(LossBuffers {
            totals,
            _temporaries: vec![uniform, moments, grads, grads_h, maps, partials],
        })
    }

    /// The loss of host images, evaluated on the device (tests and diagnostics: the
    /// trainer keeps its images on the device). Returns `None` when the rendered image
    /// or the gradient is not finite (the step the trainer would refuse).
    pub fn evaluate(
        &self,
        ctx: &GpuContext,
        rendered: &[f32],
        target: &[f32],
        mask: Option<&[f32]>,
        shape: ImageShape,
        lambda_dssim: f32,
    ) -> Result<Option<LossOutput>, GpuError> {
        for (what, v) in [("rendered", rendered), ("target", target)] {
            if v.len() != shape.values() || shape.values() == 0 {
                return Err(GpuError::Invalid(format!(
                    "{what} image: expected {} values, got {}",
                    shape.values(),
                    v.len()
                )));
            }
        }
        if !target.iter().all(|v| v.is_finite()) {
            return Err(GpuError::Invalid("target image is not finite".into()));
        }
        let weights = pixel_weights(mask, shape)?;
        let rendered_buf = ctx.storage_init("loss rendered", &f32_bytes(rendered));
        let target_buf = ctx.storage_init("loss target", &f32_bytes(target));
        let weights_buf = ctx.storage_init("loss weights", &f32_bytes(&weights));
        let stride = shape.channels + 2;
        let px_grad = ctx.storage("pixel grads", (shape.pixels() * stride * 4) as u64)?;
        let flags = ctx.storage("loss flags", 8)?;
        let mut encoder = ctx.encoder("loss");
        let images = LossImages {
            shape,
            rendered: &rendered_buf,
            target: &target_buf,
            weights: &weights_buf,
            px_grad: &px_grad,
        };
        let bufs = self.encode(ctx, &mut encoder, lambda_dssim, images, &flags, None)?;
        let back = ctx.read_back(
            encoder,
            &[
                (&bufs.totals, 8),
                (&px_grad, (shape.pixels() * stride * 4) as u64),
                (&flags, 8),
            ],
        )?;
        if super::bytes_u32(&back[2])[0] != 0 {
            return Ok(None);
        }
        let totals = bytes_f32(&back[0]);
        let rows = bytes_f32(&back[1]);
        let d_rendered = rows
            .chunks_exact(stride)
            .flat_map(|r| r[..shape.channels].iter().copied())
            .collect();
        Ok(Some(combine(
            totals[0],
            totals[1],
            lambda_dssim,
            d_rendered,
        )))
    }
}

/// The loss from the totals, in f32 as loss.rs combines them.
pub(super) fn combine(ssim: f32, l1: f32, lambda_dssim: f32, d_rendered: Vec<f32>) -> LossOutput {
    LossOutput {
        loss: (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim),
        l1,
        ssim,
        d_rendered,
    }
}
