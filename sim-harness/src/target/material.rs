//! Surface materials of target spacecraft: metallic-roughness parameters plus two procedural
//! details (MLI crinkle, solar-cell grid) that the ray tracer evaluates per hit point.
//!
//! Invariants: colours are linear RGB in [0, 1]; `roughness` is the perceptual roughness in
//! [0.02, 1] (GGX alpha = roughness^2); `metallic` in [0, 1]; `crinkle_amplitude` >= 0 and
//! `crinkle_scale_m` > 0; `cell_pitch_m` is 0 (no grid) or > 0. `Material::sanitized` enforces them.

/// One surface material (metallic-roughness model).
#[derive(Clone, Debug, PartialEq)]
pub struct Material {
    pub name: String,
    /// Diffuse albedo for dielectrics, specular colour (F0) for metals; linear RGB.
    pub base_color_linear: [f32; 3],
    pub metallic: f32,
    pub roughness: f32,
    /// Strength of the procedural normal perturbation (tangent tilt, roughly radians); 0 = flat.
    pub crinkle_amplitude: f32,
    /// Spatial scale of the crinkles in metres.
    pub crinkle_scale_m: f32,
    /// Solar-cell pitch in metres (interconnect grid lines drawn at this pitch); 0 = none.
    pub cell_pitch_m: f32,
}

/// Constructor of a preset material.
type PresetMaker = fn() -> Material;

/// Lowest roughness allowed: a perfectly smooth GGX lobe is a delta the tracer cannot sample.
pub const MIN_ROUGHNESS: f32 = 0.02;

impl Material {
    /// Gold-coloured multi-layer insulation (Kapton outer layer): metallic, crinkled.
    pub fn gold_mli() -> Material {
        Material {
            name: "gold_mli".into(),
            base_color_linear: [0.95, 0.64, 0.26],
            metallic: 1.0,
            roughness: 0.35,
            crinkle_amplitude: 0.5,
            crinkle_scale_m: 0.06,
            cell_pitch_m: 0.0,
        }
    }

    /// Silver / aluminised MLI: metallic, crinkled.
    pub(crate) fn silver_mli() -> Material {
        Material {
            name: "silver_mli".into(),
            base_color_linear: [0.90, 0.90, 0.88],
            metallic: 1.0,
            roughness: 0.32,
            crinkle_amplitude: 0.5,
            crinkle_scale_m: 0.06,
            cell_pitch_m: 0.0,
        }
    }

    /// Solar cells: dark blue glossy dielectric with a cell grid.
    pub(crate) fn solar_cell() -> Material {
        Material {
            name: "solar_cell".into(),
            // Cover glass over dark blue cells: low albedo, but a broad enough glossy lobe that
            // arrays stay visible away from the mirror direction, as in flight imagery.
            base_color_linear: [0.035, 0.05, 0.14],
            metallic: 0.0,
            roughness: 0.22,
            crinkle_amplitude: 0.0,
            crinkle_scale_m: 1.0,
            cell_pitch_m: 0.16,
        }
    }

    /// White thermal paint: bright, fairly rough dielectric.
    pub fn white_paint() -> Material {
        Material {
            name: "white_paint".into(),
            base_color_linear: [0.80, 0.80, 0.78],
            metallic: 0.0,
            roughness: 0.6,
            crinkle_amplitude: 0.0,
            crinkle_scale_m: 1.0,
            cell_pitch_m: 0.0,
        }
    }

    /// Bare (slightly brushed) aluminium.
    pub(crate) fn aluminium() -> Material {
        Material {
            name: "aluminium".into(),
            base_color_linear: [0.91, 0.92, 0.92],
            metallic: 1.0,
            roughness: 0.35,
            crinkle_amplitude: 0.0,
            crinkle_scale_m: 1.0,
            cell_pitch_m: 0.0,
        }
    }

    /// Dark grey (RTG fins, nozzles, black paint).
    pub(crate) fn dark_grey() -> Material {
        Material {
            name: "dark_grey".into(),
            base_color_linear: [0.06, 0.06, 0.06],
            metallic: 0.0,
            roughness: 0.5,
            crinkle_amplitude: 0.0,
            crinkle_scale_m: 1.0,
            cell_pitch_m: 0.0,
        }
    }

    /// Fallback for meshes without materials: a neutral light-grey dielectric.
    pub fn default_grey() -> Material {
        Material {
            name: "default".into(),
            base_color_linear: [0.5, 0.5, 0.5],
            metallic: 0.0,
            roughness: 0.5,
            crinkle_amplitude: 0.0,
            crinkle_scale_m: 1.0,
            cell_pitch_m: 0.0,
        }
    }

    /// The preset whose name (or a known alias) occurs in `name`, if any ("Gold_MLI_2" -> gold MLI).
    pub(crate) fn preset_for_name(name: &str) -> Option<Material> {
        let lower = name.to_ascii_lowercase();
        let presets: [(&[&str], PresetMaker); 5] = [
            (&["gold", "kapton"], Material::gold_mli),
            (&["silver", "mli"], Material::silver_mli),
            (&["solar", "cell"], Material::solar_cell),
            (&["paint", "white"], Material::white_paint),
            (&["alu", "metal"], Material::aluminium),
        ];
        presets
            .iter()
            .find(|(keys, _)| keys.iter().any(|k| lower.contains(k)))
            .map(|(_, make)| {
                let mut m = make();
                m.name = name.to_string();
                m
            })
    }

    /// Clamps every parameter into its documented range; non-finite values take safe defaults.
    pub(crate) fn sanitized(mut self) -> Material {
        let clean = |v: f32, lo: f32, hi: f32, fallback: f32| {
            if v.is_finite() {
                v.clamp(lo, hi)
            } else {
                fallback
            }
        };
        for c in &mut self.base_color_linear {
            *c = clean(*c, 0.0, 1.0, 0.5);
        }
        self.metallic = clean(self.metallic, 0.0, 1.0, 0.0);
        self.roughness = clean(self.roughness, MIN_ROUGHNESS, 1.0, 0.5);
        self.crinkle_amplitude = clean(self.crinkle_amplitude, 0.0, 2.0, 0.0);
        self.crinkle_scale_m = clean(self.crinkle_scale_m, 1e-4, 1e4, 1.0);
        self.cell_pitch_m = clean(self.cell_pitch_m, 0.0, 1e4, 0.0);
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_match_names_and_sanitize_clamps() {
        assert_eq!(
            Material::preset_for_name("Gold_Foil").unwrap().metallic,
            1.0
        );
        assert_eq!(
            Material::preset_for_name("SolarPanel")
                .unwrap()
                .cell_pitch_m,
            0.16
        );
        assert!(Material::preset_for_name("rubber").is_none());
        let m = Material {
            roughness: 0.0,
            metallic: f32::NAN,
            base_color_linear: [2.0, -1.0, f32::INFINITY],
            ..Material::default_grey()
        }
        .sanitized();
        assert_eq!(m.roughness, MIN_ROUGHNESS);
        assert_eq!(m.metallic, 0.0);
        assert_eq!(m.base_color_linear, [1.0, 0.0, 0.5]);
    }
}
