//! gs-core's device engine ([`gs_core::engine::Engine`]) on wgpu: the camera pass's blend
//! ([`GpuRasterizer`]), the shadow pass ([`GpuSunVisibility`]) and device-resident Sun-aware
//! training ([`SunAwareResident`]) on one Vulkan device.
//!
//! Invariants: the kernels are compiled once, when the engine opens (a failure is an
//! error then, never later a fallback); [`WgpuEngine::supports`] refuses the
//! configurations the kernels lack (`shading = "lambert"`, the shortest-axis normal;
//! `"lambert_learned"`, Phi's local-frame `appearance_inputs` and both `colour_space`s
//! run on the device) with the setting's name (the rule is `BackendKind::check_model`'s);
//! every device error reaches the caller as a `SunAwareError` (rasterizer input errors
//! keep their type).

use std::sync::Arc;

use glam::Vec3;
use gs_core::camera::Camera;
use gs_core::densify::DensifyStats;
use gs_core::engine::{
    Backend, DeviceRender, Engine, ResidentTraining, SunAwareStepInput, SunAwareStepReport,
};
use gs_core::optim::Adam;
use gs_core::raster::{GaussianView, RasterSettings};
use gs_core::sunaware::trainer::FlatAdam;
use gs_core::sunaware::{BackendKind, SunAwareConfig, SunAwareError, SunAwareModel};

use crate::resident_sunaware::SunAwareResident;
use crate::{GpuContext, GpuError, GpuMlp, GpuOptions, GpuRasterizer, GpuSunVisibility, SunLight};

/// A GPU error as a Sun-aware error (rasterizer input errors keep their type).
pub fn to_sunaware(e: GpuError) -> SunAwareError {
    match e {
        GpuError::Raster(r) => SunAwareError::Raster(r),
        other => SunAwareError::Gpu(other.to_string()),
    }
}

/// A resident step's error: every kind a device failure (the step checked its inputs).
fn resident_error(e: GpuError) -> SunAwareError {
    SunAwareError::Gpu(e.to_string())
}

/// The wgpu engine: one device's rasterizer, shadow pass and network kernels.
pub struct WgpuEngine {
    raster: Arc<GpuRasterizer>,
    shadow: Arc<GpuSunVisibility>,
    networks: Arc<GpuMlp>,
}

impl std::fmt::Debug for WgpuEngine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "WgpuEngine({:?})", self.raster)
    }
}

impl WgpuEngine {
    /// The engine on `raster`'s device: compiles the shadow pass's and the networks'
    /// kernels there.
    pub fn new(raster: Arc<GpuRasterizer>) -> Result<Self, GpuError> {
        let shadow = Arc::new(GpuSunVisibility::new(raster.clone())?);
        let networks = Arc::new(GpuMlp::new(raster.context().clone())?);
        Ok(Self {
            raster,
            shadow,
            networks,
        })
    }

    /// Opens a Vulkan adapter with `options` and compiles every kernel.
    pub fn open(options: GpuOptions) -> Result<Self, GpuError> {
        let ctx = GpuContext::with_options(options)?;
        Self::new(Arc::new(GpuRasterizer::new(ctx)?))
    }

    pub fn rasterizer(&self) -> &Arc<GpuRasterizer> {
        &self.raster
    }

    /// This engine as gs-core's backend.
    pub fn into_backend(self) -> Backend {
        Backend::Device(Arc::new(self))
    }
}

/// Opens the wgpu engine (gs-core's [`gs_core::engine::OpenEngine`], the binaries'
/// `DeviceEngines::wgpu`): `deterministic` gives bit-identical results from run to run
/// (the rasterizer's backward sums per-entry records in tile order instead of with float
/// atomics: [`GpuOptions::deterministic`]).
pub fn open_engine(deterministic: bool) -> Result<Arc<dyn Engine>, String> {
    let options = GpuOptions {
        deterministic,
        ..GpuOptions::default()
    };
    let engine = WgpuEngine::open(options).map_err(|e| e.to_string())?;
    Ok(Arc::new(engine))
}

impl Engine for WgpuEngine {
    fn describe(&self) -> String {
        format!("wgpu ({})", self.raster.context().describe())
    }

    fn supports(&self, config: &SunAwareConfig) -> Result<(), String> {
        // The rule lives beside the backend's name, so configuration files are checked
        // against the same statement before a device is opened.
        BackendKind::Wgpu.check_model(config)
    }

    fn render(
        &self,
        camera: &Camera,
        view: &GaussianView,
        settings: &RasterSettings,
    ) -> Result<DeviceRender, SunAwareError> {
        let out = self
            .raster
            .render(camera, view, settings)
            .map_err(to_sunaware)?;
        Ok(DeviceRender {
            color: out.color,
            alpha: out.alpha,
            visible: out.visible,
            radii_px: out.radii_px,
        })
    }

    fn sun_visibility(
        &self,
        model: &SunAwareModel,
        camera_position_m: Vec3,
        sun_dir: Vec3,
    ) -> Result<Vec<f32>, SunAwareError> {
        self.shadow
            .sun_visibility(
                &model.gaussians,
                &SunLight {
                    sun_dir,
                    camera_centre: camera_position_m,
                    scene_box: &model.scene_box,
                    config: &model.config.light,
                    near_m: model.config.near_m,
                },
            )
            .map_err(to_sunaware)
    }

    fn resident(&self) -> Result<Box<dyn ResidentTraining>, SunAwareError> {
        let resident = SunAwareResident::new(
            self.raster.clone(),
            self.shadow.clone(),
            self.networks.clone(),
        )
        .map_err(to_sunaware)?;
        Ok(Box::new(resident))
    }
}

impl ResidentTraining for SunAwareResident {
    fn upload(
        &mut self,
        model: &SunAwareModel,
        adam: &Adam,
        appearance_adam: &FlatAdam,
        shadow_adam: &FlatAdam,
        stats: &DensifyStats,
    ) -> Result<(), SunAwareError> {
        SunAwareResident::upload(self, model, adam, appearance_adam, shadow_adam, stats)
            .map_err(resident_error)
    }

    fn step(
        &mut self,
        model: &SunAwareModel,
        input: &SunAwareStepInput,
    ) -> Result<SunAwareStepReport, SunAwareError> {
        SunAwareResident::step(self, model, input).map_err(resident_error)
    }

    fn download(
        &self,
        model: &mut SunAwareModel,
        adam: &mut Adam,
        appearance_adam: &mut FlatAdam,
        shadow_adam: &mut FlatAdam,
        stats: &mut DensifyStats,
    ) -> Result<(), SunAwareError> {
        SunAwareResident::download(self, model, adam, appearance_adam, shadow_adam, stats)
            .map_err(resident_error)
    }
}
