//! NeRF positional encoding `gamma_L` and its derivative.
//!
//! For a vector `p` of `D` components and `L` frequencies the output has `D * 2L` values,
//! component-major, then frequency, then sine before cosine (the paper's Eq. for
//! `gamma_L(p)` applied to each component in turn):
//!
//! `[sin(2^0 pi p_0), cos(2^0 pi p_0), ..., sin(2^{L-1} pi p_0), cos(2^{L-1} pi p_0),
//!   sin(2^0 pi p_1), ...]`
//!
//! i.e. `out[c * 2L + 2k] = sin(2^k pi p_c)` and `out[c * 2L + 2k + 1] = cos(2^k pi p_c)`.
//! The raw `p` is not appended (the paper's definition has only the sinusoids).
//! The lowest frequency has period 2, so inputs should lie in a range shorter than 2
//! (unit vectors in [-1, 1] alias only at the two poles of each axis, which is harmless).

use super::error::{check_finite, check_len, NnError};

/// Most frequencies accepted: `2^15 pi` already resolves 1e-4 of the input range.
pub const MAX_FREQUENCIES: usize = 16;

/// The encoding `gamma_L` with a fixed number of frequencies `L`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PositionalEncoding {
    num_frequencies: usize,
}

impl Default for PositionalEncoding {
    /// `L = 4`, as in DESIGN.md.
    fn default() -> Self {
        Self { num_frequencies: 4 }
    }
}

impl PositionalEncoding {
    /// `L` in `1..=MAX_FREQUENCIES`.
    pub fn new(num_frequencies: usize) -> Result<Self, NnError> {
        if (1..=MAX_FREQUENCIES).contains(&num_frequencies) {
            Ok(Self { num_frequencies })
        } else {
            Err(NnError::Config(format!(
                "positional encoding needs 1..={MAX_FREQUENCIES} frequencies, got {num_frequencies}"
            )))
        }
    }

    pub fn num_frequencies(&self) -> usize {
        self.num_frequencies
    }

    /// Output width for an input of `dim` components: `dim * 2L`.
    pub fn width(&self, dim: usize) -> usize {
        dim * 2 * self.num_frequencies
    }

    /// Angular frequency of band `k`: `2^k pi`.
    fn omega(k: usize) -> f32 {
        std::f32::consts::PI * (1u32 << k) as f32
    }

    /// Writes `gamma_L(p)` into `out` (`out.len() == width(p.len())`). Unchecked for speed:
    /// the callers in this module validate finiteness once per batch.
    pub(crate) fn encode_unchecked(&self, p: &[f32], out: &mut [f32]) {
        let two_l = 2 * self.num_frequencies;
        for (c, &pc) in p.iter().enumerate() {
            let row = &mut out[c * two_l..(c + 1) * two_l];
            for k in 0..self.num_frequencies {
                let (s, co) = (Self::omega(k) * pc).sin_cos();
                row[2 * k] = s;
                row[2 * k + 1] = co;
            }
        }
    }

    /// Writes `gamma_L(p)` into `out`, checking sizes and finiteness.
    pub fn encode(&self, p: &[f32], out: &mut [f32]) -> Result<(), NnError> {
        check_len("encoding output", out.len(), self.width(p.len()))?;
        check_finite("encoding input", p)?;
        self.encode_unchecked(p, out);
        Ok(())
    }

    /// Adds `d_p += (d gamma / d p)^T d_out` (chain rule through the encoding).
    pub(crate) fn backward_unchecked(&self, p: &[f32], d_out: &[f32], d_p: &mut [f32]) {
        let two_l = 2 * self.num_frequencies;
        for (c, (&pc, dpc)) in p.iter().zip(d_p.iter_mut()).enumerate() {
            let row = &d_out[c * two_l..(c + 1) * two_l];
            let mut acc = 0.0f32;
            for k in 0..self.num_frequencies {
                let w = Self::omega(k);
                let (s, co) = (w * pc).sin_cos();
                acc += w * (co * row[2 * k] - s * row[2 * k + 1]);
            }
            *dpc += acc;
        }
    }

    /// [`Self::backward_unchecked`] with the sines and cosines read from `code`, the output
    /// of [`Self::encode_unchecked`] for the same `p` (the input assembly keeps it). Same
    /// bits as recomputing them: the same arithmetic on the same values.
    pub(crate) fn backward_from_code(&self, code: &[f32], d_out: &[f32], d_p: &mut [f32]) {
        let two_l = 2 * self.num_frequencies;
        for (c, dpc) in d_p.iter_mut().enumerate() {
            let row = &d_out[c * two_l..(c + 1) * two_l];
            let sin_cos = &code[c * two_l..(c + 1) * two_l];
            let mut acc = 0.0f32;
            for k in 0..self.num_frequencies {
                let w = Self::omega(k);
                let (s, co) = (sin_cos[2 * k], sin_cos[2 * k + 1]);
                acc += w * (co * row[2 * k] - s * row[2 * k + 1]);
            }
            *dpc += acc;
        }
    }

    /// Adds the encoding's vector-Jacobian product to `d_p`, checking sizes and finiteness.
    pub fn backward(&self, p: &[f32], d_out: &[f32], d_p: &mut [f32]) -> Result<(), NnError> {
        check_len("encoding gradient output", d_out.len(), self.width(p.len()))?;
        check_len("encoding input gradient", d_p.len(), p.len())?;
        check_finite("encoding input", p)?;
        check_finite("encoding output gradient", d_out)?;
        self.backward_unchecked(p, d_out, d_p);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_is_component_major_then_frequency_then_sin_cos() {
        let enc = PositionalEncoding::new(3).unwrap();
        let p = [0.1f32, -0.7];
        let mut out = vec![0.0; enc.width(2)];
        enc.encode(&p, &mut out).unwrap();
        for (c, &pc) in p.iter().enumerate() {
            for k in 0..3 {
                let arg = std::f64::consts::PI * (1u32 << k) as f64 * pc as f64;
                assert!((out[c * 6 + 2 * k] as f64 - arg.sin()).abs() < 1e-6);
                assert!((out[c * 6 + 2 * k + 1] as f64 - arg.cos()).abs() < 1e-6);
            }
        }
    }

    #[test]
    fn backward_matches_central_differences() {
        let enc = PositionalEncoding::new(4).unwrap();
        let p = [0.31f32, -0.52, 0.83];
        let d_out: Vec<f32> = (0..enc.width(3))
            .map(|i| ((i * 7 % 11) as f32 - 5.0) / 5.0)
            .collect();
        let mut d_p = [0.0f32; 3];
        enc.backward(&p, &d_out, &mut d_p).unwrap();
        // f64 reference of the scalar objective sum(d_out * gamma(p)).
        let objective = |q: &[f64]| -> f64 {
            let mut total = 0.0;
            for (c, &qc) in q.iter().enumerate() {
                for k in 0..4 {
                    let arg = std::f64::consts::PI * (1u32 << k) as f64 * qc;
                    total += d_out[c * 8 + 2 * k] as f64 * arg.sin()
                        + d_out[c * 8 + 2 * k + 1] as f64 * arg.cos();
                }
            }
            total
        };
        let h = 1e-6;
        for c in 0..3 {
            let mut plus: Vec<f64> = p.iter().map(|&v| v as f64).collect();
            let mut minus = plus.clone();
            plus[c] += h;
            minus[c] -= h;
            let numeric = (objective(&plus) - objective(&minus)) / (2.0 * h);
            assert!(
                (d_p[c] as f64 - numeric).abs() <= 1e-4 * (1.0 + numeric.abs()),
                "component {c}: analytic {} numeric {numeric}",
                d_p[c]
            );
        }
    }

    #[test]
    fn bad_sizes_and_nan_are_errors() {
        assert!(PositionalEncoding::new(0).is_err());
        assert!(PositionalEncoding::new(MAX_FREQUENCIES + 1).is_err());
        let enc = PositionalEncoding::default();
        let mut out = vec![0.0; 5];
        assert!(matches!(
            enc.encode(&[0.0; 3], &mut out),
            Err(NnError::Shape { .. })
        ));
        let mut out = vec![0.0; enc.width(3)];
        assert_eq!(
            enc.encode(&[0.0, f32::NAN, 0.0], &mut out),
            Err(NnError::NonFinite {
                what: "encoding input",
                index: 1
            })
        );
    }
}
