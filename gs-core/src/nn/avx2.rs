//! f32 matrix products on AVX2 with FMA: the networks' products on x86 CPUs without
//! AVX-512F (chosen at run time by `matmul.rs`), summed in exactly the order of
//! `avx512.rs`, so both give the same bits for the same operands.
//!
//! Summation order (the contract of `avx512.rs`, which this module keeps): every element is
//! one chain of fused multiply-adds along the reduction index in increasing order,
//! `c <- fma(A(i, t), B(t, j), c)` for `t = 0, 1, ..., k - 1`, starting from `+0.0`, or
//! from the value already in `C` when accumulating. `_mm256_fmadd_ps` rounds once per step
//! like `_mm512_fmadd_ps` and scalar `f32::mul_add`, and masked-off lanes never enter a
//! valid element's chain, so the result of each element depends only on its operands (and
//! the thread's denormal mode), not on the tile, the vector width or the row split.
//!
//! Blocking: one copy shared with `avx512.rs` (`tiled.rs`: B in place or packed into
//! 16-column panels, the reduction in chunks of [`CHUNK`]). A register tile is up to
//! [`TILE_ROWS`] rows by 16 columns (two 8-lane vectors): 12 accumulators, two vectors of
//! B and one broadcast of A use 15 of the 16 ymm registers. Column tails use
//! `_mm256_maskload_ps`/`_mm256_maskstore_ps`, whose masked-off lanes are neither read nor
//! written.
//!
//! Measured on an AMD EPYC (Zen 3, one thread, `examples/kernel_ab.rs`, the kernels
//! alternating): against the `gemm` crate 1.0-1.4x on the forward and input-gradient
//! products, 0.63-0.87x on Phi's 256-wide weight gradient `X^T dZ`, 0.3-0.5x on Psi's
//! 1-wide output layer (one lane of eight works); whole Phi backward about 14 % slower,
//! the rest level (`docs/bench/gemm.md`). It is the default there for its bits.
//!
//! Invariants: the kernels run only behind an [`Avx2Kernels`] value, which exists only
//! when the running CPU reports both `avx2` and `fma` ([`Avx2Kernels::detect`], never
//! compile flags); every slice length is checked against its shape by `matmul.rs` before
//! any unsafe code. Each call runs on the calling thread only.

use super::matmul::Strided;

/// Rows of the largest register tile.
pub const TILE_ROWS: usize = 6;

/// Reduction indices per chunk: 6 rows x 256 of A (6 KB) and 256 x 16 of B (16 KB) stay
/// in L1.
pub const CHUNK: usize = 256;

/// Proof that the running CPU has AVX2 and FMA: the only way to reach the kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Avx2Kernels {
    _detected: (),
}

impl Avx2Kernels {
    /// The kernels when this CPU has AVX2 and FMA, else `None`.
    pub fn detect() -> Option<Self> {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
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
            // SAFETY: `self` exists only when the CPU has avx2 and fma (`detect`);
            // `Layout::operands` checked every slice against its shape.
            unsafe { super::tiled::product::<x86::Avx2>(m, k, n, a, b, c, accumulate) }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (m, k, n, a, b, c, accumulate);
            unreachable!("Avx2Kernels cannot be constructed off x86_64");
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use super::super::tiled::Tiles;
    use super::{CHUNK, TILE_ROWS};

    /// f32 lanes of one vector.
    const LANES: usize = 8;

    /// The AVX2 register tiles (reached only through [`super::Avx2Kernels`]).
    pub(super) struct Avx2;

    // SAFETY: `tile` below touches only the elements its contract names (masked loads and
    // stores for column tails) and sums each element as one `fma` chain in increasing `t`.
    unsafe impl Tiles for Avx2 {
        const LANES: usize = LANES;
        const TILE_ROWS: usize = TILE_ROWS;
        const CHUNK: usize = CHUNK;
        // Stride a multiple of 4 KiB (a page per reduction index): packing took the
        // 1024^3 product from 23 to 48 GFLOP/s on an AMD EPYC (one thread). Packing at
        // 1 KiB strides (dZ, 256 wide, of the weight gradient) measured no faster.
        const PACK_B_STRIDE: usize = 1024;

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
            unsafe { tile_dispatch(rows, a, a_rs, a_cs, b, b_ts, kc, c, ldc, cols, from_c) };
        }
    }

    /// One register tile: `R` rows by `V` vectors of columns (`cols` of them valid), over
    /// `kc` reduction indices, into `c` (row stride `ldc`), starting from the values in `c`
    /// when `from_c`, else from zero.
    ///
    /// # Safety
    /// As `Tiles::tile`, with `rows == R` and `cols <= V * LANES`; the CPU has avx2 and fma.
    #[target_feature(enable = "avx2,fma")]
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
        // Lane l of vector v is valid when v * LANES + l < cols.
        let lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        let masks: [__m256i; V] = std::array::from_fn(|v| {
            let valid = cols.saturating_sub(v * LANES).min(LANES) as i32;
            _mm256_cmpgt_epi32(_mm256_set1_epi32(valid), lane)
        });
        let full = cols == V * LANES;
        let mut acc = [[_mm256_setzero_ps(); V]; R];
        if from_c {
            for (r, acc_row) in acc.iter_mut().enumerate() {
                for (v, acc_v) in acc_row.iter_mut().enumerate() {
                    let p = c.add(r * ldc + v * LANES);
                    *acc_v = if full {
                        _mm256_loadu_ps(p)
                    } else {
                        _mm256_maskload_ps(p, masks[v])
                    };
                }
            }
        }
        if full {
            for t in 0..kc {
                let bp = b.add(t * b_ts);
                let bv: [__m256; V] = std::array::from_fn(|v| _mm256_loadu_ps(bp.add(v * LANES)));
                let ap = a.add(t * a_cs);
                for (r, acc_row) in acc.iter_mut().enumerate() {
                    let av = _mm256_broadcast_ss(&*ap.add(r * a_rs));
                    for (acc_v, &bv_v) in acc_row.iter_mut().zip(&bv) {
                        *acc_v = _mm256_fmadd_ps(av, bv_v, *acc_v);
                    }
                }
            }
        } else {
            for t in 0..kc {
                let bp = b.add(t * b_ts);
                let bv: [__m256; V] =
                    std::array::from_fn(|v| _mm256_maskload_ps(bp.add(v * LANES), masks[v]));
                let ap = a.add(t * a_cs);
                for (r, acc_row) in acc.iter_mut().enumerate() {
                    let av = _mm256_broadcast_ss(&*ap.add(r * a_rs));
                    for (acc_v, &bv_v) in acc_row.iter_mut().zip(&bv) {
                        *acc_v = _mm256_fmadd_ps(av, bv_v, *acc_v);
                    }
                }
            }
        }
        for (r, acc_row) in acc.iter().enumerate() {
            for (v, &sum) in acc_row.iter().enumerate() {
                let p = c.add(r * ldc + v * LANES);
                if full {
                    _mm256_storeu_ps(p, sum);
                } else {
                    _mm256_maskstore_ps(p, masks[v], sum);
                }
            }
        }
    }

    /// # Safety
    /// As `Tiles::tile`; the CPU has avx2 and fma.
    #[target_feature(enable = "avx2,fma")]
    unsafe fn tile_dispatch(
        rows: usize,
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
        const { assert!(TILE_ROWS <= 6, "tile_dispatch covers 6 rows at most") };
        macro_rules! go {
            ($r:literal) => {
                if cols > LANES {
                    tile::<$r, 2>(a, rs, cs, b, b_ts, kc, c, ldc, cols, acc)
                } else {
                    tile::<$r, 1>(a, rs, cs, b, b_ts, kc, c, ldc, cols, acc)
                }
            };
        }
        match rows {
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
    use crate::nn::avx2::Avx2Kernels;
    use crate::nn::kernel_tests;
    use crate::nn::matmul::{F32Kernel, Products};

    /// The AVX2 products (the kernels behind `Products`' shape checks), or `None` after a
    /// visible skip (a failure under `GS_REQUIRE_AVX2=1`).
    fn kernels() -> Option<Products> {
        let found = Avx2Kernels::detect();
        if found.is_none() {
            crate::machine::skip_unless_required("GS_REQUIRE_AVX2", "no avx2 and fma");
        }
        found.map(|k| Products::f32_on(F32Kernel::Avx2(k)))
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

    #[test]
    fn avx2_and_avx512_give_the_same_bits_on_random_shapes() {
        let Some(avx2) = kernels() else { return };
        let Some(avx512) = crate::nn::avx512::Avx512Kernels::detect() else {
            crate::machine::skip_unless_required("GS_REQUIRE_AVX512", "no avx512f");
            return;
        };
        kernel_tests::kernels_agree_bit_for_bit(avx2, Products::f32_on(F32Kernel::Avx512(avx512)));
    }
}
