//! The shadow pass on the GPU: per-Gaussian Sun visibility `V_i`
//! (`sunaware::sun_visibility::sun_visibility`) from the packed device parameters, recordable into
//! a caller's command encoder (`GpuSunVisibility::encode_sun_visibility`, for the
//! device-resident Sun-aware step), and its host wrappers ([`GpuSunVisibility::sun_visibility`]
//! from a `GaussianModel`, [`GpuSunVisibility::visibility_from_splats`] from CPU splats).
//!
//! The light camera comes from the host (`sun_visibility::light_camera`: it depends only on the Sun,
//! the camera centre, the scene box and the config). One thread per Gaussian projects it
//! into the light image (shaders/shadow_project.wgsl: `light_splats`, perspective through
//! the rasterizer's projection or `ortho_splat`, and its receiver limit from
//! `light_axis_sigmas_m`); then the rasterizer's prefix sum, key generation, radix sort
//! and tile ranges bin and depth-sort the splats, each tile's receivers are sorted by
//! their depth limit (entries no pixel of the tile can receive at sort last), every pixel
//! walks its receivers and occluders, and the weights are summed per Gaussian with integer
//! atomics on 64-bit fixed-point sums (shadow_vis.wgsl; no float atomics).
//!
//! Invariants: the same arithmetic as the CPU functions, so `V` agrees to f32 rounding of
//! the sums, except where rounding moves an occluder across the 1/255 alpha cutoff or the
//! 1e-4 transmittance stop at a pixel; `V` in [0, 1], 1 for Gaussians no pixel saw
//! (culled, e.g. for a non-finite parameter, or off the light image). Deterministic: the
//! per-Gaussian sums are exact integer sums (of the f32 terms, each to 2^-32), so the same
//! inputs give the same bits in any order of the atomic adds. A recorded pass reads back
//! nothing when given a sort capacity; it then flags (`flags[0] |= 2`) a capacity below the
//! entry count (the flags word is only ever or-ed into, never cleared).
//! One recorded pass per `GpuSunVisibility` per submission: the uniforms of a recording (from the
//! caller's scratch and from this pipeline set's own pool for the rasterizer's scan and
//! sort, whose labels the caller's camera pass also uses) are written through the queue,
//! so a second recording before the first is submitted would overwrite them. The host
//! wrappers hold a lock from recording to readback; callers on several threads serialise
//! their recordings likewise.

use std::sync::{Arc, Mutex};

use super::packed::PackedParams;
use super::raster::{frame_bytes, prelude, GpuRasterizer, SortKeys, SSTRIDE};
use super::{bytes_f32, bytes_u32, dispatch_1d, f32_bytes, u32_bytes, GpuError, Scratch};
use gs_core::model::{Param, ParamSet};
use gs_core::nn::SceneBox;
use gs_core::raster::bin::TileGrid;
use gs_core::raster::blend::{Splat, ALPHA_MIN};
use gs_core::raster::project::CameraFrame;
use gs_core::sunaware::config::{LightConfig, LightProjection};
use gs_core::sunaware::error::SunAwareError;
use gs_core::sunaware::sun_visibility;

const SHADOW_PROJECT: &str = include_str!("shaders/shadow_project.wgsl");
const SHADOW_COUNT: &str = include_str!("shaders/shadow_count.wgsl");
const SHADOW_KEYS: &str = include_str!("shaders/shadow_keys.wgsl");
const SHADOW_VIS: &str = include_str!("shaders/shadow_vis.wgsl");
const SHADOW_FINAL: &str = include_str!("shaders/shadow_final.wgsl");
const RESIDENT_OVERFLOW: &str = include_str!("shaders/resident_overflow.wgsl");

/// `Frame::n_entries` when the entry count stays on the device (`ENTRIES_ON_DEVICE` in
/// common.wgsl).
const ENTRIES_ON_DEVICE: u32 = u32::MAX;
/// Widths of the groups the pass reads (mean, log-scale, rotation, opacity logit).
const GEOMETRY_DIMS: [usize; 4] = [3, 3, 4, 1];

/// Compiled shadow-pass pipelines on a rasterizer's device.
pub struct GpuSunVisibility {
    raster: Arc<GpuRasterizer>,
    project: wgpu::ComputePipeline,
    count: wgpu::ComputePipeline,
    receiver_keys: wgpu::ComputePipeline,
    visibility: wgpu::ComputePipeline,
    finish: wgpu::ComputePipeline,
    overflow: wgpu::ComputePipeline,
    /// The rasterizer's scan and sort temporaries of recorded passes: their uniforms
    /// carry the rasterizer's own labels ("sort stage k"), which the caller's scratch
    /// also gives its camera pass in the same submission.
    sort_scratch: Scratch,
    /// Buffers of the host wrappers, locked for a whole call, recording to readback.
    host_scratch: Mutex<Scratch>,
}

impl std::fmt::Debug for GpuSunVisibility {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuSunVisibility({:?})", self.raster)
    }
}

/// What the caller needs after submitting a recorded shadow pass.
pub struct ShadowRecord {
    /// Word 0: the light pass's tile entries (written by the recorded commands).
    pub entry_count: wgpu::Buffer,
    /// Keys the sorts' buffers hold: the entry count, or the capacity.
    pub n_sort: u64,
    /// The entry count, when it was read back (no capacity given).
    pub tile_entries: Option<u64>,
    /// Uniforms and temporaries the recorded commands read, held until submission.
    _keep: Vec<wgpu::Buffer>,
}

impl std::fmt::Debug for ShadowRecord {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "ShadowRecord(n_sort {}, entries {:?})",
            self.n_sort, self.tile_entries
        )
    }
}

/// Device splats ready for the sort and the walk (see [`GpuSunVisibility::encode_walk`]).
struct WalkInputs<'a> {
    /// `n * SSTRIDE` floats (common.wgsl's splat rows).
    splats: &'a wgpu::Buffer,
    /// Receiver depth limits, `n` floats.
    limits: &'a wgpu::Buffer,
    /// `n + 1` u32: tiles per splat, then a zero (scanned in place).
    counts: &'a wgpu::Buffer,
    n: usize,
    side_px: u32,
    footprint_radius_px: f32,
}

/// `V`, `flags[0]` and the sort's sizes of a recorded pass run from the host
/// ([`GpuSunVisibility::sun_visibility_packed`]).
#[derive(Clone, Debug, PartialEq)]
pub struct PackedVisibility {
    /// `V_i` per Gaussian (not valid where `flags` has the overflow bit).
    pub visibility: Vec<f32>,
    /// Word 0 of the flags buffer: bit 1 (value 2), the sort capacity was too small.
    pub flags: u32,
    /// The light pass's tile entries.
    pub tile_entries: u64,
    /// Keys the sorts ran over.
    pub n_sort: u64,
}

/// What the light pass renders from: the unit vector towards the Sun, the camera centre
/// (which places the light camera with the scene box, as
/// `sunaware::sun_visibility::light_camera` does), the scene box, the light settings and
/// the near plane, m.
#[derive(Clone, Copy, Debug)]
pub struct SunLight<'a> {
    pub sun_dir: glam::Vec3,
    pub camera_centre: glam::Vec3,
    pub scene_box: &'a SceneBox,
    pub config: &'a LightConfig,
    pub near_m: f32,
}

fn sunaware_error(e: SunAwareError) -> GpuError {
    GpuError::Invalid(e.to_string())
}

fn check_light_image(
    side_px: u32,
    footprint_radius_px: f32,
    depth_bias_m: f32,
) -> Result<(), GpuError> {
    if side_px == 0 || side_px > gs_core::raster::MAX_IMAGE_SIDE_PX {
        return Err(GpuError::Invalid(format!("light image side {side_px} px")));
    }
    if !(footprint_radius_px.is_finite() && depth_bias_m.is_finite()) {
        return Err(GpuError::Invalid(
            "footprint radius and depth bias must be finite".into(),
        ));
    }
    Ok(())
}

impl GpuSunVisibility {
    pub fn new(raster: Arc<GpuRasterizer>) -> Result<Self, GpuError> {
        let ctx = &raster.ctx;
        let pre = prelude(0);
        Ok(Self {
            project: ctx.pipeline("shadow_project", &format!("{pre}{SHADOW_PROJECT}"))?,
            count: ctx.pipeline("shadow_count", &format!("{pre}{SHADOW_COUNT}"))?,
            receiver_keys: ctx.pipeline("shadow_keys", &format!("{pre}{SHADOW_KEYS}"))?,
            visibility: ctx.pipeline("shadow_vis", &format!("{pre}{SHADOW_VIS}"))?,
            finish: ctx.pipeline("shadow_final", &format!("{pre}{SHADOW_FINAL}"))?,
            overflow: ctx.pipeline("shadow_overflow", RESIDENT_OVERFLOW)?,
            sort_scratch: Scratch::default(),
            host_scratch: Mutex::new(Scratch::default()),
            raster,
        })
    }

    fn host_scratch(&self) -> Result<std::sync::MutexGuard<'_, Scratch>, GpuError> {
        self.host_scratch
            .lock()
            .map_err(|_| GpuError::Device("shadow scratch lock poisoned".into()))
    }

    /// `V_i` of every Gaussian of `model` for one image: the GPU counterpart of
    /// `sunaware::sun_visibility::sun_visibility` (uploads the geometry, records
    /// `Self::encode_sun_visibility` with the entry count read back, reads `V` back).
    pub fn sun_visibility(
        &self,
        model: &gs_core::model::GaussianModel,
        light: &SunLight,
    ) -> Result<Vec<f32>, GpuError> {
        let n = model.len();
        let mut dims = [0usize; Param::COUNT];
        dims[..4].copy_from_slice(&GEOMETRY_DIMS);
        let offsets = super::packed::offsets(&dims, n)?;
        let mut packed = Vec::with_capacity(11 * n);
        for p in [
            Param::Mean,
            Param::LogScale,
            Param::Rotation,
            Param::OpacityLogit,
        ] {
            packed.extend_from_slice(model.params.get(p));
        }
        Ok(self
            .run_packed(&packed, &offsets, n, light, None)?
            .visibility)
    }

    /// `Self::encode_sun_visibility` on `params` packed in the resident layout
    /// (`crate::packed::pack`), run from the host: uploads, records with `capacity`,
    /// submits and reads back `V`, the flags word and the entry count.
    pub fn sun_visibility_packed(
        &self,
        params: &ParamSet,
        light: &SunLight,
        capacity: Option<u64>,
    ) -> Result<PackedVisibility, GpuError> {
        let n = params.len();
        let offsets = super::packed::offsets(&params.dims(), n)?;
        self.run_packed(&super::packed::pack(params), &offsets, n, light, capacity)
    }

    fn run_packed(
        &self,
        packed: &[f32],
        offsets: &[u32; Param::COUNT + 1],
        n: usize,
        light: &SunLight,
        capacity: Option<u64>,
    ) -> Result<PackedVisibility, GpuError> {
        let ctx = &self.raster.ctx;
        let scratch = self.host_scratch()?;
        let params = scratch.storage(ctx, "shadow host params", packed.len() as u64 * 4)?;
        ctx.queue.write_buffer(&params, 0, &f32_bytes(packed));
        let visibility = scratch.storage(ctx, "shadow host visibility", n as u64 * 4)?;
        let flags = scratch.storage(ctx, "shadow host flags", 4)?;
        let mut encoder = ctx.encoder("shadow");
        encoder.clear_buffer(&flags, 0, None);
        let (record, encoder) = self.encode_sun_visibility(
            encoder,
            &scratch,
            PackedParams {
                buffer: &params,
                offsets,
            },
            n,
            light,
            capacity,
            &visibility,
            &flags,
        )?;
        let back = ctx.read_back(
            encoder,
            &[
                (&visibility, n as u64 * 4),
                (&flags, 4),
                (&record.entry_count, 4),
            ],
        )?;
        Ok(PackedVisibility {
            visibility: bytes_f32(&back[0]),
            flags: bytes_u32(&back[1])[0],
            tile_entries: bytes_u32(&back[2])[0] as u64,
            n_sort: record.n_sort,
        })
    }

    /// Records `V` for every Gaussian of the packed device `params` (the resident layout:
    /// group g of `n` Gaussians at word `offsets[g]`; only the mean, log-scale, rotation
    /// and opacity-logit groups are read) into `visibility` (`n` f32). Same checks and
    /// values as `sunaware::sun_visibility::sun_visibility` (a Gaussian with a non-finite parameter
    /// is culled: `V = 1`).
    ///
    /// `capacity`: `Some(c)` sizes the sorts for `c` entries with no readback; if the
    /// entry count exceeds that, the recorded commands set `flags[0]` bit 1 (value 2) and
    /// `V` is not valid: the caller redoes the step with the count from
    /// [`ShadowRecord::entry_count`]. `None` submits `encoder` up
    /// to the count, reads its 4 bytes back and records the rest into a fresh encoder.
    /// Returns the encoder to continue recording into. `flags` is only ever or-ed into.
    /// One recorded pass per submission: the pass's uniforms (from `scratch` and from this
    /// pipeline set's own pool) are written at the next submission.
    pub(crate) fn encode_sun_visibility(
        &self,
        mut encoder: wgpu::CommandEncoder,
        scratch: &Scratch,
        PackedParams {
            buffer: params,
            offsets,
        }: PackedParams,
        n: usize,
        light: &SunLight,
        capacity: Option<u64>,
        visibility: &wgpu::Buffer,
        flags: &wgpu::Buffer,
    ) -> Result<(ShadowRecord, wgpu::CommandEncoder), GpuError> {
        let SunLight {
            sun_dir,
            camera_centre,
            scene_box,
            config,
            near_m,
        } = *light;
        let ctx = &self.raster.ctx;
        if n >= (u32::MAX as usize) / (SSTRIDE * 4) {
            return Err(GpuError::TooLarge(format!("{n} Gaussians")));
        }
        let group_fits = |g: usize| {
            offsets[g + 1].checked_sub(offsets[g]).map(u64::from)
                == Some((GEOMETRY_DIMS[g] * n) as u64)
        };
        if offsets.windows(2).any(|w| w[1] < w[0]) || !(0..4).all(group_fits) {
            return Err(GpuError::Invalid(format!(
                "parameter offsets {offsets:?} do not fit {n} Gaussians"
            )));
        }
        if (offsets[Param::COUNT] as u64) * 4 > params.size() {
            return Err(GpuError::Invalid(format!(
                "parameter buffer of {} bytes holds fewer than the {} values of its offsets",
                params.size(),
                offsets[Param::COUNT]
            )));
        }
        if visibility.size() < n as u64 * 4 || flags.size() < 4 {
            return Err(GpuError::Invalid(format!(
                "visibility buffer of {} bytes for {n} Gaussians, flags of {} bytes",
                visibility.size(),
                flags.size()
            )));
        }
        let lc = sun_visibility::light_camera(sun_dir, camera_centre, scene_box, config)
            .map_err(sunaware_error)?;
        let side = config.resolution_px;
        check_light_image(side, config.footprint_radius_px, lc.depth_bias_m)?;
        let (frame, orthographic) = match lc.projection {
            LightProjection::Perspective => (
                gs_core::raster::camera_frame(&lc.camera, near_m)
                    .map_err(|e| sunaware_error(e.into()))?,
                false,
            ),
            LightProjection::Orthographic => {
                // ortho_splat's world-to-camera rotation; the rest of the frame is unused.
                let m = glam::Mat3::from_quat(lc.camera.rotation.normalize());
                let mut rot = [[0.0f32; 3]; 3];
                for (r, row) in rot.iter_mut().enumerate() {
                    *row = m.row(r).to_array();
                }
                let frame = CameraFrame {
                    rot_cam_from_world: rot,
                    translation: lc.camera.translation.to_array(),
                    fx: 0.0,
                    fy: 0.0,
                    cx: 0.0,
                    cy: 0.0,
                    lim_x: 0.0,
                    lim_y: 0.0,
                    near_m,
                };
                (frame, true)
            }
        };
        let grid = TileGrid::new(side, side);
        let frame_buf = scratch.uniform(
            ctx,
            "shadow projection frame",
            &frame_bytes(&frame, ALPHA_MIN, &grid, n as u32, false, 0, 0, &[]),
        )?;
        let mut words = [0u32; 12];
        words[..4].copy_from_slice(&offsets[..4]);
        words[4] = orthographic as u32;
        words[5] = lc.ortho_px_per_m.to_bits();
        words[6] = (0.5 * side as f32).to_bits();
        words[7] = lc.depth_bias_m.to_bits();
        words[8] = sun_visibility::RECEIVER_EXTENT_SIGMAS.to_bits();
        let project_buf = scratch.uniform(ctx, "shadow projection", &u32_bytes(&words))?;
        let splats = scratch.storage(ctx, "shadow splats", (n * SSTRIDE * 4) as u64)?;
        let limits = scratch.storage(ctx, "shadow receiver limits", n as u64 * 4)?;
        // One extra zero at the end: its exclusive prefix sum is the entry count.
        let counts = scratch.storage(ctx, "shadow tile counts", (n as u64 + 1) * 4)?;
        encoder.clear_buffer(&counts, 0, None);
        {
            let bind = ctx.bind_group(
                &self.project,
                &[&frame_buf, &project_buf, params, &splats, &counts, &limits],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.project, &bind, n as u64);
        }
        let inputs = WalkInputs {
            splats: &splats,
            limits: &limits,
            counts: &counts,
            n,
            side_px: side,
            footprint_radius_px: config.footprint_radius_px,
        };
        let (mut record, encoder) = self.encode_walk(
            encoder,
            scratch,
            Some(&self.sort_scratch),
            &inputs,
            capacity,
            visibility,
            Some(flags),
        )?;
        record
            ._keep
            .extend([frame_buf, project_buf, splats, limits, counts]);
        Ok((record, encoder))
    }

    /// Scan of the tile counts, (readback,) keys, sort, tile ranges, receiver keys and
    /// sort, the walk and `V`, recorded into `encoder` (see [`Self::encode_sun_visibility`]
    /// for `capacity` and `flags`, which only a capacity uses).
    fn encode_walk(
        &self,
        mut encoder: wgpu::CommandEncoder,
        scratch: &Scratch,
        sort_scratch: Option<&Scratch>,
        inputs: &WalkInputs,
        capacity: Option<u64>,
        visibility: &wgpu::Buffer,
        flags: Option<&wgpu::Buffer>,
    ) -> Result<(ShadowRecord, wgpu::CommandEncoder), GpuError> {
        let ctx = &self.raster.ctx;
        let raster = &self.raster;
        let pipelines = raster.channel_pipelines(0)?;
        let n = inputs.n;
        let grid = TileGrid::new(inputs.side_px, inputs.side_px);
        let mut keep = Vec::new();
        let len = n as u64 + 1;
        match sort_scratch {
            Some(pool) => {
                raster.encode_scan_in(
                    &mut encoder,
                    inputs.counts,
                    len,
                    &mut keep,
                    Some(pool),
                    0,
                )?;
            }
            None => raster.encode_scan(&mut encoder, inputs.counts, len, &mut keep)?,
        }
        let entry_count = scratch.storage(ctx, "shadow entry count", 4)?;
        encoder.copy_buffer_to_buffer(inputs.counts, 4 * n as u64, &entry_count, 0, 4);
        let (total, n_sort, mut encoder) = match capacity {
            None => {
                let back = ctx.read_back(encoder, &[(&entry_count, 4)])?;
                let total = bytes_u32(&back[0])[0] as u64;
                (Some(total), total, ctx.encoder("shadow: sort and walk"))
            }
            Some(cap) => (None, cap, encoder),
        };
        if n_sort > u32::MAX as u64 / 2 {
            return Err(GpuError::TooLarge(format!("{n_sort} tile entries")));
        }
        if let (None, Some(flags)) = (total, flags) {
            let cap = scratch.uniform(
                ctx,
                "shadow sort capacity",
                &u32_bytes(&[n as u32, n_sort as u32, 0, 0]),
            )?;
            let bind = ctx.bind_group(&self.overflow, &[&cap, inputs.counts, flags]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.overflow);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(1, 1, 1);
            drop(pass);
            keep.push(cap);
        }
        // Only the grid, the counts and the squared radius (carried in `cx`) are read.
        let r = inputs.footprint_radius_px;
        let frame = CameraFrame {
            rot_cam_from_world: [[0.0; 3]; 3],
            translation: [0.0; 3],
            fx: 0.0,
            fy: 0.0,
            cx: r * r,
            cy: 0.0,
            lim_x: 0.0,
            lim_y: 0.0,
            near_m: 0.0,
        };
        let frame_buf = scratch.uniform(
            ctx,
            "shadow frame",
            &frame_bytes(
                &frame,
                0.0,
                &grid,
                n as u32,
                false,
                total.map_or(ENTRIES_ON_DEVICE, |t| t as u32),
                n_sort as u32,
                &[],
            ),
        )?;
        let keys = scratch.storage(ctx, "shadow keys", n_sort * 16)?;
        let receivers = scratch.storage(ctx, "shadow receivers", n_sort * 16)?;
        let ranges = scratch.storage(ctx, "shadow tile ranges", grid.n_tiles() as u64 * 8)?;
        // Two 64-bit fixed-point sums per Gaussian (shadow_vis.wgsl).
        let sums = scratch.storage(ctx, "shadow sums", (4 * n as u64) * 4)?;
        {
            let bind = ctx.bind_group(
                &pipelines.keygen,
                &[&frame_buf, inputs.splats, inputs.counts, &keys],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &pipelines.keygen, &bind, n_sort.max(n as u64));
        }
        // Both sorts read the live count from the scanned tile counts; their uniforms are
        // labelled apart (they share `sort_scratch` within one submission).
        let mut sort = |encoder: &mut wgpu::CommandEncoder, keys: &wgpu::Buffer, label: &str| {
            let sort = SortKeys {
                keys,
                n_sort,
                count: inputs.counts,
                count_word: n as u32,
                n_tiles: grid.n_tiles() as u32,
                label,
            };
            raster.encode_sort_in(encoder, &sort, &mut keep, sort_scratch)
        };
        sort(&mut encoder, &keys, "shadow occluders")?;
        encoder.clear_buffer(&ranges, 0, None);
        encoder.clear_buffer(&sums, 0, None);
        {
            let bind = ctx.bind_group(&pipelines.ranges, &[&frame_buf, &keys, &ranges]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &pipelines.ranges, &bind, n_sort);
        }
        {
            let bind = ctx.bind_group(
                &self.receiver_keys,
                &[&frame_buf, &keys, inputs.limits, &receivers, inputs.splats],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.receiver_keys, &bind, n_sort);
        }
        sort(&mut encoder, &receivers, "shadow receivers")?;
        {
            let bind = ctx.bind_group_at(
                &self.visibility,
                &[
                    (0, &frame_buf),
                    (1, &keys),
                    (2, &receivers),
                    (3, &ranges),
                    (4, inputs.splats),
                    (5, inputs.limits),
                    (7, &sums),
                ],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.visibility);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(grid.tiles_x, grid.tiles_y, 1);
        }
        {
            let bind = ctx.bind_group(&self.finish, &[&frame_buf, &sums, visibility]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.finish, &bind, n as u64);
        }
        keep.extend([frame_buf, keys, receivers, ranges, sums]);
        Ok((
            ShadowRecord {
                entry_count,
                n_sort,
                tile_entries: total,
                _keep: keep,
            },
            encoder,
        ))
    }

    /// `V_i` for every Gaussian from its splats in the `side_px` x `side_px` light image:
    /// the GPU counterpart of `sunaware::sun_visibility::visibility_from_splats` (same arguments;
    /// the splats and limits are uploaded, the sort and walk are
    /// `Self::encode_sun_visibility`'s).
    pub fn visibility_from_splats(
        &self,
        splats: &[Option<Splat>],
        side_px: u32,
        footprint_radius_px: f32,
        depth_bias_m: f32,
        receiver_margin_m: &[f32],
    ) -> Result<Vec<f32>, GpuError> {
        let n = splats.len();
        check_light_image(side_px, footprint_radius_px, depth_bias_m)?;
        if !receiver_margin_m.is_empty() && receiver_margin_m.len() != n {
            return Err(GpuError::Invalid(format!(
                "receiver margins: {} values for {n} splats",
                receiver_margin_m.len()
            )));
        }
        if n >= (u32::MAX as usize) / (SSTRIDE * 4) {
            return Err(GpuError::TooLarge(format!("{n} splats")));
        }
        let ctx = &self.raster.ctx;
        let mut packed = vec![0.0f32; n * SSTRIDE];
        let mut limits = vec![0.0f32; n];
        for (i, (row, s)) in packed.chunks_exact_mut(SSTRIDE).zip(splats).enumerate() {
            match s {
                Some(s) => {
                    row[..7].copy_from_slice(&[
                        s.mean_px[0],
                        s.mean_px[1],
                        s.conic[0],
                        s.conic[1],
                        s.conic[2],
                        s.opacity,
                        s.depth,
                    ]);
                    row[7] = 0.0;
                    for (v, c) in row[8..]
                        .iter_mut()
                        .zip([s.rect.x0, s.rect.y0, s.rect.x1, s.rect.y1])
                    {
                        *v = f32::from_bits(c);
                    }
                    let margin = receiver_margin_m.get(i).copied().unwrap_or(0.0);
                    limits[i] = s.depth - depth_bias_m - margin.max(0.0);
                }
                None => row[7] = -1.0,
            }
        }
        let scratch = self.host_scratch()?;
        let splat_buf = ctx.storage_init("light splats", &f32_bytes(&packed));
        let limit_buf = ctx.storage_init("receiver limits", &f32_bytes(&limits));
        let counts = scratch.storage(ctx, "shadow tile counts", (n as u64 + 1) * 4)?;
        let visibility = scratch.storage(ctx, "shadow host visibility", n as u64 * 4)?;
        // The count kernel reads only the frame's splat count.
        let frame = CameraFrame {
            rot_cam_from_world: [[0.0; 3]; 3],
            translation: [0.0; 3],
            fx: 0.0,
            fy: 0.0,
            cx: 0.0,
            cy: 0.0,
            lim_x: 0.0,
            lim_y: 0.0,
            near_m: 0.0,
        };
        let grid = TileGrid::new(side_px, side_px);
        let frame0 = scratch.uniform(
            ctx,
            "shadow count frame",
            &frame_bytes(&frame, 0.0, &grid, n as u32, false, 0, 0, &[]),
        )?;
        let mut encoder = ctx.encoder("shadow: count");
        encoder.clear_buffer(&counts, 0, None);
        {
            let bind = ctx.bind_group(&self.count, &[&frame0, &splat_buf, &counts]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.count, &bind, n as u64);
        }
        let inputs = WalkInputs {
            splats: &splat_buf,
            limits: &limit_buf,
            counts: &counts,
            n,
            side_px,
            footprint_radius_px,
        };
        // Fresh scan and sort temporaries (the rasterizer's own).
        let (record, encoder) =
            self.encode_walk(encoder, &scratch, None, &inputs, None, &visibility, None)?;
        let back = ctx.read_back(encoder, &[(&visibility, n as u64 * 4)])?;
        drop(record);
        Ok(bytes_f32(&back[0]))
    }
}
