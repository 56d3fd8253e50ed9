//! The shadow pass's per-pixel work on the GPU: `sunaware::light::visibility_from_splats`
//! (per-Gaussian Sun visibility `V_i` from splats in the light image) as kernels.
//!
//! The light camera and its splats come from the CPU (`sunaware::light::light_camera`,
//! `light_splats`: one projection per Gaussian); the GPU bins and depth-sorts them (the
//! rasterizer's prefix sum, key generation, bitonic sort and tile ranges), sorts each
//! tile's receivers by their depth limit, walks every pixel's receivers and occluders,
//! and sums weights per Gaussian with atomics.
//!
//! Invariants: the same arithmetic as the CPU function (see shaders/shadow_vis.wgsl),
//! so `V` agrees to f32 rounding of the sums, except where rounding moves an occluder
//! across the 1/255 alpha cutoff or the 1e-4 transmittance stop at a pixel; `V` in
//! [0, 1], 1 for Gaussians no pixel saw. The atomic sums make the last bits vary from run
//! to run.

use std::sync::Arc;

use super::raster::{frame_bytes, prelude, GpuRasterizer, SORT_BLOCK, SSTRIDE};
use super::{bytes_f32, bytes_u32, dispatch_1d, f32_bytes, GpuError};
use crate::raster::bin::TileGrid;
use crate::raster::blend::Splat;
use crate::raster::project::CameraFrame;

const SHADOW_COUNT: &str = include_str!("shaders/shadow_count.wgsl");
const SHADOW_KEYS: &str = include_str!("shaders/shadow_keys.wgsl");
const SHADOW_VIS: &str = include_str!("shaders/shadow_vis.wgsl");
const SHADOW_FINAL: &str = include_str!("shaders/shadow_final.wgsl");

/// Compiled shadow-pass pipelines on a rasterizer's device.
pub struct GpuShadow {
    raster: Arc<GpuRasterizer>,
    count: wgpu::ComputePipeline,
    receiver_keys: wgpu::ComputePipeline,
    visibility: wgpu::ComputePipeline,
    finish: wgpu::ComputePipeline,
}

impl std::fmt::Debug for GpuShadow {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuShadow({:?})", self.raster)
    }
}

impl GpuShadow {
    pub fn new(raster: Arc<GpuRasterizer>) -> Result<Self, GpuError> {
        let ctx = &raster.ctx;
        let pre = prelude(0);
        let acc = raster.atomic_accumulator();
        Ok(Self {
            count: ctx.pipeline("shadow_count", &format!("{pre}{SHADOW_COUNT}"))?,
            receiver_keys: ctx.pipeline("shadow_keys", &format!("{pre}{SHADOW_KEYS}"))?,
            visibility: ctx.pipeline("shadow_vis", &format!("{pre}{acc}\n{SHADOW_VIS}"))?,
            finish: ctx.pipeline("shadow_final", &format!("{pre}{SHADOW_FINAL}"))?,
            raster,
        })
    }

    /// `V_i` of every Gaussian of `model` for one image: the GPU counterpart of
    /// `sunaware::light::sun_visibility` (light camera, splats and receiver margins from
    /// the CPU functions, the per-pixel pass here).
    pub fn sun_visibility(
        &self,
        model: &crate::model::GaussianModel,
        sun_dir: glam::Vec3,
        camera_centre: glam::Vec3,
        scene_box: &crate::nn::SceneBox,
        config: &crate::sunaware::config::LightConfig,
        near_m: f32,
    ) -> Result<Vec<f32>, GpuError> {
        use crate::sunaware::light;
        let bad = |e: crate::sunaware::error::SunAwareError| GpuError::Invalid(e.to_string());
        let camera = light::light_camera(sun_dir, camera_centre, scene_box, config).map_err(bad)?;
        let splats = light::light_splats(model, &camera, near_m).map_err(bad)?;
        let margin: Vec<f32> = light::light_axis_sigmas_m(model, &camera)
            .iter()
            .map(|s| s * light::RECEIVER_EXTENT_SIGMAS)
            .collect();
        self.visibility_from_splats(
            &splats,
            config.resolution_px,
            config.footprint_radius_px,
            camera.depth_bias_m,
            &margin,
        )
    }

    /// `V_i` for every Gaussian from its splats in the `side_px` x `side_px` light image:
    /// the GPU counterpart of `sunaware::light::visibility_from_splats` (same arguments).
    pub fn visibility_from_splats(
        &self,
        splats: &[Option<Splat>],
        side_px: u32,
        footprint_radius_px: f32,
        depth_bias_m: f32,
        receiver_margin_m: &[f32],
    ) -> Result<Vec<f32>, GpuError> {
        let n = splats.len();
        if side_px == 0 || side_px > crate::raster::MAX_IMAGE_SIDE_PX {
            return Err(GpuError::Invalid(format!("light image side {side_px} px")));
        }
        if !(footprint_radius_px.is_finite() && depth_bias_m.is_finite()) {
            return Err(GpuError::Invalid(
                "footprint radius and depth bias must be finite".into(),
            ));
        }
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
        let pipelines = self.raster.channel_pipelines(0)?;
        let grid = TileGrid::new(side_px, side_px);
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
        // Only the grid, the counts and the squared radius (carried in `cx`) are read.
        let frame = CameraFrame {
            rot_cam_from_world: [[0.0; 3]; 3],
            translation: [0.0; 3],
            fx: 0.0,
            fy: 0.0,
            cx: footprint_radius_px * footprint_radius_px,
            cy: 0.0,
            lim_x: 0.0,
            lim_y: 0.0,
            near_m: 0.0,
        };
        let splat_buf = ctx.storage_init("light splats", &f32_bytes(&packed));
        let limit_buf = ctx.storage_init("receiver limits", &f32_bytes(&limits));
        let frame0 = ctx.uniform_init(
            "shadow frame",
            &frame_bytes(&frame, 0.0, &grid, n as u32, false, 0, 0, &[]),
        );
        let counts = ctx.storage("shadow tile counts", (n as u64 + 1) * 4)?;
        let mut keep = Vec::new();
        let mut encoder = ctx.encoder("shadow: count");
        encoder.clear_buffer(&counts, 0, None);
        {
            let bind = ctx.bind_group(&self.count, &[&frame0, &splat_buf, &counts]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.count, &bind, n as u64);
        }
        self.raster
            .encode_scan(&mut encoder, &counts, n as u64 + 1, &mut keep)?;
        let total_buf = ctx.storage("shadow entry count", 4)?;
        encoder.copy_buffer_to_buffer(&counts, 4 * n as u64, &total_buf, 0, 4);
        let total = bytes_u32(&ctx.read_back(encoder, &[(&total_buf, 4)])?[0])[0] as u64;
        drop(keep);

        let n_sort = total.next_power_of_two().max(SORT_BLOCK);
        if n_sort > u32::MAX as u64 / 2 {
            return Err(GpuError::TooLarge(format!("{total} tile entries")));
        }
        let frame_buf = ctx.uniform_init(
            "shadow frame",
            &frame_bytes(
                &frame,
                0.0,
                &grid,
                n as u32,
                false,
                total as u32,
                n_sort as u32,
                &[],
            ),
        );
        let keys = ctx.storage("shadow keys", n_sort * 16)?;
        let receivers = ctx.storage("shadow receivers", n_sort * 16)?;
        let ranges = ctx.storage("shadow tile ranges", grid.n_tiles() as u64 * 8)?;
        let sums = ctx.storage("shadow sums", (2 * n as u64) * 4)?;
        let vis = ctx.storage("visibility", n as u64 * 4)?;
        let mut keep = Vec::new();
        let mut encoder = ctx.encoder("shadow: sort and walk");
        {
            let bind = ctx.bind_group(&pipelines.keygen, &[&frame_buf, &splat_buf, &counts, &keys]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &pipelines.keygen, &bind, n_sort.max(n as u64));
        }
        self.raster
            .encode_sort(&mut encoder, &keys, n_sort, &mut keep);
        encoder.clear_buffer(&ranges, 0, None);
        encoder.clear_buffer(&sums, 0, None);
        {
            let bind = ctx.bind_group(&pipelines.ranges, &[&frame_buf, &keys, &ranges]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &pipelines.ranges, &bind, total);
        }
        {
            let bind = ctx.bind_group(
                &self.receiver_keys,
                &[&frame_buf, &keys, &limit_buf, &receivers],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.receiver_keys, &bind, n_sort);
        }
        self.raster
            .encode_sort(&mut encoder, &receivers, n_sort, &mut keep);
        {
            let bind = ctx.bind_group_at(
                &self.visibility,
                &[
                    (0, &frame_buf),
                    (1, &keys),
                    (2, &receivers),
                    (3, &ranges),
                    (4, &splat_buf),
                    (5, &limit_buf),
                    (7, &sums),
                ],
            );
            let mut pass = encoder.begin_compute_pass(&Default::default());
            pass.set_pipeline(&self.visibility);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(grid.tiles_x, grid.tiles_y, 1);
        }
        {
            let bind = ctx.bind_group(&self.finish, &[&frame_buf, &sums, &vis]);
            let mut pass = encoder.begin_compute_pass(&Default::default());
            dispatch_1d(&mut pass, &self.finish, &bind, n as u64);
        }
        let back = ctx.read_back(encoder, &[(&vis, n as u64 * 4)])?;
        drop(keep);
        Ok(bytes_f32(&back[0]))
    }
}
