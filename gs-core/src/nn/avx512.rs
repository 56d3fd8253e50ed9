//! f32 matrix products on AVX-512F: the networks' products on CPUs that have it (chosen at
//! run time by `matmul.rs`; elsewhere the AVX2 kernels of `avx2.rs`, which sum in the same
//! order, or the portable `gemm` crate where the CPU lacks AVX2 or FMA).
//!
//! Summation order (what makes the bits reproducible): every element is one chain of fused
//! multiply-adds along the reduction index in increasing order,
//! `c <- fma(A(i, t), B(t, j), c)` for `t = 0, 1, ..., k - 1`, starting from `+0.0`, or
//! from the value already in `C` when accumulating. Each step rounds once. The chain is the
//! same for every element whatever its place in a register tile, the tile's size, the
//! chunking of the reduction (partial sums pass through `C` as f32, which changes no bit)
//! or the caller's split of the rows, so results depend only on the operands (and the
//! thread's denormal mode): bit-reproducible for any shape split and thread count, and the
//! same bits as `avx2.rs`, which keeps this contract. The error against exact arithmetic is
//! at most `gamma_k * (|c_0| + sum_t |A(i,t) B(t,j)|)`, `gamma_k = k u / (1 - k u)`,
//! `u = 2^-24` (one rounding per step, `k` steps).
//!
//! Blocking (one copy, shared with `avx2.rs`: `tiled.rs`): A is read in place through its
//! strides (one broadcast per row and reduction index), so the row-major forward product
//! and the transposed weight-gradient product share one kernel. B is read 32 columns (two
//! vectors) at a time, either in place when row-major or from panels packed into
//! thread-local, 64-byte aligned scratch. A register tile is up to [`TILE_ROWS`] rows by 32
//! columns (28 accumulators of the 32 vector registers), the rows spread evenly over the
//! tiles; the reduction runs in chunks of [`CHUNK`] indices so a tile's slice of A and a
//! panel's slice of B stay in L1 together. Measured on an Intel Xeon (AVX-512, one thread)
//! at 130-165 GFLOP/s on the networks' 2048-row block shapes, about twice the `gemm` crate.
//!
//! Invariants: the kernels run only behind an [`Avx512Kernels`] value, which exists only
//! when the running CPU reports `avx512f` ([`Avx512Kernels::detect`]); every slice length
//! is checked against its shape before any unsafe code (a mismatch is a bug in this crate
//! and panics, like `matmul.rs`). Each call runs on the calling thread only.

use super::matmul::Strided;

/// Rows of the largest register tile.
pub const TILE_ROWS: usize = 14;

/// Reduction indices per chunk: 14 rows x 128 of A (7 KB) and 128 x 32 of B (16 KB) stay in
/// L1 (128 measured faster than 256 on the weight gradient's 2048-long reductions).
pub const CHUNK: usize = 128;

/// Proof that the running CPU has AVX-512F: the only way to reach the kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Avx512Kernels {
    _detected: (),
}

impl Avx512Kernels {
    /// The kernels when this CPU has AVX-512F, else `None`.
    pub fn detect() -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return Some(Self { _detected: () });
            }
        }
        None
    }

    /// `C = A B`, or `C += A B` when `accumulate` (`C` row-major `m x n`), for
    /// `Products`: `m, n, k >= 1` and every operand checked against its shape there.
    pub(crate) fn product(
        self,
        (m, k, n): (usize, usize, usize),
        a: Strided,
        b: Strided,
        c: &mut [f32],
        accumulate: bool,
    ) {
        #[cfg(target_arch = "x86_64")]
        {
            // SAFETY: `self` exists only when the CPU has avx512f (`detect`);
            // `Layout::operands` checked every slice against its shape.
            unsafe { super::tiled::product::<x86::Avx512>(m, k, n, a, b, c, accumulate) }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (m, k, n, a, b, c, accumulate);
            unreachable!("Avx512Kernels cannot be constructed off x86_64");
        }
    }
}

// The AVX-512 intrinsics are stable from Rust 1.89 (the workspace's `rust-version`).
#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use super::super::tiled::Tiles;
    use super::{CHUNK, TILE_ROWS};

    /// f32 lanes of one vector.
    const LANES: usize = 16;

    /// The AVX-512 register tiles (reached only through [`super::Avx512Kernels`]).
    pub(super) struct Avx512;

    // SAFETY: `tile` below touches only the elements its contract names (masked loads and
    // stores for column tails) and sums each element as one `fma` chain in increasing `t`.
    unsafe impl Tiles for Avx512 {
        const LANES: usize = LANES;
        const TILE_ROWS: usize = TILE_ROWS;
        const CHUNK: usize = CHUNK;
        const PACK_B_STRIDE: usize = 0;

        unsafe fn tile(
            rows: usize,
            a: *const f32,
            a_rs: usize,
            a_cs: usize,
            b: *const f32,
            b_ts: usize,
            kc: usize,
            c: *mut f32,
            ldc: usize,
            cols: usize,
            from_c: bool,
        ) {
            // SAFETY: the caller's contract (`Tiles::tile`), passed on unchanged.
            unsafe {
                tile_dispatch(
                    rows,
                    cols > LANES,
                    a,
                    a_rs,
                    a_cs,
                    b,
                    b_ts,
                    kc,
                    c,
                    ldc,
                    cols,
                    from_c,
                );
            }
        }
    }

    /// One register tile: `R` rows by `V` vectors of columns (`cols` of them valid), over
    /// `kc` reduction indices, into `c` (row stride `ldc`), starting from the values in `c`
    /// when `from_c`, else from zero.
    ///
    /// # Safety
    /// As `Tiles::tile`, with `rows == R` and `cols <= V * LANES`; the CPU has avx512f.
    #[target_feature(enable = "avx512f")]
    unsafe fn tile<const R: usize, const V: usize>(
        a: *const f32,
        a_rs: usize,
        a_cs: usize,
        b: *const f32,
        b_ts: usize,
        kc: usize,
        c: *mut f32,
        ldc: usize,
        cols: usize,
        from_c: bool,
    ) {
        let mask_of = |v: usize| -> __mmask16 {
            let valid = cols.saturating_sub(v * LANES).min(LANES);
            ((1u32 << valid) - 1) as u16
        };
        let mut acc = [[_mm512_setzero_ps(); V]; R];
        if from_c {
            for (r, acc_row) in acc.iter_mut().enumerate() {
                for (v, acc_v) in acc_row.iter_mut().enumerate() {
                    *acc_v = _mm512_maskz_loadu_ps(mask_of(v), c.add(r * ldc + v * LANES));
                }
            }
        }
        let full = cols == V * LANES;
        for t in 0..kc {
            let bp = b.add(t * b_ts);
            let bv: [__m512; V] = if full {
                std::array::from_fn(|v| _mm512_loadu_ps(bp.add(v * LANES)))
            } else {
                std::array::from_fn(|v| _mm512_maskz_loadu_ps(mask_of(v), bp.add(v * LANES)))
            };
            let ap = a.add(t * a_cs);
            for (r, acc_row) in acc.iter_mut().enumerate() {
                let av = _mm512_set1_ps(*ap.add(r * a_rs));
                for (acc_v, &bv_v) in acc_row.iter_mut().zip(&bv) {
                    *acc_v = _mm512_fmadd_ps(av, bv_v, *acc_v);
                }
            }
        }
        for (r, acc_row) in acc.iter().enumerate() {
            for (v, &sum) in acc_row.iter().enumerate() {
                _mm512_mask_storeu_ps(c.add(r * ldc + v * LANES), mask_of(v), sum);
            }
        }
    }

    /// # Safety
    /// As `Tiles::tile`, with `wide == (cols > LANES)`; the CPU has avx512f.
    #[target_feature(enable = "avx512f")]
    unsafe fn tile_dispatch(
        rows: usize,
        wide: bool,
        a: *const f32,
        rs: usize,
        cs: usize,
        b: *const f32,
        b_ts: usize,
        kc: usize,
        c: *mut f32,
        ldc: usize,
        cols: usize,
        acc: bool,
    ) {
        macro_rules! go {
            ($r:literal) => {
                if wide {
                    tile::<$r, 2>(a, rs, cs, b, b_ts, kc, c, ldc, cols, acc)
                } else {
                    tile::<$r, 1>(a, rs, cs, b, b_ts, kc, c, ldc, cols, acc)
                }
            };
        }
        match rows {
            14 => go!(14),
            13 => go!(13),
            12 => go!(12),
            11 => go!(11),
            10 => go!(10),
            9 => go!(9),
            8 => go!(8),
            7 => go!(7),
            6 => go!(6),
            5 => go!(5),
            4 => go!(4),
            3 => go!(3),
            2 => go!(2),
            _ => go!(1),
        }
    }
}

#[cfg(test)]
mod tests {
    use crate::nn::avx512::Avx512Kernels;
    use crate::nn::kernel_tests;
    use crate::nn::matmul::{F32Kernel, Products};

    /// The AVX-512 products (the kernels behind `Products`' shape checks), or `None` after
    /// a visible skip (a failure under `GS_REQUIRE_AVX512=1`).
    fn kernels() -> Option<Products> {
        let found = Avx512Kernels::detect();
        if found.is_none() {
            crate::machine::skip_unless_required("GS_REQUIRE_AVX512", "no avx512f");
        }
        found.map(|k| Products::f32_on(F32Kernel::Avx512(k)))
    }

    #[test]
    fn products_follow_the_stated_order_in_all_three_layouts_and_odd_shapes() {
        let Some(kernels) = kernels() else { return };
        kernel_tests::products_follow_the_stated_order(kernels);
    }

    #[test]
    fn empty_shapes_leave_or_zero_the_output() {
        let Some(kernels) = kernels() else { return };
        kernel_tests::empty_shapes_leave_or_zero_the_output(kernels);
    }

    #[test]
    fn results_repeat_bit_for_bit_whatever_the_row_split_and_reduction_split() {
        let Some(kernels) = kernels() else { return };
        kernel_tests::results_repeat_whatever_the_splits(kernels, (45, 300, 40), &[1, 77, 256]);
    }
}
