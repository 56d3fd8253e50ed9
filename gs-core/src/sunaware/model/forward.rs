//! Forward of one image through the Sun-aware model: the visible list, Phi (or SH),
//! the optional Lambertian factor, the Sun visibility and Psi, then the blend and the
//! `RGB * S` product, sRGB-encoded per pixel under `ColourSpace::Linear` (see the parent
//! module's header for the stages).
//!
//! Invariants: the visible list, the channel layout and the networks' batch are fixed
//! by the inputs (deterministic); a non-finite or zero Sun vector is an error before any
//! work; the kept buffers are overwritten before they are read, so reuse changes no bit.

use std::time::Instant;

use glam::Vec3;
use rayon::prelude::*;

use crate::camera::Camera;
use crate::model::Param;
use crate::nn::shadow_net::ShadowBatch;
use crate::nn::TapeMode;
use crate::raster::blend::AlphaMode;
use crate::raster::{
    camera_frame, prepare_view, project_splats, render_prepared,
    ForwardTimings as RasterForwardTimings, GaussianView, RasterSettings,
};
use crate::sh::sh_to_rgb;
use crate::srgb::{self, ColourSpace};

use crate::sunaware::config::ShadowRefinement;
use crate::sunaware::error::SunAwareError;
use crate::sunaware::shading::{assemble_phi_input, shade_forward, Shading};

use super::{indices_of, ms_since, FramePass, NetPass, PassRender, SunAwareModel};

/// Wall-clock split of one forward, milliseconds. The intervals are disjoint and lie
/// inside the forward call (so their sum never exceeds its duration).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ForwardTimings {
    /// Building the visible list from the projection (the projection itself is in
    /// `raster`).
    pub cull_ms: f64,
    /// The alpha-only pass that finds the Gaussians the blend reads (0 when
    /// `skip_noncontributing_in_mlp` is off).
    pub contribution_ms: f64,
    /// Light camera, its splats and `V_i` ([`crate::sunaware::sun_visibility::sun_visibility`]).
    pub shadow_pass_ms: f64,
    /// Phi's input assembly, forward and the scatter of its RGB into the channels (or the
    /// SH evaluation in configuration a).
    pub phi_forward_ms: f64,
    /// Psi's input assembly, forward and scatter.
    pub psi_forward_ms: f64,
    /// The rasterizer's own split (projection, depth sort + binning, blend).
    pub raster: RasterForwardTimings,
    /// Rest of the blend call (checks, visibility flags) and the `RGB * S` product.
    pub compose_ms: f64,
}

/// Values per parallel task of the per-pixel sRGB encoding (elementwise: the split changes
/// no bit).
pub(super) const ENCODE_CHUNK: usize = 1 << 14;

impl SunAwareModel {
    /// Forward of one image with the networks run on every visible Gaussian, so the
    /// per-Gaussian outputs (`refined_visibility`) are complete. `visibility` overrides the
    /// shadow pass (tests hold `V` fixed while they perturb the geometry, since no gradient
    /// flows through it).
    pub fn forward(
        &self,
        camera: &Camera,
        sun_dir: Vec3,
        sh_degree: u32,
        settings: &RasterSettings,
        visibility: Option<&[f32]>,
    ) -> Result<FramePass, SunAwareError> {
        self.forward_with(camera, sun_dir, sh_degree, settings, visibility, false)
    }

    /// [`SunAwareModel::forward`] as training steps and renders run it: with
    /// `config.skip_noncontributing_in_mlp` the networks run only on the Gaussians the
    /// blend reads (the image and the rasterizer's gradients are the same bits; the
    /// networks' gradients differ by summation order; `refined_visibility` is 0 outside
    /// `network_list`).
    pub fn forward_for_step(
        &self,
        camera: &Camera,
        sun_dir: Vec3,
        sh_degree: u32,
        settings: &RasterSettings,
        visibility: Option<&[f32]>,
    ) -> Result<FramePass, SunAwareError> {
        let skip = self.config.skip_noncontributing_in_mlp;
        self.forward_with(camera, sun_dir, sh_degree, settings, visibility, skip)
    }

    fn forward_with(
        &self,
        camera: &Camera,
        sun_dir: Vec3,
        sh_degree: u32,
        settings: &RasterSettings,
        visibility: Option<&[f32]>,
        skip_noncontributing: bool,
    ) -> Result<FramePass, SunAwareError> {
        if !(sun_dir.is_finite() && sun_dir.length_squared() > 1e-12) {
            return Err(SunAwareError::BadObservation(format!(
                "Sun vector {sun_dir:?} is not a finite non-zero vector"
            )));
        }
        let sun_dir = sun_dir.normalize();
        let n = self.len();
        let p = &self.gaussians.params;
        let cam_pos = camera.position();
        let mut timings = ForwardTimings::default();

        let t0 = Instant::now();
        let k = &camera.intrinsics;
        let bare = GaussianView::from_model(&self.gaussians, &[], 0);
        let (prepared, visible_list, network_list) = if self.engine().is_some() {
            // The GPU projects, sorts and bins again in its render; here only the visible
            // list for the networks' batch.
            let frame = camera_frame(camera, settings.near_m)?;
            let mode = AlphaMode {
                smooth: settings.smooth_cutoff,
            };
            let projected = project_splats(&frame, &bare, mode, k.width, k.height);
            timings.raster.project_ms = ms_since(t0);
            let survived: Vec<bool> = projected.splats.iter().map(Option::is_some).collect();
            let visible_list = indices_of(&survived);
            (None, visible_list.clone(), visible_list)
        } else {
            let prepared = prepare_view(camera, &bare, settings)?;
            timings.raster = prepared.timings;
            let survived = prepared.survived();
            let visible_list = indices_of(&survived);
            timings.cull_ms =
                (ms_since(t0) - prepared.timings.project_ms - prepared.timings.sort_bin_ms)
                    .max(0.0);
            let t_contrib = Instant::now();
            let network_list = if skip_noncontributing && self.appearance.is_some() {
                indices_of(&prepared.contributing())
            } else {
                visible_list.clone()
            };
            timings.contribution_ms = ms_since(t_contrib);
            (Some(prepared), visible_list, network_list)
        };

        let shadowed = self.config.variant.uses_shadow();
        let nc = if shadowed { 4 } else { 3 };
        let mut channels = vec![0.0f32; n * nc];

        // Visibility first: it is part of the shadow pass, timed apart from the networks.
        let t1 = Instant::now();
        let vis = if shadowed {
            match visibility {
                Some(v) if v.len() == n => v.to_vec(),
                Some(v) => {
                    return Err(SunAwareError::BadObservation(format!(
                        "visibility override has {} values for {n} Gaussians",
                        v.len()
                    )))
                }
                None => self.sun_visibility(camera, sun_dir)?,
            }
        } else {
            Vec::new()
        };
        timings.shadow_pass_ms = t1.elapsed().as_secs_f64() * 1e3;

        let t2 = Instant::now();
        let sun = sun_dir.to_array();
        let tape = if self.config.mlp_recompute_activations {
            TapeMode::Recompute
        } else {
            TapeMode::Cache
        };
        let (mut phi_buffers, mut psi_buffers) =
            self.scratch.take_nets(self.config.reuse_step_buffers);
        let phi = match &self.appearance {
            None => {
                let rgb = sh_to_rgb(p, sh_degree, cam_pos)?;
                for i in 0..n {
                    channels[i * nc..i * nc + 3].copy_from_slice(&rgb[i * 3..i * 3 + 3]);
                }
                None
            }
            Some(net) => {
                let NetPass {
                    mut input,
                    mut forward,
                } = std::mem::take(&mut phi_buffers);
                assemble_phi_input(net, p, &network_list, cam_pos, sun_dir, &mut input)?;
                net.mlp
                    .forward_train_into(&input, network_list.len(), tape, &mut forward)?;
                for (r, &g) in network_list.iter().enumerate() {
                    let g = g as usize;
                    channels[g * nc..g * nc + 3].copy_from_slice(&forward.output[r * 3..r * 3 + 3]);
                }
                Some(NetPass { input, forward })
            }
        };
        let shade = match self.config.shading {
            Shading::None => None,
            Shading::Lambert | Shading::LambertLearned => {
                let mut colour = vec![0.0f32; n * 3];
                for i in 0..n {
                    colour[i * 3..i * 3 + 3].copy_from_slice(&channels[i * nc..i * nc + 3]);
                }
                let pass = shade_forward(
                    self.config.shading,
                    p,
                    &network_list,
                    cam_pos,
                    sun_dir,
                    self.config.shading_ambient,
                    &mut colour,
                );
                for i in 0..n {
                    channels[i * nc..i * nc + 3].copy_from_slice(&colour[i * 3..i * 3 + 3]);
                }
                Some(pass)
            }
        };
        timings.phi_forward_ms = ms_since(t2);
        let t_psi = Instant::now();
        let mut refined = Vec::new();
        let psi = match &self.shadow {
            Some(net) if shadowed => {
                let mut forward = std::mem::take(&mut psi_buffers);
                let batch = ShadowBatch {
                    gaussians: &network_list,
                    visibility: &vis,
                    latents: p.get(Param::ShadowLatent),
                    means: p.get(Param::Mean),
                    sun_dir: sun,
                    scene_box: &self.scene_box,
                };
                // Psi recomputes its hidden activations in backward whatever the setting:
                // writing its fresh 96-float-per-row tape costs more than the small
                // GEMMs that rebuild it (nn::shadow, docs/bench/step.md).
                net.forward_train_into(&batch, TapeMode::Recompute, &mut forward)?;
                refined = vec![0.0f32; n];
                let multiply = self.config.shadow_refinement == ShadowRefinement::Multiply;
                let gain = self.config.shadow_gain;
                for (r, &g) in network_list.iter().enumerate() {
                    let g = g as usize;
                    let v = if multiply {
                        gain * vis[g] * forward.output[r]
                    } else {
                        forward.output[r]
                    };
                    channels[g * nc + 3] = v;
                    refined[g] = v;
                }
                Some(forward)
            }
            _ => None,
        };
        timings.psi_forward_ms = ms_since(t_psi);

        let t3 = Instant::now();
        let render_out = match prepared {
            Some(prepared) => {
                let out = self
                    .scratch
                    .with_raster(self.config.reuse_step_buffers, |ws| {
                        render_prepared(ws, prepared, &channels, nc)
                    })?;
                timings.raster.blend_ms = out.timings.blend_ms;
                PassRender::Cpu(out)
            }
            None => {
                let out = self.render_on_device(camera, &channels, nc, settings)?;
                timings.raster.blend_ms = ms_since(t3);
                out
            }
        };
        let render_color = render_out.color();
        let pixels = k.pixel_count();
        let mut rgb = vec![0.0f32; pixels * 3];
        let mut shadow_image = Vec::new();
        let mut image = vec![0.0f32; pixels * 3];
        if shadowed {
            shadow_image = vec![0.0f32; pixels];
        }
        for px in 0..pixels {
            let c = &render_color[px * nc..px * nc + nc];
            let s = if shadowed { c[3] } else { 1.0 };
            for ch in 0..3 {
                rgb[px * 3 + ch] = c[ch];
                image[px * 3 + ch] = c[ch] * s;
            }
            if shadowed {
                shadow_image[px] = s;
            }
        }
        if self.config.colour_space == ColourSpace::Linear {
            // The camera encodes each pixel's summed light once (crate::srgb).
            image
                .par_chunks_mut(ENCODE_CHUNK)
                .for_each(|chunk| chunk.iter_mut().for_each(|v| *v = srgb::encode(*v)));
        }
        timings.compose_ms = (ms_since(t3) - timings.raster.blend_ms).max(0.0);
        Ok(FramePass {
            camera: *camera,
            sun_dir,
            visible_list,
            network_list,
            image,
            rgb,
            shadow_image,
            alpha: render_out.alpha().to_vec(),
            visibility: vis,
            refined_visibility: refined,
            sh_degree,
            timings,
            channels,
            n_channels: nc,
            phi,
            psi,
            shade,
            render: render_out,
            settings: settings.clone(),
        })
    }

    /// The camera pass's blend on the device (projection, sort and binning included).
    fn render_on_device(
        &self,
        camera: &Camera,
        channels: &[f32],
        nc: usize,
        settings: &RasterSettings,
    ) -> Result<PassRender, SunAwareError> {
        let Some(engine) = self.engine() else {
            return Err(SunAwareError::Config("no device backend set".into()));
        };
        let view = GaussianView::from_model(&self.gaussians, channels, nc);
        Ok(PassRender::Device(engine.render(camera, &view, settings)?))
    }
}
