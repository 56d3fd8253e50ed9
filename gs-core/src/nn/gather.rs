//! Shared checks for the input-assembly helpers: per-Gaussian arrays and index lists.
//!
//! Per-Gaussian arrays are flat row-major `count x width` slices of the model's parameter
//! groups; index lists name the Gaussians to evaluate (for example those that survived
//! culling) and may be in any order, with repeats.

use super::error::{check_finite, NnError};

/// Number of Gaussians in a flat `count x width` array, or a shape error.
pub(crate) fn rows_of(what: &'static str, values: &[f32], width: usize) -> Result<usize, NnError> {
    if width == 0 || !values.len().is_multiple_of(width) {
        return Err(NnError::Shape {
            what,
            expected: width * (values.len() / width.max(1)),
            got: values.len(),
        });
    }
    Ok(values.len() / width)
}

/// Every index below `count`.
pub(crate) fn check_indices(gaussians: &[u32], count: usize) -> Result<(), NnError> {
    match gaussians.iter().find(|&&i| i as usize >= count) {
        None => Ok(()),
        Some(&i) => Err(NnError::Index {
            index: i as usize,
            len: count,
        }),
    }
}

/// The rows of `values` (width `width`) named by `gaussians` are finite; the error names the
/// Gaussian.
pub(crate) fn check_rows_finite(
    what: &'static str,
    values: &[f32],
    width: usize,
    gaussians: &[u32],
) -> Result<(), NnError> {
    for &g in gaussians {
        let g = g as usize;
        if check_finite(what, &values[g * width..(g + 1) * width]).is_err() {
            return Err(NnError::NonFinite { what, index: g });
        }
    }
    Ok(())
}

/// A finite, non-zero 3-vector scaled to unit length.
pub(crate) fn unit_vector(what: &'static str, v: [f32; 3]) -> Result<[f32; 3], NnError> {
    check_finite(what, &v)?;
    let norm = (v[0] as f64).hypot(v[1] as f64).hypot(v[2] as f64);
    if norm < 1e-12 {
        return Err(NnError::Degenerate { what, index: 0 });
    }
    Ok([
        (v[0] as f64 / norm) as f32,
        (v[1] as f64 / norm) as f32,
        (v[2] as f64 / norm) as f32,
    ])
}
