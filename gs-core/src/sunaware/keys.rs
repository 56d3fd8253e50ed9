//! The model's settings by name: the keys configuration files write ([`ModelKey`], set by
//! [`SunAwareConfig::set_key`]), the learning rates a file may replace ([`RateOverrides`],
//! a `[rates]` table) and the settings two configurations differ in
//! ([`SunAwareConfig::differences`]).
//!
//! The simulator's presets and the flight component's `[training]` section both set these
//! keys through [`SunAwareConfig::set_key`], and both read their rates table as one
//! [`RateOverrides`], so one string means one model in both: the text is parsed by the
//! model's own `FromStr` (one parser per setting), and the whole configuration is validated
//! after each key, so an error belongs to the key just set.
//!
//! Invariants: a refused key leaves the configuration unchanged; an unknown rate name is a
//! parse error naming it, and a named rate must be finite and >= 0; the Lambertian shadings,
//! Phi's inputs and the linear colour space are set only where the variant has Phi
//! (configuration (a) keeps the paper's form, so one file's shading applies to every
//! configuration it names);
//! `differences` lists every field (an exhaustive destructuring, so a new field fails to
//! compile until it is listed).

use super::config::{SunAwareConfig, SunAwareRates};
use super::error::SunAwareError;
use crate::nn::MatmulPrecision;
use serde::{Deserialize, Serialize};

/// A `[rates]` table: any of [`SunAwareRates`]' fields by name, each replacing gs-core's
/// default; an unnamed one keeps it. Unknown names are parse errors (serde names the key).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RateOverrides {
    pub position_init: Option<f32>,
    pub position_final: Option<f32>,
    pub sh_dc: Option<f32>,
    pub sh_rest: Option<f32>,
    pub opacity: Option<f32>,
    pub scale: Option<f32>,
    pub rotation: Option<f32>,
    pub feature: Option<f32>,
    pub shadow_latent: Option<f32>,
    pub appearance_mlp: Option<f32>,
    pub shadow_mlp: Option<f32>,
    pub normal: Option<f32>,
}

impl RateOverrides {
    /// `base` with the named rates replaced.
    pub fn applied_to(&self, base: SunAwareRates) -> SunAwareRates {
        let pick = |o: Option<f32>, d: f32| o.unwrap_or(d);
        SunAwareRates {
            position_init: pick(self.position_init, base.position_init),
            position_final: pick(self.position_final, base.position_final),
            sh_dc: pick(self.sh_dc, base.sh_dc),
            sh_rest: pick(self.sh_rest, base.sh_rest),
            opacity: pick(self.opacity, base.opacity),
            scale: pick(self.scale, base.scale),
            rotation: pick(self.rotation, base.rotation),
            feature: pick(self.feature, base.feature),
            shadow_latent: pick(self.shadow_latent, base.shadow_latent),
            appearance_mlp: pick(self.appearance_mlp, base.appearance_mlp),
            shadow_mlp: pick(self.shadow_mlp, base.shadow_mlp),
            normal: pick(self.normal, base.normal),
        }
    }

    /// The rates this table names, and `base`'s where it names none (a file's table over a
    /// default table, key by key).
    pub fn or(self, base: RateOverrides) -> RateOverrides {
        RateOverrides {
            position_init: self.position_init.or(base.position_init),
            position_final: self.position_final.or(base.position_final),
            sh_dc: self.sh_dc.or(base.sh_dc),
            sh_rest: self.sh_rest.or(base.sh_rest),
            opacity: self.opacity.or(base.opacity),
            scale: self.scale.or(base.scale),
            rotation: self.rotation.or(base.rotation),
            feature: self.feature.or(base.feature),
            shadow_latent: self.shadow_latent.or(base.shadow_latent),
            appearance_mlp: self.appearance_mlp.or(base.appearance_mlp),
            shadow_mlp: self.shadow_mlp.or(base.shadow_mlp),
            normal: self.normal.or(base.normal),
        }
    }

    /// Each rate by name (`SunAwareRates`' field), `None` where the table does not name it.
    pub fn named(&self) -> [(&'static str, Option<f32>); 12] {
        [
            ("position_init", self.position_init),
            ("position_final", self.position_final),
            ("sh_dc", self.sh_dc),
            ("sh_rest", self.sh_rest),
            ("opacity", self.opacity),
            ("scale", self.scale),
            ("rotation", self.rotation),
            ("feature", self.feature),
            ("shadow_latent", self.shadow_latent),
            ("appearance_mlp", self.appearance_mlp),
            ("shadow_mlp", self.shadow_mlp),
            ("normal", self.normal),
        ]
    }

    /// Replaces `model`'s named rates: a rate that is not finite and >= 0 (the model's own
    /// rule, `SunAwareConfig::validate`) is an error naming it (`rates.NAME`) and changes
    /// nothing. Only the rates are checked, so a bad other setting is never blamed on them.
    pub fn set_on(&self, model: &mut SunAwareConfig) -> Result<(), SunAwareError> {
        for (name, value) in self.named() {
            if let Some(v) = value.filter(|v| !(v.is_finite() && *v >= 0.0)) {
                return Err(SunAwareError::Config(format!(
                    "rates.{name} = {v} must be finite and >= 0"
                )));
            }
        }
        model.lr = self.applied_to(model.lr);
        Ok(())
    }
}

/// One model setting as a configuration file writes it: the key and its value.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ModelKey<'a> {
    /// Width of Phi's hidden layers.
    AppearanceHiddenWidth(usize),
    /// L of the positional encoding of the Sun and view vectors.
    EncodingFrequencies(usize),
    /// "f32" or "bf16".
    MlpPrecision(&'a str),
    /// `V' = shadow_gain * V * Psi`.
    ShadowGain(f32),
    /// "none", "lambert" or "lambert_learned".
    Shading(&'a str),
    /// `k_a` of the Lambertian shadings.
    ShadingAmbient(f32),
    /// "paper", "local" or "local_no_sun".
    AppearanceInputs(&'a str),
    /// "srgb" or "linear".
    ColourSpace(&'a str),
}

impl ModelKey<'_> {
    /// The key as files write it (the `SunAwareConfig` field it sets).
    pub fn name(&self) -> &'static str {
        match self {
            Self::AppearanceHiddenWidth(_) => "appearance_hidden_width",
            Self::EncodingFrequencies(_) => "encoding_frequencies",
            Self::MlpPrecision(_) => "mlp_precision",
            Self::ShadowGain(_) => "shadow_gain",
            Self::Shading(_) => "shading",
            Self::ShadingAmbient(_) => "shading_ambient",
            Self::AppearanceInputs(_) => "appearance_inputs",
            Self::ColourSpace(_) => "colour_space",
        }
    }

    /// Writes the value into `model` (text parsed, nothing validated yet).
    fn write(&self, model: &mut SunAwareConfig) -> Result<(), SunAwareError> {
        // Only Phi's colour is shaded and only Phi has inputs: (a) stays the paper's.
        let has_phi = model.variant.uses_appearance_mlp();
        match *self {
            Self::AppearanceHiddenWidth(width) => model.appearance_hidden_width = width,
            Self::EncodingFrequencies(l) => model.encoding_frequencies = l,
            Self::MlpPrecision(text) => model.mlp_precision = text.parse()?,
            Self::ShadowGain(gain) => model.shadow_gain = gain,
            Self::Shading(text) => {
                let shading = text.parse()?;
                if has_phi {
                    model.shading = shading;
                }
            }
            Self::ShadingAmbient(k_a) => model.shading_ambient = k_a,
            Self::AppearanceInputs(text) => {
                let inputs = text.parse()?;
                if has_phi {
                    model.appearance_inputs = inputs;
                }
            }
            Self::ColourSpace(text) => {
                let space = text.parse().map_err(SunAwareError::Config)?;
                if has_phi {
                    model.colour_space = space;
                }
            }
        }
        Ok(())
    }
}

impl std::str::FromStr for MatmulPrecision {
    type Err = SunAwareError;

    /// `f32` or `bf16` (exactly: the names the files and the benchmarks print).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "f32" => Ok(MatmulPrecision::F32),
            "bf16" => Ok(MatmulPrecision::Bf16),
            other => Err(SunAwareError::Config(format!(
                "mlp_precision {other:?} is not \"f32\" or \"bf16\""
            ))),
        }
    }
}

impl SunAwareConfig {
    /// Sets `key` and validates the whole configuration: a text the model's parser refuses,
    /// or a value that makes the configuration invalid, is an error and changes nothing.
    /// Keys that depend on each other are set in order (`shading` before
    /// `appearance_inputs`, which needs `"lambert_learned"`).
    pub fn set_key(&mut self, key: ModelKey<'_>) -> Result<(), SunAwareError> {
        let mut next = self.clone();
        key.write(&mut next)?;
        next.validate()?;
        *self = next;
        Ok(())
    }

    /// Every setting whose value differs between `self` and `other`, as
    /// `name: self's value, other's value` (Debug formatting); empty when they are equal.
    /// Names what a refused checkpoint's model differs in.
    pub fn differences(&self, other: &SunAwareConfig) -> Vec<String> {
        fields(self)
            .into_iter()
            .zip(fields(other))
            .filter(|((_, a), (_, b))| a != b)
            .map(|((name, a), (_, b))| format!("{name}: {a}, {b}"))
            .collect()
    }
}

/// Every field of `c` by name, its value in Debug formatting.
fn fields(c: &SunAwareConfig) -> Vec<(&'static str, String)> {
    // The list is written once: it destructures `c` with no `..`, so a field added to
    // SunAwareConfig fails to compile until it is listed here.
    macro_rules! named {
        ($($field:ident),* $(,)?) => {{
            let SunAwareConfig { $($field),* } = c;
            vec![$((stringify!($field), format!("{:?}", $field))),*]
        }};
    }
    named![
        variant,
        sh_degree,
        sh_degree_interval,
        feature_dim,
        shadow_latent_dim,
        encoding_frequencies,
        lambda_dssim,
        lambda_iso,
        iso_reduction,
        light,
        shadow_refinement,
        shadow_gain,
        shading,
        shading_ambient,
        appearance_inputs,
        colour_space,
        lr,
        densify,
        size_prune,
        max_gaussians,
        densify_from_step,
        background,
        near_m,
        seed,
        feature_init_std,
        skip_noncontributing_in_mlp,
        mlp_recompute_activations,
        reuse_step_buffers,
        appearance_hidden_width,
        mlp_precision,
        cull_outside_frustum,
        early_termination,
        skip_masked_background_tiles,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sunaware::{AppearanceInputs, Shading, Variant};

    #[test]
    fn rate_overrides_replace_only_the_named_rates_and_refuse_bad_ones() {
        let mut c = SunAwareConfig::for_variant(Variant::D);
        let base = c.lr;
        let rates = RateOverrides {
            opacity: Some(0.05),
            normal: Some(0.0),
            ..RateOverrides::default()
        };
        rates.set_on(&mut c).unwrap();
        assert_eq!((c.lr.opacity, c.lr.normal), (0.05, 0.0));
        let over = RateOverrides {
            opacity: Some(0.5),
            sh_dc: Some(0.01),
            ..RateOverrides::default()
        }
        .or(rates);
        assert_eq!(
            (over.opacity, over.sh_dc, over.normal, over.feature),
            (Some(0.5), Some(0.01), Some(0.0), None),
            "a table over a base: its own rates win, the base's fill the rest"
        );
        assert_eq!(
            SunAwareRates {
                opacity: base.opacity,
                normal: base.normal,
                ..c.lr
            },
            base,
            "unnamed rates keep the default"
        );
        let before = c.clone();
        for (bad, named) in [
            (
                RateOverrides {
                    sh_dc: Some(-0.01),
                    ..RateOverrides::default()
                },
                "sh_dc",
            ),
            (
                RateOverrides {
                    feature: Some(f32::NAN),
                    ..RateOverrides::default()
                },
                "feature",
            ),
            (
                RateOverrides {
                    shadow_mlp: Some(f32::INFINITY),
                    ..RateOverrides::default()
                },
                "shadow_mlp",
            ),
        ] {
            let e = bad.set_on(&mut c).unwrap_err().to_string();
            assert!(e.contains(&format!("rates.{named}")), "{e}");
            assert_eq!(c, before, "{named}: a refused rate changed the model");
        }
    }

    #[test]
    fn keys_parse_with_the_models_parsers_and_validate_one_at_a_time() {
        let mut c = SunAwareConfig::for_variant(Variant::D);
        for key in [
            ModelKey::ShadowGain(2.0),
            ModelKey::Shading("lambert_learned"),
            ModelKey::AppearanceInputs("local"),
            ModelKey::MlpPrecision("bf16"),
            ModelKey::AppearanceHiddenWidth(64),
            ModelKey::EncodingFrequencies(2),
            ModelKey::ShadingAmbient(0.2),
            ModelKey::ColourSpace("linear"),
        ] {
            c.set_key(key)
                .unwrap_or_else(|e| panic!("{}: {e}", key.name()));
        }
        assert_eq!(c.shadow_gain, 2.0);
        assert_eq!(c.shading, Shading::LambertLearned);
        assert_eq!(c.appearance_inputs, AppearanceInputs::Local);
        assert_eq!(c.mlp_precision, MatmulPrecision::Bf16);
        assert_eq!((c.appearance_hidden_width, c.encoding_frequencies), (64, 2));
        assert_eq!(c.shading_ambient, 0.2);
        assert_eq!(c.colour_space, crate::srgb::ColourSpace::Linear);
        // A refused key names itself and changes nothing.
        let before = c.clone();
        for (key, named) in [
            (ModelKey::ShadowGain(0.0), "shadow_gain"),
            (ModelKey::Shading("phong"), "shading"),
            (ModelKey::Shading("none"), "appearance_inputs"),
            (ModelKey::AppearanceInputs("global"), "appearance_inputs"),
            (ModelKey::MlpPrecision("f16"), "mlp_precision"),
            (
                ModelKey::AppearanceHiddenWidth(0),
                "appearance_hidden_width",
            ),
            (ModelKey::EncodingFrequencies(0), "encoding_frequencies"),
            (ModelKey::ShadingAmbient(1.0), "shading_ambient"),
            (ModelKey::ColourSpace("gamma"), "colour_space"),
        ] {
            let e = c.set_key(key).unwrap_err().to_string();
            assert!(e.contains(named), "{key:?}: {e}");
            assert_eq!(c, before, "{key:?} changed the configuration");
        }
    }

    #[test]
    fn configuration_a_parses_the_shading_keys_but_keeps_the_papers_form() {
        let mut a = SunAwareConfig::for_variant(Variant::A);
        a.set_key(ModelKey::Shading("lambert_learned")).unwrap();
        a.set_key(ModelKey::AppearanceInputs("local")).unwrap();
        assert_eq!(a, SunAwareConfig::for_variant(Variant::A));
        assert!(a.set_key(ModelKey::Shading("phong")).is_err());
        a.set_key(ModelKey::ColourSpace("linear")).unwrap();
        assert_eq!(a, SunAwareConfig::for_variant(Variant::A));
        assert!(a.set_key(ModelKey::ColourSpace("gamma")).is_err());
    }

    #[test]
    fn differences_name_each_differing_setting() {
        let paper = SunAwareConfig::default();
        assert!(paper.differences(&paper.clone()).is_empty());
        let demo = SunAwareConfig {
            shading: Shading::LambertLearned,
            shadow_gain: 2.0,
            ..paper.clone()
        };
        assert_eq!(
            paper.differences(&demo),
            ["shadow_gain: 1.0, 2.0", "shading: None, LambertLearned"]
        );
    }
}
