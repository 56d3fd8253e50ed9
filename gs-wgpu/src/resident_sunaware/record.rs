//! The recording of one Sun-aware resident step (the module header's steps 1-7) as one
//! command buffer, its readback and report ([`SunAwareResident::step_with`]), and the
//! numbering and finiteness helpers it records with.
//!
//! Invariants: every kernel that changes state (statistics, Adam on the Gaussians and on
//! the networks) reads the step's refusal flags and changes nothing when they are set; the
//! host's step counters advance only for a step the device applied; a sort overflow is
//! reported as [`Attempt::Overflow`] with the exact counts and changes nothing.

use super::kernels::{
    adam_words, count_words, step_words, StepSink, GSTRIDE, OUT_FIXED, RECENT_STEPS,
    REFUSED_NONFINITE, REFUSED_OVERFLOW,
};
use super::{Attempt, SunAwareResident, SunAwareStepInput, SunAwareStepReport};
use crate::loss::{combine, LossImages};
use crate::mlp::MlpRecording;
use crate::network_io::{NetworkBatch, PackedParams, PhiShading, PhiShadingGrad};
use crate::packed::offsets;
use crate::raster::DeviceInputs;
use crate::sun_visibility::SunLight;
use crate::{bytes_f32, bytes_u32, dispatch_1d, groups_1d, u32_bytes, GpuError};
use gs_core::loss::ImageShape;
use gs_core::model::Param;
use gs_core::regularizer::IsoReduction;
use gs_core::sunaware::config::{ColourSpace, ShadowRefinement};
use gs_core::sunaware::Shading;
use gs_core::sunaware::StepTimings;
use gs_core::sunaware::SunAwareModel;

impl SunAwareResident {
    pub(super) fn step_with(
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
        // The learned-normal Lambertian factor on Phi's colour (the shortest-axis one has
        // no device kernels: the engine refuses it).
        let learned_shading = match model.config.shading {
            Shading::None => false,
            Shading::LambertLearned if self.dims[Param::Normal.index()] == 3 => true,
            other => {
                return Err(GpuError::Invalid(format!(
                    "shading = {:?} on the device (normal group of width {}): only \
                     \"lambert_learned\" with its normal group has device kernels",
                    other.name(),
                    self.dims[Param::Normal.index()]
                )))
            }
        };
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
        // The Normal group's gradient: only Phi's output gradient adds to it (lit rows).
        let normal_values = (off[Param::COUNT] - off[Param::Normal.index()]) as u64;
        if normal_values > 0 {
            encoder.clear_buffer(
                &b.grads,
                off[Param::Normal.index()] as u64 * 4,
                Some(normal_values * 4),
            );
        }
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
                PackedParams {
                    buffer: &b.params,
                    offsets: &off,
                },
                n,
                &SunLight {
                    sun_dir: input.sun_dir,
                    camera_centre: cam_pos,
                    scene_box: &model.scene_box,
                    config: &model.config.light,
                    near_m: model.config.near_m,
                },
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
        let batch = NetworkBatch {
            scratch: nets,
            n,
            list: &list,
            count: &count,
        };
        let packed = PackedParams {
            buffer: &b.params,
            offsets: &off,
        };
        let sun = input.sun_dir.to_array();
        // Per row: the shading factor and the lit normal's sign (scatter to d_output).
        let shade_factors = if learned_shading && phi_parts.is_some() {
            Some(nets.storage(ctx, "sa phi shading", n.max(1) as u64 * 8)?)
        } else {
            None
        };
        // `input.sun_dir` is the unit vector the CPU's forward uses (the trainer
        // normalised it).
        let shading = shade_factors.as_ref().map(|factors| PhiShading {
            params: packed,
            camera_centre: cam_pos.to_array(),
            sun_dir: sun,
            ambient: model.config.shading_ambient,
            factors,
        });
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
                    batch,
                    appearance,
                    packed,
                    sun,
                    cam_pos.to_array(),
                    &phi_in,
                    &flags,
                )?;
                let phi_tape = self.mlp.encode_forward(
                    &mut encoder,
                    MlpRecording {
                        scratch: nets,
                        label: "phi",
                        net: phi,
                    },
                    &phi_in,
                    &count,
                    n,
                    &phi_out,
                )?;
                self.io
                    .encode_phi_scatter(&mut encoder, batch, nc, &phi_out, shading, &chans)?;
                Some((phi_tape, phi_out))
            }
        };
        mark(&mut encoder, "phi-f");
        let multiply_gain = (model.config.shadow_refinement == ShadowRefinement::Multiply)
            .then_some(model.config.shadow_gain);
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
                    batch,
                    net,
                    &model.scene_box,
                    packed,
                    sun,
                    &visibility,
                    &psi_in,
                    &flags,
                )?;
                let tape = self.mlp.encode_forward(
                    &mut encoder,
                    MlpRecording {
                        scratch: nets,
                        label: "psi",
                        net: psi,
                    },
                    &psi_in,
                    &count,
                    n,
                    &psi_out,
                )?;
                self.io.encode_psi_scatter(
                    &mut encoder,
                    batch,
                    nc,
                    &visibility,
                    &psi_out,
                    multiply_gain,
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
        // `RGB * S` (c-d) and the per-pixel sRGB encoding (`colour_space = "linear"`):
        // without either the image is the colour buffer (a-b in sRGB).
        let linear = model.config.colour_space == ColourSpace::Linear;
        let compose = shadowed || linear;
        let compose_u = own.uniform(
            ctx,
            "sa compose",
            &u32_bytes(&[pixels as u32, nc as u32, linear as u32, 0]),
        )?;
        let d_image = own.storage(ctx, "sa image gradient", pixels * 5 * 4)?;
        encoder.clear_buffer(&d_image, 0, None);
        let image = if compose {
            let image = own.storage(ctx, "sa image", pixels * 12)?;
            let bind = ctx.bind_group(
                &self.pipelines.compose,
                &[&compose_u, &device.color, &image],
            );
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
            model.config.lambda_dssim,
            LossImages {
                shape,
                rendered: &image,
                target: &target,
                weights: &pixel_weights_buf,
                px_grad: &d_image,
            },
            &flags,
            Some(&pools.raster),
        )?;
        let px_grad = if compose {
            // The rasterizer's rows: the channels, alpha and depth.
            let d_color = own.storage(ctx, "sa colour gradient", pixels * (nc as u64 + 2) * 4)?;
            let bind = ctx.bind_group(
                &self.pipelines.compose_backward,
                &[&compose_u, &device.color, &d_image, &d_color],
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
        if let (Some((appearance, phi)), Some((phi_tape, phi_out))) = (phi_parts, &phi_tape) {
            let phi_d_out = nets.storage(ctx, "sa phi output gradient", n.max(1) as u64 * 12)?;
            let phi_d_in = nets.storage(
                ctx,
                "sa phi input gradient",
                (n.max(1) * appearance.input_width()) as u64 * 4,
            )?;
            let shading_grad = shading.map(|shading| PhiShadingGrad {
                shading,
                output: phi_out,
                grads: &b.grads,
            });
            self.io.encode_phi_d_output(
                &mut encoder,
                batch,
                nc,
                &rows,
                shading_grad,
                &phi_d_out,
            )?;
            self.mlp.encode_backward(
                &mut encoder,
                MlpRecording {
                    scratch: nets,
                    label: "phi",
                    net: phi,
                },
                phi_tape,
                &phi_d_out,
                Some(&phi_d_in),
            )?;
            // With local inputs, their gradient joins the Normal group after the
            // shading's term (Phi's output gradient above), as on the CPU.
            self.io.encode_phi_input_grad(
                &mut encoder,
                batch,
                appearance,
                packed,
                cam_pos.to_array(),
                sun,
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
                batch,
                nc,
                &visibility,
                &rows,
                multiply_gain,
                &psi_d_out,
            )?;
            self.mlp.encode_backward(
                &mut encoder,
                MlpRecording {
                    scratch: nets,
                    label: "psi",
                    net: psi,
                },
                tape,
                &psi_d_out,
                Some(&psi_d_in),
            )?;
            self.io.encode_psi_input_grad(
                &mut encoder,
                batch,
                net,
                &model.scene_box,
                packed,
                &psi_d_in,
                &b.grads,
            )?;
        }

        mark(&mut encoder, "psi-b");

        // Checks, statistics, Adam.
        self.encode_finite(
            &mut encoder,
            &b.grads,
            off[Param::COUNT] as usize,
            "gradients",
            &flags,
        )?;
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
        let sink = StepSink {
            ctx,
            pool: own,
            flags: &flags,
        };
        self.pipelines
            .optim
            .encode_adam(sink, &mut encoder, b, &words)?;
        if let Some((_, phi)) = phi_parts {
            self.mlp.encode_adam(
                &mut encoder,
                MlpRecording {
                    scratch: nets,
                    label: "phi",
                    net: phi,
                },
                input.appearance_lr,
                &flags,
            )?;
        }
        if let Some((_, psi, _)) = &psi_parts {
            self.mlp.encode_adam(
                &mut encoder,
                MlpRecording {
                    scratch: nets,
                    label: "psi",
                    net: psi,
                },
                input.shadow_lr,
                &flags,
            )?;
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
        let sink = StepSink {
            ctx: self.raster.context(),
            pool: &self.pools.own,
            flags,
        };
        self.pipelines
            .optim
            .encode_finite(sink, encoder, data, len, what)
    }
}
