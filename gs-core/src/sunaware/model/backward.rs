//! Backward of one image through the Sun-aware model: `dL/d(RGB, S)` from
//! `dL/d(RGB * S)` (through the per-pixel sRGB encoding under `ColourSpace::Linear`), the rasterizer's backward, the Lambertian factor's, then Phi (or SH)
//! and Psi into their weights, the features, the latents and the means.
//!
//! Invariants: the model must not have changed since the forward that made the pass; `V`
//! is data (no gradient through it); a device render has no backward here (an error: the
//! device trains device-resident); gradients are returned as computed, the caller checks
//! finiteness before stepping.

use std::time::Instant;

use rayon::prelude::*;

use crate::model::{Param, ParamSet};
use crate::nn::shadow_net::ShadowBatch;
use crate::raster::{
    render_backward_with, BackwardTimings as RasterBackwardTimings, GaussianGrads, GaussianView,
    PixelGrads,
};
use crate::sh::sh_to_rgb_backward;
use crate::srgb::{self, ColourSpace};

use crate::sunaware::config::ShadowRefinement;
use crate::sunaware::error::SunAwareError;
use crate::sunaware::shading::{scatter_local_input_grad, shade_backward};

use super::{ms_since, FramePass, PassRender, SunAwareGrads, SunAwareModel};

/// Wall-clock split of one backward, milliseconds (disjoint intervals inside the call).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BackwardTimings {
    /// `dL/d(RGB, S)` from `dL/d(RGB * S)`.
    pub compose_ms: f64,
    /// The rasterizer's own split (blend backward, per-Gaussian reduction + projection
    /// backward).
    pub raster: RasterBackwardTimings,
    /// Rest of the rasterizer call (checks, gradient scatter) and the geometry gather.
    pub raster_other_ms: f64,
    /// Phi's output-gradient gather, backward and input-gradient scatter.
    pub phi_backward_ms: f64,
    /// Psi's output-gradient gather, backward and input-gradient scatter.
    pub psi_backward_ms: f64,
}

/// Pixels per parallel task of `dL/d(RGB, S)`.
const COMPOSE_CHUNK_PX: usize = 4096;

fn gather_geometry(params: &ParamSet, g: &GaussianGrads) -> ParamSet {
    let mut out = params.zeros_like();
    out.get_mut(Param::Mean).copy_from_slice(&g.d_means);
    out.get_mut(Param::LogScale)
        .copy_from_slice(&g.d_log_scales);
    out.get_mut(Param::Rotation).copy_from_slice(&g.d_rotations);
    out.get_mut(Param::OpacityLogit)
        .copy_from_slice(&g.d_opacity_logits);
    out
}

impl SunAwareModel {
    /// Backward of [`SunAwareModel::forward`] for `d_image = dL/d(RGB * S)` (`H * W * 3`).
    /// The model must not have changed since the forward.
    pub fn backward(
        &self,
        pass: &FramePass,
        d_image: &[f32],
    ) -> Result<SunAwareGrads, SunAwareError> {
        Ok(self.backward_timed(pass, d_image)?.0)
    }

    /// [`SunAwareModel::backward`] with the wall-clock split of its stages (the timing
    /// only reads clocks: the gradients are the same bits).
    pub fn backward_timed(
        &self,
        pass: &FramePass,
        d_image: &[f32],
    ) -> Result<(SunAwareGrads, BackwardTimings), SunAwareError> {
        let mut timings = BackwardTimings::default();
        let t0 = Instant::now();
        let n = self.len();
        let nc = pass.n_channels;
        let pixels = pass.camera.intrinsics.pixel_count();
        if d_image.len() != pixels * 3 {
            return Err(SunAwareError::BadObservation(format!(
                "image gradient has {} values, expected {}",
                d_image.len(),
                pixels * 3
            )));
        }
        let shadowed = nc == 4;
        let linear = self.config.colour_space == ColourSpace::Linear;
        let color = pass.render.color();
        let mut d_color = vec![0.0f32; pixels * nc];
        // Pixels are independent: the split changes no bit.
        d_color
            .par_chunks_mut(COMPOSE_CHUNK_PX * nc)
            .enumerate()
            .for_each(|(chunk, d_chunk)| {
                let first_px = chunk * COMPOSE_CHUNK_PX;
                for (i, d_px) in d_chunk.chunks_exact_mut(nc).enumerate() {
                    let px = first_px + i;
                    let c = &color[px * nc..px * nc + nc];
                    let s = if shadowed { c[3] } else { 1.0 };
                    let mut d_s = 0.0f32;
                    for ch in 0..3 {
                        let mut d = d_image[px * 3 + ch];
                        if linear {
                            // Through the per-pixel encoding of the forward's `c * s`.
                            d *= srgb::encode_slope(c[ch] * s);
                        }
                        d_px[ch] = d * s;
                        d_s += d * c[ch];
                    }
                    if shadowed {
                        d_px[3] = d_s;
                    }
                }
            });
        timings.compose_ms = ms_since(t0);
        let t1 = Instant::now();
        let view = GaussianView::from_model(&self.gaussians, &pass.channels, nc);
        let pixel_grads = PixelGrads {
            d_color: &d_color,
            d_alpha: None,
            d_depth: None,
        };
        let g = match &pass.render {
            PassRender::Cpu(render) => {
                self.scratch
                    .with_raster(self.config.reuse_step_buffers, |ws| {
                        // The records are one per tile entry (tens of MB): keeping them
                        // through the networks' backward would raise the step's peak, so
                        // they go now.
                        let g = render_backward_with(
                            ws,
                            &pass.camera,
                            &view,
                            &pass.settings,
                            render,
                            &pixel_grads,
                        );
                        ws.release_backward_buffers();
                        g
                    })?
            }
            // Training on a device runs device-resident (`SunAwareTrainer::step_many`):
            // a device render is for images only.
            PassRender::Device(_) => {
                return Err(SunAwareError::Config(
                    "backward of a device render: the device trains device-resident \
                     (SunAwareTrainer::step_many), render on the CPU to differentiate"
                        .into(),
                ))
            }
        };
        let p = &self.gaussians.params;
        let mut params = gather_geometry(p, &g);
        let mut g = g;
        if let Some(shade) = &pass.shade {
            // dL/d colour before shading, and the normal's share of the rotation gradient.
            let mut d_colour = vec![0.0f32; n * 3];
            for i in 0..n {
                d_colour[i * 3..i * 3 + 3].copy_from_slice(&g.d_channels[i * nc..i * nc + 3]);
            }
            shade_backward(
                shade,
                p,
                pass.sun_dir,
                self.config.shading_ambient,
                &mut d_colour,
                &mut params,
            );
            for i in 0..n {
                g.d_channels[i * nc..i * nc + 3].copy_from_slice(&d_colour[i * 3..i * 3 + 3]);
            }
        }
        timings.raster = g.timings;
        let r = &timings.raster;
        timings.raster_other_ms = (ms_since(t1) - r.blend_ms - r.reduce_project_ms).max(0.0);
        let t2 = Instant::now();
        let cam_pos = pass.camera.position();
        let rows = pass.network_list.len();
        let mut d_appearance = Vec::new();
        match (&self.appearance, &pass.phi) {
            (None, _) => {
                let mut d_rgb = vec![0.0f32; n * 3];
                for i in 0..n {
                    d_rgb[i * 3..i * 3 + 3].copy_from_slice(&g.d_channels[i * nc..i * nc + 3]);
                }
                sh_to_rgb_backward(p, pass.sh_degree, cam_pos, &d_rgb, &mut params)?;
            }
            (Some(net), Some(phi)) => {
                let mut d_out = vec![0.0f32; rows * 3];
                for (r, &gi) in pass.network_list.iter().enumerate() {
                    let gi = gi as usize;
                    d_out[r * 3..r * 3 + 3].copy_from_slice(&g.d_channels[gi * nc..gi * nc + 3]);
                }
                d_appearance = vec![0.0f32; net.mlp.num_params()];
                let mut d_input = vec![0.0f32; phi.input.len()];
                net.mlp.backward(
                    &phi.input,
                    &phi.forward,
                    &d_out,
                    &mut d_appearance,
                    Some(&mut d_input),
                )?;
                // The rasterizer gives features no gradient: the group is still zeros, so
                // the scatter adds straight into it (as into a fresh zero buffer).
                let mut d_means = vec![0.0f32; n * 3];
                // The view encoding comes from the assembled input (same bits, no sin/cos).
                net.scatter_input_grad_from_input(
                    &pass.network_list,
                    &phi.input,
                    p.get(Param::Mean),
                    cam_pos.to_array(),
                    &d_input,
                    params.get_mut(Param::Feature),
                    &mut d_means,
                )?;
                // The local-frame inputs (when Phi has them): into the learned normal,
                // on top of the shading's term, and into the means.
                scatter_local_input_grad(
                    net,
                    p,
                    &pass.network_list,
                    cam_pos,
                    pass.sun_dir,
                    &d_input,
                    params.get_mut(Param::Normal),
                    &mut d_means,
                );
                for (a, b) in params.get_mut(Param::Mean).iter_mut().zip(&d_means) {
                    *a += b;
                }
            }
            (Some(_), None) => {
                return Err(SunAwareError::BadObservation(
                    "forward pass has no appearance batch for this model".into(),
                ))
            }
        }
        timings.phi_backward_ms = ms_since(t2);
        let t3 = Instant::now();
        let mut d_shadow = Vec::new();
        if let (Some(net), Some(psi)) = (&self.shadow, &pass.psi) {
            let multiply = self.config.shadow_refinement == ShadowRefinement::Multiply;
            let gain = self.config.shadow_gain;
            let d_out: Vec<f32> = pass
                .network_list
                .iter()
                .map(|&gi| {
                    let gi = gi as usize;
                    // d V' / d Psi is gain * V under Multiply; V itself is data (no
                    // gradient).
                    let d = g.d_channels[gi * nc + 3];
                    if multiply {
                        d * gain * pass.visibility[gi]
                    } else {
                        d
                    }
                })
                .collect();
            d_shadow = vec![0.0f32; net.mlp.num_params()];
            let batch = ShadowBatch {
                gaussians: &pass.network_list,
                visibility: &pass.visibility,
                latents: p.get(Param::ShadowLatent),
                means: p.get(Param::Mean),
                sun_dir: pass.sun_dir.to_array(),
                scene_box: &self.scene_box,
            };
            // Means gain Psi's term straight on top of the rasterizer's (the list has no
            // repeats, so the same bits as through a zeroed buffer).
            let mut d_latents = vec![0.0f32; p.get(Param::ShadowLatent).len()];
            net.backward(
                &batch,
                psi,
                &d_out,
                &mut d_shadow,
                &mut d_latents,
                params.get_mut(Param::Mean),
            )?;
            params
                .get_mut(Param::ShadowLatent)
                .copy_from_slice(&d_latents);
        }
        timings.psi_backward_ms = ms_since(t3);
        let grads = SunAwareGrads {
            params,
            appearance: d_appearance,
            shadow: d_shadow,
            mean2d_grad_ndc: g.mean2d_grad_ndc,
            raster_dropped: g.dropped_nonfinite,
        };
        Ok((grads, timings))
    }
}
