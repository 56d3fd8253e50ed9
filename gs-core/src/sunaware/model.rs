//! The Sun-aware model (Gaussians + Phi + Psi + scene box + settings) and the forward and
//! backward pass of one image.
//!
//! Forward for a camera and a Sun vector (target body frame):
//! 1. project every Gaussian into the camera, depth-sort and bin once
//!    ([`crate::raster::prepare_view`]); those that survive culling are the *visible list*.
//!    The networks' batch (*network list*, index order) is the visible list, or in
//!    [`SunAwareModel::forward_for_step`] with `config.skip_noncontributing_in_mlp` only
//!    the Gaussians the blend reads (an alpha-only pass,
//!    [`crate::raster::PreparedView::contributing`]): the others have no effect on the
//!    image, so their channels are left at 0;
//! 2. colour: SH (a) or Phi([f_i, gamma(sun), gamma(view_i)]) (b-d);
//! 3. shadow (c-d): `V` from the light pass ([`super::light`]), `P = Psi([V_i, gamma(sun),
//!    gamma(mu_i normalised), l_i])`, and `V' = V_i * P` (default) or `V' = P` (the paper's
//!    form), per [`super::config::ShadowRefinement`];
//! 4. the blend of the prepared view ([`crate::raster::render_prepared`]) with channels
//!    `[R, G, B]` or `[R, G, B, V']` (background `[bg, 1]`); the image is `RGB * S` with
//!    `S` the fourth channel.
//!
//! Backward takes `dL/d image` and returns gradients for every Gaussian group and for both
//! networks' weights: through `S` into Psi, the latents and (through the rasterizer) the
//! main pass geometry; through `RGB` into Phi, the features and the means (view vector).
//! `V` is data: no gradient flows through it.
//!
//! Every stage is timed ([`ForwardTimings`], [`BackwardTimings`]); timing only reads clocks.
//!
//! Backend ([`SunAwareModel::set_backend`], not part of the model's value nor of its
//! checkpoint): on a [`Backend::Device`] engine ([`super::engine::Engine`]) the camera
//! pass's blend ([`super::engine::Engine::render`]) and the shadow pass
//! ([`super::engine::Engine::sun_visibility`]) run on the device. The visible list then
//! comes from the CPU projection alone ([`crate::raster::project_splats`], no sort or
//! binning), the networks run on the CPU on every visible Gaussian
//! (`skip_noncontributing_in_mlp` needs the CPU's prepared view, so it has no effect
//! there). A device render is for images only: training on a device is device-resident
//! (`SunAwareTrainer::step_many`), and [`SunAwareModel::backward`] of a device render is an
//! error.
//! The CPU backend is the reference and its results are unchanged by this switch.
//!
//! Invariants: the visible list, the channel layout and every network batch are fixed by
//! the inputs, so results are deterministic; nothing non-finite is returned as a gradient
//! (the caller checks before stepping); the speed switches (`skip_noncontributing_in_mlp`,
//! `mlp_recompute_activations`, `reuse_step_buffers`) never change the image, and change
//! gradients at most by float summation order (the skip's smaller network batch).

use std::sync::Arc;
use std::sync::Mutex;
use std::time::Instant;

use glam::Vec3;

use crate::camera::Camera;
use crate::init::SplitMix64;
use crate::model::{GaussianModel, Param, ParamSet};
use crate::nn::shadow_net::{ShadowBatch, ShadowPass};
use crate::nn::{AppearanceNet, MlpForward, PositionalEncoding, SceneBox, ShadowNet, TapeMode};
use crate::raster::blend::AlphaMode;
use crate::raster::{
    camera_frame, prepare_view, project_splats, render_backward_with, render_prepared,
    BackwardTimings as RasterBackwardTimings, ForwardTimings as RasterForwardTimings,
    GaussianGrads, GaussianView, PixelGrads, RasterSettings, RasterWorkspace, RenderOutput,
};
use crate::sh::{sh_to_rgb, sh_to_rgb_backward};

use super::config::{ShadowRefinement, SunAwareConfig};
use super::engine::{Backend, DeviceRender, Engine};
use super::error::SunAwareError;
use super::shading::{initial_normals, shade_backward, shade_forward, ShadePass, Shading};
use super::sun_visibility::sun_visibility;

/// Where the camera pass's rasterizer and the shadow pass run (see the module header).
/// Not part of the model's value: equality ignores it, checkpoints never hold it.
#[derive(Clone, Default)]
struct BackendSlot(Option<Arc<dyn Engine>>);

impl PartialEq for BackendSlot {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for BackendSlot {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.0 {
            Some(engine) => write!(f, "Device({engine:?})"),
            None => f.write_str("Cpu"),
        }
    }
}

/// The camera pass's render, from the backend that made it (its backward runs there too).
/// One per step, moved rarely: the size difference between the variants costs nothing.
#[derive(Clone, Debug)]
#[allow(clippy::large_enum_variant)]
enum PassRender {
    Cpu(RenderOutput),
    Device(DeviceRender),
}

impl PassRender {
    fn color(&self) -> &[f32] {
        match self {
            PassRender::Cpu(r) => &r.color,
            PassRender::Device(out) => &out.color,
        }
    }

    fn alpha(&self) -> &[f32] {
        match self {
            PassRender::Cpu(r) => &r.alpha,
            PassRender::Device(out) => &out.alpha,
        }
    }

    fn visible(&self) -> &[bool] {
        match self {
            PassRender::Cpu(r) => &r.visible,
            PassRender::Device(out) => &out.visible,
        }
    }

    fn radii_px(&self) -> &[f32] {
        match self {
            PassRender::Cpu(r) => &r.radii_px,
            PassRender::Device(out) => &out.radii_px,
        }
    }
}

/// Gaussians, networks, scene box and settings.
#[derive(Clone, Debug, PartialEq)]
pub struct SunAwareModel {
    pub gaussians: GaussianModel,
    /// Phi (configurations b-d).
    pub appearance: Option<AppearanceNet>,
    /// Psi (configurations c-d).
    pub shadow: Option<ShadowNet>,
    pub scene_box: SceneBox,
    pub config: SunAwareConfig,
    scratch: Scratch,
    backend: BackendSlot,
}

/// Buffers a forward and backward reuse from the previous step when
/// `config.reuse_step_buffers` is on: the rasterizer's scratch memory and the networks'
/// inputs and tapes (handed back by [`SunAwareModel::recycle`]).
/// Reuse only spares allocation and page faults: every reused value is overwritten before
/// it is read, so results are the same bits as with fresh buffers. Not part of the model's
/// value: a clone starts empty and equality ignores it. A call that finds the buffers in
/// use by another thread works with fresh ones.
#[derive(Default)]
struct Scratch(Mutex<ScratchBuffers>);

#[derive(Default)]
struct ScratchBuffers {
    raster: RasterWorkspace,
    phi: Option<NetPass>,
    psi: Option<ShadowPass>,
}

impl Clone for Scratch {
    fn clone(&self) -> Self {
        Self::default()
    }
}

impl PartialEq for Scratch {
    fn eq(&self, _: &Self) -> bool {
        true
    }
}

impl std::fmt::Debug for Scratch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Scratch")
    }
}

impl Scratch {
    /// Runs `f` with the kept rasterizer workspace (`reuse`), or a fresh one when not
    /// reusing or when it is busy.
    fn with_raster<T>(&self, reuse: bool, f: impl FnOnce(&mut RasterWorkspace) -> T) -> T {
        match self.0.try_lock() {
            Ok(mut s) if reuse => f(&mut s.raster),
            _ => f(&mut RasterWorkspace::default()),
        }
    }

    /// The kept network buffers (Phi, Psi), leaving none behind (fresh ones unless
    /// `reuse`).
    fn take_nets(&self, reuse: bool) -> (NetPass, ShadowPass) {
        if !reuse {
            return Default::default();
        }
        match self.0.try_lock() {
            Ok(mut s) => (
                s.phi.take().unwrap_or_default(),
                s.psi.take().unwrap_or_default(),
            ),
            Err(_) => Default::default(),
        }
    }
}

/// Gradients of one step: every Gaussian group and both networks' flat weights.
#[derive(Clone, Debug, PartialEq)]
pub struct SunAwareGrads {
    pub params: ParamSet,
    /// Phi's weights (empty without Phi).
    pub appearance: Vec<f32>,
    /// Psi's weights (empty without Psi).
    pub shadow: Vec<f32>,
    /// Per Gaussian `|dL/d mean2d|` in NDC units, for densification.
    pub mean2d_grad_ndc: Vec<f32>,
    /// Gaussians whose rasterizer gradient was non-finite and replaced by zeros.
    pub raster_dropped: usize,
}

impl SunAwareGrads {
    /// First value an optimiser step would refuse (non-finite or oversized: see
    /// [`crate::optim::MAX_GRADIENT_MAGNITUDE`]), named by group.
    pub fn first_non_finite(&self) -> Option<&'static str> {
        if let Some((p, _)) = crate::optim::Adam::first_non_finite(&self.params) {
            return Some(p.name());
        }
        let usable = |v: &[f32]| v.iter().all(|&g| crate::optim::is_usable_gradient(g));
        if !usable(&self.appearance) {
            return Some("appearance MLP");
        }
        if !usable(&self.shadow) {
            return Some("shadow MLP");
        }
        None
    }
}

/// Network batch kept from forward for backward.
#[derive(Clone, Debug, Default)]
struct NetPass {
    input: Vec<f32>,
    forward: MlpForward,
}

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
    /// Light camera, its splats and `V_i` ([`super::sun_visibility::sun_visibility`]).
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

/// Everything one forward produced (images and what backward needs).
#[derive(Clone, Debug)]
pub struct FramePass {
    pub camera: Camera,
    pub sun_dir: Vec3,
    /// Gaussians that survived culling, ascending.
    pub visible_list: Vec<u32>,
    /// The networks' batch, ascending: the Gaussians the blend reads when
    /// `config.skip_noncontributing_in_mlp` in [`SunAwareModel::forward_for_step`] (a subset
    /// of `visible_list`), else `visible_list` itself.
    pub network_list: Vec<u32>,
    /// `H * W * 3`, `RGB * S`.
    pub image: Vec<f32>,
    /// `H * W * 3` colour before the shadow product.
    pub rgb: Vec<f32>,
    /// `H * W` shadow image S (c-d), else empty.
    pub shadow_image: Vec<f32>,
    /// `H * W` accumulated opacity.
    pub alpha: Vec<f32>,
    /// `V_i` per Gaussian (c-d), else empty.
    pub visibility: Vec<f32>,
    /// `V'_i` per Gaussian (c-d; 0 outside `network_list`), else empty.
    pub refined_visibility: Vec<f32>,
    pub sh_degree: u32,
    pub timings: ForwardTimings,
    channels: Vec<f32>,
    n_channels: usize,
    phi: Option<NetPass>,
    psi: Option<ShadowPass>,
    /// The Lambertian factors ([`super::shading`]) when `config.shading` is on.
    shade: Option<ShadePass>,
    render: PassRender,
    settings: RasterSettings,
}

impl FramePass {
    /// Per Gaussian: touched the image.
    pub fn visible(&self) -> &[bool] {
        self.render.visible()
    }

    pub fn radii_px(&self) -> &[f32] {
        self.render.radii_px()
    }

    /// Per Gaussian the Lambertian factor of `config.shading` (`None` when it is off).
    pub fn shading_factors(&self) -> Option<&[f32]> {
        self.shade.as_ref().map(|s| s.factor.as_slice())
    }
}

/// Indices of the set flags, ascending.
fn indices_of(flags: &[bool]) -> Vec<u32> {
    flags
        .iter()
        .enumerate()
        .filter_map(|(i, &f)| f.then_some(i as u32))
        .collect()
}

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

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
    /// A model from initial Gaussians (whose layout must be `config.layout()`), the scene
    /// box that normalises means for Psi (and sizes the light camera), and the settings.
    /// Appearance features start as small seeded normals, shadow latents as ones.
    pub fn new(
        gaussians: GaussianModel,
        scene_box: SceneBox,
        config: SunAwareConfig,
    ) -> Result<Self, SunAwareError> {
        config.validate()?;
        if gaussians.layout() != config.layout() {
            return Err(SunAwareError::Config(format!(
                "initial Gaussians have layout {:?}, configuration {} needs {:?}",
                gaussians.layout(),
                config.variant,
                config.layout()
            )));
        }
        if let Some((p, i)) = crate::optim::Adam::first_non_finite(&gaussians.params) {
            return Err(SunAwareError::Config(format!(
                "initial Gaussians hold a non-finite {} at value {i}",
                p.name()
            )));
        }
        let mut gaussians = gaussians;
        let (lo, hi) = (Vec3::from(scene_box.min_m()), Vec3::from(scene_box.max_m()));
        initial_normals(&mut gaussians.params, (lo + hi) * 0.5);
        let encoding = PositionalEncoding::new(config.encoding_frequencies)?;
        let v = config.variant;
        // A precision this CPU cannot run fails here, at configuration, not mid-training.
        config.mlp_precision.check_supported()?;
        let mut appearance = if v.uses_appearance_mlp() {
            let mut rng = SplitMix64::new(config.seed ^ 0xFEA7_0000);
            for f in gaussians.params.get_mut(Param::Feature) {
                *f = rng.normal() * config.feature_init_std;
            }
            Some(AppearanceNet::with_hidden_width(
                config.feature_dim,
                config.appearance_hidden_width,
                encoding,
                config.seed.wrapping_add(1),
            )?)
        } else {
            None
        };
        let mut shadow = if v.uses_shadow() {
            gaussians.params.get_mut(Param::ShadowLatent).fill(1.0);
            Some(ShadowNet::new(
                config.shadow_latent_dim,
                encoding,
                config.seed.wrapping_add(2),
            )?)
        } else {
            None
        };
        for net in appearance.iter_mut().map(|n| &mut n.mlp) {
            net.set_precision(config.mlp_precision)?;
        }
        for net in shadow.iter_mut().map(|n| &mut n.mlp) {
            net.set_precision(config.mlp_precision)?;
        }
        Ok(Self {
            gaussians,
            appearance,
            shadow,
            scene_box,
            config,
            scratch: Scratch::default(),
            backend: BackendSlot::default(),
        })
    }

    /// Moves the camera pass's rasterizer and the shadow pass to `backend` (the networks,
    /// SH colour and every optimiser stay on the CPU; training on a device is
    /// device-resident, see `SunAwareTrainer::step_many`). An engine that does not run
    /// this model's configuration ([`Engine::supports`]) is an error naming the setting,
    /// and the model stays where it was.
    pub fn set_backend(&mut self, backend: &Backend) -> Result<(), SunAwareError> {
        match backend {
            Backend::Cpu => self.backend = BackendSlot(None),
            Backend::Device(engine) => {
                engine.supports(&self.config).map_err(|why| {
                    SunAwareError::Config(format!("backend {}: {why}", engine.describe()))
                })?;
                self.backend = BackendSlot(Some(engine.clone()));
            }
        }
        Ok(())
    }

    /// The backend in use (`Cpu` unless [`SunAwareModel::set_backend`] moved it).
    pub fn backend(&self) -> Backend {
        match &self.backend.0 {
            Some(engine) => Backend::Device(engine.clone()),
            None => Backend::Cpu,
        }
    }

    /// The device engine, when the model is on one.
    pub(crate) fn engine(&self) -> Option<&Arc<dyn Engine>> {
        self.backend.0.as_ref()
    }

    /// Switches the networks' matrix products (and `config.mlp_precision`) to `precision`;
    /// an error, and no change, when this CPU cannot run it.
    pub fn set_mlp_precision(
        &mut self,
        precision: crate::nn::MatmulPrecision,
    ) -> Result<(), SunAwareError> {
        precision.check_supported()?;
        for net in self.appearance.iter_mut().map(|n| &mut n.mlp) {
            net.set_precision(precision)?;
        }
        for net in self.shadow.iter_mut().map(|n| &mut n.mlp) {
            net.set_precision(precision)?;
        }
        self.config.mlp_precision = precision;
        Ok(())
    }

    pub fn len(&self) -> usize {
        self.gaussians.len()
    }

    pub fn is_empty(&self) -> bool {
        self.gaussians.is_empty()
    }

    /// Rasterizer settings for this model: near plane, background, the frustum-cull and
    /// early-termination switches of the config (test code may switch on the smooth cutoff).
    pub fn raster_settings(&self, smooth_cutoff: bool) -> RasterSettings {
        let mut background = self.config.background.to_vec();
        if self.config.variant.uses_shadow() {
            background.push(1.0);
        }
        RasterSettings {
            near_m: self.config.near_m,
            background,
            smooth_cutoff,
            cull_outside_frustum: self.config.cull_outside_frustum,
            early_termination: self.config.early_termination,
            // Per frame: the step adds the mask's tiles (`trainer::loss_and_grads`).
            blend_tiles: None,
        }
    }

    /// `V_i` of every Gaussian for a camera and a Sun vector.
    pub fn sun_visibility(
        &self,
        camera: &Camera,
        sun_dir: Vec3,
    ) -> Result<Vec<f32>, SunAwareError> {
        if let Some(engine) = self.engine() {
            return engine.sun_visibility(self, camera.position(), sun_dir);
        }
        sun_visibility(
            &self.gaussians,
            sun_dir,
            camera.position(),
            &self.scene_box,
            &self.config.light,
            self.config.near_m,
        )
    }

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
                net.assemble_input(
                    &network_list,
                    p.get(Param::Feature),
                    p.get(Param::Mean),
                    sun,
                    cam_pos.to_array(),
                    &mut input,
                )?;
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

    /// Hands a finished pass's network buffers back, so the next forward reuses them
    /// instead of allocating (the trainer calls this after each step; a no-op unless
    /// `config.reuse_step_buffers`).
    pub fn recycle(&self, pass: FramePass) {
        if !self.config.reuse_step_buffers {
            return;
        }
        if let Ok(mut s) = self.scratch.0.try_lock() {
            s.phi = pass.phi;
            s.psi = pass.psi;
        }
    }

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
        let mut d_color = vec![0.0f32; pixels * nc];
        for px in 0..pixels {
            let c = &pass.render.color()[px * nc..px * nc + nc];
            let s = if shadowed { c[3] } else { 1.0 };
            let mut d_s = 0.0f32;
            for ch in 0..3 {
                let d = d_image[px * 3 + ch];
                d_color[px * nc + ch] = d * s;
                d_s += d * c[ch];
            }
            if shadowed {
                d_color[px * nc + 3] = d_s;
            }
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::init::from_points;
    use crate::sunaware::config::{LightConfig, Variant};
    use crate::sunaware::synthetic::sun_direction;
    use crate::Intrinsics;

    /// A configuration-(d) model of `n` fairly opaque Gaussians filling a box, so the
    /// front ones hide many behind them.
    fn dense_model(n: usize, skip: bool) -> SunAwareModel {
        let config = SunAwareConfig {
            light: LightConfig {
                resolution_px: 48,
                ..LightConfig::default()
            },
            skip_noncontributing_in_mlp: skip,
            ..SunAwareConfig::for_variant(Variant::D)
        };
        let mut rng = SplitMix64::new(21);
        let points: Vec<Vec3> = (0..n)
            .map(|_| {
                Vec3::new(
                    rng.uniform(-0.6, 0.6),
                    rng.uniform(-0.4, 0.4),
                    rng.uniform(-0.4, 0.4),
                )
            })
            .collect();
        let mut init = from_points(&points, None, config.layout()).unwrap().model;
        init.params.get_mut(Param::OpacityLogit).fill(2.5);
        let scene_box = SceneBox::new([-0.6, -0.4, -0.4], [0.6, 0.4, 0.4]).unwrap();
        SunAwareModel::new(init, scene_box, config).unwrap()
    }

    fn camera() -> Camera {
        Camera::look_at(
            Intrinsics::from_fov_x(0.8, 64, 48),
            Vec3::new(1.2, -2.2, 0.9),
            Vec3::ZERO,
            Vec3::Z,
        )
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// `a` and `b` agree to float summation-order noise: every difference within 1e-5 of
    /// the largest magnitude of the group (f32 sums of a few thousand terms reassociated).
    fn assert_close(what: &str, a: &[f32], b: &[f32]) {
        assert_eq!(a.len(), b.len(), "{what}");
        let scale = a.iter().fold(0.0f32, |m, v| m.max(v.abs()));
        assert!(scale > 0.0, "{what} is all zeros: nothing compared");
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                (x - y).abs() <= 1e-5 * scale,
                "{what}[{i}]: {x} vs {y} (scale {scale})"
            );
        }
    }

    fn camera_sized(width: u32, height: u32, eye: Vec3) -> Camera {
        Camera::look_at(
            Intrinsics::from_fov_x(0.8, width, height),
            eye,
            Vec3::ZERO,
            Vec3::Z,
        )
    }

    #[test]
    fn reused_step_buffers_give_the_same_bits_as_fresh_ones() {
        for recompute in [false, true] {
            let mut warm = dense_model(700, true);
            warm.config.mlp_recompute_activations = recompute;
            warm.config.reuse_step_buffers = true;
            let settings = warm.raster_settings(false);
            // Large, small, large again (leftovers of a bigger call sit in the buffers),
            // and different views, so the network batches change size too.
            let views = [
                (80, 60, Vec3::new(1.2, -2.2, 0.9)),
                (24, 20, Vec3::new(-2.0, 0.5, 1.5)),
                (64, 48, Vec3::new(0.3, 2.4, -0.8)),
                (80, 60, Vec3::new(2.5, 0.2, 0.1)),
            ];
            for (i, &(w, h, eye)) in views.iter().enumerate() {
                let cam = camera_sized(w, h, eye);
                let sun = sun_direction(0.3 + i as f32, 0.4);
                // A clone starts with empty buffers: the fresh reference.
                let fresh = warm.clone();
                let a = warm
                    .forward_for_step(&cam, sun, 0, &settings, None)
                    .unwrap();
                let b = fresh
                    .forward_for_step(&cam, sun, 0, &settings, None)
                    .unwrap();
                assert_eq!(bits(&a.image), bits(&b.image), "view {i}");
                assert_eq!(a.network_list, b.network_list);
                let d_image: Vec<f32> = (0..a.image.len())
                    .map(|k| ((k * 31 + i) % 7) as f32 / 7.0 - 0.4)
                    .collect();
                let ga = warm.backward(&a, &d_image).unwrap();
                let gb = fresh.backward(&b, &d_image).unwrap();
                for p in Param::ALL {
                    assert_eq!(
                        bits(ga.params.get(p)),
                        bits(gb.params.get(p)),
                        "{}",
                        p.name()
                    );
                }
                assert_eq!(bits(&ga.appearance), bits(&gb.appearance));
                assert_eq!(bits(&ga.shadow), bits(&gb.shadow));
                warm.recycle(a);
            }
        }
    }

    #[test]
    fn recomputed_network_activations_give_the_same_gradient_bits() {
        let cached = dense_model(500, true);
        let mut recompute = cached.clone();
        recompute.config.mlp_recompute_activations = true;
        let settings = cached.raster_settings(false);
        let sun = sun_direction(1.1, 0.6);
        let a = cached.forward(&camera(), sun, 0, &settings, None).unwrap();
        let b = recompute
            .forward(&camera(), sun, 0, &settings, None)
            .unwrap();
        assert_eq!(bits(&a.image), bits(&b.image));
        // Recompute keeps no hidden activations.
        let tape = |p: &FramePass| {
            p.phi.as_ref().unwrap().forward.tape_len() + p.psi.as_ref().unwrap().tape_len()
        };
        assert!(tape(&a) > 0);
        assert_eq!(tape(&b), 0);
        let d_image: Vec<f32> = (0..a.image.len())
            .map(|i| ((i * 104729) % 11) as f32 / 11.0 - 0.5)
            .collect();
        let ga = cached.backward(&a, &d_image).unwrap();
        let gb = recompute.backward(&b, &d_image).unwrap();
        for p in Param::ALL {
            assert_eq!(
                bits(ga.params.get(p)),
                bits(gb.params.get(p)),
                "{}",
                p.name()
            );
        }
        assert_eq!(bits(&ga.appearance), bits(&gb.appearance));
        assert_eq!(bits(&ga.shadow), bits(&gb.shadow));
        assert!(ga.appearance.iter().any(|&v| v != 0.0));
    }

    #[test]
    fn skipping_non_contributing_gaussians_changes_no_image_and_no_gradient() {
        let full = dense_model(1200, false);
        let skip = dense_model(1200, true);
        assert_eq!(full.gaussians, skip.gaussians);
        let settings = full.raster_settings(false);
        let sun = sun_direction(0.7, 0.5);
        let a = full
            .forward_for_step(&camera(), sun, 0, &settings, None)
            .unwrap();
        let b = skip
            .forward_for_step(&camera(), sun, 0, &settings, None)
            .unwrap();
        // The plain forward never skips: complete per-Gaussian outputs.
        let plain = skip.forward(&camera(), sun, 0, &settings, None).unwrap();
        assert_eq!(plain.network_list, plain.visible_list);
        assert_eq!(bits(&plain.image), bits(&b.image));
        assert_eq!(a.visible_list, b.visible_list);
        assert_eq!(a.network_list, a.visible_list);
        // The skip must actually drop rows here, or this test shows nothing.
        assert!(
            b.network_list.len() + 100 < a.network_list.len(),
            "{} of {} rows kept",
            b.network_list.len(),
            a.network_list.len()
        );
        assert!(b.network_list.len() > 100);
        assert_eq!(bits(&a.image), bits(&b.image));
        assert_eq!(bits(&a.rgb), bits(&b.rgb));
        assert_eq!(bits(&a.shadow_image), bits(&b.shadow_image));
        assert_eq!(bits(&a.alpha), bits(&b.alpha));
        for &g in &b.network_list {
            let g = g as usize;
            assert_eq!(
                a.refined_visibility[g].to_bits(),
                b.refined_visibility[g].to_bits()
            );
        }

        let d_image: Vec<f32> = (0..a.image.len())
            .map(|i| ((i * 7919) % 17) as f32 / 17.0 - 0.45)
            .collect();
        let ga = full.backward(&a, &d_image).unwrap();
        let gb = skip.backward(&b, &d_image).unwrap();
        // Rasterizer-only groups: the same bits.
        for p in [Param::LogScale, Param::Rotation, Param::OpacityLogit] {
            assert_eq!(
                bits(ga.params.get(p)),
                bits(gb.params.get(p)),
                "{}",
                p.name()
            );
        }
        assert_eq!(bits(&ga.mean2d_grad_ndc), bits(&gb.mean2d_grad_ndc));
        // Through the networks: batches of different sizes sum in a different order.
        for p in [Param::Mean, Param::Feature, Param::ShadowLatent] {
            assert_close(p.name(), ga.params.get(p), gb.params.get(p));
        }
        assert_close("Phi weights", &ga.appearance, &gb.appearance);
        assert_close("Psi weights", &ga.shadow, &gb.shadow);
        // Skipped Gaussians get exactly nothing through the networks.
        let kept: std::collections::HashSet<u32> = b.network_list.iter().copied().collect();
        for &g in a.visible_list.iter().filter(|g| !kept.contains(g)) {
            let g = g as usize;
            let f = &gb.params.get(Param::Feature)[72 * g..72 * g + 72];
            assert!(f.iter().all(|&v| v == 0.0));
            assert!(ga.params.get(Param::Feature)[72 * g..72 * g + 72]
                .iter()
                .all(|&v| v == 0.0));
        }
    }
}
