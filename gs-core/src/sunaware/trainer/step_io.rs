//! What goes into a training step ([`Observation`], checked by `validate`) and what
//! comes out of it ([`StepStats`] with its [`StepTimings`]).
//!
//! Invariant: the timing stages are disjoint intervals inside the step (see [`StepTimings`]).

use glam::Vec3;

use crate::camera::Camera;
use crate::loss::ImageShape;
use crate::sunaware::error::SunAwareError;
use crate::sunaware::model::{BackwardTimings, ForwardTimings};

/// One training or evaluation image.
#[derive(Clone, Copy, Debug)]
pub struct Observation<'a> {
    pub camera: Camera,
    /// Unit vector from the target towards the Sun, target body frame.
    pub sun_dir: Vec3,
    /// `H * W * 3` RGB in [0, 1], pixel-major.
    pub image: &'a [f32],
    /// Optional `H * W` foreground weights in [0, 1].
    pub mask: Option<&'a [f32]>,
}

impl Observation<'_> {
    pub fn shape(&self) -> ImageShape {
        let k = &self.camera.intrinsics;
        ImageShape::new(k.width as usize, k.height as usize, 3)
    }

    /// Sizes, finiteness and ranges; the error says what is wrong.
    pub fn validate(&self) -> Result<(), SunAwareError> {
        let bad = |m: String| Err(SunAwareError::BadObservation(m));
        let shape = self.shape();
        if shape.pixels() == 0 {
            return bad("camera image size is zero".into());
        }
        if self.image.len() != shape.values() {
            return bad(format!(
                "image has {} values, the camera needs {} (H * W * 3)",
                self.image.len(),
                shape.values()
            ));
        }
        if let Some(i) = self.image.iter().position(|v| !v.is_finite()) {
            return bad(format!("image value {i} is not finite"));
        }
        if !(self.sun_dir.is_finite() && self.sun_dir.length_squared() > 1e-12) {
            return bad(format!(
                "Sun vector {:?} is not finite and non-zero",
                self.sun_dir
            ));
        }
        if let Some(mask) = self.mask {
            if mask.len() != shape.pixels() {
                return bad(format!(
                    "mask has {} values, the camera needs {} (H * W)",
                    mask.len(),
                    shape.pixels()
                ));
            }
            if let Some(i) = mask.iter().position(|v| !(0.0..=1.0).contains(v)) {
                return bad(format!("mask value {i} is not in [0, 1]"));
            }
            if mask.iter().all(|&v| v == 0.0) {
                return bad("mask is zero everywhere".into());
            }
        }
        Ok(())
    }
}

/// Wall-clock split of one step by stage, milliseconds (`std::time::Instant`, a few tens
/// of nanoseconds per stage; timing only reads clocks, so the arithmetic of a step is the
/// same with or without anyone looking at it).
///
/// Invariant: the stages are disjoint intervals inside the step, so
/// [`StepTimings::stage_sum_ms`] never exceeds `total_ms` (up to the rounding of the
/// conversion to floating-point milliseconds); [`StepTimings::other_ms`] is the rest
/// (validation, bookkeeping, buffer allocation between stages).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepTimings {
    /// Projection of the Gaussians: the culling pass that fixes the networks' batch and
    /// the rasterizer's own projection.
    pub project_ms: f64,
    /// Depth sort and tile binning.
    pub sort_bin_ms: f64,
    /// The alpha-only pass that finds the Gaussians the blend reads, so the networks run
    /// on those alone (`SunAwareConfig::skip_noncontributing_in_mlp`; 0 when off).
    pub contribution_ms: f64,
    /// The light camera's pass that gives `V_i` (configurations c-d).
    pub shadow_pass_ms: f64,
    /// Phi forward with its input assembly (SH evaluation in configuration a).
    pub phi_forward_ms: f64,
    /// Psi forward with its input assembly.
    pub psi_forward_ms: f64,
    /// Tile blending, untiling and the `RGB * S` product.
    pub blend_forward_ms: f64,
    /// L1 + SSIM value and image gradient, plus `L_iso` and its gradient.
    pub loss_ms: f64,
    /// `d(RGB, S)` from `d(RGB * S)` and the tile blending backward.
    pub blend_backward_ms: f64,
    /// Per-Gaussian sum of the blend records, projection backward and gradient gather.
    pub project_backward_ms: f64,
    /// Phi backward with its gradient gather and scatter (SH backward in configuration a).
    pub phi_backward_ms: f64,
    /// Psi backward with its gradient gather and scatter.
    pub psi_backward_ms: f64,
    /// Adam on every group and both networks, densification statistics.
    pub optimizer_ms: f64,
    /// The whole step.
    pub total_ms: f64,
}

impl StepTimings {
    /// Stage names and times in pipeline order (`total_ms` not included).
    pub fn stages(&self) -> [(&'static str, f64); 13] {
        [
            ("project", self.project_ms),
            ("sort_bin", self.sort_bin_ms),
            ("contribution", self.contribution_ms),
            ("shadow_pass", self.shadow_pass_ms),
            ("phi_forward", self.phi_forward_ms),
            ("psi_forward", self.psi_forward_ms),
            ("blend_forward", self.blend_forward_ms),
            ("loss", self.loss_ms),
            ("blend_backward", self.blend_backward_ms),
            ("project_backward", self.project_backward_ms),
            ("phi_backward", self.phi_backward_ms),
            ("psi_backward", self.psi_backward_ms),
            ("optimizer", self.optimizer_ms),
        ]
    }

    /// Sum of the stage times.
    pub fn stage_sum_ms(&self) -> f64 {
        self.stages().iter().map(|(_, t)| t).sum()
    }

    /// Time of the step outside every named stage.
    pub fn other_ms(&self) -> f64 {
        self.total_ms - self.stage_sum_ms()
    }

    /// Both networks' forward.
    pub fn mlp_forward_ms(&self) -> f64 {
        self.phi_forward_ms + self.psi_forward_ms
    }

    /// Both networks' backward.
    pub fn mlp_backward_ms(&self) -> f64 {
        self.phi_backward_ms + self.psi_backward_ms
    }

    pub(super) fn add_forward(&mut self, f: &ForwardTimings) {
        self.project_ms += f.cull_ms + f.raster.project_ms;
        self.sort_bin_ms += f.raster.sort_bin_ms;
        self.contribution_ms += f.contribution_ms;
        self.shadow_pass_ms += f.shadow_pass_ms;
        self.phi_forward_ms += f.phi_forward_ms;
        self.psi_forward_ms += f.psi_forward_ms;
        self.blend_forward_ms += f.raster.blend_ms + f.compose_ms;
    }

    pub(super) fn add_backward(&mut self, b: &BackwardTimings) {
        self.blend_backward_ms += b.compose_ms + b.raster.blend_ms;
        self.project_backward_ms += b.raster.reduce_project_ms + b.raster_other_ms;
        self.phi_backward_ms += b.phi_backward_ms;
        self.psi_backward_ms += b.psi_backward_ms;
    }
}

/// What one step did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepStats {
    /// Steps applied so far (after this one).
    pub step: u64,
    /// Total loss (photometric + weighted L_iso).
    pub loss: f32,
    pub l1: f32,
    pub ssim: f32,
    /// `lambda_iso * L_iso` (0 unless configuration d).
    pub iso: f32,
    /// Gaussians that survived culling.
    pub visible: usize,
    /// Rows each network evaluated: the Gaussians the blend reads
    /// (`skip_noncontributing_in_mlp`), else `visible`.
    pub network_rows: usize,
    pub gaussians: usize,
    pub position_lr: f32,
    /// The step was refused because something was non-finite.
    pub skipped: bool,
    /// Device-resident steps only: 1 when a sort outgrew the capacity sized from recent
    /// steps and the step was redone at the exact count (nothing applied twice).
    pub device_sort_retries: usize,
    pub timings: StepTimings,
}
