//! The rasterizer's forward pass: on device buffers for the resident step
//! ([`GpuRasterizer::forward_device_prepare`], then [`GpuRasterizer::encode_contributing`]
//! and [`GpuRasterizer::forward_device_blend`]) and from host arrays
//! ([`GpuRasterizer::render`], [`GpuRasterizer::contributing`]).
//!
//! Invariants: host inputs are checked (lengths, finiteness, counts a `u32` indexes)
//! before any device work; without a capacity the sort is sized from the entry count read
//! back mid-pass, with one the caller checks the scanned total afterwards (keys beyond
//! the capacity were dropped); the state a backward needs stays in the returned output.

use super::*;

impl GpuRasterizer {
    /// Projection, prefix sum (and the 4-byte entry-count readback), key generation,
    /// sort, tile ranges and blending of `inputs`' device buffers:
    /// [`Self::forward_device_prepare`] then [`Self::forward_device_blend`] with
    /// `inputs.chans`. `encoder` may already hold work that fills them (it is submitted
    /// first). Returns the forward's device state and an encoder with the sort and blend
    /// recorded but not submitted, so the caller appends its own readbacks or kernels.
    pub(crate) fn forward_device(
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
    pub(crate) fn forward_device_prepare(
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
    pub(crate) fn encode_contributing(
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
    pub(crate) fn forward_device_blend(
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
    pub(super) fn upload_view<'a>(
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
    /// contribution pass, `Self::encode_contributing`); the same list as
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
}
