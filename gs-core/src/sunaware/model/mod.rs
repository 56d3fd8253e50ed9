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
//! 2. colour: SH (a) or Phi([f_i, gamma(sun), gamma(view_i)]) (b-d), with
//!    `[n.s, n.v, n.h]` appended under `config.appearance_inputs` = local
//!    ([`super::shading::local_inputs`]);
//! 3. shadow (c-d): `V` from the light pass ([`super::sun_visibility`]), `P = Psi([V_i, gamma(sun),
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
//!
//! Files: this one holds the model's state (constructor, backend, accessors, the kept
//! step buffers and the pass it hands between forward and backward); `forward.rs` the
//! forward of one image, `backward.rs` its backward.

mod backward;
mod forward;
#[cfg(test)]
mod tests;

use std::sync::Arc;
use std::sync::Mutex;
use std::time::Instant;

use glam::Vec3;

use crate::camera::Camera;
use crate::init::SplitMix64;
use crate::model::{GaussianModel, Param, ParamSet};
use crate::nn::shadow_net::ShadowPass;
use crate::nn::{AppearanceNet, MlpForward, PositionalEncoding, SceneBox, ShadowNet};
use crate::raster::{RasterSettings, RasterWorkspace, RenderOutput};

use super::config::SunAwareConfig;
use super::engine::{Backend, DeviceRender, Engine};
use super::error::SunAwareError;
use super::shading::{initial_normals, ShadePass};
use super::sun_visibility::sun_visibility;

pub use backward::BackwardTimings;
pub use forward::ForwardTimings;

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
            Some(AppearanceNet::with_inputs(
                config.feature_dim,
                config.appearance_hidden_width,
                encoding,
                config.appearance_inputs,
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
}
