//! Settings of the Sun-aware pipeline: which of the paper's configurations (a)-(d), network
//! and encoding sizes, the light camera of the shadow pass, learning rates, densification.
//!
//! Invariants checked by [`SunAwareConfig::validate`]: every rate finite and >= 0, weights in
//! range, light settings positive; the parameter layout follows from the variant alone
//! ([`SunAwareConfig::layout`]).

use std::str::FromStr;

use crate::densify::DensifyConfig;
use crate::model::ModelLayout;
use crate::regularizer::IsoReduction;

use super::engine::{Backend, DeviceEngines, OpenEngine};
use super::error::SunAwareError;
pub use super::shading::Shading;
pub use crate::nn::AppearanceInputs;
pub use crate::srgb::ColourSpace;

/// The four configurations of the paper's Table I.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Variant {
    /// Plain 3DGS: SH colour.
    A,
    /// + appearance MLP Phi on features, Sun and view vectors.
    B,
    /// + shadow splatting (visibility refined by Psi, image = RGB * S).
    C,
    /// + isotropic scale loss.
    D,
}

impl Variant {
    pub const ALL: [Variant; 4] = [Variant::A, Variant::B, Variant::C, Variant::D];

    /// Colour from Phi rather than SH.
    pub fn uses_appearance_mlp(self) -> bool {
        self != Variant::A
    }

    /// Shadow pass and channel S.
    pub fn uses_shadow(self) -> bool {
        matches!(self, Variant::C | Variant::D)
    }

    /// `lambda_iso L_iso` in the loss.
    pub fn uses_isotropic_loss(self) -> bool {
        self == Variant::D
    }

    /// Lower-case letter as in the table.
    pub fn name(self) -> &'static str {
        match self {
            Variant::A => "a",
            Variant::B => "b",
            Variant::C => "c",
            Variant::D => "d",
        }
    }

    pub(crate) fn code(self) -> u8 {
        self as u8
    }

    pub(crate) fn from_code(code: u8) -> Option<Self> {
        Self::ALL.get(code as usize).copied()
    }
}

impl FromStr for Variant {
    type Err = SunAwareError;

    /// `a`..`d` (either case).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "a" => Ok(Variant::A),
            "b" => Ok(Variant::B),
            "c" => Ok(Variant::C),
            "d" => Ok(Variant::D),
            other => Err(SunAwareError::Config(format!(
                "unknown configuration {other:?}: expected one of a, b, c, d"
            ))),
        }
    }
}

impl std::fmt::Display for Variant {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Where the rasterizer and the shadow pass run, by name (`--backend cpu|wgpu` and the
/// component's `[training] backend`). Not part of [`SunAwareConfig`] or of a checkpoint:
/// it moves arithmetic, never changes the model. [`BackendKind::open`] turns it into a
/// [`Backend`] for [`super::SunAwareTrainer::set_backend`], from the device engines the
/// binary was built with ([`DeviceEngines`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum BackendKind {
    /// The CPU rasterizer and shadow pass (the reference).
    #[default]
    Cpu,
    /// The wgpu compute backend (crate `gs-wgpu`, the binaries' cargo feature `wgpu`).
    Wgpu,
}

impl BackendKind {
    pub fn name(self) -> &'static str {
        match self {
            BackendKind::Cpu => "cpu",
            BackendKind::Wgpu => "wgpu",
        }
    }

    /// Errors unless `engines` can open the backend: the message names the cargo feature.
    pub fn check_compiled_in(self, engines: &DeviceEngines) -> Result<(), SunAwareError> {
        self.opener(engines).map(|_| ())
    }

    /// `Ok` when this backend's kernels run models of `config`; otherwise why not, naming
    /// the setting and what to set instead. The one statement of what each backend runs:
    /// gs-wgpu's engine answers `Engine::supports` with it, and configuration files are
    /// checked against it when they load, before any device is opened. The CPU runs every
    /// model; wgpu runs `shading = "none"` and `"lambert_learned"` (the shortest-axis
    /// `"lambert"` has no device kernels); every `appearance_inputs` (`"paper"`, and the
    /// local-frame `"local"` / `"local_no_sun"`, which `validate` ties to
    /// `"lambert_learned"`), `shadow_gain` and both `colour_space`s run on both.
    pub fn check_model(self, config: &SunAwareConfig) -> Result<(), String> {
        if self == BackendKind::Cpu {
            return Ok(());
        }
        match config.shading {
            Shading::None | Shading::LambertLearned => Ok(()),
            Shading::Lambert => Err(format!(
                "the wgpu backend supports shading = \"none\" and \"lambert_learned\" \
                 (this model has {:?}, the shortest-axis normal, which has no device \
                 kernels): use shading = \"lambert_learned\" or train on the CPU",
                config.shading.name()
            )),
        }
    }

    fn opener(self, engines: &DeviceEngines) -> Result<Option<OpenEngine>, SunAwareError> {
        match self {
            BackendKind::Cpu => Ok(None),
            BackendKind::Wgpu => engines.wgpu.map(Some).ok_or_else(|| {
                SunAwareError::Config(format!(
                    "backend {:?} is not compiled into this build: rebuild with the cargo \
                     feature `wgpu` (e.g. `cargo build --release --features wgpu`; \
                     sim-harness and fsw-component build it with crate gs-wgpu)",
                    self.name()
                ))
            }),
        }
    }

    /// Opens the backend: `Cpu` always succeeds; a device opens through `engines` (for
    /// `Wgpu`: a Vulkan adapter and the kernels), with bit-identical results from run to
    /// run when `deterministic` (on wgpu the rasterizer's backward then sums per-entry
    /// records in tile order instead of with float atomics; no effect on the CPU, which is
    /// always deterministic). No adapter, or an engine this build lacks, is an error, never
    /// a silent fallback to the CPU.
    pub fn open(
        self,
        engines: &DeviceEngines,
        deterministic: bool,
    ) -> Result<Backend, SunAwareError> {
        match self.opener(engines)? {
            None => Ok(Backend::Cpu),
            Some(open) => open(deterministic)
                .map(Backend::Device)
                .map_err(|e| SunAwareError::Config(format!("backend {:?}: {e}", self.name()))),
        }
    }
}

impl FromStr for BackendKind {
    type Err = SunAwareError;

    /// `cpu` or `wgpu` (either case). Parsing never checks the build: see
    /// [`BackendKind::check_compiled_in`].
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "cpu" => Ok(BackendKind::Cpu),
            "wgpu" => Ok(BackendKind::Wgpu),
            other => Err(SunAwareError::Config(format!(
                "unknown backend {other:?}: expected \"cpu\" or \"wgpu\""
            ))),
        }
    }
}

impl FromStr for AppearanceInputs {
    type Err = SunAwareError;

    /// `paper`, `local` or `local_no_sun` (either case).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let s = s.trim().to_ascii_lowercase();
        AppearanceInputs::ALL
            .into_iter()
            .find(|i| i.name() == s)
            .ok_or_else(|| {
                SunAwareError::Config(format!(
                    "unknown appearance_inputs {s:?}: expected paper, local or local_no_sun"
                ))
            })
    }
}

impl std::fmt::Display for BackendKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// How the light camera projects.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LightProjection {
    /// A pinhole at the camera-to-target distance along the Sun vector (the paper, GS3).
    Perspective,
    /// Parallel rays along the Sun vector: the Sun is a directional source.
    Orthographic,
}

/// The shadow pass's light camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LightConfig {
    pub projection: LightProjection,
    /// Side of the square light image, pixels. The field of view (or the orthographic
    /// extent) is fitted to the scene box's bounding sphere, so this sets the resolution
    /// of the shadows.
    pub resolution_px: u32,
    /// `V_i` averages the transmittance over pixels whose centres lie within this distance
    /// of the Gaussian's projected centre (DESIGN.md: about 2 px).
    pub footprint_radius_px: f32,
    /// Occluders must be nearer to the light than `depth_i - bias` to shadow Gaussian `i`;
    /// the bias is this fraction of the scene box's bounding radius (so `i` and its
    /// immediate neighbours on the same surface do not shadow themselves).
    pub depth_bias_fraction: f32,
    /// Field of view (or orthographic extent) = bounding sphere times this margin.
    pub fov_margin: f32,
}

impl Default for LightConfig {
    fn default() -> Self {
        Self {
            projection: LightProjection::Perspective,
            resolution_px: 256,
            footprint_radius_px: 2.0,
            depth_bias_fraction: 0.02,
            fov_margin: 1.05,
        }
    }
}

/// Learning rates per group (3DGS defaults for the geometry; DESIGN.md section 3).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SunAwareRates {
    /// Position rate at the start of a round, times the scene extent.
    pub position_init: f32,
    /// Position rate at the end of a round, times the scene extent (log-linear decay).
    pub position_final: f32,
    pub sh_dc: f32,
    pub sh_rest: f32,
    pub opacity: f32,
    pub scale: f32,
    pub rotation: f32,
    pub feature: f32,
    pub shadow_latent: f32,
    pub appearance_mlp: f32,
    pub shadow_mlp: f32,
    /// The learned shading normal `v` of `shading = "lambert_learned"` (Adam step size on
    /// the unnormalised vector; `v` starts unit length, so this is about radians per step).
    pub normal: f32,
}

impl Default for SunAwareRates {
    fn default() -> Self {
        Self {
            position_init: 1.6e-4,
            position_final: 1.6e-6,
            sh_dc: 2.5e-3,
            sh_rest: 2.5e-3 / 20.0,
            opacity: 0.025,
            scale: 5e-3,
            rotation: 1e-3,
            // As the SH DC rate: the feature plays the role of the colour coefficients.
            feature: 2.5e-3,
            shadow_latent: 2.5e-3,
            appearance_mlp: 5e-4,
            shadow_mlp: 1e-3,
            // The best of 1e-3, 1e-2, 3e-2 on the demo's preset, (d), k_a = 0.1: L0 window
            // 20.32 / 21.23 / 21.56 dB, L2 11.03 / 11.03 / 11.42 dB (docs/results/accuracy.md
            // section 6). The normal has far to turn from its radial start.
            normal: 3e-2,
        }
    }
}

/// How the shadow MLP Psi turns the light pass's visibility `V_i` into the refined `V'_i`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ShadowRefinement {
    /// The paper's formula as written: `V'_i = Psi(V_i, gamma(sun), gamma(mu_i), l_i)`.
    Replace,
    /// `V'_i = V_i * Psi(..)` (default): Psi can only darken what the light pass leaves lit,
    /// so the geometric shadow always reaches the image. With `Replace`, Psi learnt to ignore
    /// `V_i` on our scenes and the appearance MLP memorised the training orbit's shadows
    /// instead; `Multiply` scored +1.1 dB (Cassini) and +1.35 dB (Rosetta) over (b) where
    /// `Replace` scored -0.3 dB (docs/shadows.md).
    Multiply,
}

/// Largest `feature_dim` (the paper: 72); bounds a loaded checkpoint's network sizes.
pub const MAX_FEATURE_DIM: usize = 1024;
/// Largest `shadow_latent_dim` (the paper: 6).
pub const MAX_SHADOW_LATENT_DIM: usize = 1024;
/// Largest `max_gaussians` (the paper's preset: 200 000).
pub const MAX_GAUSSIANS_LIMIT: usize = 1 << 24;

/// Everything that shapes a Sun-aware model and its training.
#[derive(Clone, Debug, PartialEq)]
pub struct SunAwareConfig {
    pub variant: Variant,
    /// SH degree of configuration (a).
    pub sh_degree: u32,
    /// The active SH degree grows by one every this many steps (3DGS: 1000).
    pub sh_degree_interval: u64,
    /// Width of the appearance feature f_i (paper: 72).
    pub feature_dim: usize,
    /// Width of the shadow latent l_i (paper: 6).
    pub shadow_latent_dim: usize,
    /// L of the positional encoding (DESIGN.md: 4).
    pub encoding_frequencies: usize,
    /// Weight of (1 - SSIM) in the photometric loss (paper: 0.2).
    pub lambda_dssim: f32,
    /// Weight of L_iso in configuration (d). Default 10 with [`IsoReduction::MeanOverEntries`]:
    /// MonoGS's setting, which the paper cites for this loss. The mean keeps the pull per
    /// Gaussian constant while densification grows the model (the paper's plain sum with a
    /// fixed weight would strengthen with every added Gaussian), and with scales of a few
    /// centimetres on a metre-sized target it is of the order of the photometric loss.
    pub lambda_iso: f32,
    pub iso_reduction: IsoReduction,
    pub light: LightConfig,
    /// How Psi's output makes the refined visibility `V'` of configurations (c)-(d).
    pub shadow_refinement: ShadowRefinement,
    /// Under [`ShadowRefinement::Multiply`], `V' = shadow_gain * V * Psi`. The light pass's
    /// `V` of a Gaussian the ray tracer says is lit averages 0.5-0.65 (the splatting
    /// approximation: neighbours on the same surface occlude part of its footprint), and
    /// Psi and Phi's colour are sigmoids, so with a gain of 1 a lit white surface renders
    /// at about half its brightness. A gain of 2 lets Psi restore it while a Gaussian the
    /// light pass puts in full shadow (`V = 0`) stays dark: +1.65 dB masked training fit on
    /// the demo scenario (offline reference, 1,500 steps; docs/results/accuracy.md). The
    /// default stays 1 (the paper's form); the experiment presets set 2. Both backends
    /// apply it. A model knob, stored in checkpoints (from version 4; older
    /// ones load as 1).
    pub shadow_gain: f32,
    /// Colour times a Lambertian factor of each Gaussian's normal and the Sun
    /// ([`Shading`], `super::shading`): `None` is the paper's form. A model knob, stored in
    /// checkpoints (from version 5; older ones load as `None`). The wgpu backend runs
    /// `LambertLearned` (which adds the per-Gaussian group `Param::Normal`) device-resident
    /// and refuses `Lambert` (the shortest-axis normal has no device kernels).
    pub shading: Shading,
    /// The ambient floor `k_a` of the Lambertian shadings, in [0, 1): the factor is
    /// `k_a + (1 - k_a) max(0, n . s)`. Stored in checkpoints with `shading`.
    pub shading_ambient: f32,
    /// What Phi reads beyond the feature ([`AppearanceInputs`]): the paper's
    /// `[gamma(sun) | gamma(view)]`, or that and `[n.s, n.v, n.h]` in the Gaussian's local
    /// frame (`n` the learned shading normal facing the camera, `h` the half vector;
    /// `LocalNoSun` also zeroes `gamma(sun)`). The local ones need
    /// `shading = LambertLearned` (it owns the normal). A model knob: it sets Phi's input
    /// width, so checkpoints store it (from version 7; older ones load as `Paper`). Both
    /// backends run all three.
    pub appearance_inputs: AppearanceInputs,
    /// What the colours, the shadow channel and the blend are ([`ColourSpace`]): sRGB
    /// values (the paper's form) or linear radiance with each pixel of `RGB * S` encoded to
    /// sRGB before the loss, as the camera and the simulator's ray tracer form an image.
    /// A model knob, stored in checkpoints (from version 8; older ones load as `Srgb`).
    /// `Linear` needs Phi (configurations b-d): Phi's colour is a sigmoid, while (a)'s SH
    /// colour is clamped at zero with no gradient, and dark materials sit near zero in
    /// linear radiance (the static-target fit of (a) fell from 6.2 to 2.6 dB over black).
    /// Both backends run both.
    pub colour_space: ColourSpace,
    pub lr: SunAwareRates,
    pub densify: DensifyConfig,
    /// Prune Gaussians whose screen radius or world size is too big at densification.
    pub size_prune: bool,
    /// Densification stops adding Gaussians at this count (pruning continues).
    pub max_gaussians: usize,
    /// Before this many applied steps densification only prunes (3DGS `densify_from_iter`
    /// = 500): early gradients come from a colour model still far from converged and would
    /// clone nearly every Gaussian.
    pub densify_from_step: u64,
    /// RGB behind the Gaussians (the shadow channel's background is 1: background unshadowed).
    pub background: [f32; 3],
    pub near_m: f32,
    /// Seeds the networks, the features and densification.
    pub seed: u64,
    /// Standard deviation of the random initial appearance features.
    pub feature_init_std: f32,
    /// Run Phi and Psi only for the Gaussians the blend reads (an alpha-only pass over the
    /// tiles finds them first), instead of every Gaussian that survived culling. The
    /// image and the rasterizer's gradients are the same bits either way (a Gaussian the
    /// blend never reads has no effect and gets zero gradient); the networks' weight
    /// gradients differ only by float summation order (their batch has fewer rows). It
    /// applies to training steps and renders (`SunAwareModel::forward_for_step`);
    /// `SunAwareModel::forward` always runs the networks on every visible Gaussian, so its
    /// per-Gaussian outputs stay complete. A speed setting, not part of the model:
    /// checkpoints do not store it.
    pub skip_noncontributing_in_mlp: bool,
    /// Phi and Psi keep only their inputs and outputs from forward to backward, and the
    /// backward recomputes each block's hidden activations (one more forward pass of the
    /// networks, against `rows * 768 * 4` bytes of Phi activations kept: about 86 MB at
    /// 28K rows). Gradients are the same bits either way. A speed/memory setting, not
    /// stored in checkpoints.
    pub mlp_recompute_activations: bool,
    /// Keep the networks' inputs and tapes and the rasterizer's forward buffers from one
    /// step to the next instead of allocating them afresh (same bits either way). Spares
    /// page faults (about 5-8 % of a step's CPU time at 100K Gaussians) but holds those
    /// buffers between steps: +45-60 MB of peak at 100K, 960x600 on the volume scene, and
    /// Phi's whole tape when every Gaussian contributes. Not stored in checkpoints.
    pub reuse_step_buffers: bool,
    /// Width of each of Phi's three hidden layers (paper: 256). A model knob: it sets the
    /// network's shape, so checkpoints store it (from version 3; older ones load as 256).
    pub appearance_hidden_width: usize,
    /// Arithmetic of the networks' matrix products on the CPU: `F32`, or `Bf16` (inputs
    /// rounded to bfloat16, f32 accumulation, on AMX tiles or AVX-512 BF16;
    /// `SunAwareModel::new` fails on a CPU with neither). Both Phi and Psi. A speed setting, not stored in checkpoints:
    /// a loaded model runs f32 until `SunAwareModel::set_mlp_precision`.
    pub mlp_precision: crate::nn::MatmulPrecision,
    /// Early frustum cull (`RasterSettings::cull_outside_frustum`): a Gaussian whose
    /// footprint certainly misses the image is dropped before its covariance is projected.
    /// Same image and gradients either way (a pure time skip); Gaussians behind the near
    /// plane are dropped in both modes (no perspective projection there). Not stored in
    /// checkpoints.
    pub cull_outside_frustum: bool,
    /// Stop blending a pixel before its transmittance falls below 1e-4
    /// (`RasterSettings::early_termination`; off: the whole tile list is blended and the
    /// image moves by at most the stopped pixel's transmittance, below 0.01, times the
    /// largest |colour - background|). The backward is exact in both modes. CPU
    /// rasterizer only. Not stored in checkpoints.
    pub early_termination: bool,
    /// When the training observation has a foreground mask (the loss is then masked):
    /// only the tiles within the SSIM window's half width (5 px) of a mask pixel are
    /// blended and back-propagated (`RasterSettings::blend_tiles`). The loss and every
    /// gradient are the same bits as without the skip; only the rendered background away
    /// from the mask differs. CPU rasterizer only. Not stored in checkpoints.
    pub skip_masked_background_tiles: bool,
}

impl Default for SunAwareConfig {
    fn default() -> Self {
        Self {
            variant: Variant::D,
            sh_degree: 3,
            sh_degree_interval: 1000,
            feature_dim: 72,
            shadow_latent_dim: 6,
            encoding_frequencies: 4,
            lambda_dssim: 0.2,
            lambda_iso: 10.0,
            iso_reduction: IsoReduction::MeanOverEntries,
            light: LightConfig::default(),
            shadow_refinement: ShadowRefinement::Multiply,
            shadow_gain: 1.0,
            shading: Shading::None,
            shading_ambient: 0.1,
            appearance_inputs: AppearanceInputs::Paper,
            colour_space: ColourSpace::Srgb,
            lr: SunAwareRates::default(),
            densify: DensifyConfig::default(),
            size_prune: false,
            max_gaussians: 200_000,
            densify_from_step: 500,
            background: [0.0; 3],
            near_m: 0.01,
            seed: 0,
            feature_init_std: 0.1,
            skip_noncontributing_in_mlp: true,
            mlp_recompute_activations: false,
            reuse_step_buffers: false,
            appearance_hidden_width: 256,
            mlp_precision: crate::nn::MatmulPrecision::F32,
            cull_outside_frustum: true,
            early_termination: true,
            skip_masked_background_tiles: true,
        }
    }
}

impl SunAwareConfig {
    /// Defaults for one variant.
    pub fn for_variant(variant: Variant) -> Self {
        Self {
            variant,
            ..Self::default()
        }
    }

    /// Parameter groups the variant needs.
    pub fn layout(&self) -> ModelLayout {
        let v = self.variant;
        ModelLayout {
            sh_degree: if v.uses_appearance_mlp() {
                0
            } else {
                self.sh_degree
            },
            feature_dim: if v.uses_appearance_mlp() {
                self.feature_dim
            } else {
                0
            },
            shadow_latent_dim: if v.uses_shadow() {
                self.shadow_latent_dim
            } else {
                0
            },
            normal_dim: if self.shading == Shading::LambertLearned {
                3
            } else {
                0
            },
        }
    }

    /// Checks every setting; the error names the first bad one.
    pub fn validate(&self) -> Result<(), SunAwareError> {
        let bad = |m: String| Err(SunAwareError::Config(m));
        if !(self.shadow_gain.is_finite() && (0.5..=8.0).contains(&self.shadow_gain)) {
            return bad(format!(
                "shadow_gain {} is outside [0.5, 8]",
                self.shadow_gain
            ));
        }
        if !(self.shading_ambient.is_finite() && (0.0..1.0).contains(&self.shading_ambient)) {
            return bad(format!(
                "shading_ambient {} is outside [0, 1)",
                self.shading_ambient
            ));
        }
        if self.colour_space == ColourSpace::Linear && !self.variant.uses_appearance_mlp() {
            return bad(format!(
                "colour_space = \"linear\" needs the appearance MLP's colour (configurations \
                 b-d), not {}: SH colour is clamped at zero with no gradient, and in linear \
                 radiance dark surfaces sit at that clamp",
                self.variant
            ));
        }
        if self.shading != Shading::None && !self.variant.uses_appearance_mlp() {
            return bad(format!(
                "shading = {:?} needs the appearance MLP (configurations b-d), not {}",
                self.shading.name(),
                self.variant
            ));
        }
        if self.appearance_inputs != AppearanceInputs::Paper
            && !(self.shading == Shading::LambertLearned && self.variant.uses_appearance_mlp())
        {
            return bad(format!(
                "appearance_inputs = {:?} reads the learned normal: it needs shading = \
                 \"lambert_learned\" and the appearance MLP (configurations b-d), not \
                 shading = {:?} in configuration {}",
                self.appearance_inputs.name(),
                self.shading.name(),
                self.variant
            ));
        }
        if self.sh_degree > 3 {
            return bad(format!("sh_degree {} is above 3", self.sh_degree));
        }
        if self.sh_degree_interval == 0 {
            return bad("sh_degree_interval must be positive".into());
        }
        if self.feature_dim > MAX_FEATURE_DIM {
            return bad(format!(
                "feature_dim {} is above {MAX_FEATURE_DIM}",
                self.feature_dim
            ));
        }
        if self.shadow_latent_dim > MAX_SHADOW_LATENT_DIM {
            return bad(format!(
                "shadow_latent_dim {} is above {MAX_SHADOW_LATENT_DIM}",
                self.shadow_latent_dim
            ));
        }
        if self.max_gaussians > MAX_GAUSSIANS_LIMIT {
            return bad(format!(
                "max_gaussians {} is above {MAX_GAUSSIANS_LIMIT}",
                self.max_gaussians
            ));
        }
        if self.variant.uses_appearance_mlp() && self.feature_dim == 0 {
            return bad("feature_dim must be positive for configurations b-d".into());
        }
        if self.variant.uses_shadow() && self.shadow_latent_dim == 0 {
            return bad("shadow_latent_dim must be positive for configurations c-d".into());
        }
        if !(1..=crate::nn::encoding::MAX_FREQUENCIES).contains(&self.encoding_frequencies) {
            return bad(format!(
                "encoding_frequencies {} is outside 1..={}",
                self.encoding_frequencies,
                crate::nn::encoding::MAX_FREQUENCIES
            ));
        }
        if !(0.0..=1.0).contains(&self.lambda_dssim) {
            return bad(format!(
                "lambda_dssim {} is outside [0, 1]",
                self.lambda_dssim
            ));
        }
        if !(self.lambda_iso.is_finite() && self.lambda_iso >= 0.0) {
            return bad(format!(
                "lambda_iso {} must be finite and >= 0",
                self.lambda_iso
            ));
        }
        let l = &self.light;
        if l.resolution_px < 8 || l.resolution_px > 8192 {
            return bad(format!(
                "light.resolution_px {} is outside 8..=8192",
                l.resolution_px
            ));
        }
        if !(l.footprint_radius_px.is_finite() && l.footprint_radius_px >= 0.5) {
            return bad("light.footprint_radius_px must be finite and >= 0.5".into());
        }
        if !(l.depth_bias_fraction.is_finite() && l.depth_bias_fraction >= 0.0) {
            return bad("light.depth_bias_fraction must be finite and >= 0".into());
        }
        if !(l.fov_margin.is_finite() && (1.0..=4.0).contains(&l.fov_margin)) {
            return bad("light.fov_margin must be in [1, 4]".into());
        }
        let r = &self.lr;
        let rates = [
            ("position_init", r.position_init),
            ("position_final", r.position_final),
            ("sh_dc", r.sh_dc),
            ("sh_rest", r.sh_rest),
            ("opacity", r.opacity),
            ("scale", r.scale),
            ("rotation", r.rotation),
            ("feature", r.feature),
            ("shadow_latent", r.shadow_latent),
            ("appearance_mlp", r.appearance_mlp),
            ("shadow_mlp", r.shadow_mlp),
            ("normal", r.normal),
        ];
        for (name, v) in rates {
            if !(v.is_finite() && v >= 0.0) {
                return bad(format!(
                    "learning rate {name} = {v} must be finite and >= 0"
                ));
            }
        }
        if !(1..=4096).contains(&self.appearance_hidden_width) {
            return bad(format!(
                "appearance_hidden_width {} is outside 1..=4096",
                self.appearance_hidden_width
            ));
        }
        if self.max_gaussians == 0 {
            return bad("max_gaussians must be positive".into());
        }
        if !self.background.iter().all(|v| v.is_finite()) {
            return bad("background must be finite".into());
        }
        if !(self.near_m.is_finite() && self.near_m > 0.0) {
            return bad("near_m must be finite and positive".into());
        }
        if !(self.feature_init_std.is_finite() && self.feature_init_std >= 0.0) {
            return bad("feature_init_std must be finite and >= 0".into());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn backend_names_parse_and_a_missing_feature_is_a_clear_error() {
        assert_eq!("cpu".parse::<BackendKind>().unwrap(), BackendKind::Cpu);
        assert_eq!(" WGPU ".parse::<BackendKind>().unwrap(), BackendKind::Wgpu);
        let e = "cuda".parse::<BackendKind>().unwrap_err().to_string();
        assert!(e.contains("cuda") && e.contains("wgpu"), "{e}");
        let none = DeviceEngines::default();
        assert!(BackendKind::Cpu.check_compiled_in(&none).is_ok());
        assert!(matches!(
            BackendKind::Cpu.open(&none, true).unwrap(),
            Backend::Cpu
        ));
        let e = BackendKind::Wgpu.open(&none, true).unwrap_err().to_string();
        assert!(e.contains("feature `wgpu`"), "{e}");
        // An engine that fails to open (no adapter) is an error naming the backend.
        let failing = DeviceEngines {
            wgpu: Some(|_| Err("no Vulkan adapter".into())),
        };
        assert!(BackendKind::Wgpu.check_compiled_in(&failing).is_ok());
        let e = BackendKind::Wgpu
            .open(&failing, true)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("\"wgpu\"") && e.contains("no Vulkan adapter"),
            "{e}"
        );
    }

    #[test]
    fn wgpu_runs_every_appearance_input_and_colour_space_and_the_learned_normal_only() {
        let demo = SunAwareConfig {
            shading: Shading::LambertLearned,
            appearance_inputs: AppearanceInputs::Local,
            shadow_gain: 2.0,
            ..SunAwareConfig::default()
        };
        for space in ColourSpace::ALL {
            for inputs in AppearanceInputs::ALL {
                let config = SunAwareConfig {
                    appearance_inputs: inputs,
                    colour_space: space,
                    ..demo.clone()
                };
                assert!(BackendKind::Cpu.check_model(&config).is_ok());
                assert!(
                    BackendKind::Wgpu.check_model(&config).is_ok(),
                    "{inputs} {space}"
                );
            }
        }
        let paper_inputs = SunAwareConfig {
            appearance_inputs: AppearanceInputs::Paper,
            ..demo
        };
        assert!(BackendKind::Wgpu.check_model(&paper_inputs).is_ok());
        for space in ColourSpace::ALL {
            let lambert = SunAwareConfig {
                shading: Shading::Lambert,
                colour_space: space,
                ..paper_inputs.clone()
            };
            assert!(BackendKind::Cpu.check_model(&lambert).is_ok());
            let e = BackendKind::Wgpu.check_model(&lambert).unwrap_err();
            assert!(e.contains("\"lambert\""), "{e}");
        }
    }

    #[test]
    fn linear_colour_needs_phi() {
        for variant in Variant::ALL {
            let config = SunAwareConfig {
                colour_space: ColourSpace::Linear,
                ..SunAwareConfig::for_variant(variant)
            };
            let result = config.validate();
            if variant.uses_appearance_mlp() {
                assert!(result.is_ok(), "{variant}: {result:?}");
            } else {
                let e = result.unwrap_err().to_string();
                assert!(e.contains("colour_space") && e.contains("clamped"), "{e}");
            }
        }
    }

    #[test]
    fn variants_parse_and_name_round_trip() {
        for v in Variant::ALL {
            assert_eq!(v.name().parse::<Variant>().unwrap(), v);
            assert_eq!(Variant::from_code(v.code()), Some(v));
        }
        assert_eq!(" C ".parse::<Variant>().unwrap(), Variant::C);
        assert!("e".parse::<Variant>().is_err());
        assert!(!Variant::B.uses_shadow() && Variant::C.uses_shadow());
        assert!(Variant::D.uses_isotropic_loss() && !Variant::C.uses_isotropic_loss());
    }

    #[test]
    fn layout_follows_the_variant() {
        let a = SunAwareConfig::for_variant(Variant::A).layout();
        assert_eq!((a.sh_degree, a.feature_dim, a.shadow_latent_dim), (3, 0, 0));
        let b = SunAwareConfig::for_variant(Variant::B).layout();
        assert_eq!(
            (b.sh_degree, b.feature_dim, b.shadow_latent_dim),
            (0, 72, 0)
        );
        let d = SunAwareConfig::for_variant(Variant::D).layout();
        assert_eq!((d.feature_dim, d.shadow_latent_dim), (72, 6));
        // Only the learned-normal shading carries a normal group.
        assert_eq!((a.normal_dim, b.normal_dim, d.normal_dim), (0, 0, 0));
        for (shading, width) in [(Shading::Lambert, 0), (Shading::LambertLearned, 3)] {
            let c = SunAwareConfig {
                shading,
                ..SunAwareConfig::for_variant(Variant::D)
            };
            assert_eq!(c.layout().normal_dim, width, "{shading}");
        }
    }

    #[test]
    fn a_bad_normal_rate_or_learned_shading_on_a_is_refused() {
        let mut c = SunAwareConfig {
            shading: Shading::LambertLearned,
            ..SunAwareConfig::for_variant(Variant::D)
        };
        assert!(c.validate().is_ok());
        c.lr.normal = f32::INFINITY;
        let msg = c.validate().unwrap_err().to_string();
        assert!(msg.contains("learning rate normal"), "{msg}");
        let c = SunAwareConfig {
            shading: Shading::LambertLearned,
            ..SunAwareConfig::for_variant(Variant::A)
        };
        let msg = c.validate().unwrap_err().to_string();
        assert!(msg.contains("lambert_learned"), "{msg}");
    }

    #[test]
    fn local_appearance_inputs_need_the_learned_normal() {
        for inputs in AppearanceInputs::ALL {
            assert_eq!(inputs.name().parse::<AppearanceInputs>().unwrap(), inputs);
            assert_eq!(AppearanceInputs::from_code(inputs.code()), Some(inputs));
        }
        assert_eq!(
            " Local_No_Sun ".parse::<AppearanceInputs>().unwrap(),
            AppearanceInputs::LocalNoSun
        );
        let e = "global"
            .parse::<AppearanceInputs>()
            .unwrap_err()
            .to_string();
        assert!(e.contains("paper, local or local_no_sun"), "{e}");
        for inputs in [AppearanceInputs::Local, AppearanceInputs::LocalNoSun] {
            let ok = SunAwareConfig {
                shading: Shading::LambertLearned,
                appearance_inputs: inputs,
                ..SunAwareConfig::for_variant(Variant::B)
            };
            assert!(ok.validate().is_ok());
            for shading in [Shading::None, Shading::Lambert] {
                let c = SunAwareConfig {
                    shading,
                    ..ok.clone()
                };
                let msg = c.validate().unwrap_err().to_string();
                assert!(
                    msg.contains("appearance_inputs") && msg.contains("lambert_learned"),
                    "{msg}"
                );
            }
        }
        // The paper's row needs nothing.
        assert!(SunAwareConfig::default().validate().is_ok());
    }

    #[test]
    fn bad_settings_are_named() {
        let mut c = SunAwareConfig::default();
        c.lr.feature = f32::NAN;
        let msg = c.validate().unwrap_err().to_string();
        assert!(msg.contains("feature"), "{msg}");
        let mut c = SunAwareConfig::default();
        c.light.resolution_px = 2;
        assert!(c.validate().unwrap_err().to_string().contains("resolution"));
        assert!(SunAwareConfig::default().validate().is_ok());
    }
}
