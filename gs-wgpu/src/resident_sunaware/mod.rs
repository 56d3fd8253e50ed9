//! Device-resident training of the Sun-aware model (configurations a-d): the Gaussians,
//! both networks' weights, every Adam moment and the densification statistics live in
//! device buffers, and one training step (the CPU's `SunAwareTrainer::step`) runs as one
//! command buffer with one small readback ([`SunAwareResident::step`]).
//!
//! A step, in recording order:
//! 1. the rasterizer rows from the packed parameters (`resident_pack`; SH colour only in
//!    configuration (a));
//! 2. the camera pass up to its blend (`GpuRasterizer::forward_device_prepare`:
//!    projection, prefix sum, keys, sort, tile ranges; the channels are not needed yet);
//!    the visible Gaussians (projection survivors, `sa_survive`) counted, and the
//!    networks' batch listed in index order with its count on the device (`sa_list`):
//!    with `skip_noncontributing_in_mlp` the Gaussians the blend reads (the device's
//!    alpha-only walk, `encode_contributing`: exactly the CPU's `contributing` list),
//!    else the visible ones. With `skip_masked_background_tiles` and a mask, the camera
//!    pass blends only the tiles the masked loss reads (the CPU step's selection);
//! 3. (c-d) the shadow pass `V` from the packed parameters ([`GpuSunVisibility`]);
//! 4. (a) SH colour in step 1 instead (`resident_pack`, the SH-colour kernel, whose
//!    `resident_grads` then gives the SH and geometry gradients in step 6);
//!    (b-d) Phi's input (with `appearance_inputs = "local"` / `"local_no_sun"` ending in
//!    `[n.s, n.v, n.h]` of the learned normal), forward, and scatter into channels 0..3
//!    (with `shading = "lambert_learned"` times each Gaussian's Lambertian factor of its
//!    learned normal);
//!    (c-d) Psi's, into channel 3 (`V * P` or `P`) ([`NetworkIo`], [`GpuMlp`]); the
//!    channels are checked finite;
//! 5. the blend with those channels, `RGB * S` (`sa_compose`; with
//!    `colour_space = "linear"` each pixel then sRGB-encoded, in a-b too, whose sRGB
//!    image is the colour buffer itself), the masked L1 + SSIM loss and its image
//!    gradient ([`GpuLoss`](crate::GpuLoss)), `d(RGB, S)` (`sa_compose_backward`, through
//!    the encoding's slope under `"linear"`), the rasterizer's backward;
//! 6. the geometry gradients and `L_iso` (`sa_grads`), then Phi's and Psi's backward and
//!    the scatter of their input gradients into features, latents and means (Phi's output
//!    gradient times the shading factor, and the learned normals' gradient, the Normal
//!    group cleared at the step's start; with local inputs their gradient into the normals
//!    and the means in the same input-gradient kernel, one writer per Gaussian);
//! 7. every gradient checked finite (`sa_finite`); densification statistics; Adam on the
//!    Gaussians (`adam.wgsl`, per-group rates, the learned normal's included) and on each
//!    network (the same kernel).
//!
//! The networks' row count lives on the device: their kernels are dispatched over all `n`
//! Gaussians and skip rows past the count, so nothing waits for it. The two sorts
//! (rasterizer, light pass) are sized from the recent steps' entry counts; a step that
//! outgrows either is refused on the device (flags bit 1) and redone at the exact counts.
//! Any non-finite or degenerate value (flags bit 0) refuses the step: nothing changes,
//! as on the CPU, which skips such a step.
//!
//! Each subsystem (rasterizer and loss, light pass, networks, this module's kernels) takes
//! its per-step buffers from its own `Scratch` pool: pools key buffers and uniforms by
//! label, and a uniform written twice before one submission would hold only its last
//! value.
//!
//! Files: this one holds the state, its upload and download, the batch's targets and the
//! overflow retry; `record.rs` records one step; `kernels.rs` holds the pipelines, the
//! uniforms and the optimiser's kernels ([`GpuAdam`] runs those on their own).
//!
//! Invariants: the CPU path is the reference (`tests/gpu_sunaware.rs` compares one step's
//! gradients, through Adam's first moments, and short trainings' PSNR); the host copy is
//! brought up to date only by [`SunAwareResident::download`]; a refused step changes
//! nothing on the device and is reported as refused.

mod kernels;
mod record;

use std::sync::Arc;

use super::loss::pixel_weights;
use super::mlp::{DeviceNetwork, GpuMlp};
use super::network_io::NetworkIo;
use super::packed::{offsets, pad4, GaussianBuffers};
use super::raster::GpuRasterizer;
use super::sun_visibility::GpuSunVisibility;
use super::{f32_bytes, GpuError, Scratch, StageClock};
use gs_core::densify::DensifyStats;
use gs_core::loss::{ImageShape, SSIM_WINDOW};
use gs_core::model::{Param, ParamSet};
use gs_core::optim::Adam;
use gs_core::raster::bin::TileSelection;
use gs_core::sunaware::trainer::FlatAdam;
use gs_core::sunaware::SunAwareModel;
use kernels::Pipelines;

pub use kernels::GpuAdam;

/// Every per-step scratch pool (see the module header: one per subsystem).
#[derive(Default)]
struct Pools {
    raster: Scratch,
    shadow: Scratch,
    networks: Scratch,
    own: Scratch,
}

// The step's inputs and report are gs-core's (the engine trait's types).
pub use gs_core::engine::{SunAwareStepInput, SunAwareStepReport};

/// The Sun-aware model's training state on the device (see the module header).
pub struct SunAwareResident {
    raster: Arc<GpuRasterizer>,
    shadow: Arc<GpuSunVisibility>,
    mlp: Arc<GpuMlp>,
    io: NetworkIo,
    pipelines: Pipelines,
    dims: [usize; Param::COUNT],
    n: usize,
    buffers: GaussianBuffers,
    appearance: Option<DeviceNetwork>,
    shadow_net: Option<DeviceNetwork>,
    pools: Pools,
    /// Per-stage device times, where the adapter has timestamp queries.
    clock: Option<StageClock>,
    /// Targets and pixel weights uploaded in this batch, by the host slices' identity
    /// (see [`SunAwareResident::begin_batch`]).
    targets: Vec<CachedTarget>,
    recent_entries: std::collections::VecDeque<(u64, u64)>,
    adam_step: u64,
    beta1: f32,
    beta2: f32,
    eps: f32,
}

impl std::fmt::Debug for SunAwareResident {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "SunAwareResident({} Gaussians, capacity {}, {} Adam steps)",
            self.n, self.buffers.capacity, self.adam_step
        )
    }
}

/// A target image and its pixel weights on the device, with the identity (address and
/// length) of the host slices they came from.
struct CachedTarget {
    key: (usize, usize, usize, usize),
    target: wgpu::Buffer,
    weights: wgpu::Buffer,
    /// The tiles the masked loss reads (`skip_masked_background_tiles`), from the mask.
    tiles: Option<TileSelection>,
}

/// Keyframes a batch keeps on the device at most (beyond it the oldest upload is reused).
const MAX_CACHED_TARGETS: usize = 64;
impl SunAwareResident {
    /// Compiles the kernels on the rasterizer's device; [`SunAwareResident::upload`] then
    /// puts a trainer's state on it.
    pub fn new(
        raster: Arc<GpuRasterizer>,
        shadow: Arc<GpuSunVisibility>,
        mlp: Arc<GpuMlp>,
    ) -> Result<Self, GpuError> {
        let ctx = raster.context();
        let pipelines = Pipelines::new(ctx)?;
        let io = NetworkIo::new(ctx)?;
        let dims = [0; Param::COUNT];
        let buffers = GaussianBuffers::allocate(ctx, "sa", &dims, 1)?;
        let clock = StageClock::new(ctx, 16);
        Ok(Self {
            raster,
            shadow,
            mlp,
            io,
            pipelines,
            dims,
            n: 0,
            buffers,
            appearance: None,
            shadow_net: None,
            pools: Pools::default(),
            clock,
            targets: Vec::new(),
            recent_entries: std::collections::VecDeque::new(),
            adam_step: 0,
            beta1: 0.9,
            beta2: 0.999,
            eps: gs_core::optim::ADAM_EPS,
        })
    }

    pub fn len(&self) -> usize {
        self.n
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// Adam steps taken on the device (the Gaussians' optimiser).
    pub fn adam_step(&self) -> u64 {
        self.adam_step
    }

    /// Replaces the device state with the trainer's parts: the model's Gaussians and
    /// networks, the three optimisers and the statistics. Buffers grow with 50% head room.
    pub fn upload(
        &mut self,
        model: &SunAwareModel,
        adam: &Adam,
        appearance_adam: &FlatAdam,
        shadow_adam: &FlatAdam,
        stats: &DensifyStats,
    ) -> Result<(), GpuError> {
        let params = &model.gaussians.params;
        let n = params.len();
        let dims = params.dims();
        let same = |a: &ParamSet| a.dims() == dims && a.len() == n;
        if !same(&adam.m) || !same(&adam.v) || stats.len() != n {
            return Err(GpuError::Invalid(format!(
                "parameters ({n} rows), moments ({} and {} rows) and statistics ({} rows) \
                 differ",
                adam.m.len(),
                adam.v.len(),
                stats.len()
            )));
        }
        offsets(&dims, n)?;
        let ctx = self.raster.context();
        if n > self.buffers.capacity || dims != self.dims {
            let capacity = n.saturating_add(n / 2).max(1);
            self.buffers = GaussianBuffers::allocate(ctx, "sa", &dims, capacity)?;
        }
        self.dims = dims;
        self.buffers.write(ctx, params, adam, stats);
        self.appearance = Self::network(
            ctx,
            self.appearance.take(),
            model.appearance.as_ref().map(|a| &a.mlp),
            appearance_adam,
        )?;
        self.shadow_net = Self::network(
            ctx,
            self.shadow_net.take(),
            model.shadow.as_ref().map(|s| &s.mlp),
            shadow_adam,
        )?;
        self.n = n;
        self.adam_step = adam.step;
        (self.beta1, self.beta2, self.eps) = (adam.beta1, adam.beta2, adam.eps);
        self.begin_batch();
        Ok(())
    }

    /// A network's device state from the host's, reusing `old`'s buffers when it fits.
    fn network(
        ctx: &super::GpuContext,
        old: Option<DeviceNetwork>,
        mlp: Option<&gs_core::nn::Mlp>,
        adam: &FlatAdam,
    ) -> Result<Option<DeviceNetwork>, GpuError> {
        let Some(mlp) = mlp else {
            return Ok(None);
        };
        if let Some(mut net) = old {
            if net.widths() == mlp.widths() {
                net.upload(ctx, mlp, &adam.m, &adam.v, adam.step)?;
                return Ok(Some(net));
            }
        }
        Ok(Some(DeviceNetwork::new(
            ctx, mlp, &adam.m, &adam.v, adam.step,
        )?))
    }

    /// Starts a batch of steps whose observations' images stay alive and unchanged until
    /// the next call: each distinct target (and mask) is uploaded once per batch, when
    /// first stepped on, and found again by its slices' address and length. The upload
    /// ([`SunAwareResident::upload`]) starts a batch too.
    pub fn begin_batch(&mut self) {
        self.targets.clear();
    }

    /// The device copy of `target` and its pixel weights, uploading them on first use in
    /// this batch.
    fn target_buffers(
        &mut self,
        target: &[f32],
        mask: Option<&[f32]>,
        shape: ImageShape,
    ) -> Result<(wgpu::Buffer, wgpu::Buffer, Option<TileSelection>), GpuError> {
        let key = (
            target.as_ptr() as usize,
            target.len(),
            mask.map_or(0, |m| m.as_ptr() as usize),
            mask.map_or(0, <[f32]>::len),
        );
        if let Some(c) = self.targets.iter().find(|c| c.key == key) {
            return Ok((c.target.clone(), c.weights.clone(), c.tiles.clone()));
        }
        let weights = pixel_weights(mask, shape)?;
        // The masked loss's tiles: the mask dilated by the SSIM window's half width, as
        // the CPU step's `masked_background_tiles` (every other pixel has zero gradient).
        let tiles = match mask {
            Some(m) => Some(
                TileSelection::from_mask(
                    m,
                    shape.width as u32,
                    shape.height as u32,
                    (SSIM_WINDOW / 2) as u32,
                )
                .map_err(|e| GpuError::Invalid(format!("mask: {e}")))?,
            ),
            None => None,
        };
        let ctx = self.raster.context();
        let (target_buf, weights_buf) = if self.targets.len() >= MAX_CACHED_TARGETS {
            let old = self.targets.remove(0);
            (old.target, old.weights)
        } else {
            let pixels = shape.pixels() as u64;
            (
                ctx.storage("sa target", pixels * 12)?,
                ctx.storage("sa pixel weights", pixels * 4)?,
            )
        };
        let (target_buf, weights_buf) = if target_buf.size() >= shape.values() as u64 * 4 {
            (target_buf, weights_buf)
        } else {
            let pixels = shape.pixels() as u64;
            (
                ctx.storage("sa target", pixels * 12)?,
                ctx.storage("sa pixel weights", pixels * 4)?,
            )
        };
        ctx.queue
            .write_buffer(&target_buf, 0, &pad4(f32_bytes(target)));
        ctx.queue
            .write_buffer(&weights_buf, 0, &pad4(f32_bytes(&weights)));
        self.targets.push(CachedTarget {
            key,
            target: target_buf.clone(),
            weights: weights_buf.clone(),
            tiles: tiles.clone(),
        });
        Ok((target_buf, weights_buf, tiles))
    }

    /// Copies the device state into the trainer's parts (same shapes as uploaded).
    pub fn download(
        &self,
        model: &mut SunAwareModel,
        adam: &mut Adam,
        appearance_adam: &mut FlatAdam,
        shadow_adam: &mut FlatAdam,
        stats: &mut DensifyStats,
    ) -> Result<(), GpuError> {
        let n = self.n;
        let params = &mut model.gaussians.params;
        let same = |set: &ParamSet| set.len() == n && set.dims() == self.dims;
        if !same(params) || !same(&adam.m) || !same(&adam.v) {
            return Err(GpuError::Invalid(format!(
                "host model has {} rows, the device {n}",
                params.len()
            )));
        }
        let ctx = self.raster.context();
        self.buffers.read(ctx, params, adam, stats)?;
        adam.step = self.adam_step;
        if let (Some(net), Some(host)) = (&self.appearance, model.appearance.as_mut()) {
            net.download(
                ctx,
                &mut host.mlp,
                &mut appearance_adam.m,
                &mut appearance_adam.v,
            )?;
            appearance_adam.step = net.adam_step();
        }
        if let (Some(net), Some(host)) = (&self.shadow_net, model.shadow.as_mut()) {
            net.download(ctx, &mut host.mlp, &mut shadow_adam.m, &mut shadow_adam.v)?;
            shadow_adam.step = net.adam_step();
        }
        Ok(())
    }

    /// One training step of `model`'s configuration on the device state (the model itself
    /// supplies the settings, the scene box and the networks' shapes; its host values are
    /// not read). Sorts are sized from recent steps; a step that outgrows them is redone
    /// once at the exact counts.
    pub fn step(
        &mut self,
        model: &SunAwareModel,
        input: &SunAwareStepInput,
    ) -> Result<SunAwareStepReport, GpuError> {
        let t0 = std::time::Instant::now();
        let head = |e: u64| e + e / 16 + 256;
        let capacity = self
            .recent_entries
            .iter()
            .copied()
            .reduce(|a, b| (a.0.max(b.0), a.1.max(b.1)))
            .map(|(c, l)| (head(c), head(l)));
        let first = self.step_with(model, input, capacity)?;
        let mut report = match first {
            Attempt::Done(r) => r,
            Attempt::Overflow { camera, light } => {
                match self.step_with(model, input, Some((camera, light)))? {
                    Attempt::Done(mut r) => {
                        r.sort_retries = 1;
                        r
                    }
                    Attempt::Overflow { .. } => {
                        return Err(GpuError::Invalid(
                            "a sort overflowed at its exact entry count".into(),
                        ))
                    }
                }
            }
        };
        report.total_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(report)
    }
}

/// A step's outcome before the retry logic.
enum Attempt {
    Done(SunAwareStepReport),
    /// A sort outgrew its capacity: the exact entry counts for the redo.
    Overflow {
        camera: u64,
        light: u64,
    },
}
