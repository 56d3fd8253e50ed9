//! Single-threaded row-major f32 matrix products on the `gemm` crate, and [`Products`]: the
//! networks' choice between these and the bfloat16 kernels of `bf16.rs`.
//!
//! Invariants: every matrix is a dense row-major slice whose length is checked against its
//! shape before the unsafe call (a mismatch is a bug in this crate, so it panics here rather
//! than reading out of bounds). Each call runs on the calling thread only
//! (`Parallelism::None`): callers parallelise over fixed row blocks, which keeps results
//! independent of the thread count. For fixed shapes, strides and CPU the kernel is fixed,
//! so results are bit-reproducible.
//!
//! `gemm` was chosen over `matrixmultiply` by measurement on the target machine (see
//! `examples/mlp_bench.rs`): similar on the 256-wide shapes, several times faster on the
//! narrow shapes of the shadow network (55 x 32, 32 x 32).

use gemm::Parallelism;

use super::bf16::Bf16Kernels;
use super::error::NnError;

/// Arithmetic of the networks' matrix products.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum MatmulPrecision {
    /// f32 inputs, f32 accumulation (the `gemm` crate).
    #[default]
    F32,
    /// Inputs rounded to bfloat16, f32 accumulation (AVX-512 BF16 where the CPU has it).
    Bf16,
}

impl MatmulPrecision {
    /// `Ok` when this CPU runs products of this precision; for `Bf16` without AVX-512 BF16
    /// a configuration error naming the missing feature (never a silent fallback).
    pub fn check_supported(self) -> Result<(), NnError> {
        Products::new(self).map(|_| ())
    }
}

/// The matrix products of one precision, checked against the CPU when chosen: the three
/// layouts the MLP uses, each single-threaded and deterministic.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Products {
    /// `Some` for bfloat16 products (its existence proves the CPU runs them).
    bf16: Option<Bf16Kernels>,
}

impl Products {
    /// Products of `precision`, or an error when the CPU lacks what it needs.
    pub fn new(precision: MatmulPrecision) -> Result<Self, NnError> {
        Ok(Self {
            bf16: match precision {
                MatmulPrecision::F32 => None,
                MatmulPrecision::Bf16 => Some(Bf16Kernels::detect()?),
            },
        })
    }

    pub fn precision(self) -> MatmulPrecision {
        match self.bf16 {
            None => MatmulPrecision::F32,
            Some(_) => MatmulPrecision::Bf16,
        }
    }

    /// [`matmul`] in this precision.
    #[allow(clippy::too_many_arguments)]
    pub fn matmul(
        self,
        a: &[f32],
        b: &[f32],
        c: &mut [f32],
        m: usize,
        k: usize,
        n: usize,
        accumulate: bool,
    ) {
        match self.bf16 {
            None => matmul(a, b, c, m, k, n, accumulate),
            Some(kernels) => kernels.matmul(a, b, c, m, k, n, accumulate),
        }
    }

    /// [`matmul_at_b`] in this precision.
    #[allow(clippy::too_many_arguments)]
    pub fn matmul_at_b(
        self,
        a: &[f32],
        b: &[f32],
        c: &mut [f32],
        k: usize,
        m: usize,
        n: usize,
        accumulate: bool,
    ) {
        match self.bf16 {
            None => matmul_at_b(a, b, c, k, m, n, accumulate),
            Some(kernels) => kernels.matmul_at_b(a, b, c, k, m, n, accumulate),
        }
    }

    /// [`matmul_a_bt`] in this precision.
    #[allow(clippy::too_many_arguments)]
    pub fn matmul_a_bt(
        self,
        a: &[f32],
        b: &[f32],
        c: &mut [f32],
        m: usize,
        k: usize,
        n: usize,
        accumulate: bool,
    ) {
        match self.bf16 {
            None => matmul_a_bt(a, b, c, m, k, n, accumulate),
            Some(kernels) => kernels.matmul_a_bt(a, b, c, m, k, n, accumulate),
        }
    }
}

/// Row-major stride pair `(column stride, row stride)` of a dense `rows x cols` matrix.
const fn row_major(cols: usize) -> (isize, isize) {
    (1, cols as isize)
}

/// Stride pair of the transpose of a dense row-major matrix with `cols` columns.
const fn transposed(cols: usize) -> (isize, isize) {
    (cols as isize, 1)
}

#[allow(clippy::too_many_arguments)]
fn gemm_raw(
    m: usize,
    k: usize,
    n: usize,
    a: &[f32],
    a_strides: (isize, isize),
    b: &[f32],
    b_strides: (isize, isize),
    c: &mut [f32],
    accumulate: bool,
) {
    assert!(a.len() >= m * k && b.len() >= k * n && c.len() >= m * n);
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            c[..m * n].fill(0.0);
        }
        return;
    }
    // SAFETY: the asserts above guarantee that every element addressed through the given
    // strides, (i, j) -> i * rs + j * cs with i < rows, j < cols, lies inside its slice:
    // row-major strides address at most (rows - 1) * cols + cols - 1 < rows * cols, and
    // transposed strides address the same set of elements. `c` is borrowed mutably and
    // cannot alias `a` or `b`.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            c.as_mut_ptr(),
            1,
            n as isize,
            accumulate,
            a.as_ptr(),
            a_strides.0,
            a_strides.1,
            b.as_ptr(),
            b_strides.0,
            b_strides.1,
            1.0f32,
            1.0f32,
            false,
            false,
            false,
            Parallelism::None,
        );
    }
}

/// `C (m x n) = A (m x k) * B (k x n)`, or `C += ...` when `accumulate`.
pub fn matmul(a: &[f32], b: &[f32], c: &mut [f32], m: usize, k: usize, n: usize, accumulate: bool) {
    assert_eq!((a.len(), b.len(), c.len()), (m * k, k * n, m * n));
    gemm_raw(m, k, n, a, row_major(k), b, row_major(n), c, accumulate);
}

/// `C (m x n) = A^T * B` with `A` stored `k x m` and `B` stored `k x n`, or `C += ...`.
/// This is the weight-gradient product `X^T dZ` (reduction over the `k` batch rows).
pub fn matmul_at_b(
    a: &[f32],
    b: &[f32],
    c: &mut [f32],
    k: usize,
    m: usize,
    n: usize,
    accumulate: bool,
) {
    assert_eq!((a.len(), b.len(), c.len()), (k * m, k * n, m * n));
    gemm_raw(m, k, n, a, transposed(m), b, row_major(n), c, accumulate);
}

/// `C (m x n) = A (m x k) * B^T` with `B` stored `n x k`, or `C += ...`.
/// This is the input-gradient product `dZ W^T`.
pub fn matmul_a_bt(
    a: &[f32],
    b: &[f32],
    c: &mut [f32],
    m: usize,
    k: usize,
    n: usize,
    accumulate: bool,
) {
    assert_eq!((a.len(), b.len(), c.len()), (m * k, n * k, m * n));
    gemm_raw(m, k, n, a, row_major(k), b, transposed(k), c, accumulate);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn naive(a: &[f32], b: &[f32], m: usize, k: usize, n: usize) -> Vec<f64> {
        let mut c = vec![0.0f64; m * n];
        for i in 0..m {
            for j in 0..n {
                c[i * n + j] = (0..k)
                    .map(|t| a[i * k + t] as f64 * b[t * n + j] as f64)
                    .sum();
            }
        }
        c
    }

    fn transpose(x: &[f32], rows: usize, cols: usize) -> Vec<f32> {
        let mut t = vec![0.0; x.len()];
        for i in 0..rows {
            for j in 0..cols {
                t[j * rows + i] = x[i * cols + j];
            }
        }
        t
    }

    fn filled(len: usize, seed: u32) -> Vec<f32> {
        (0..len)
            .map(|i| {
                ((i as u32).wrapping_mul(2654435761).wrapping_add(seed) % 1000) as f32 / 500.0 - 1.0
            })
            .collect()
    }

    fn assert_close(got: &[f32], want: &[f64]) {
        for (g, w) in got.iter().zip(want) {
            assert!(
                (*g as f64 - w).abs() <= 1e-4 * (1.0 + w.abs()),
                "{g} vs {w}"
            );
        }
    }

    #[test]
    fn products_match_naive_reference_in_all_three_layouts() {
        // Odd sizes exercise the kernels' edge handling.
        let (m, k, n) = (37, 19, 23);
        let a = filled(m * k, 1);
        let b = filled(k * n, 2);
        let want = naive(&a, &b, m, k, n);

        let mut c = vec![0.0; m * n];
        matmul(&a, &b, &mut c, m, k, n, false);
        assert_close(&c, &want);

        let a_t = transpose(&a, m, k); // stored k x m
        let mut c2 = vec![0.0; m * n];
        matmul_at_b(&a_t, &b, &mut c2, k, m, n, false);
        assert_close(&c2, &want);

        let b_t = transpose(&b, k, n); // stored n x k
        let mut c3 = vec![0.0; m * n];
        matmul_a_bt(&a, &b_t, &mut c3, m, k, n, false);
        assert_close(&c3, &want);

        // Accumulation adds to what is there.
        matmul(&a, &b, &mut c, m, k, n, true);
        let doubled: Vec<f64> = want.iter().map(|w| 2.0 * w).collect();
        assert_close(&c, &doubled);
    }

    #[test]
    fn empty_reduction_gives_zero_or_leaves_accumulator() {
        let mut c = vec![5.0; 6];
        matmul(&[], &[], &mut c, 2, 0, 3, true);
        assert_eq!(c, vec![5.0; 6]);
        matmul(&[], &[], &mut c, 2, 0, 3, false);
        assert_eq!(c, vec![0.0; 6]);
    }
}
