//! What the rasterizer takes in and how it fails: [`RasterSettings`], the borrowed
//! per-Gaussian inputs ([`GaussianView`]) and [`RasterError`].
//!
//! Invariants: a [`GaussianView`] that passes `check` has slice lengths consistent with
//! `N` Gaussians and `N < u32::MAX` (ranks and tile entries are `u32`); every bad input
//! is a [`RasterError`], never a panic.

use super::bin::TileSelection;
use super::project::GaussianParams;
#[cfg(doc)]
use super::{bin, blend, project, render_prepared};
use crate::model::{GaussianModel, Param};

/// Largest accepted image side, pixels.
pub const MAX_IMAGE_SIDE_PX: u32 = 1 << 15;

/// Rasterizer settings.
#[derive(Clone, Debug, PartialEq)]
pub struct RasterSettings {
    /// Near plane, camera z, metres. Gaussians with a nearer centre are culled.
    pub near_m: f32,
    /// One value per channel, composited as `C + T_final * bg`; empty means zeros.
    pub background: Vec<f32>,
    /// Test-only: a C1 ramp instead of the 1/255 alpha step, and no early stop at
    /// T < 1e-4, so finite differences can check the analytic gradients.
    pub smooth_cutoff: bool,
    /// Cull a Gaussian before its covariance is projected when a conservative bound from
    /// its centre and largest scale shows that its footprint misses the image
    /// ([`project::footprint_certainly_misses`]). Changes no bit of any output, only time.
    /// Off: every Gaussian in front of the near plane is projected in full and dropped only
    /// when its footprint misses the image. Gaussians whose centre is nearer than `near_m`
    /// are dropped either way: the perspective projection is not defined there.
    pub cull_outside_frustum: bool,
    /// Stop blending a pixel before a Gaussian that would take its transmittance below
    /// 1e-4 ([`blend::TRANSMITTANCE_STOP`]). Off: every pixel blends its whole tile list
    /// (stopping only below 1.2e-38, [`blend::TRANSMITTANCE_FLOOR`], where the backward
    /// could no longer rebuild the transmittance). A stopped pixel has `T * (1 - alpha) <
    /// 1e-4` with alpha <= 0.99, so `T < 0.01`: the image with it on differs from the one
    /// without by at most `T` times the largest `|channel - background|` per pixel.
    /// Ignored in smooth mode (which never stops). The wgpu rasterizer honours it.
    pub early_termination: bool,
    /// Tiles to blend; `None`: every tile. Tiles left out get the background (alpha 0,
    /// depth 0) and no gradient. For a loss whose gradient is zero outside a foreground
    /// mask and its neighbourhood ([`bin::TileSelection::from_mask`] with the loss's reach),
    /// the loss, the image where the loss reads it and every gradient are the same bits
    /// as with `None`. Must be built for this image size (else
    /// [`RasterError::InvalidSettings`]). The wgpu rasterizer honours it.
    pub blend_tiles: Option<TileSelection>,
}

impl Default for RasterSettings {
    fn default() -> Self {
        Self {
            near_m: 0.01,
            background: Vec::new(),
            smooth_cutoff: false,
            cull_outside_frustum: true,
            early_termination: true,
            blend_tiles: None,
        }
    }
}

/// Borrowed per-Gaussian inputs for `N` Gaussians.
#[derive(Clone, Copy, Debug)]
pub struct GaussianView<'a> {
    /// 3N, world frame.
    pub means: &'a [f32],
    /// 3N, natural log of the standard deviations.
    pub log_scales: &'a [f32],
    /// 4N, `[w, x, y, z]`, not necessarily unit.
    pub rotations: &'a [f32],
    /// N.
    pub opacity_logits: &'a [f32],
    /// N * n_channels, Gaussian-major.
    pub channels: &'a [f32],
    pub n_channels: usize,
}

impl<'a> GaussianView<'a> {
    pub fn from_model(model: &'a GaussianModel, channels: &'a [f32], n_channels: usize) -> Self {
        Self {
            means: model.params.get(Param::Mean),
            log_scales: model.params.get(Param::LogScale),
            rotations: model.params.get(Param::Rotation),
            opacity_logits: model.params.get(Param::OpacityLogit),
            channels,
            n_channels,
        }
    }

    /// Number of Gaussians (from the opacity slice).
    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity_logits.is_empty()
    }

    #[inline]
    pub(super) fn params(&self, i: usize) -> GaussianParams {
        let m = &self.means[3 * i..3 * i + 3];
        let s = &self.log_scales[3 * i..3 * i + 3];
        let q = &self.rotations[4 * i..4 * i + 4];
        GaussianParams {
            mean: [m[0], m[1], m[2]],
            log_scale: [s[0], s[1], s[2]],
            rotation: [q[0], q[1], q[2], q[3]],
            opacity_logit: self.opacity_logits[i],
        }
    }

    pub(super) fn check(&self) -> Result<usize, RasterError> {
        let n = self.len();
        let expect = |what, expected: usize, got: usize| {
            if expected == got {
                Ok(())
            } else {
                Err(RasterError::Length {
                    what,
                    expected,
                    got,
                })
            }
        };
        expect("means (3 per Gaussian)", 3 * n, self.means.len())?;
        expect("log_scales (3 per Gaussian)", 3 * n, self.log_scales.len())?;
        expect("rotations (4 per Gaussian)", 4 * n, self.rotations.len())?;
        let nc = n
            .checked_mul(self.n_channels)
            .ok_or(RasterError::TooLarge("channel count overflows"))?;
        expect(
            "channels (n_channels per Gaussian)",
            nc,
            self.channels.len(),
        )?;
        if n >= u32::MAX as usize {
            return Err(RasterError::TooLarge("more than u32::MAX Gaussians"));
        }
        Ok(n)
    }
}

/// Rasterizer error: bad inputs are reported, never panicked on.
#[derive(Clone, Debug, PartialEq)]
pub enum RasterError {
    /// Width or height is zero.
    EmptyImage { width: u32, height: u32 },
    /// A slice has the wrong length.
    Length {
        what: &'static str,
        expected: usize,
        got: usize,
    },
    /// Camera intrinsics or pose unusable (non-finite, non-positive focal length...).
    InvalidCamera(&'static str),
    /// Settings unusable (near plane, background).
    InvalidSettings(&'static str),
    /// Image or list sizes beyond what the rasterizer indexes.
    TooLarge(&'static str),
    /// Pixel gradients contain NaN or Inf.
    NonFiniteGradient(&'static str),
    /// Backward called with inputs that differ from the forward's.
    ForwardMismatch(&'static str),
    /// A channel of a projected Gaussian is NaN or Inf ([`render_prepared`]).
    NonFiniteChannel { gaussian: usize },
}

impl std::fmt::Display for RasterError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RasterError::EmptyImage { width, height } => {
                write!(f, "image of {width}x{height} pixels is empty")
            }
            RasterError::Length {
                what,
                expected,
                got,
            } => write!(f, "{what}: expected {expected} values, got {got}"),
            RasterError::InvalidCamera(why) => write!(f, "invalid camera: {why}"),
            RasterError::InvalidSettings(why) => write!(f, "invalid raster settings: {why}"),
            RasterError::TooLarge(why) => write!(f, "too large: {why}"),
            RasterError::NonFiniteGradient(what) => {
                write!(f, "pixel gradient {what} contains NaN or Inf")
            }
            RasterError::ForwardMismatch(why) => {
                write!(f, "backward inputs do not match the forward pass: {why}")
            }
            RasterError::NonFiniteChannel { gaussian } => {
                write!(f, "channel of Gaussian {gaussian} is NaN or Inf")
            }
        }
    }
}

impl std::error::Error for RasterError {}
