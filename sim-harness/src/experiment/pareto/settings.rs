//! The sweep's settings: a [`Knob`] is one preset field set to a value, a [`Setting`] a
//! named set of knobs applied on top of a base preset; the default and optional sweeps.
//!
//! Invariant: a setting changes only the knobs it names; the rest come from the base.

use crate::experiment::preset::Preset;
use crate::experiment::ExperimentError;
use gs_core::nn::MatmulPrecision;
use gs_core::sunaware::Variant;

/// One knob of a preset set to a value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Knob {
    /// SPEED camera divided by this (image resolution).
    Downsample(u32),
    /// Gaussian cap (initial points are capped at half of it).
    MaxGaussians(usize),
    /// Width of the appearance feature f_i (Phi's per-Gaussian input).
    FeatureDim(usize),
    EncodingFrequencies(usize),
    RoundsPerWindowChange(u32),
    PassesPerRound(u32),
    Window(usize),
    SkipEclipse(bool),
    SkipUnlit(bool),
    SkipUnchangedWindow(bool),
    /// Phi and Psi only for the Gaussians the blend reads.
    SkipNoncontributingMlp(bool),
    /// Training frames carry their masks and the loss is weighed by them.
    MaskedLoss(bool),
    /// gs-core's early frustum cull.
    CullOutsideFrustum(bool),
    /// Blending stops at transmittance 1e-4.
    EarlyTermination(bool),
    /// With masked training: only the tiles the masked loss reads are blended.
    SkipMaskedBackgroundTiles(bool),
    /// Hidden width of Phi's layers.
    AppearanceHiddenWidth(usize),
    /// Arithmetic of the networks' matrix products.
    MlpPrecision(MatmulPrecision),
    Config(Variant),
}

impl Knob {
    /// Sets this knob on `preset`.
    pub fn apply(&self, preset: &mut Preset) {
        match *self {
            Knob::Downsample(v) => preset.downsample = v,
            Knob::MaxGaussians(v) => {
                preset.max_gaussians = v;
                preset.init_points = preset.init_points.min((v / 2).max(2) as u32);
            }
            Knob::FeatureDim(v) => preset.feature_dim = v,
            Knob::EncodingFrequencies(v) => preset.encoding_frequencies = v,
            Knob::RoundsPerWindowChange(v) => preset.rounds_per_window_change = v,
            Knob::PassesPerRound(v) => preset.passes_per_round = v,
            Knob::Window(v) => preset.window = v,
            Knob::SkipEclipse(v) => preset.skip_eclipse = v,
            Knob::SkipUnlit(v) => preset.skip_unlit = v,
            Knob::SkipUnchangedWindow(v) => preset.skip_unchanged_window = v,
            Knob::SkipNoncontributingMlp(v) => preset.skip_noncontributing_in_mlp = v,
            Knob::MaskedLoss(v) => preset.masked_loss = v,
            Knob::CullOutsideFrustum(v) => preset.cull_outside_frustum = v,
            Knob::EarlyTermination(v) => preset.early_termination = v,
            Knob::SkipMaskedBackgroundTiles(v) => preset.skip_masked_background_tiles = v,
            Knob::AppearanceHiddenWidth(v) => preset.appearance_hidden_width = v,
            Knob::MlpPrecision(v) => preset.mlp_precision = precision_name(v).into(),
            Knob::Config(v) => preset.configs = vec![v.name().to_string()],
        }
    }
}

/// The preset's name of a matrix-product precision (`Preset::mlp_precision`).
pub fn precision_name(p: MatmulPrecision) -> &'static str {
    match p {
        MatmulPrecision::F32 => "f32",
        MatmulPrecision::Bf16 => "bf16",
    }
}

/// A named set of knob values applied on top of a base preset.
#[derive(Clone, Debug, PartialEq)]
pub struct Setting {
    pub name: String,
    pub knobs: Vec<Knob>,
}

impl Setting {
    pub fn new(name: &str, knobs: &[Knob]) -> Setting {
        Setting {
            name: name.to_string(),
            knobs: knobs.to_vec(),
        }
    }

    /// The base preset with this setting's knobs, validated.
    pub fn preset(&self, base: &Preset) -> Result<Preset, ExperimentError> {
        let mut p = base.clone();
        for k in &self.knobs {
            k.apply(&mut p);
        }
        p.name = format!("{}+{}", base.name, self.name);
        p.validate()?;
        Ok(p)
    }
}

/// The default sweep around the base: one knob at a time, configurations (a) and (b), and a
/// few combined cheap points. The skips are toggled by the `skips` job on the same base
/// ([`crate::experiment::skips`]); [`optional_settings`] has more (dearer) points for `--settings`.
pub fn default_settings() -> Vec<Setting> {
    use Knob::*;
    vec![
        Setting::new("base", &[]),
        Setting::new("ds24", &[Downsample(24)]),
        Setting::new("ds12", &[Downsample(12)]),
        Setting::new("cap1500", &[MaxGaussians(1500)]),
        Setting::new("cap6000", &[MaxGaussians(6000)]),
        Setting::new("feat32", &[FeatureDim(32)]),
        Setting::new("enc2", &[EncodingFrequencies(2)]),
        Setting::new("enc6", &[EncodingFrequencies(6)]),
        Setting::new("rounds1", &[RoundsPerWindowChange(1)]),
        Setting::new("rounds4", &[RoundsPerWindowChange(4)]),
        Setting::new("w4", &[Window(4)]),
        Setting::new("w10", &[Window(10)]),
        Setting::new("config-a", &[Config(Variant::A)]),
        Setting::new("config-b", &[Config(Variant::B)]),
        Setting::new(
            "fast",
            &[
                Downsample(24),
                MaxGaussians(1500),
                FeatureDim(32),
                RoundsPerWindowChange(1),
            ],
        ),
        Setting::new(
            "fast-b",
            &[Config(Variant::B), Downsample(24), MaxGaussians(1500)],
        ),
    ]
}

/// Settings `--settings` can name besides the default sweep: the skips toggled (also in
/// the `skips` table), a second pass per round, a dear combined point, Phi's hidden width
/// 128 and 64 (`mlp128`, `mlp64`) and bfloat16 matrix products (`bf16`, a CPU with
/// AMX-BF16 or AVX-512 BF16).
pub fn optional_settings() -> Vec<Setting> {
    use Knob::*;
    vec![
        Setting::new("mlp128", &[AppearanceHiddenWidth(128)]),
        Setting::new("mlp64", &[AppearanceHiddenWidth(64)]),
        Setting::new("bf16", &[MlpPrecision(MatmulPrecision::Bf16)]),
        Setting::new("frustum-off", &[CullOutsideFrustum(false)]),
        Setting::new("earlystop-off", &[EarlyTermination(false)]),
        Setting::new("masked", &[MaskedLoss(true)]),
        Setting::new(
            "masked-tiles-off",
            &[MaskedLoss(true), SkipMaskedBackgroundTiles(false)],
        ),
        Setting::new("passes2", &[PassesPerRound(2)]),
        Setting::new("eclipse-off", &[SkipEclipse(false)]),
        Setting::new("unlit-on", &[SkipUnlit(true)]),
        Setting::new("unchanged-off", &[SkipUnchangedWindow(false)]),
        Setting::new("mlpskip-off", &[SkipNoncontributingMlp(false)]),
        Setting::new("dear", &[Downsample(12), RoundsPerWindowChange(4)]),
    ]
}

/// The default or optional settings named in `names`, in the given order (the default
/// sweep when empty);
/// an unknown name is an error listing the known ones.
pub fn select_settings(names: &[String]) -> Result<Vec<Setting>, ExperimentError> {
    if names.is_empty() {
        return Ok(default_settings());
    }
    let mut all = default_settings();
    all.extend(optional_settings());
    names
        .iter()
        .map(|n| {
            all.iter().find(|s| &s.name == n).cloned().ok_or_else(|| {
                ExperimentError::Invalid(format!(
                    "unknown setting {n:?}; the settings are {}",
                    all.iter()
                        .map(|s| s.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
            })
        })
        .collect()
}

/// Knob values as text (`downsample=24 max_gaussians=1500`; `base` for none).
pub fn describe(knobs: &[Knob]) -> String {
    if knobs.is_empty() {
        return "base".into();
    }
    knobs
        .iter()
        .map(|k| match k {
            Knob::Downsample(v) => format!("downsample={v}"),
            Knob::MaxGaussians(v) => format!("max_gaussians={v}"),
            Knob::FeatureDim(v) => format!("feature_dim={v}"),
            Knob::EncodingFrequencies(v) => format!("encoding_frequencies={v}"),
            Knob::RoundsPerWindowChange(v) => format!("rounds_per_window_change={v}"),
            Knob::PassesPerRound(v) => format!("passes_per_round={v}"),
            Knob::Window(v) => format!("window={v}"),
            Knob::SkipEclipse(v) => format!("skip_eclipse={v}"),
            Knob::SkipUnlit(v) => format!("skip_unlit={v}"),
            Knob::SkipUnchangedWindow(v) => format!("skip_unchanged_window={v}"),
            Knob::SkipNoncontributingMlp(v) => format!("skip_noncontributing_in_mlp={v}"),
            Knob::MaskedLoss(v) => format!("masked_loss={v}"),
            Knob::CullOutsideFrustum(v) => format!("cull_outside_frustum={v}"),
            Knob::EarlyTermination(v) => format!("early_termination={v}"),
            Knob::SkipMaskedBackgroundTiles(v) => format!("skip_masked_background_tiles={v}"),
            Knob::AppearanceHiddenWidth(v) => format!("appearance_hidden_width={v}"),
            Knob::MlpPrecision(v) => format!("mlp_precision={}", precision_name(*v)),
            Knob::Config(v) => format!("config={}", v.name()),
        })
        .collect::<Vec<_>>()
        .join(" ")
}
