//! The rasterizer's backward pass: the per-tile back-to-front walk accumulating each
//! Gaussian's gradients (f32 atomics, a compare-and-swap loop, or per-entry records summed
//! in tile order when deterministic), then the projection backward
//! ([`GpuRasterizer::encode_backward`] on device buffers, [`GpuRasterizer::render_backward`]
//! from a host render's output).
//!
//! Invariants: gradients are those of `gs_core::raster::render_backward` to rounding;
//! non-finite pixel gradients are refused before any device work; a Gaussian whose
//! gradient comes out non-finite is zeroed and counted (`dropped_nonfinite`).

use super::*;

impl GpuRasterizer {
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
    pub(crate) fn encode_backward(
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
