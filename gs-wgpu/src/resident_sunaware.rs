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
//! 4. (a) SH colour in step 1 instead (`resident_pack`, the plain trainer's kernel, whose
//!    `resident_grads` then gives the SH and geometry gradients in step 6);
//!    (b-d) Phi's input, forward, and scatter into channels 0..3; (c-d) Psi's, into channel 3
//!    (`V * P` or `P`) ([`NetworkIo`], [`GpuMlp`]); the channels are checked finite;
//! 5. the blend with those channels, `RGB * S` (`sa_compose`), the masked
//!    L1 + SSIM loss and its image gradient ([`GpuLoss`]), `d(RGB, S)`
//!    (`sa_compose_backward`), the rasterizer's backward;
//! 6. the geometry gradients and `L_iso` (`sa_grads`), then Phi's and Psi's backward and
//!    the scatter of their input gradients into features, latents and means;
//! 7. every gradient checked finite (`sa_finite`); densification statistics; Adam on the
//!    Gaussians (`adam.wgsl`, per-group rates) and on each network (the same kernel).
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
//! Invariants: the CPU path is the reference (`tests/gpu_sunaware.rs` compares one step's
//! gradients, through Adam's first moments, and short trainings' PSNR); the host copy is
//! brought up to date only by [`SunAwareResident::download`]; a refused step changes
//! nothing on the device and is reported as refused.

use std::sync::Arc;

use super::loss::{combine, pixel_weights, GpuLoss};
use super::mlp::{DeviceNetwork, GpuMlp};
use super::network_io::NetworkIo;
use super::raster::{DeviceInputs, GpuRasterizer};
use super::resident::{
    adam_words, offsets, pad4, step_words, GaussianBuffers, ADAM, GSTRIDE, RECENT_STEPS,
    REFUSED_NONFINITE, REFUSED_OVERFLOW, RESIDENT_COLOUR, RESIDENT_COMMON, RESIDENT_GRADS,
    RESIDENT_OVERFLOW, RESIDENT_PACK, RESIDENT_STATS,
};
use super::sun_visibility::GpuSunVisibility;
use super::{
    bytes_f32, bytes_u32, dispatch_1d, f32_bytes, groups_1d, u32_bytes, GpuError, Scratch,
    StageClock,
};
use gs_core::densify::DensifyStats;
use gs_core::loss::{ImageShape, SSIM_WINDOW};
use gs_core::model::{Param, ParamSet};
use gs_core::optim::Adam;
use gs_core::raster::bin::TileSelection;
use gs_core::regularizer::IsoReduction;
use gs_core::sunaware::config::ShadowRefinement;
use gs_core::sunaware::trainer::FlatAdam;
use gs_core::sunaware::StepTimings;
use gs_core::sunaware::SunAwareModel;

const SA_COMMON: &str = include_str!("shaders/sa_common.wgsl");
const SA_SURVIVE: &str = include_str!("shaders/sa_survive.wgsl");
const SA_LIST: &str = include_str!("shaders/sa_list.wgsl");
const SA_COMPOSE: &str = include_str!("shaders/sa_compose.wgsl");
const SA_COMPOSE_BACKWARD: &str = include_str!("shaders/sa_compose_backward.wgsl");
const SA_GRADS: &str = include_str!("shaders/sa_grads.wgsl");
const SA_FINITE: &str = include_str!("shaders/sa_finite.wgsl");

/// Floats of the rasterizer's gradient row ahead of the channels (project_backward.wgsl).
const OUT_FIXED: u32 = 13;

/// This module's kernels and the shared resident ones.
struct Pipelines {
    pack: wgpu::ComputePipeline,
    survive: wgpu::ComputePipeline,
    list: wgpu::ComputePipeline,
    compose: wgpu::ComputePipeline,
    compose_backward: wgpu::ComputePipeline,
    grads: wgpu::ComputePipeline,
    sh_grads: wgpu::ComputePipeline,
    finite: wgpu::ComputePipeline,
    stats: wgpu::ComputePipeline,
    adam: wgpu::ComputePipeline,
    overflow: wgpu::ComputePipeline,
    loss: GpuLoss,
}

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

/// A one-word-count uniform (`struct { n, pad, pad, pad }` in the kernels).
fn count_words(n: usize) -> Vec<u8> {
    u32_bytes(&[n as u32, 0, 0, 0])
}

impl SunAwareResident {
    /// Compiles the kernels on the rasterizer's device; [`SunAwareResident::upload`] then
    /// puts a trainer's state on it.
    pub fn new(
        raster: Arc<GpuRasterizer>,
        shadow: Arc<GpuSunVisibility>,
        mlp: Arc<GpuMlp>,
    ) -> Result<Self, GpuError> {
        let ctx = raster.context();
        let common = format!("{RESIDENT_COMMON}\n");
        let pipelines = Pipelines {
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
            finite: ctx.pipeline("sa finite", &format!("{common}{SA_COMMON}\n{SA_FINITE}"))?,
            stats: ctx.pipeline("sa stats", &format!("{common}{RESIDENT_STATS}"))?,
            adam: ctx.pipeline("sa adam", ADAM)?,
            overflow: ctx.pipeline("sa overflow", RESIDENT_OVERFLOW)?,
            loss: GpuLoss::new(ctx, 3)?,
        };
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

impl SunAwareResident {
    fn step_with(
        &mut self,
        model: &SunAwareModel,
        input: &SunAwareStepInput,
        capacity: Option<(u64, u64)>,
    ) -> Result<Attempt, GpuError> {
        // Configuration (a): SH colour on the device (resident_pack), no networks.
        let sh_colour = model.appearance.is_none();
        let shadowed = model.config.variant.uses_shadow();
        let nc = if shadowed { 4 } else { 3 };
        let n = self.n;
        let camera = input.camera;
        let settings = model.raster_settings(false);
        let shape = ImageShape::new(
            camera.intrinsics.width as usize,
            camera.intrinsics.height as usize,
            3,
        );
        if input.target.len() != shape.values() || shape.values() == 0 {
            return Err(GpuError::Invalid(format!(
                "target image: expected {} values (H * W * 3), got {}",
                shape.values(),
                input.target.len()
            )));
        }
        let (target, pixel_weights_buf, mask_tiles) =
            self.target_buffers(input.target, input.mask, shape)?;
        let mut settings = settings;
        if model.config.skip_masked_background_tiles {
            settings.blend_tiles = mask_tiles;
        }
        let phi_parts = match (model.appearance.as_ref(), self.appearance.as_ref()) {
            (Some(net), Some(phi)) => Some((net, phi)),
            (None, _) => None,
            (Some(_), None) => return Err(GpuError::Invalid("no state uploaded".into())),
        };
        let ctx = self.raster.context();
        let pools = &self.pools;
        let own = &pools.own;
        let off = offsets(&self.dims, n)?;
        let ostride = OUT_FIXED + nc as u32;
        let b = &self.buffers;
        let pixels = shape.pixels() as u64;

        let step_u = own.uniform(
            ctx,
            "sa step",
            &step_words(
                &self.dims,
                n,
                sh_colour.then_some(input.sh_degree),
                camera,
                true,
                ostride,
            ),
        )?;
        let n_u = own.uniform(ctx, "sa n", &count_words(n))?;
        let flags = own.storage(ctx, "sa flags", 16)?;
        let gauss = own.storage(ctx, "sa gauss", n as u64 * GSTRIDE * 4)?;
        let zero_chans = own.storage(ctx, "sa zero channels", (n * nc) as u64 * 4)?;
        let chans = own.storage(ctx, "sa channels", (n * nc) as u64 * 4)?;
        let visible_member = own.storage(ctx, "sa visible flags", (n as u64 + 1) * 4)?;
        let network_member = own.storage(ctx, "sa network flags", (n as u64 + 1) * 4)?;
        let visible_count = own.storage(ctx, "sa visible count", 4)?;
        let list = own.storage(ctx, "sa list", n.max(1) as u64 * 4)?;
        let count = own.storage(ctx, "sa count", 4)?;
        let mut encoder = ctx.encoder("sa step");
        let clock = self.clock.as_ref();
        let mark = |encoder: &mut wgpu::CommandEncoder, label| {
            if let Some(c) = clock {
                c.mark(encoder, label);
            }
        };
        if let Some(c) = clock {
            c.reset();
        }
        mark(&mut encoder, "start");
        encoder.clear_buffer(&flags, 0, None);
        encoder.clear_buffer(&zero_chans, 0, None);
        encoder.clear_buffer(&chans, 0, None);
        encoder.clear_buffer(&list, 0, None);
        let mut keep = Vec::new();
        {
            let bind = ctx.bind_group(
                &self.pipelines.pack,
                &[
                    &step_u,
                    &b.params,
                    &gauss,
                    if sh_colour { &chans } else { &zero_chans },
                ],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.pipelines.pack, &bind, n as u64);
        }
        // The camera pass up to its blend: projection (zero channels are finite, so only
        // geometry culls; the real channels are checked below), prefix sum, keys, sort,
        // tile ranges. The networks run before the blend, which needs their channels.
        let (prepared, mut encoder) = self.raster.forward_device_prepare(
            DeviceInputs {
                camera,
                settings: &settings,
                n,
                nc,
                background: &settings.background,
                gauss,
                chans: zero_chans,
            },
            encoder,
            Some(&pools.raster),
            capacity.map(|c| c.0),
        )?;
        // The visible list (survivors of the projection, index order, counted on the
        // device) and, with the non-contributing skip, the networks' list: the Gaussians
        // the blend reads (the device's alpha-only walk, the CPU's `contributing`).
        {
            let bind = ctx.bind_group(
                &self.pipelines.survive,
                &[&n_u, &prepared.state.splats, &visible_member],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.pipelines.survive, &bind, n as u64 + 1);
        }
        let visible_scan =
            self.encode_numbering(&mut encoder, &visible_member, n, "visible", &mut keep)?;
        encoder.copy_buffer_to_buffer(&visible_scan, 4 * n as u64, &visible_count, 0, 4);
        let (member, scanned) = if model.config.skip_noncontributing_in_mlp {
            self.raster
                .encode_contributing(&prepared, &mut encoder, &network_member)?;
            let scanned =
                self.encode_numbering(&mut encoder, &network_member, n, "network", &mut keep)?;
            (&network_member, scanned)
        } else {
            (&visible_member, visible_scan)
        };
        {
            let bind = ctx.bind_group(
                &self.pipelines.list,
                &[&n_u, member, &scanned, &list, &count],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.pipelines.list, &bind, n as u64 + 1);
        }

        mark(&mut encoder, "project");

        // (c-d) The light pass.
        let cam_pos = camera.position();
        let visibility = own.storage(ctx, "sa visibility", n.max(1) as u64 * 4)?;
        let mut light_record = None;
        if shadowed {
            let (record, enc) = self.shadow.encode_sun_visibility(
                encoder,
                &pools.shadow,
                &b.params,
                &off,
                n,
                input.sun_dir,
                cam_pos,
                &model.scene_box,
                &model.config.light,
                model.config.near_m,
                capacity.map(|c| c.1),
                &visibility,
                &flags,
            )?;
            encoder = enc;
            light_record = Some(record);
        }

        mark(&mut encoder, "shadow");

        // The networks' forward and their channels.
        let nets = &pools.networks;
        let sun = input.sun_dir.to_array();
        let phi_tape = match phi_parts {
            None => None,
            Some((appearance, phi)) => {
                let phi_in = nets.storage(
                    ctx,
                    "sa phi input",
                    (n.max(1) * appearance.input_width()) as u64 * 4,
                )?;
                let phi_out = nets.storage(ctx, "sa phi output", n.max(1) as u64 * 12)?;
                self.io.encode_phi_input(
                    &mut encoder,
                    nets,
                    appearance,
                    &b.params,
                    &off,
                    n,
                    &list,
                    &count,
                    sun,
                    cam_pos.to_array(),
                    &phi_in,
                    &flags,
                )?;
                let phi_tape = self.mlp.encode_forward(
                    &mut encoder,
                    nets,
                    "phi",
                    phi,
                    &phi_in,
                    &count,
                    n,
                    &phi_out,
                )?;
                self.io.encode_phi_scatter(
                    &mut encoder,
                    nets,
                    n,
                    nc,
                    &list,
                    &count,
                    &phi_out,
                    &chans,
                )?;
                Some(phi_tape)
            }
        };
        mark(&mut encoder, "phi-f");
        let multiply = model.config.shadow_refinement == ShadowRefinement::Multiply;
        let psi_parts = match (model.shadow.as_ref(), self.shadow_net.as_ref(), shadowed) {
            (Some(net), Some(psi), true) => {
                let psi_in = nets.storage(
                    ctx,
                    "sa psi input",
                    (n.max(1) * net.input_width()) as u64 * 4,
                )?;
                let psi_out = nets.storage(ctx, "sa psi output", n.max(1) as u64 * 4)?;
                self.io.encode_psi_input(
                    &mut encoder,
                    nets,
                    net,
                    &model.scene_box,
                    &b.params,
                    &off,
                    n,
                    &list,
                    &count,
                    sun,
                    &visibility,
                    &psi_in,
                    &flags,
                )?;
                let tape = self.mlp.encode_forward(
                    &mut encoder,
                    nets,
                    "psi",
                    psi,
                    &psi_in,
                    &count,
                    n,
                    &psi_out,
                )?;
                self.io.encode_psi_scatter(
                    &mut encoder,
                    nets,
                    n,
                    nc,
                    &list,
                    &count,
                    &visibility,
                    &psi_out,
                    multiply,
                    &chans,
                )?;
                Some((net, psi, tape))
            }
            _ => None,
        };
        mark(&mut encoder, "psi-f");
        self.encode_finite(&mut encoder, &chans, n * nc, "channels", &flags)?;

        // Camera pass, loss, backward.
        let device = self.raster.forward_device_blend(prepared, chans, encoder);
        let mut encoder = device.encoder;
        mark(&mut encoder, "blend-f");
        let st = &device.state;
        let cap_u = own.uniform(
            ctx,
            "sa sort capacity",
            &u32_bytes(&[n as u32, device.n_sort as u32, 0, 0]),
        )?;
        {
            let bind = ctx.bind_group(&self.pipelines.overflow, &[&cap_u, &device.counts, &flags]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.pipelines.overflow);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(1, 1, 1);
        }
        let px_u = own.uniform(ctx, "sa pixels", &count_words(pixels as usize))?;
        let d_image = own.storage(ctx, "sa image gradient", pixels * 5 * 4)?;
        encoder.clear_buffer(&d_image, 0, None);
        let image = if shadowed {
            let image = own.storage(ctx, "sa image", pixels * 12)?;
            let bind = ctx.bind_group(&self.pipelines.compose, &[&px_u, &device.color, &image]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.pipelines.compose, &bind, pixels);
            drop(pass);
            image
        } else {
            device.color.clone()
        };
        let loss_buffers = self.pipelines.loss.encode(
            ctx,
            &mut encoder,
            shape,
            model.config.lambda_dssim,
            &image,
            &target,
            &pixel_weights_buf,
            &d_image,
            &flags,
            Some(&pools.raster),
        )?;
        let px_grad = if shadowed {
            let d_color = own.storage(ctx, "sa colour gradient", pixels * 6 * 4)?;
            let bind = ctx.bind_group(
                &self.pipelines.compose_backward,
                &[&px_u, &device.color, &d_image, &d_color],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.pipelines.compose_backward, &bind, pixels);
            drop(pass);
            d_color
        } else {
            d_image.clone()
        };
        mark(&mut encoder, "loss");
        let rows = self.raster.encode_backward(
            st,
            device.tile_entries.unwrap_or(device.n_sort as usize),
            &px_grad,
            &mut encoder,
            Some(&pools.raster),
        )?;

        mark(&mut encoder, "blend-b");

        // Gradients: geometry and L_iso, then the networks' terms.
        let iso_factor = if model.config.variant.uses_isotropic_loss() {
            model.config.lambda_iso as f64
                * match model.config.iso_reduction {
                    IsoReduction::Sum => 1.0,
                    IsoReduction::MeanOverEntries => 1.0 / (3 * n.max(1)) as f64,
                }
        } else {
            0.0
        };
        // One partial per dispatched workgroup (the grid may pad past ceil(n / 256)).
        let (gx, gy) = groups_1d(n as u64);
        let groups = gx as usize * gy as usize;
        let partials = own.storage(ctx, "sa iso partials", groups as u64 * 4)?;
        encoder.clear_buffer(&partials, 0, None);
        {
            let iso_u = own.uniform(
                ctx,
                "sa iso",
                &u32_bytes(&[(iso_factor as f32).to_bits(), 0, 0, 0]),
            )?;
            let mut pass = encoder.begin_compute_pass(&Default::default());
            if sh_colour {
                // resident_grads: geometry plus the SH colour backward (no L_iso in (a)).
                let bind = ctx.bind_group(
                    &self.pipelines.sh_grads,
                    &[&step_u, &b.params, &rows, &b.grads, &flags],
                );
                dispatch_1d(&mut pass, &self.pipelines.sh_grads, &bind, n as u64);
            } else {
                let bind = ctx.bind_group(
                    &self.pipelines.grads,
                    &[
                        &step_u, &iso_u, &b.params, &rows, &b.grads, &flags, &partials,
                    ],
                );
                dispatch_1d(&mut pass, &self.pipelines.grads, &bind, n as u64);
            }
        }
        if let (Some((appearance, phi)), Some(phi_tape)) = (phi_parts, &phi_tape) {
            let phi_d_out = nets.storage(ctx, "sa phi output gradient", n.max(1) as u64 * 12)?;
            let phi_d_in = nets.storage(
                ctx,
                "sa phi input gradient",
                (n.max(1) * appearance.input_width()) as u64 * 4,
            )?;
            self.io.encode_phi_d_output(
                &mut encoder,
                nets,
                n,
                nc,
                &list,
                &count,
                &rows,
                &phi_d_out,
            )?;
            self.mlp.encode_backward(
                &mut encoder,
                nets,
                "phi",
                phi,
                phi_tape,
                &phi_d_out,
                Some(&phi_d_in),
            )?;
            self.io.encode_phi_input_grad(
                &mut encoder,
                nets,
                appearance,
                &b.params,
                &off,
                n,
                &list,
                &count,
                cam_pos.to_array(),
                &phi_d_in,
                &b.grads,
            )?;
        }
        mark(&mut encoder, "phi-b");
        if let Some((net, psi, tape)) = &psi_parts {
            let psi_d_out = nets.storage(ctx, "sa psi output gradient", n.max(1) as u64 * 4)?;
            let psi_d_in = nets.storage(
                ctx,
                "sa psi input gradient",
                (n.max(1) * net.input_width()) as u64 * 4,
            )?;
            self.io.encode_psi_d_output(
                &mut encoder,
                nets,
                n,
                nc,
                &list,
                &count,
                &visibility,
                &rows,
                multiply,
                &psi_d_out,
            )?;
            self.mlp.encode_backward(
                &mut encoder,
                nets,
                "psi",
                psi,
                tape,
                &psi_d_out,
                Some(&psi_d_in),
            )?;
            self.io.encode_psi_input_grad(
                &mut encoder,
                nets,
                net,
                &model.scene_box,
                &b.params,
                &off,
                n,
                &list,
                &count,
                &psi_d_in,
                &b.grads,
            )?;
        }

        mark(&mut encoder, "psi-b");

        // Checks, statistics, Adam.
        self.encode_finite(&mut encoder, &b.grads, off[8] as usize, "gradients", &flags)?;
        if let Some((_, phi)) = phi_parts {
            self.encode_finite(
                &mut encoder,
                phi.grads(),
                phi.len(),
                "phi gradients",
                &flags,
            )?;
        }
        if let Some((_, psi, _)) = &psi_parts {
            self.encode_finite(
                &mut encoder,
                psi.grads(),
                psi.len(),
                "psi gradients",
                &flags,
            )?;
        }
        {
            let bind = ctx.bind_group(
                &self.pipelines.stats,
                &[&step_u, &rows, &st.splats, &flags, &b.stats],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.pipelines.stats, &bind, n as u64);
        }
        let words = adam_words(
            &self.dims,
            n,
            input.rates,
            self.adam_step + 1,
            (self.beta1, self.beta2, self.eps),
        )?;
        {
            let adam_u = own.uniform(ctx, "sa adam", &u32_bytes(&words))?;
            let bind = ctx.bind_group(
                &self.pipelines.adam,
                &[&adam_u, &b.params, &b.grads, &b.m, &b.v, &flags],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.pipelines.adam, &bind, words[8] as u64);
        }
        if let Some((_, phi)) = phi_parts {
            self.mlp
                .encode_adam(&mut encoder, nets, "phi", phi, input.appearance_lr, &flags)?;
        }
        if let Some((_, psi, _)) = &psi_parts {
            self.mlp
                .encode_adam(&mut encoder, nets, "psi", psi, input.shadow_lr, &flags)?;
        }

        mark(&mut encoder, "optim");

        // The report: flags, loss totals, the visible count, both entry counts, L_iso,
        // the stage marks.
        let entry_count = own.storage(ctx, "sa entry count", 4)?;
        encoder.copy_buffer_to_buffer(&device.counts, 4 * n as u64, &entry_count, 0, 4);
        let light_count = match &light_record {
            Some(r) => r.entry_count.clone(),
            None => {
                let zero = own.storage(ctx, "sa no light entries", 4)?;
                encoder.clear_buffer(&zero, 0, None);
                zero
            }
        };
        let clock_read = match clock {
            Some(c) => c.resolve(&mut encoder),
            None => (&partials, 4),
        };
        let back = ctx.read_back(
            encoder,
            &[
                (&flags, 8),
                (&loss_buffers.totals, 8),
                (&count, 4),
                (&visible_count, 4),
                (&entry_count, 4),
                (&light_count, 4),
                (&partials, groups as u64 * 4),
                clock_read,
            ],
        )?;
        drop((
            keep,
            device.state,
            loss_buffers,
            light_record,
            phi_tape,
            psi_parts,
        ));
        let flag_words = bytes_u32(&back[0]);
        let totals = bytes_f32(&back[1]);
        let network_rows = bytes_u32(&back[2])[0] as usize;
        let visible = bytes_u32(&back[3])[0] as usize;
        let camera_entries = bytes_u32(&back[4])[0] as u64;
        let light_entries = bytes_u32(&back[5])[0] as u64;
        if self.recent_entries.len() == RECENT_STEPS {
            self.recent_entries.pop_front();
        }
        self.recent_entries
            .push_back((camera_entries, light_entries));
        if flag_words[0] & REFUSED_OVERFLOW != 0 {
            return Ok(Attempt::Overflow {
                camera: camera_entries,
                light: light_entries,
            });
        }
        let refused = flag_words[0] & REFUSED_NONFINITE != 0;
        if !refused {
            self.adam_step += 1;
            if let Some(net) = self.appearance.as_mut() {
                net.mark_stepped();
            }
            if shadowed {
                if let Some(net) = self.shadow_net.as_mut() {
                    net.mark_stepped();
                }
            }
        }
        let mut stages = StepTimings::default();
        if let Some(c) = clock {
            for (label, ms) in c.stages_ms(&back[7]) {
                let slot = match label {
                    "project" => &mut stages.project_ms,
                    "shadow" => &mut stages.shadow_pass_ms,
                    "phi-f" => &mut stages.phi_forward_ms,
                    "psi-f" => &mut stages.psi_forward_ms,
                    "blend-f" => &mut stages.blend_forward_ms,
                    "loss" => &mut stages.loss_ms,
                    "blend-b" => &mut stages.blend_backward_ms,
                    "phi-b" => &mut stages.phi_backward_ms,
                    "psi-b" => &mut stages.psi_backward_ms,
                    _ => &mut stages.optimizer_ms,
                };
                *slot += ms;
            }
        }
        let iso_sum: f64 = bytes_f32(&back[6]).iter().map(|&v| v as f64).sum();
        let iso = (iso_factor * iso_sum) as f32;
        let photometric = combine(totals[0], totals[1], model.config.lambda_dssim, Vec::new());
        Ok(Attempt::Done(SunAwareStepReport {
            refused,
            sort_retries: 0,
            dropped_nonfinite: flag_words[1] as usize,
            loss: photometric.loss + iso,
            l1: photometric.l1,
            ssim: photometric.ssim,
            iso,
            visible,
            network_rows,
            tile_entries: camera_entries as usize,
            light_entries: light_entries as usize,
            total_ms: 0.0,
            stages,
        }))
    }

    /// Records the numbering of the Gaussians flagged in `member` (`n + 1` u32, 0 or 1, the
    /// last 0): the exclusive prefix sum of a copy, so `scanned[i]` is flagged Gaussian
    /// `i`'s row and `scanned[n]` their count. `member` is left as it is.
    fn encode_numbering(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        member: &wgpu::Buffer,
        n: usize,
        what: &str,
        keep: &mut Vec<wgpu::Buffer>,
    ) -> Result<wgpu::Buffer, GpuError> {
        let ctx = self.raster.context();
        let own = &self.pools.own;
        let bytes = (n as u64 + 1) * 4;
        let scanned = own.storage(ctx, &format!("sa {what} numbering"), bytes)?;
        encoder.copy_buffer_to_buffer(member, 0, &scanned, 0, bytes);
        // Every numbering of a step has the same length, so the scan's pooled uniforms
        // hold the same values each time.
        self.raster
            .encode_scan_in(encoder, &scanned, n as u64 + 1, keep, Some(own), 0)?;
        Ok(scanned)
    }

    /// Records the finiteness check of the first `len` values of `data`.
    fn encode_finite(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        data: &wgpu::Buffer,
        len: usize,
        what: &str,
        flags: &wgpu::Buffer,
    ) -> Result<(), GpuError> {
        if len == 0 {
            return Ok(());
        }
        let ctx = self.raster.context();
        let u = self
            .pools
            .own
            .uniform(ctx, &format!("sa finite {what}"), &count_words(len))?;
        let bind = ctx.bind_group(&self.pipelines.finite, &[&u, data, flags]);
        let mut pass = encoder.begin_compute_pass(&Default::default());
        dispatch_1d(&mut pass, &self.pipelines.finite, &bind, len as u64);
        Ok(())
    }
}
