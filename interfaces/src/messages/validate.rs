//! Field checks shared by the messages: finite numbers, unit vectors and quaternions within a
//! tolerance, non-negative uncertainties, image buffer sizes. Each returns a typed error that
//! names the offending field, so a receiver can count it and a command can be refused with
//! VALIDATION_ERROR.

use core::fmt;

/// Allowed | |v| - 1 | for unit vectors and quaternions on the bus.
pub const UNIT_NORM_TOLERANCE: f32 = 1e-3;

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ValidationError {
    NonFinite {
        field: &'static str,
    },
    NotUnitNorm {
        field: &'static str,
        norm: f32,
    },
    Negative {
        field: &'static str,
    },
    ZeroSize {
        field: &'static str,
    },
    SizeMismatch {
        field: &'static str,
        expected: usize,
        actual: usize,
    },
    OutOfRange {
        field: &'static str,
    },
}

impl core::error::Error for ValidationError {}

impl fmt::Display for ValidationError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ValidationError::NonFinite { field } => write!(f, "{field}: not finite"),
            ValidationError::NotUnitNorm { field, norm } => {
                write!(
                    f,
                    "{field}: norm {norm} is not 1 within {UNIT_NORM_TOLERANCE}"
                )
            }
            ValidationError::Negative { field } => write!(f, "{field}: negative"),
            ValidationError::ZeroSize { field } => write!(f, "{field}: zero size"),
            ValidationError::SizeMismatch {
                field,
                expected,
                actual,
            } => write!(f, "{field}: {actual} bytes, expected {expected}"),
            ValidationError::OutOfRange { field } => write!(f, "{field}: out of range"),
        }
    }
}

/// Every component finite.
pub fn check_finite(field: &'static str, values: &[f32]) -> Result<(), ValidationError> {
    if values.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(ValidationError::NonFinite { field })
    }
}

/// Finite and Euclidean norm within [`UNIT_NORM_TOLERANCE`] of 1.
pub fn check_unit_norm(field: &'static str, values: &[f32]) -> Result<(), ValidationError> {
    check_finite(field, values)?;
    let norm_sq: f64 = values.iter().map(|&v| f64::from(v) * f64::from(v)).sum();
    // sqrt without std: one Newton step from the f32 estimate is exact enough for a tolerance test.
    let norm = sqrt_f64(norm_sq) as f32;
    if (norm - 1.0).abs() <= UNIT_NORM_TOLERANCE {
        Ok(())
    } else {
        Err(ValidationError::NotUnitNorm { field, norm })
    }
}

/// Finite and >= 0.
pub fn check_non_negative(field: &'static str, value: f32) -> Result<(), ValidationError> {
    check_finite(field, &[value])?;
    if value >= 0.0 {
        Ok(())
    } else {
        Err(ValidationError::Negative { field })
    }
}

/// `actual == expected` bytes.
pub fn check_len(
    field: &'static str,
    expected: usize,
    actual: usize,
) -> Result<(), ValidationError> {
    if expected == actual {
        Ok(())
    } else {
        Err(ValidationError::SizeMismatch {
            field,
            expected,
            actual,
        })
    }
}

/// Square root for non-negative finite input by Newton iteration (core has no sqrt in no_std).
fn sqrt_f64(x: f64) -> f64 {
    if x <= 0.0 || !x.is_finite() {
        return if x == 0.0 { 0.0 } else { f64::NAN };
    }
    // Start from the exponent-halved bit pattern, then Newton converges quadratically.
    let mut y = f64::from_bits((x.to_bits() >> 1) + (1023u64 << 51));
    for _ in 0..6 {
        y = 0.5 * (y + x / y);
    }
    y
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sqrt_matches_std_over_wide_range() {
        extern crate std;
        for &x in &[1e-30, 1e-6, 0.25, 1.0, 2.0, 3.999, 1e6, 1e30] {
            let ours = sqrt_f64(x);
            assert!((ours - x.sqrt()).abs() <= 1e-12 * x.sqrt(), "{x}");
        }
        assert_eq!(sqrt_f64(0.0), 0.0);
        assert!(sqrt_f64(-1.0).is_nan());
    }

    #[test]
    fn unit_norm_checks() {
        assert!(check_unit_norm("v", &[1.0, 0.0, 0.0]).is_ok());
        assert!(check_unit_norm("v", &[0.6, 0.8, 0.0]).is_ok());
        assert!(check_unit_norm("q", &[0.5, 0.5, 0.5, 0.5]).is_ok());
        assert!(check_unit_norm("v", &[1.0005, 0.0, 0.0]).is_ok());
        assert!(matches!(
            check_unit_norm("v", &[1.002, 0.0, 0.0]),
            Err(ValidationError::NotUnitNorm { field: "v", .. })
        ));
        assert!(matches!(
            check_unit_norm("v", &[0.0, 0.0, 0.0]),
            Err(ValidationError::NotUnitNorm { .. })
        ));
        assert_eq!(
            check_unit_norm("v", &[f32::NAN, 0.0, 1.0]),
            Err(ValidationError::NonFinite { field: "v" })
        );
        assert_eq!(
            check_unit_norm("v", &[f32::INFINITY, 0.0, 0.0]),
            Err(ValidationError::NonFinite { field: "v" })
        );
        assert_eq!(
            check_non_negative("s", -0.1),
            Err(ValidationError::Negative { field: "s" })
        );
        assert!(check_non_negative("s", 0.0).is_ok());
    }
}
