//! Tile rasterizer for Gaussians: projection, binning, blending, and the backward pass.
//!
//! Two ways in: [`render`] / [`render_with`] do everything in one call; or
//! [`prepare_view`] projects, sorts and bins the geometry alone, [`PreparedView::contributing`]
//! tells which Gaussians the blend will read (an alpha-only walk of the tiles), and
//! [`render_prepared`] blends channels computed afterwards (e.g. by a network, for those
//! Gaussians only) without projecting again. Both give the same bits. The alpha-only walk
//! also compacts the tile lists to the entries that change some pixel of their tile
//! (blended there, or ending a pixel's blend); after it the blend and the backward walk
//! only those (about a fifth of the entries on a dense 100K-Gaussian scene), same bits.
//!
//! Stages (each a reusable function, so a shadow pass from a light camera is an
//! addition): [`project_splats`] (per Gaussian, rayon), depth sort + [`bin::bin_tiles`]
//! (serial radix/counting sorts), [`blend::blend_tile_forward`] (rayon over 16x16 tiles).
//! Backward: [`blend::blend_tile_backward`] per tile writes one gradient record per
//! tile-list entry; records are summed per Gaussian in tile order and pushed through
//! [`project::project_backward`] (rayon over blocks of Gaussians, each Gaussian's sum in
//! one task, so the thread count changes no bit). The forward's tile-major buffers go to
//! the image layout by bands of tile rows (rayon), one tile row per copy.
//!
//! Invariants:
//! - outputs are pixel-major, row-major: `color[(y * W + x) * C + c]`;
//! - `depth` is the alpha-weighted camera z, NOT normalised by alpha (divide by `alpha`
//!   for the mean depth of what was hit); background depth is 0;
//! - culled or invalid Gaussians (non-finite values, `|q|^2 < 1e-6`, z < near, opacity
//!   below the cutoff, no pixel touched) have no effect on the output and get zero
//!   gradients; nothing non-finite reaches the outputs or the gradients (a Gaussian whose
//!   gradient is non-finite gets zeros, counted in `GaussianGrads::dropped_nonfinite`);
//! - results do not depend on the thread count at all: every reduction runs in a fixed
//!   order (tile order per Gaussian), and tiles never share memory.

pub mod bin;
pub mod blend;
pub mod project;

use std::sync::OnceLock;
use std::time::Instant;

use rayon::prelude::*;

use crate::camera::Camera;
use crate::model::{GaussianModel, Param};
use bin::{PixelRect, TileBins, TileGrid, TileSelection, TILE_PIXELS, TILE_PX};
use blend::{AlphaMode, Splat, REC_CHANNELS, REC_CONIC, REC_DEPTH, REC_OPACITY};
use project::{CameraFrame, GaussianParams, ProjectedGrad, JACOBIAN_CLAMP_FACTOR};

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
    fn params(&self, i: usize) -> GaussianParams {
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

    fn check(&self) -> Result<usize, RasterError> {
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

/// Wall-clock split of one forward pass, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ForwardTimings {
    pub project_ms: f64,
    pub sort_bin_ms: f64,
    pub blend_ms: f64,
}

/// Wall-clock split of one backward pass, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BackwardTimings {
    pub blend_ms: f64,
    pub reduce_project_ms: f64,
}

/// What backward needs from the forward pass.
#[derive(Clone, Debug)]
struct ForwardState {
    camera: Camera,
    settings: RasterSettings,
    background: Vec<f32>,
    n_gaussians: usize,
    grid: TileGrid,
    splats: Vec<Splat>,
    splat_channels: Vec<f32>,
    gaussian_of_rank: Vec<u32>,
    /// The tile lists the forward blended: the compacted ones when the view's
    /// [`PreparedView::contributing`] ran, else the full bins. One gradient record per entry.
    bins: TileBins,
    /// Entries of the full bins (before any compaction).
    n_tile_entries: usize,
    /// Tile-major final transmittance and last-blended index per pixel.
    tile_transmittance: Vec<f32>,
    tile_last: Vec<u32>,
}

/// Rendered images and per-Gaussian screen data.
#[derive(Clone, Debug)]
pub struct RenderOutput {
    pub width: u32,
    pub height: u32,
    pub n_channels: usize,
    /// `H * W * n_channels`, `(y * W + x) * C + c`.
    pub color: Vec<f32>,
    /// `H * W` accumulated opacity `1 - T_final`.
    pub alpha: Vec<f32>,
    /// `H * W` alpha-weighted camera z (not normalised by alpha).
    pub depth: Vec<f32>,
    /// Per Gaussian: screen radius in pixels beyond which its alpha is below the cutoff
    /// (`sqrt(2 ln(o / cutoff) * lambda_max)`, at most about 3.3 sigma); 0 when culled.
    pub radii_px: Vec<f32>,
    /// Per Gaussian: survived culling and touched at least one tile.
    pub visible: Vec<bool>,
    pub timings: ForwardTimings,
    state: ForwardState,
}

impl RenderOutput {
    /// Number of (tile, Gaussian) pairs binned: the rasterizer's work measure (before any
    /// compaction by [`PreparedView::contributing`]).
    pub fn tile_entry_count(&self) -> usize {
        self.state.n_tile_entries
    }

    /// Number of (tile, Gaussian) pairs the blend and its backward walked: the compacted
    /// lists' entries when the view's [`PreparedView::contributing`] ran, else
    /// [`RenderOutput::tile_entry_count`].
    pub fn blended_entry_count(&self) -> usize {
        self.state.bins.tile_ranks.len()
    }
}

/// Loss gradients with respect to the rendered images (same layouts as [`RenderOutput`]).
#[derive(Clone, Copy, Debug)]
pub struct PixelGrads<'a> {
    pub d_color: &'a [f32],
    pub d_alpha: Option<&'a [f32]>,
    pub d_depth: Option<&'a [f32]>,
}

/// Gradients of the loss with respect to the Gaussians (same layouts as [`GaussianView`]).
#[derive(Clone, Debug, Default)]
pub struct GaussianGrads {
    pub d_means: Vec<f32>,
    pub d_log_scales: Vec<f32>,
    pub d_rotations: Vec<f32>,
    pub d_opacity_logits: Vec<f32>,
    pub d_channels: Vec<f32>,
    /// Per Gaussian `|dL/d(mean2d)|` in NDC units (pixel gradient times W/2, H/2).
    pub mean2d_grad_ndc: Vec<f32>,
    /// Gaussians whose gradient came out non-finite and was replaced by zeros.
    pub dropped_nonfinite: usize,
    pub timings: BackwardTimings,
}

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Validates the camera and builds the projection frame.
pub fn camera_frame(camera: &Camera, near_m: f32) -> Result<CameraFrame, RasterError> {
    let k = &camera.intrinsics;
    if k.width == 0 || k.height == 0 {
        return Err(RasterError::EmptyImage {
            width: k.width,
            height: k.height,
        });
    }
    if k.width > MAX_IMAGE_SIDE_PX || k.height > MAX_IMAGE_SIDE_PX {
        return Err(RasterError::TooLarge("image side above 32768 pixels"));
    }
    if !(k.fx.is_finite() && k.fy.is_finite() && k.fx > 0.0 && k.fy > 0.0) {
        return Err(RasterError::InvalidCamera(
            "focal lengths must be finite and positive",
        ));
    }
    if !(k.cx.is_finite() && k.cy.is_finite()) {
        return Err(RasterError::InvalidCamera("principal point is not finite"));
    }
    let q = camera.rotation;
    if !(q.is_finite() && camera.translation.is_finite()) {
        return Err(RasterError::InvalidCamera("pose is not finite"));
    }
    if q.length_squared() <= 1e-6 {
        return Err(RasterError::InvalidCamera("rotation quaternion is zero"));
    }
    if !(near_m.is_finite() && near_m > 0.0) {
        return Err(RasterError::InvalidSettings(
            "near plane must be finite and positive",
        ));
    }
    let m = glam::Mat3::from_quat(q.normalize());
    let mut rot = [[0.0f32; 3]; 3];
    for (r, row) in rot.iter_mut().enumerate() {
        for (c, v) in row.iter_mut().enumerate() {
            *v = m.col(c)[r];
        }
    }
    let half_w = k.cx.max(k.width as f32 - k.cx).max(0.5 * k.width as f32);
    let half_h = k.cy.max(k.height as f32 - k.cy).max(0.5 * k.height as f32);
    Ok(CameraFrame {
        rot_cam_from_world: rot,
        translation: camera.translation.to_array(),
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
        lim_x: JACOBIAN_CLAMP_FACTOR * half_w / k.fx,
        lim_y: JACOBIAN_CLAMP_FACTOR * half_h / k.fy,
        near_m,
    })
}

/// Splats of the Gaussians that survived projection, with their original index.
#[derive(Clone, Debug, Default)]
pub struct ProjectedSet {
    /// Per Gaussian: `Some(splat)` when it survived culling and touches the image.
    pub splats: Vec<Option<Splat>>,
    pub radii_px: Vec<f32>,
}

/// Pixel rectangle outside which `o exp(power) < cutoff` for certain (also the light
/// pass's bound, `sunaware::light`).
pub(crate) fn splat_rect(
    mean_px: [f32; 2],
    cov2: [f32; 3],
    q_max: f32,
    width: u32,
    height: u32,
) -> PixelRect {
    // Extent of the ellipse d^T K d <= q_max along x is sqrt(q_max * Sigma_xx); the margin
    // covers rounding in the conic and in exp.
    let ext_x = (q_max * cov2[0]).sqrt() * 1.001 + 0.01;
    let ext_y = (q_max * cov2[2]).sqrt() * 1.001 + 0.01;
    let to_px = |v: f32, hi: u32| v.clamp(0.0, hi as f32) as u32;
    // Pixel x is inside when |mean - (x + 0.5)| <= ext.
    PixelRect {
        x0: to_px((mean_px[0] - ext_x - 0.5).floor(), width),
        y0: to_px((mean_px[1] - ext_y - 0.5).floor(), height),
        x1: to_px((mean_px[0] + ext_x - 0.5).floor() + 1.0, width),
        y1: to_px((mean_px[1] + ext_y - 0.5).floor() + 1.0, height),
    }
}

/// Projects every Gaussian (rayon); culled ones and those touching no pixel are `None`.
/// Same as [`project_splats_with`] with the early frustum cull on.
pub fn project_splats(
    frame: &CameraFrame,
    gaussians: &GaussianView,
    mode: AlphaMode,
    width: u32,
    height: u32,
) -> ProjectedSet {
    project_splats_with(frame, gaussians, mode, width, height, true)
}

/// [`project_splats`] with the early frustum cull switchable
/// ([`RasterSettings::cull_outside_frustum`]): the result is the same either way.
pub fn project_splats_with(
    frame: &CameraFrame,
    gaussians: &GaussianView,
    mode: AlphaMode,
    width: u32,
    height: u32,
    cull_outside_frustum: bool,
) -> ProjectedSet {
    let nc = gaussians.n_channels;
    let cutoff = mode.cutoff();
    let results: Vec<(Option<Splat>, f32)> = (0..gaussians.len())
        .into_par_iter()
        .with_min_len(1024)
        .map(|i| {
            if !gaussians.channels[i * nc..i * nc + nc]
                .iter()
                .all(|v| v.is_finite())
            {
                return (None, 0.0);
            }
            let params = gaussians.params(i);
            if cull_outside_frustum
                && project::footprint_certainly_misses(frame, &params, cutoff, width, height)
            {
                return (None, 0.0);
            }
            let Ok(p) = project::project_forward(frame, &params, cutoff) else {
                return (None, 0.0);
            };
            let q_max = 2.0 * (p.opacity / cutoff).ln();
            let [xx, xy, yy] = p.cov2;
            let mid = 0.5 * (xx + yy);
            let lambda_max = mid + (mid * mid - (xx * yy - xy * xy)).max(0.0).sqrt();
            let radius = (q_max * lambda_max).sqrt();
            let rect = splat_rect(p.mean_px, p.cov2, q_max, width, height);
            if rect.is_empty() || !radius.is_finite() {
                return (None, 0.0);
            }
            let splat = Splat {
                mean_px: p.mean_px,
                conic: p.conic,
                opacity: p.opacity,
                depth: p.t_cam[2],
                rect,
            };
            (Some(splat), radius)
        })
        .collect();
    let (splats, radii_px) = results.into_iter().unzip();
    ProjectedSet { splats, radii_px }
}

/// Depth-sorts the visible splats: returns the Gaussian index of each rank.
pub fn depth_order(splats: &[Option<Splat>]) -> Vec<u32> {
    let mut keys = Vec::new();
    let mut values = Vec::new();
    for (i, s) in splats.iter().enumerate() {
        if let Some(s) = s {
            // Depths are >= near > 0, so the bit pattern orders like the value.
            keys.push(s.depth.to_bits());
            values.push(i as u32);
        }
    }
    bin::radix_sort_u32(&mut keys, &mut values);
    values
}

fn resolve_background(settings: &RasterSettings, nc: usize) -> Result<Vec<f32>, RasterError> {
    if settings.background.is_empty() {
        return Ok(vec![0.0; nc]);
    }
    if settings.background.len() != nc {
        return Err(RasterError::Length {
            what: "background (one value per channel)",
            expected: nc,
            got: settings.background.len(),
        });
    }
    if !settings.background.iter().all(|v| v.is_finite()) {
        return Err(RasterError::InvalidSettings("background is not finite"));
    }
    Ok(settings.background.clone())
}

/// Scratch memory that [`render_with`] and [`render_backward_with`] reuse from call to
/// call (tile-major forward buffers, backward gradient records). Every reused
/// value is overwritten before it is read, so results are bit-identical to [`render`] and
/// [`render_backward`]; reuse only saves the allocation and the page faults of fresh
/// memory (about 20 MB per call at 960x600). Buffers only grow.
#[derive(Clone, Debug, Default)]
pub struct RasterWorkspace {
    tile_color: Vec<f32>,
    tile_depth: Vec<f32>,
    records: Vec<f32>,
}

impl RasterWorkspace {
    /// Frees the backward's gradient records (the largest buffer: one record per tile
    /// entry), keeping the forward's tile buffers. For callers that hold the
    /// workspace across other memory-hungry work and care more about peak memory than
    /// about the backward's page faults.
    pub fn release_backward_buffers(&mut self) {
        self.records = Vec::new();
    }
}

/// The first `len` values of `buf`, growing it (with zeros) when shorter. Values already
/// there are left as they are: callers overwrite or clear what they read.
fn scratch(buf: &mut Vec<f32>, len: usize) -> &mut [f32] {
    if buf.len() < len {
        buf.resize(len, 0.0);
    }
    &mut buf[..len]
}

/// Renders `gaussians` from `camera`.
pub fn render(
    camera: &Camera,
    gaussians: &GaussianView,
    settings: &RasterSettings,
) -> Result<RenderOutput, RasterError> {
    render_with(&mut RasterWorkspace::default(), camera, gaussians, settings)
}

/// [`render`] with scratch memory kept in `workspace` between calls.
pub fn render_with(
    workspace: &mut RasterWorkspace,
    camera: &Camera,
    gaussians: &GaussianView,
    settings: &RasterSettings,
) -> Result<RenderOutput, RasterError> {
    // Projection with the channels in view culls Gaussians whose channels are not finite,
    // so the blend below never meets one.
    let prepared = prepare(camera, gaussians, settings)?;
    render_prepared(
        workspace,
        prepared,
        gaussians.channels,
        gaussians.n_channels,
    )
}

/// The geometry of one view, before any channel is read: projection, depth order and tile
/// bins. [`PreparedView::contributing`] finds the Gaussians the blend will read, so a
/// caller can compute channels (e.g. network outputs) for those alone and hand them to
/// [`render_prepared`], which blends without projecting again.
#[derive(Clone, Debug)]
pub struct PreparedView {
    camera: Camera,
    settings: RasterSettings,
    mode: AlphaMode,
    n_gaussians: usize,
    grid: TileGrid,
    /// Splats in depth order (rank), and the Gaussian of each rank.
    splats: Vec<Splat>,
    gaussian_of_rank: Vec<u32>,
    bins: TileBins,
    /// Per Gaussian, from the projection (0 when culled).
    radii_px: Vec<f32>,
    /// Filled by the first [`PreparedView::contributing`]; the blend then walks these lists.
    compact: OnceLock<CompactLists>,
    /// Projection and sort/bin times (`blend_ms` is 0 here).
    pub timings: ForwardTimings,
}

/// The tile lists without the entries that change no pixel of their tile, found by the
/// alpha-only pass ([`blend::tile_contributions`]): an entry is kept when it is blended into
/// a pixel of its tile or ends a pixel's blend there. Every pixel meets the same kept
/// entries in the same order, with the same transmittance before each, so the forward
/// blend over these lists is the same operations as over the full ones, and the backward
/// (which walks a list back to front, changing a pixel only at entries blended into it)
/// writes records that differ only by the records of the dropped entries, which are all
/// zero: the per-Gaussian sums, which start at +0.0, are the same bits without them.
#[derive(Clone, Debug)]
struct CompactLists {
    bins: TileBins,
    /// Per rank: blended into at least one pixel (the flag [`blend::ENTRY_BLENDS`]).
    blended_rank: Vec<bool>,
}

/// Projection, depth sort and binning of `gaussians` (channels in the view, if any, are
/// only checked for finiteness: a Gaussian with a non-finite channel is culled).
fn prepare(
    camera: &Camera,
    gaussians: &GaussianView,
    settings: &RasterSettings,
) -> Result<PreparedView, RasterError> {
    let frame = camera_frame(camera, settings.near_m)?;
    let n = gaussians.check()?;
    let mode = AlphaMode {
        smooth: settings.smooth_cutoff,
    };
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    let grid = TileGrid::new(width, height);
    if let Some(selection) = &settings.blend_tiles {
        if selection.image_size() != (width, height) {
            return Err(RasterError::InvalidSettings(
                "blend_tiles was built for another image size",
            ));
        }
    }

    let t0 = Instant::now();
    let projected = project_splats_with(
        &frame,
        gaussians,
        mode,
        width,
        height,
        settings.cull_outside_frustum,
    );
    let project_ms = ms_since(t0);

    let t1 = Instant::now();
    let gaussian_of_rank = depth_order(&projected.splats);
    let splats: Vec<Splat> = gaussian_of_rank
        .iter()
        .filter_map(|&g| projected.splats[g as usize])
        .collect();
    let rects: Vec<PixelRect> = splats.iter().map(|s| s.rect).collect();
    let total_entries: usize = rects.iter().map(|r| grid.tile_count(r)).sum();
    if total_entries >= u32::MAX as usize {
        return Err(RasterError::TooLarge("more than u32::MAX tile entries"));
    }
    let bins = bin::bin_tiles(&grid, &rects);
    let sort_bin_ms = ms_since(t1);
    Ok(PreparedView {
        camera: *camera,
        settings: settings.clone(),
        mode,
        n_gaussians: n,
        grid,
        splats,
        gaussian_of_rank,
        bins,
        radii_px: projected.radii_px,
        compact: OnceLock::new(),
        timings: ForwardTimings {
            project_ms,
            sort_bin_ms,
            blend_ms: 0.0,
        },
    })
}

/// Projects, depth-sorts and bins the Gaussians of `geometry` for `camera` (its channels
/// are ignored: they come later, to [`render_prepared`]).
pub fn prepare_view(
    camera: &Camera,
    geometry: &GaussianView,
    settings: &RasterSettings,
) -> Result<PreparedView, RasterError> {
    let bare = GaussianView {
        channels: &[],
        n_channels: 0,
        ..*geometry
    };
    prepare(camera, &bare, settings)
}

impl PreparedView {
    pub fn n_gaussians(&self) -> usize {
        self.n_gaussians
    }

    /// Per Gaussian: survived culling and touches the image (the Gaussians a render
    /// projects; [`RenderOutput::visible`] is the same set).
    pub fn survived(&self) -> Vec<bool> {
        let mut out = vec![false; self.n_gaussians];
        for &g in &self.gaussian_of_rank {
            out[g as usize] = true;
        }
        out
    }

    /// Number of (tile, Gaussian) pairs the blend walks.
    pub fn tile_entry_count(&self) -> usize {
        self.bins.tile_ranks.len()
    }

    /// Per Gaussian: blended into at least one pixel, i.e. its alpha passes the cutoff
    /// there before the pixel's transmittance stops (an alpha-only pass over the tiles,
    /// rayon). The blend and its backward read the channels of these Gaussians only:
    /// channels of the others may hold anything finite without changing a single bit of
    /// the image or of any gradient.
    ///
    /// The first call also keeps the compacted tile lists (only the entries that change
    /// some pixel of their tile, see `CompactLists`): [`render_prepared`] then blends those
    /// and the backward walks them, with the same bits as the full lists.
    pub fn contributing(&self) -> Vec<bool> {
        let compact = self.compact.get_or_init(|| self.compact_lists());
        let mut out = vec![false; self.n_gaussians];
        for (&g, &blended) in self.gaussian_of_rank.iter().zip(&compact.blended_rank) {
            out[g as usize] = blended;
        }
        out
    }

    /// The alpha-only pass over every tile (rayon) and the lists without the entries that
    /// change no pixel (serial, in tile order, so each rank's entries stay in tile order
    /// as in [`bin::bin_tiles`]).
    fn compact_lists(&self) -> CompactLists {
        let grid = &self.grid;
        let bins = &self.bins;
        let n_tiles = grid.n_tiles();
        let mut entry_flags = vec![0u8; bins.tile_ranks.len()];
        let mut per_tile: Vec<&mut [u8]> = Vec::with_capacity(n_tiles);
        let mut rest: &mut [u8] = &mut entry_flags;
        for t in 0..n_tiles {
            let (head, tail) = rest.split_at_mut(bins.tile_offsets[t + 1] - bins.tile_offsets[t]);
            per_tile.push(head);
            rest = tail;
        }
        per_tile.into_par_iter().enumerate().for_each(|(t, flags)| {
            let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
            blend::tile_contributions(
                &grid.tile_rect(t),
                list,
                &self.splats,
                self.mode,
                self.settings.early_termination,
                flags,
            );
        });
        let n_ranks = self.splats.len();
        let mut blended_rank = vec![false; n_ranks];
        let mut rank_counts = vec![0usize; n_ranks];
        let mut tile_offsets = Vec::with_capacity(n_tiles + 1);
        let mut tile_ranks = Vec::new();
        tile_offsets.push(0);
        for t in 0..n_tiles {
            let entries = bins.tile_offsets[t]..bins.tile_offsets[t + 1];
            for (&flag, &rank) in entry_flags[entries.clone()]
                .iter()
                .zip(&bins.tile_ranks[entries])
            {
                if flag != 0 {
                    tile_ranks.push(rank);
                    rank_counts[rank as usize] += 1;
                    blended_rank[rank as usize] |= flag & blend::ENTRY_BLENDS != 0;
                }
            }
            tile_offsets.push(tile_ranks.len());
        }
        let mut rank_offsets = Vec::with_capacity(n_ranks + 1);
        let mut sum = 0usize;
        rank_offsets.push(0);
        for &c in &rank_counts {
            sum += c;
            rank_offsets.push(sum);
        }
        let mut cursor = rank_offsets[..n_ranks].to_vec();
        let mut entry_of_rank = vec![0u32; tile_ranks.len()];
        for (entry, &rank) in tile_ranks.iter().enumerate() {
            entry_of_rank[cursor[rank as usize]] = entry as u32;
            cursor[rank as usize] += 1;
        }
        CompactLists {
            bins: TileBins {
                tile_offsets,
                tile_ranks,
                rank_offsets,
                entry_of_rank,
            },
            blended_rank,
        }
    }
}

/// Blends a prepared view with `n_channels` channels per Gaussian (`channels`,
/// Gaussian-major, for every Gaussian of the view). Same output, bit for bit, as
/// [`render_with`] on a view with these channels, provided every channel the blend reads
/// is finite; a non-finite channel of a projected Gaussian is an error here (a full
/// render would have culled that Gaussian).
pub fn render_prepared(
    workspace: &mut RasterWorkspace,
    prepared: PreparedView,
    channels: &[f32],
    n_channels: usize,
) -> Result<RenderOutput, RasterError> {
    let PreparedView {
        camera,
        settings,
        mode,
        n_gaussians: n,
        grid,
        splats,
        gaussian_of_rank,
        bins,
        radii_px,
        compact,
        timings,
    } = prepared;
    let nc = n_channels;
    let expected = n
        .checked_mul(nc)
        .ok_or(RasterError::TooLarge("channel count overflows"))?;
    if channels.len() != expected {
        return Err(RasterError::Length {
            what: "channels (n_channels per Gaussian)",
            expected,
            got: channels.len(),
        });
    }
    let background = resolve_background(&settings, nc)?;
    let (width, height) = (grid.width, grid.height);
    let mut splat_channels = Vec::with_capacity(gaussian_of_rank.len() * nc);
    for &g in &gaussian_of_rank {
        let g = g as usize;
        let ch = &channels[g * nc..g * nc + nc];
        if !ch.iter().all(|v| v.is_finite()) {
            return Err(RasterError::NonFiniteChannel { gaussian: g });
        }
        splat_channels.extend_from_slice(ch);
    }
    let ForwardTimings {
        project_ms,
        sort_bin_ms,
        ..
    } = timings;

    // Visibility from the full bins (touched a tile), before they give way to the
    // compacted lists.
    let mut visible = vec![false; n];
    for w in bins.rank_offsets.windows(2).zip(&gaussian_of_rank) {
        let ((start, end), &g) = ((w.0[0], w.0[1]), w.1);
        visible[g as usize] = end > start;
    }
    let n_tile_entries = bins.tile_ranks.len();
    let bins = match compact.into_inner() {
        Some(compact) => compact.bins,
        None => bins,
    };

    let t2 = Instant::now();
    let n_tiles = grid.n_tiles();
    // Tile-major buffers; a colour chunk of at least one float per pixel keeps the chunk
    // size non-zero when there are no channels.
    let color_chunk = TILE_PIXELS * nc.max(1);
    // Every tile's blend clears its own part of these first.
    let tile_color = scratch(&mut workspace.tile_color, n_tiles * color_chunk);
    let tile_depth = scratch(&mut workspace.tile_depth, n_tiles * TILE_PIXELS);
    let mut tile_transmittance = vec![0.0f32; n_tiles * TILE_PIXELS];
    let mut tile_last = vec![0u32; n_tiles * TILE_PIXELS];
    let blend_tiles = settings.blend_tiles.as_ref();
    tile_color
        .par_chunks_mut(color_chunk)
        .zip(tile_depth.par_chunks_mut(TILE_PIXELS))
        .zip(tile_transmittance.par_chunks_mut(TILE_PIXELS))
        .zip(tile_last.par_chunks_mut(TILE_PIXELS))
        .enumerate()
        .for_each(|(t, (((color, depth), trans), last))| {
            if blend_tiles.is_some_and(|sel| !sel.is_active(t)) {
                // A tile left out: nothing blended, the background behind T = 1.
                for px in color[..TILE_PIXELS * nc].chunks_exact_mut(nc.max(1)) {
                    px[..nc].copy_from_slice(&background);
                }
                depth.fill(0.0);
                trans.fill(1.0);
                last.fill(0);
                return;
            }
            let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
            blend::blend_tile_forward(
                &grid.tile_rect(t),
                list,
                &splats,
                &splat_channels,
                nc,
                &background,
                mode,
                settings.early_termination,
                blend::TileForwardOut {
                    color: &mut color[..TILE_PIXELS * nc],
                    depth,
                    transmittance: trans,
                    last,
                },
            );
        });

    let w = width as usize;
    let h = height as usize;
    let mut color = vec![0.0f32; w * h * nc];
    let mut alpha = vec![0.0f32; w * h];
    let mut depth = vec![0.0f32; w * h];
    untile(
        &grid,
        nc,
        TileMajor {
            color: tile_color,
            color_chunk,
            depth: tile_depth,
            transmittance: &tile_transmittance,
        },
        &mut color,
        &mut alpha,
        &mut depth,
    );
    let blend_ms = ms_since(t2);

    let mut radii_px = radii_px;
    for (r, v) in radii_px.iter_mut().zip(&visible) {
        if !v {
            *r = 0.0;
        }
    }

    Ok(RenderOutput {
        width,
        height,
        n_channels: nc,
        color,
        alpha,
        depth,
        radii_px,
        visible,
        timings: ForwardTimings {
            project_ms,
            sort_bin_ms,
            blend_ms,
        },
        state: ForwardState {
            camera,
            settings,
            background,
            n_gaussians: n,
            grid,
            splats,
            splat_channels,
            gaussian_of_rank,
            bins,
            n_tile_entries,
            tile_transmittance,
            tile_last,
        },
    })
}

/// Hints the cache to fetch the line holding `value` (never faults; no effect elsewhere).
#[inline(always)]
fn prefetch<T>(value: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: SSE is part of the x86_64 baseline, and a prefetch is only a hint: it
        // never faults and the pointer comes from a live reference.
        unsafe { _mm_prefetch::<_MM_HINT_T0>((value as *const T).cast::<i8>()) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = value;
}

/// Tile-major forward buffers (`TILE_PIXELS` pixels per tile, row-major in the tile).
struct TileMajor<'a> {
    color: &'a [f32],
    /// Values per tile in `color` (at least `TILE_PIXELS * nc`).
    color_chunk: usize,
    depth: &'a [f32],
    transmittance: &'a [f32],
}

/// Copies the tile-major buffers into the image layout (`alpha = 1 - T`), one band of
/// tile rows per rayon task, one tile row (up to 16 pixels) per copy. Only copies: the
/// bits do not depend on the split.
fn untile(
    grid: &TileGrid,
    nc: usize,
    tiles: TileMajor,
    color: &mut [f32],
    alpha: &mut [f32],
    depth: &mut [f32],
) {
    let w = grid.width as usize;
    let tile_px = TILE_PX as usize;
    let tiles_x = grid.tiles_x as usize;
    let band = tile_px * w;
    // Empty colour bands when there are no channels (a chunk size of zero is not allowed).
    let color_bands: Vec<&mut [f32]> = if nc > 0 {
        color.chunks_mut(band * nc).collect()
    } else {
        (0..grid.tiles_y).map(|_| <&mut [f32]>::default()).collect()
    };
    let bands: Vec<_> = color_bands
        .into_iter()
        .zip(alpha.chunks_mut(band).zip(depth.chunks_mut(band)))
        .collect();
    bands
        .into_par_iter()
        .enumerate()
        .for_each(|(ty, (color_band, (alpha_band, depth_band)))| {
            let rows = alpha_band.len() / w;
            for tx in 0..tiles_x {
                let t = ty * tiles_x + tx;
                let x0 = tx * tile_px;
                let cols = tile_px.min(w - x0);
                for ly in 0..rows {
                    let src = t * TILE_PIXELS + ly * tile_px;
                    let dst = ly * w + x0;
                    for (a, &tr) in alpha_band[dst..dst + cols]
                        .iter_mut()
                        .zip(&tiles.transmittance[src..src + cols])
                    {
                        *a = 1.0 - tr;
                    }
                    depth_band[dst..dst + cols].copy_from_slice(&tiles.depth[src..src + cols]);
                    if nc > 0 {
                        let c_src = t * tiles.color_chunk + ly * tile_px * nc;
                        color_band[dst * nc..(dst + cols) * nc]
                            .copy_from_slice(&tiles.color[c_src..c_src + cols * nc]);
                    }
                }
            }
        });
}

/// The backward blend of every tile (rayon): one gradient record of
/// `REC_CHANNELS + n_channels` values per entry of `st.bins` into `records` (every value
/// written).
fn write_records(
    st: &ForwardState,
    mode: AlphaMode,
    nc: usize,
    pixel_view: &blend::PixelGradsView,
    records: &mut [f32],
) {
    let grid = st.grid;
    let bins = &st.bins;
    let stride = REC_CHANNELS + nc;
    let mut per_tile: Vec<&mut [f32]> = Vec::with_capacity(grid.n_tiles());
    let mut rest: &mut [f32] = &mut *records;
    for t in 0..grid.n_tiles() {
        let len = (bins.tile_offsets[t + 1] - bins.tile_offsets[t]) * stride;
        let (head, tail) = rest.split_at_mut(len);
        per_tile.push(head);
        rest = tail;
    }
    let blend_tiles = st.settings.blend_tiles.as_ref();
    per_tile
        .into_par_iter()
        .enumerate()
        .for_each(|(t, tile_records)| {
            if blend_tiles.is_some_and(|sel| !sel.is_active(t)) {
                // Not blended in the forward: no gradient reaches its entries.
                tile_records.fill(0.0);
                return;
            }
            let list = &bins.tile_ranks[bins.tile_offsets[t]..bins.tile_offsets[t + 1]];
            let px = t * TILE_PIXELS..(t + 1) * TILE_PIXELS;
            blend::blend_tile_backward(
                &grid.tile_rect(t),
                list,
                &st.splats,
                &st.splat_channels,
                nc,
                &st.background,
                mode,
                blend::TileForwardState {
                    transmittance: &st.tile_transmittance[px.clone()],
                    last: &st.tile_last[px],
                },
                pixel_view,
                tile_records,
            );
        });
}

/// Gaussians per block of the backward reduction (one rayon task each).
const REDUCE_BLOCK: usize = 256;

/// How far ahead (in Gaussians) the reduction fetches what it will read: a rank's
/// offsets and splat first, then its list of entries, then the entries' records, each
/// step reading only what the previous one fetched.
const PREFETCH_RANK_AHEAD: usize = 12;
const PREFETCH_ENTRIES_AHEAD: usize = 8;
const PREFETCH_RECORDS_AHEAD: usize = 4;

/// Marks a Gaussian without a rank (culled) in [`rank_of_gaussian`].
const NO_RANK: u32 = u32::MAX;

/// Inverse of `gaussian_of_rank` over `n` Gaussians; [`NO_RANK`] for the culled ones.
fn rank_of_gaussian(gaussian_of_rank: &[u32], n: usize) -> Vec<u32> {
    let mut out = vec![NO_RANK; n];
    for (rank, &g) in gaussian_of_rank.iter().enumerate() {
        out[g as usize] = rank as u32;
    }
    out
}

/// What the per-Gaussian reduction of the backward reads.
struct ReduceInputs<'a> {
    frame: &'a CameraFrame,
    mode: AlphaMode,
    /// Half the image width and height, pixels (pixel to NDC gradient scale).
    half_px: [f32; 2],
    gaussians: &'a GaussianView<'a>,
    state: &'a ForwardState,
    rank_of_gaussian: &'a [u32],
    /// One record of `stride` values per entry of `state.bins`.
    records: &'a [f32],
    stride: usize,
}

/// The output rows of Gaussians `first..first + d_opacity_logits.len()`.
struct GradBlock<'a> {
    first: usize,
    d_means: &'a mut [f32],
    d_log_scales: &'a mut [f32],
    d_rotations: &'a mut [f32],
    d_opacity_logits: &'a mut [f32],
    d_channels: &'a mut [f32],
    mean2d_grad_ndc: &'a mut [f32],
}

/// `out` cut into blocks of [`REDUCE_BLOCK`] Gaussians (any channel count, zero too).
fn gaussian_blocks(out: &mut GaussianGrads, nc: usize) -> Vec<GradBlock<'_>> {
    let n = out.d_opacity_logits.len();
    let mut blocks = Vec::with_capacity(n.div_ceil(REDUCE_BLOCK));
    let mut means = &mut out.d_means[..];
    let mut log_scales = &mut out.d_log_scales[..];
    let mut rotations = &mut out.d_rotations[..];
    let mut opacity = &mut out.d_opacity_logits[..];
    let mut channels = &mut out.d_channels[..];
    let mut ndc = &mut out.mean2d_grad_ndc[..];
    let mut first = 0;
    while first < n {
        let len = REDUCE_BLOCK.min(n - first);
        let (m, m_rest) = std::mem::take(&mut means).split_at_mut(3 * len);
        let (s, s_rest) = std::mem::take(&mut log_scales).split_at_mut(3 * len);
        let (r, r_rest) = std::mem::take(&mut rotations).split_at_mut(4 * len);
        let (o, o_rest) = std::mem::take(&mut opacity).split_at_mut(len);
        let (c, c_rest) = std::mem::take(&mut channels).split_at_mut(nc * len);
        let (d, d_rest) = std::mem::take(&mut ndc).split_at_mut(len);
        blocks.push(GradBlock {
            first,
            d_means: m,
            d_log_scales: s,
            d_rotations: r,
            d_opacity_logits: o,
            d_channels: c,
            mean2d_grad_ndc: d,
        });
        (means, log_scales, rotations, opacity, channels, ndc) =
            (m_rest, s_rest, r_rest, o_rest, c_rest, d_rest);
        first += len;
    }
    blocks
}

/// Sums the records of each Gaussian of `block` (in tile order, from +0.0: the order of
/// `entry_of_rank`, whatever the thread count) and pushes them through the projection
/// backward into the block's rows. Rows of culled Gaussians stay zero, as do those of a
/// Gaussian whose gradient is not finite (counted). Returns (dropped, mismatch): mismatch
/// when a Gaussian's parameters or channels no longer give the forward's splat.
fn reduce_block(inputs: &ReduceInputs, block: GradBlock) -> (usize, bool) {
    let ReduceInputs {
        frame,
        mode,
        half_px: [half_w, half_h],
        gaussians,
        state: st,
        rank_of_gaussian,
        records,
        stride,
    } = *inputs;
    let nc = gaussians.n_channels;
    let bins = &st.bins;
    let n = rank_of_gaussian.len();
    let rank_ahead = |g: usize, ahead: usize| {
        rank_of_gaussian
            .get(g + ahead)
            .copied()
            .filter(|&r| r != NO_RANK)
            .map(|r| r as usize)
    };
    let mut dropped = 0;
    for i in 0..block.d_opacity_logits.len() {
        let g = block.first + i;
        // Ranks lie scattered in Gaussian order: fetch what a Gaussian a few steps ahead
        // will read while this one is summed.
        if let Some(r) = rank_ahead(g, PREFETCH_RANK_AHEAD) {
            prefetch(&bins.rank_offsets[r]);
            prefetch(&st.splats[r]);
            if nc > 0 {
                prefetch(&st.splat_channels[r * nc]);
            }
        }
        if let Some(r) = rank_ahead(g, PREFETCH_ENTRIES_AHEAD) {
            if let Some(e) = bins.entry_of_rank.get(bins.rank_offsets[r]) {
                prefetch(e);
            }
        }
        if let Some(r) = rank_ahead(g, PREFETCH_RECORDS_AHEAD) {
            for &e in &bins.entry_of_rank[bins.rank_offsets[r]..bins.rank_offsets[r + 1]] {
                prefetch(&records[e as usize * stride]);
            }
        }
        debug_assert!(g < n);
        let rank = rank_of_gaussian[g];
        if rank == NO_RANK {
            continue;
        }
        let rank = rank as usize;
        // The geometry part of the sum here, the channel part in the output row (which
        // starts at +0.0 like the sum).
        let mut sum = [0.0f32; REC_CHANNELS];
        let d_ch = &mut block.d_channels[i * nc..(i + 1) * nc];
        for &e in &bins.entry_of_rank[bins.rank_offsets[rank]..bins.rank_offsets[rank + 1]] {
            let rec = &records[e as usize * stride..(e as usize + 1) * stride];
            let (rec_geo, rec_ch) = rec.split_at(REC_CHANNELS);
            for (s, r) in sum.iter_mut().zip(rec_geo) {
                *s += r;
            }
            for (s, r) in d_ch.iter_mut().zip(rec_ch) {
                *s += r;
            }
        }
        let splat = &st.splats[rank];
        let Ok(p) = project::project_forward(frame, &gaussians.params(g), mode.cutoff()) else {
            return (dropped, true);
        };
        if p.mean_px != splat.mean_px
            || p.conic != splat.conic
            || p.opacity != splat.opacity
            || p.t_cam[2] != splat.depth
            || gaussians.channels[g * nc..g * nc + nc]
                != st.splat_channels[rank * nc..rank * nc + nc]
        {
            return (dropped, true);
        }
        let d = ProjectedGrad {
            d_mean_px: [sum[0], sum[1]],
            d_conic: [sum[REC_CONIC], sum[REC_CONIC + 1], sum[REC_CONIC + 2]],
            d_opacity: sum[REC_OPACITY],
            d_depth: sum[REC_DEPTH],
        };
        let pg = project::project_backward(frame, &p, &d);
        let ndc = (sum[0] * half_w).hypot(sum[1] * half_h);
        if !(pg.is_finite() && d_ch.iter().all(|v| v.is_finite()) && ndc.is_finite()) {
            d_ch.fill(0.0);
            dropped += 1;
            continue;
        }
        block.d_means[3 * i..3 * i + 3].copy_from_slice(&pg.d_mean);
        block.d_log_scales[3 * i..3 * i + 3].copy_from_slice(&pg.d_log_scale);
        block.d_rotations[4 * i..4 * i + 4].copy_from_slice(&pg.d_rotation);
        block.d_opacity_logits[i] = pg.d_opacity_logit;
        block.mean2d_grad_ndc[i] = ndc;
    }
    (dropped, false)
}

fn check_grad_slice(what: &'static str, slice: &[f32], expected: usize) -> Result<(), RasterError> {
    if slice.len() != expected {
        return Err(RasterError::Length {
            what,
            expected,
            got: slice.len(),
        });
    }
    if !slice.iter().all(|v| v.is_finite()) {
        return Err(RasterError::NonFiniteGradient(what));
    }
    Ok(())
}

/// Gradients of a loss with respect to the Gaussians, given its pixel gradients.
/// `camera`, `gaussians` and `settings` must be those `forward` was rendered with.
pub fn render_backward(
    camera: &Camera,
    gaussians: &GaussianView,
    settings: &RasterSettings,
    forward: &RenderOutput,
    grads: &PixelGrads,
) -> Result<GaussianGrads, RasterError> {
    render_backward_with(
        &mut RasterWorkspace::default(),
        camera,
        gaussians,
        settings,
        forward,
        grads,
    )
}

/// [`render_backward`] with scratch memory kept in `workspace` between calls.
pub fn render_backward_with(
    workspace: &mut RasterWorkspace,
    camera: &Camera,
    gaussians: &GaussianView,
    settings: &RasterSettings,
    forward: &RenderOutput,
    grads: &PixelGrads,
) -> Result<GaussianGrads, RasterError> {
    let st = &forward.state;
    let frame = camera_frame(camera, settings.near_m)?;
    let n = gaussians.check()?;
    let nc = gaussians.n_channels;
    if *camera != st.camera {
        return Err(RasterError::ForwardMismatch("camera differs"));
    }
    if *settings != st.settings {
        return Err(RasterError::ForwardMismatch("settings differ"));
    }
    if n != st.n_gaussians || nc != forward.n_channels {
        return Err(RasterError::ForwardMismatch(
            "number of Gaussians or channels differs",
        ));
    }
    let pixels = forward.width as usize * forward.height as usize;
    check_grad_slice("d_color", grads.d_color, pixels * nc)?;
    if let Some(d) = grads.d_alpha {
        check_grad_slice("d_alpha", d, pixels)?;
    }
    if let Some(d) = grads.d_depth {
        check_grad_slice("d_depth", d, pixels)?;
    }
    let mode = AlphaMode {
        smooth: settings.smooth_cutoff,
    };
    let bins = &st.bins;
    let stride = REC_CHANNELS + nc;

    let t0 = Instant::now();
    let n_entries = bins.tile_ranks.len();
    // Each tile writes every value of its records (see `blend_tile_backward`).
    let records = scratch(&mut workspace.records, n_entries * stride);
    let pixel_view = blend::PixelGradsView {
        width: forward.width as usize,
        d_color: grads.d_color,
        d_alpha: grads.d_alpha,
        d_depth: grads.d_depth,
    };
    write_records(st, mode, nc, &pixel_view, records);
    let blend_ms = ms_since(t0);

    let t1 = Instant::now();
    let mut out = GaussianGrads {
        d_means: vec![0.0; 3 * n],
        d_log_scales: vec![0.0; 3 * n],
        d_rotations: vec![0.0; 4 * n],
        d_opacity_logits: vec![0.0; n],
        d_channels: vec![0.0; nc * n],
        mean2d_grad_ndc: vec![0.0; n],
        dropped_nonfinite: 0,
        timings: BackwardTimings::default(),
    };
    let reduce = ReduceInputs {
        frame: &frame,
        mode,
        half_px: [0.5 * forward.width as f32, 0.5 * forward.height as f32],
        gaussians,
        state: st,
        rank_of_gaussian: &rank_of_gaussian(&st.gaussian_of_rank, n),
        records,
        stride,
    };
    let (dropped, mismatch) = gaussian_blocks(&mut out, nc)
        .into_par_iter()
        .map(|block| reduce_block(&reduce, block))
        .reduce(|| (0, false), |a, b| (a.0 + b.0, a.1 || b.1));
    if mismatch {
        return Err(RasterError::ForwardMismatch(
            "Gaussian parameters changed since the forward pass",
        ));
    }
    out.dropped_nonfinite = dropped;
    out.timings = BackwardTimings {
        blend_ms,
        reduce_project_ms: ms_since(t1),
    };
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;
    use crate::Intrinsics;
    use glam::Vec3;

    /// Geometry of `n` random Gaussians, dense enough that many are hidden.
    struct Scene {
        means: Vec<f32>,
        log_scales: Vec<f32>,
        rotations: Vec<f32>,
        opacity_logits: Vec<f32>,
    }

    impl Scene {
        fn random(seed: u64, n: usize) -> Self {
            let mut rng = SplitMix64::new(seed);
            let mut u = |lo, hi, count: usize| (0..count).map(|_| rng.uniform(lo, hi)).collect();
            Self {
                means: u(-1.0, 1.0, 3 * n),
                log_scales: u(-3.0, -1.6, 3 * n),
                rotations: u(-1.0, 1.0, 4 * n),
                opacity_logits: u(-1.0, 5.0, n),
            }
        }

        fn view<'a>(&'a self, channels: &'a [f32], n_channels: usize) -> GaussianView<'a> {
            GaussianView {
                means: &self.means,
                log_scales: &self.log_scales,
                rotations: &self.rotations,
                opacity_logits: &self.opacity_logits,
                channels,
                n_channels,
            }
        }
    }

    fn camera() -> Camera {
        Camera::look_at(
            Intrinsics::from_fov_x(0.9, 72, 56),
            Vec3::new(0.5, -4.0, 1.0),
            Vec3::ZERO,
            Vec3::Z,
        )
    }

    fn settings() -> RasterSettings {
        RasterSettings {
            background: vec![0.2, 0.1, 0.0, 1.0],
            ..RasterSettings::default()
        }
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    fn backward(scene: &Scene, channels: &[f32], out: &RenderOutput) -> GaussianGrads {
        let d_color: Vec<f32> = (0..out.color.len())
            .map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.4)
            .collect();
        let d_alpha: Vec<f32> = (0..out.alpha.len()).map(|i| (i % 5) as f32 * 0.1).collect();
        render_backward(
            &camera(),
            &scene.view(channels, 4),
            &settings(),
            out,
            &PixelGrads {
                d_color: &d_color,
                d_alpha: Some(&d_alpha),
                d_depth: None,
            },
        )
        .unwrap()
    }

    fn assert_same_grads(a: &GaussianGrads, b: &GaussianGrads) {
        assert_eq!(bits(&a.d_means), bits(&b.d_means));
        assert_eq!(bits(&a.d_log_scales), bits(&b.d_log_scales));
        assert_eq!(bits(&a.d_rotations), bits(&b.d_rotations));
        assert_eq!(bits(&a.d_opacity_logits), bits(&b.d_opacity_logits));
        assert_eq!(bits(&a.d_channels), bits(&b.d_channels));
        assert_eq!(bits(&a.mean2d_grad_ndc), bits(&b.mean2d_grad_ndc));
    }

    #[test]
    fn prepared_render_is_the_plain_render_bit_for_bit() {
        let n = 900;
        let scene = Scene::random(3, n);
        let mut rng = SplitMix64::new(4);
        let channels: Vec<f32> = (0..4 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
        let plain = render(&camera(), &scene.view(&channels, 4), &settings()).unwrap();
        let prepared = prepare_view(&camera(), &scene.view(&[], 0), &settings()).unwrap();
        assert_eq!(prepared.survived(), plain.visible);
        assert_eq!(prepared.tile_entry_count(), plain.tile_entry_count());
        let mut ws = RasterWorkspace::default();
        let out = render_prepared(&mut ws, prepared, &channels, 4).unwrap();
        assert_eq!(bits(&out.color), bits(&plain.color));
        assert_eq!(bits(&out.alpha), bits(&plain.alpha));
        assert_eq!(bits(&out.depth), bits(&plain.depth));
        assert_eq!(bits(&out.radii_px), bits(&plain.radii_px));
        assert_same_grads(
            &backward(&scene, &channels, &out),
            &backward(&scene, &channels, &plain),
        );
    }

    #[test]
    fn channels_of_non_contributing_gaussians_are_never_read() {
        let n = 1500;
        let scene = Scene::random(5, n);
        let mut rng = SplitMix64::new(6);
        let channels: Vec<f32> = (0..4 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
        let prepared = prepare_view(&camera(), &scene.view(&[], 0), &settings()).unwrap();
        let survived = prepared.survived();
        let contributing = prepared.contributing();
        let n_survived = survived.iter().filter(|&&v| v).count();
        let n_contributing = contributing.iter().filter(|&&v| v).count();
        // The scene must exercise both sides: hidden Gaussians and blended ones.
        assert!(n_contributing > 100, "{n_contributing} contribute");
        assert!(
            n_contributing + 100 < n_survived,
            "{n_contributing} of {n_survived} contribute: too few hidden to test"
        );
        for (c, s) in contributing.iter().zip(&survived) {
            assert!(!c || *s, "a culled Gaussian contributes");
        }
        // Garbage (finite) channels wherever the blend should not look.
        let mut garbage = channels.clone();
        for (g, &c) in contributing.iter().enumerate() {
            if !c {
                for (k, v) in garbage[4 * g..4 * g + 4].iter_mut().enumerate() {
                    *v = 1e3 * (k as f32 + 1.0) - g as f32;
                }
            }
        }
        let clean = render(&camera(), &scene.view(&channels, 4), &settings()).unwrap();
        let dirty = render(&camera(), &scene.view(&garbage, 4), &settings()).unwrap();
        assert_eq!(bits(&dirty.color), bits(&clean.color));
        assert_eq!(bits(&dirty.alpha), bits(&clean.alpha));
        let g_clean = backward(&scene, &channels, &clean);
        let g_dirty = backward(&scene, &garbage, &dirty);
        assert_same_grads(&g_clean, &g_dirty);
        // ... and they get no channel gradient, while every contributing one is read: a
        // change of its channels changes the image.
        for (g, &c) in contributing.iter().enumerate() {
            if !c {
                assert!(g_clean.d_channels[4 * g..4 * g + 4]
                    .iter()
                    .all(|&v| v == 0.0));
            }
        }
        for g in (0..n).filter(|&g| contributing[g]).step_by(37) {
            let mut bumped = channels.clone();
            bumped[4 * g] += 0.5;
            let out = render(&camera(), &scene.view(&bumped, 4), &settings()).unwrap();
            assert_ne!(bits(&out.color), bits(&clean.color), "Gaussian {g} unread");
        }
    }

    /// The backward reduction as it was written first: serial, in rank order, each
    /// rank's records summed in tile order into a buffer starting at +0.0, then pushed
    /// through the projection backward and scattered to the Gaussians.
    fn serial_reduction(
        scene: &Scene,
        channels: &[f32],
        out: &RenderOutput,
        d_color: &[f32],
        d_alpha: &[f32],
    ) -> GaussianGrads {
        let st = &out.state;
        let nc = 4;
        let stride = REC_CHANNELS + nc;
        let gaussians = scene.view(channels, nc);
        let frame = camera_frame(&camera(), settings().near_m).unwrap();
        let mode = AlphaMode { smooth: false };
        let mut records = vec![f32::NAN; st.bins.tile_ranks.len() * stride];
        let view = blend::PixelGradsView {
            width: out.width as usize,
            d_color,
            d_alpha: Some(d_alpha),
            d_depth: None,
        };
        write_records(st, mode, nc, &view, &mut records);
        let n = gaussians.len();
        let mut g_out = GaussianGrads {
            d_means: vec![0.0; 3 * n],
            d_log_scales: vec![0.0; 3 * n],
            d_rotations: vec![0.0; 4 * n],
            d_opacity_logits: vec![0.0; n],
            d_channels: vec![0.0; nc * n],
            mean2d_grad_ndc: vec![0.0; n],
            ..GaussianGrads::default()
        };
        let (half_w, half_h) = (0.5 * out.width as f32, 0.5 * out.height as f32);
        for (rank, &g) in st.gaussian_of_rank.iter().enumerate() {
            let g = g as usize;
            let mut sum = vec![0.0f32; stride];
            let bins = &st.bins;
            for &e in &bins.entry_of_rank[bins.rank_offsets[rank]..bins.rank_offsets[rank + 1]] {
                let rec = &records[e as usize * stride..(e as usize + 1) * stride];
                for (s, r) in sum.iter_mut().zip(rec) {
                    *s += r;
                }
            }
            let p = project::project_forward(&frame, &gaussians.params(g), mode.cutoff()).unwrap();
            let d = ProjectedGrad {
                d_mean_px: [sum[0], sum[1]],
                d_conic: [sum[REC_CONIC], sum[REC_CONIC + 1], sum[REC_CONIC + 2]],
                d_opacity: sum[REC_OPACITY],
                d_depth: sum[REC_DEPTH],
            };
            let pg = project::project_backward(&frame, &p, &d);
            let ndc = (sum[0] * half_w).hypot(sum[1] * half_h);
            let d_ch = &sum[REC_CHANNELS..];
            if !(pg.is_finite() && d_ch.iter().all(|v| v.is_finite()) && ndc.is_finite()) {
                g_out.dropped_nonfinite += 1;
                continue;
            }
            g_out.d_means[3 * g..3 * g + 3].copy_from_slice(&pg.d_mean);
            g_out.d_log_scales[3 * g..3 * g + 3].copy_from_slice(&pg.d_log_scale);
            g_out.d_rotations[4 * g..4 * g + 4].copy_from_slice(&pg.d_rotation);
            g_out.d_opacity_logits[g] = pg.d_opacity_logit;
            g_out.d_channels[nc * g..nc * g + nc].copy_from_slice(d_ch);
            g_out.mean2d_grad_ndc[g] = ndc;
        }
        g_out
    }

    /// The blocked, parallel reduction gives the serial one's bits, on the full lists and
    /// on the compacted ones, with culled Gaussians and more than one block.
    #[test]
    fn backward_reduction_is_the_serial_rank_order_sum() {
        let n = 2 * REDUCE_BLOCK + 77;
        let mut scene = Scene::random(11, n);
        // Every ninth Gaussian far off to the side: culled, no rank.
        for g in (0..n).step_by(9) {
            scene.means[3 * g] = 40.0;
        }
        let mut rng = SplitMix64::new(12);
        let channels: Vec<f32> = (0..4 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
        let plain = render(&camera(), &scene.view(&channels, 4), &settings()).unwrap();
        let prepared = prepare_view(&camera(), &scene.view(&[], 0), &settings()).unwrap();
        prepared.contributing();
        let compacted =
            render_prepared(&mut RasterWorkspace::default(), prepared, &channels, 4).unwrap();
        assert!(compacted.blended_entry_count() < plain.blended_entry_count());
        let n_culled = plain.visible.iter().filter(|&&v| !v).count();
        assert!(n_culled > 0 && n_culled < n / 2, "{n_culled} culled");
        for out in [&plain, &compacted] {
            let d_color: Vec<f32> = (0..out.color.len())
                .map(|i| ((i * 7919) % 13) as f32 / 13.0 - 0.4)
                .collect();
            let d_alpha: Vec<f32> = (0..out.alpha.len()).map(|i| (i % 5) as f32 * 0.1).collect();
            let expected = serial_reduction(&scene, &channels, out, &d_color, &d_alpha);
            let got = backward(&scene, &channels, out);
            assert_same_grads(&got, &expected);
            assert_eq!(got.dropped_nonfinite, expected.dropped_nonfinite);
            let nonzero = got.d_means.iter().filter(|&&v| v != 0.0).count();
            assert!(nonzero > n, "only {nonzero} non-zero mean gradients");
        }
    }

    /// Images and gradients are the same bits with 1, 2 and 3 worker threads.
    #[test]
    fn results_do_not_depend_on_the_thread_count() {
        let n = 1200;
        let scene = Scene::random(13, n);
        let mut rng = SplitMix64::new(14);
        let channels: Vec<f32> = (0..4 * n).map(|_| rng.uniform(0.0, 1.0)).collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let prepared = prepare_view(&camera(), &scene.view(&[], 0), &settings()).unwrap();
                prepared.contributing();
                let out = render_prepared(&mut RasterWorkspace::default(), prepared, &channels, 4)
                    .unwrap();
                let grads = backward(&scene, &channels, &out);
                (out, grads)
            })
        };
        let (out1, grads1) = run(1);
        for threads in [2, 3] {
            let (out, grads) = run(threads);
            assert_eq!(bits(&out.color), bits(&out1.color), "{threads} threads");
            assert_eq!(bits(&out.alpha), bits(&out1.alpha), "{threads} threads");
            assert_eq!(bits(&out.depth), bits(&out1.depth), "{threads} threads");
            assert_same_grads(&grads, &grads1);
        }
    }

    /// The band-wise copy puts every tile-major value at its pixel, ragged edge tiles and
    /// zero channels included.
    #[test]
    fn untile_puts_each_tile_pixel_at_its_image_pixel() {
        for (w, h, nc) in [(37u32, 21u32, 3usize), (32, 16, 1), (5, 40, 0)] {
            let grid = TileGrid::new(w, h);
            let color_chunk = TILE_PIXELS * nc.max(1);
            let n_tiles = grid.n_tiles();
            let value = |i: usize| i as f32 * 0.25 + 1.0;
            let color: Vec<f32> = (0..n_tiles * color_chunk).map(value).collect();
            let depth: Vec<f32> = (0..n_tiles * TILE_PIXELS).map(|i| -value(i)).collect();
            let trans: Vec<f32> = (0..n_tiles * TILE_PIXELS).map(|i| 1.0 / value(i)).collect();
            let (wu, hu) = (w as usize, h as usize);
            let mut img_color = vec![f32::NAN; wu * hu * nc];
            let mut img_alpha = vec![f32::NAN; wu * hu];
            let mut img_depth = vec![f32::NAN; wu * hu];
            untile(
                &grid,
                nc,
                TileMajor {
                    color: &color,
                    color_chunk,
                    depth: &depth,
                    transmittance: &trans,
                },
                &mut img_color,
                &mut img_alpha,
                &mut img_depth,
            );
            let tile_px = TILE_PX as usize;
            for y in 0..hu {
                for x in 0..wu {
                    let t = (y / tile_px) * grid.tiles_x as usize + x / tile_px;
                    let p = (y % tile_px) * tile_px + x % tile_px;
                    let q = t * TILE_PIXELS + p;
                    let at = y * wu + x;
                    assert_eq!(img_alpha[at].to_bits(), (1.0 - trans[q]).to_bits());
                    assert_eq!(img_depth[at].to_bits(), depth[q].to_bits());
                    for c in 0..nc {
                        let src = color[t * color_chunk + p * nc + c];
                        assert_eq!(img_color[at * nc + c].to_bits(), src.to_bits());
                    }
                }
            }
        }
    }

    #[test]
    fn prepared_render_rejects_bad_channels() {
        let n = 200;
        let scene = Scene::random(7, n);
        let prepare = || prepare_view(&camera(), &scene.view(&[], 0), &settings()).unwrap();
        let mut ws = RasterWorkspace::default();
        let short = vec![0.5f32; 4 * n - 1];
        assert!(matches!(
            render_prepared(&mut ws, prepare(), &short, 4),
            Err(RasterError::Length { .. })
        ));
        let prepared = prepare();
        let g = prepared.survived().iter().position(|&v| v).unwrap();
        let mut channels = vec![0.5f32; 4 * n];
        channels[4 * g + 2] = f32::NAN;
        assert_eq!(
            render_prepared(&mut ws, prepared, &channels, 4).unwrap_err(),
            RasterError::NonFiniteChannel { gaussian: g }
        );
        // Background of the wrong length is still an error.
        let three = vec![0.5f32; 3 * n];
        assert!(matches!(
            render_prepared(&mut ws, prepare(), &three, 3),
            Err(RasterError::Length { .. })
        ));
    }
}
