//! The sRGB transfer function (IEC 61966-2-1), and the colour space the model blends in.
//!
//! A camera (and the simulator's ray tracer) sums light linearly (over the pixel's area,
//! over a Gaussian's footprint, over the surfaces it sees) and encodes the sum to sRGB once
//! per pixel. A model that blends sRGB values instead multiplies encoded values: a
//! Lambertian `cos` or a shadow fraction applied to an sRGB colour is too dark everywhere
//! but at 0 and 1 (the encoding of `0.5 x` is about `0.73` times the encoding of `x`). With
//! [`ColourSpace::Linear`] the model's colours, its shadow channel and the blend are linear
//! radiance, and [`encode`] turns each pixel of the blended image into sRGB, as the camera
//! does (`SunAwareConfig::colour_space`; configurations b-d, whose colour is Phi's sigmoid:
//! (a)'s SH colour is clamped at zero with no gradient, where dark linear colours sit).
//!
//! Invariants: [`encode`] is the standard's piecewise curve, continuous at its knee,
//! extended past 1 by the same power law (a training render may overshoot; the 8-bit
//! conversion clamps) and linear below 0; [`encode_slope`] is its derivative (finite
//! everywhere, 12.92 on the linear segment). Both are plain `f32` arithmetic with `powf`:
//! the same bits on every run.

use std::str::FromStr;

/// Where the linear segment of the encoding ends (linear value).
pub const LINEAR_KNEE: f32 = 0.003_130_8;

/// sRGB value (0..1 for 0..1) of a linear value.
#[inline]
pub fn encode(linear: f32) -> f32 {
    if linear <= LINEAR_KNEE {
        12.92 * linear
    } else {
        1.055 * linear.powf(1.0 / 2.4) - 0.055
    }
}

/// `d encode / d linear` at `linear`.
#[inline]
pub fn encode_slope(linear: f32) -> f32 {
    if linear <= LINEAR_KNEE {
        12.92
    } else {
        (1.055 / 2.4) * linear.powf(1.0 / 2.4 - 1.0)
    }
}

/// What the model's colours and its blend are (`SunAwareConfig::colour_space`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum ColourSpace {
    /// The paper's (and 3DGS's) form: colours are sRGB values and the blended image is
    /// compared with the camera's image as it is.
    #[default]
    Srgb,
    /// Colours, the shadow channel and the blend are linear radiance; each pixel of the
    /// blended `RGB * S` is sRGB-encoded ([`encode`]) before the loss, like the camera's.
    Linear,
}

impl ColourSpace {
    pub const ALL: [ColourSpace; 2] = [ColourSpace::Srgb, ColourSpace::Linear];

    pub fn name(self) -> &'static str {
        match self {
            ColourSpace::Srgb => "srgb",
            ColourSpace::Linear => "linear",
        }
    }

    pub fn code(self) -> u8 {
        self as u8
    }

    pub fn from_code(code: u8) -> Option<Self> {
        Self::ALL.get(code as usize).copied()
    }

    /// An sRGB value of a colour this space stores (for viewers, which know sRGB).
    pub fn to_srgb(self, value: f32) -> f32 {
        match self {
            ColourSpace::Srgb => value,
            ColourSpace::Linear => encode(value),
        }
    }
}

impl std::fmt::Display for ColourSpace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for ColourSpace {
    type Err = String;

    /// `srgb` or `linear` (either case).
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s.trim().to_ascii_lowercase().as_str() {
            "srgb" => Ok(ColourSpace::Srgb),
            "linear" => Ok(ColourSpace::Linear),
            other => Err(format!(
                "unknown colour_space {other:?}: expected \"srgb\" or \"linear\""
            )),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The standard's inverse of [`encode`].
    fn decode(encoded: f32) -> f32 {
        if encoded <= 0.040_45 {
            encoded / 12.92
        } else {
            ((encoded + 0.055) / 1.055).powf(2.4)
        }
    }

    #[test]
    fn encode_matches_the_standard_at_its_reference_points() {
        // IEC 61966-2-1: 0 -> 0, 1 -> 1, the knee continuous, 0.5 -> 0.7354 (188 / 255).
        assert_eq!(encode(0.0), 0.0);
        assert!((encode(1.0) - 1.0).abs() < 1e-6);
        let below = 12.92 * LINEAR_KNEE;
        let above = 1.055 * LINEAR_KNEE.powf(1.0 / 2.4) - 0.055;
        assert!((below - above).abs() < 1e-6, "{below} {above}");
        assert!((encode(0.5) - 0.735_357).abs() < 1e-5, "{}", encode(0.5));
        assert!((encode(0.5) * 255.0).round() == 188.0);
        assert!(encode(1.2) > 1.0, "extended past 1, not clamped");
        assert!(encode(-0.1) < 0.0, "linear below 0");
    }

    #[test]
    fn slope_agrees_with_finite_differences() {
        for &x in &[-0.2f32, 0.0, 0.002, 0.01, 0.05, 0.2, 0.5, 0.9, 1.0, 1.5] {
            let h = 1e-3 * x.abs().max(1e-2);
            let fd = (encode(x + h) as f64 - encode(x - h) as f64) / (2.0 * h as f64);
            let s = encode_slope(x) as f64;
            assert!(
                (fd - s).abs() <= 2e-3 * s.abs().max(1.0),
                "x {x}: slope {s}, finite difference {fd}"
            );
        }
    }

    #[test]
    fn decode_inverts_encode() {
        for i in 0..=1000 {
            let x = i as f32 / 1000.0;
            let back = decode(encode(x));
            assert!((back - x).abs() <= 2e-6 + 1e-5 * x, "{x} -> {back}");
        }
        assert_eq!(ColourSpace::Srgb.to_srgb(0.3), 0.3);
        assert_eq!(ColourSpace::Linear.to_srgb(0.3), encode(0.3));
    }

    #[test]
    fn names_and_codes_round_trip() {
        for space in ColourSpace::ALL {
            assert_eq!(space.name().parse::<ColourSpace>(), Ok(space));
            assert_eq!(ColourSpace::from_code(space.code()), Some(space));
        }
        assert_eq!("LINEAR".parse::<ColourSpace>(), Ok(ColourSpace::Linear));
        assert!(ColourSpace::from_code(2).is_none());
        let err = "gamma".parse::<ColourSpace>().unwrap_err();
        assert!(err.contains("gamma") && err.contains("linear"), "{err}");
    }
}
