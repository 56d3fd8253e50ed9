//! Geometric regularisers: the isotropic scale loss `L_iso` of the paper (Eq. 6).
//!
//! `L_iso = sum_i || s_i - mean(s_i) 1 ||_1` over the activated scales `s_i = exp(log_scale_i)`
//! (three per Gaussian), weighted by `lambda_iso`. It pulls each Gaussian towards a sphere.
//!
//! Normalisation ([`IsoReduction`]): the paper writes a plain sum over Gaussians
//! ([`IsoReduction::Sum`]), so with a fixed `lambda_iso` its pull grows with the number of
//! Gaussians. MonoGS (which the paper cites) takes the mean over the `N x 3` entries and
//! multiplies by 10 ([`IsoReduction::MeanOverEntries`] with `lambda_iso = 10`), which is the
//! sum scaled by `10 / (3N)`: its strength per Gaussian does not change as densification
//! grows the model.
//!
//! The gradient is taken w.r.t. the log-scales (the stored parameters). The absolute value
//! uses the subgradient `sign(0) = 0`, so an exactly isotropic Gaussian gets no gradient.
//! Sums run in f64 and in index order: deterministic. Non-finite log-scales or a
//! non-finite result are errors, and nothing is written then.

/// Error from a regulariser.
#[derive(Debug, Clone, PartialEq)]
pub enum RegularizerError {
    /// Log-scales or gradient buffer had the wrong length.
    Shape {
        what: &'static str,
        expected: usize,
        got: usize,
    },
    /// A log-scale, the weight, or the result was NaN or infinite.
    NonFinite { what: &'static str, index: usize },
}

impl std::fmt::Display for RegularizerError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            RegularizerError::Shape {
                what,
                expected,
                got,
            } => write!(f, "{what}: expected {expected} values, got {got}"),
            RegularizerError::NonFinite { what, index } => {
                write!(f, "{what}: non-finite value at index {index}")
            }
        }
    }
}

impl std::error::Error for RegularizerError {}

/// How per-Gaussian terms are combined.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IsoReduction {
    /// Sum over Gaussians, as written in the paper's Eq. 6.
    Sum,
    /// Mean over the `3N` scale entries (MonoGS; use `lambda_iso = 10` to match it).
    MeanOverEntries,
}

/// The weighted isotropic scale loss `lambda_iso * L_iso`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IsotropicLoss {
    lambda_iso: f32,
    reduction: IsoReduction,
}

impl IsotropicLoss {
    /// `lambda_iso` must be finite and non-negative.
    pub fn new(lambda_iso: f32, reduction: IsoReduction) -> Result<Self, RegularizerError> {
        if !lambda_iso.is_finite() || lambda_iso < 0.0 {
            return Err(RegularizerError::NonFinite {
                what: "lambda_iso (must be finite and >= 0)",
                index: 0,
            });
        }
        Ok(Self {
            lambda_iso,
            reduction,
        })
    }

    pub fn lambda_iso(&self) -> f32 {
        self.lambda_iso
    }

    pub fn reduction(&self) -> IsoReduction {
        self.reduction
    }

    /// Returns `lambda_iso * L_iso` for `log_scales` (`N x 3`, natural log) and adds its
    /// gradient w.r.t. the log-scales into `d_log_scales` (same length).
    pub fn value_and_grad(
        &self,
        log_scales: &[f32],
        d_log_scales: &mut [f32],
    ) -> Result<f32, RegularizerError> {
        if !log_scales.len().is_multiple_of(3) {
            return Err(RegularizerError::Shape {
                what: "log-scales (3 per Gaussian)",
                expected: log_scales.len() / 3 * 3,
                got: log_scales.len(),
            });
        }
        if d_log_scales.len() != log_scales.len() {
            return Err(RegularizerError::Shape {
                what: "log-scale gradient",
                expected: log_scales.len(),
                got: d_log_scales.len(),
            });
        }
        if let Some(index) = log_scales.iter().position(|v| !v.is_finite()) {
            return Err(RegularizerError::NonFinite {
                what: "log-scales",
                index,
            });
        }
        let n = log_scales.len() / 3;
        if n == 0 {
            return Ok(0.0);
        }
        let factor = self.lambda_iso as f64
            * match self.reduction {
                IsoReduction::Sum => 1.0,
                IsoReduction::MeanOverEntries => 1.0 / (3 * n) as f64,
            };
        let mut total = 0.0f64;
        let mut grads = vec![0.0f32; log_scales.len()];
        for (u, g) in log_scales.chunks_exact(3).zip(grads.chunks_exact_mut(3)) {
            let s = [
                (u[0] as f64).exp(),
                (u[1] as f64).exp(),
                (u[2] as f64).exp(),
            ];
            let mean = (s[0] + s[1] + s[2]) / 3.0;
            let sign = [
                sign_or_zero(s[0] - mean),
                sign_or_zero(s[1] - mean),
                sign_or_zero(s[2] - mean),
            ];
            total += (s[0] - mean).abs() + (s[1] - mean).abs() + (s[2] - mean).abs();
            let sign_mean = (sign[0] + sign[1] + sign[2]) / 3.0;
            for a in 0..3 {
                // d/ds_a sum_b |s_b - m| = sign_a - mean(sign); then ds_a/du_a = s_a.
                g[a] = (factor * s[a] * (sign[a] - sign_mean)) as f32;
            }
        }
        let value = (factor * total) as f32;
        if !value.is_finite() {
            return Err(RegularizerError::NonFinite {
                what: "isotropic loss (scales overflow)",
                index: 0,
            });
        }
        if let Some(index) = grads.iter().position(|v| !v.is_finite()) {
            return Err(RegularizerError::NonFinite {
                what: "isotropic loss gradient",
                index,
            });
        }
        for (d, g) in d_log_scales.iter_mut().zip(&grads) {
            *d += g;
        }
        Ok(value)
    }
}

fn sign_or_zero(x: f64) -> f64 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn value_matches_hand_computation_and_reductions_differ_by_3n() {
        // Scales 1, 2, 6: mean 3, L1 deviation 2 + 1 + 3 = 6. Second Gaussian isotropic.
        let log_scales = [0.0f32, 2.0f32.ln(), 6.0f32.ln(), 0.5, 0.5, 0.5];
        let mut grad = vec![0.0f32; 6];
        let sum = IsotropicLoss::new(1.0, IsoReduction::Sum)
            .unwrap()
            .value_and_grad(&log_scales, &mut grad)
            .unwrap();
        assert!((sum - 6.0).abs() < 1e-5, "{sum}");
        assert_eq!(&grad[3..], &[0.0, 0.0, 0.0]);
        let mut grad_mean = vec![0.0f32; 6];
        let monogs = IsotropicLoss::new(10.0, IsoReduction::MeanOverEntries)
            .unwrap()
            .value_and_grad(&log_scales, &mut grad_mean)
            .unwrap();
        assert!((monogs - 10.0 * 6.0 / 6.0).abs() < 1e-5, "{monogs}");
        for (a, b) in grad.iter().zip(&grad_mean) {
            assert!((b - a * 10.0 / 6.0).abs() < 1e-5);
        }
    }

    #[test]
    fn gradient_accumulates_and_errors_leave_buffer_untouched() {
        let loss = IsotropicLoss::new(0.5, IsoReduction::Sum).unwrap();
        let log_scales = [0.1f32, -0.4, 0.9];
        let mut grad = vec![1.0f32; 3];
        loss.value_and_grad(&log_scales, &mut grad).unwrap();
        let mut fresh = vec![0.0f32; 3];
        loss.value_and_grad(&log_scales, &mut fresh).unwrap();
        for (a, b) in grad.iter().zip(&fresh) {
            assert_eq!(*a, 1.0 + b);
        }
        let mut untouched = vec![0.0f32; 3];
        assert!(matches!(
            loss.value_and_grad(&[0.0, f32::NAN, 0.0], &mut untouched),
            Err(RegularizerError::NonFinite { index: 1, .. })
        ));
        assert!(matches!(
            loss.value_and_grad(&[0.0, 200.0, 0.0], &mut untouched),
            Err(RegularizerError::NonFinite { .. })
        ));
        assert!(matches!(
            loss.value_and_grad(&[0.0; 4], &mut [0.0; 4]),
            Err(RegularizerError::Shape { .. })
        ));
        assert!(matches!(
            loss.value_and_grad(&[0.0; 3], &mut [0.0; 6]),
            Err(RegularizerError::Shape { .. })
        ));
        assert_eq!(untouched, vec![0.0; 3]);
        assert!(IsotropicLoss::new(-1.0, IsoReduction::Sum).is_err());
        assert!(IsotropicLoss::new(f32::NAN, IsoReduction::Sum).is_err());
        assert_eq!(loss.value_and_grad(&[], &mut []), Ok(0.0));
    }
}
