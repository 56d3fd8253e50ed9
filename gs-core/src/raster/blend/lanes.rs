//! Sixteen f32 lanes (one tile row of pixels) and the few operations the tile loops of
//! `blend.rs` use, in two implementations: [`Portable`] (plain arrays and loops, the
//! fallback, compiled for whatever the build targets) and, on x86_64, [`Avx512`]
//! (AVX-512F/BW/VL/DQ intrinsics, one register per row, lane masks in mask registers).
//!
//! Invariants:
//! - every operation rounds exactly as the scalar f32 expression it stands for (single
//!   IEEE operations, never fused), so both implementations give the same bits: the tile
//!   loops are generic over [`RowOps`], and tests compare both builds with each other and
//!   with the scalar loops they replaced;
//! - lane masks are `u16`, bit `i` for lane `i` (pixel `i` of the row);
//! - an [`Avx512`] value exists only where the CPU has those features
//!   ([`Avx512::detect`]), which is what makes its safe methods sound.

use super::{fast_exp, Row, LANE_GROUP, ROW};

/// Eight per-lane partial sums.
pub(super) type Half = [f32; LANE_GROUP];

/// Row operations. `F` holds 16 lanes; comparisons are ordered (false on NaN), as Rust's.
pub(super) trait RowOps: Copy {
    type F: Copy;
    /// Eight lanes of per-splat partial sums.
    type H: Copy;
    fn splat(self, v: f32) -> Self::F;
    /// Lane `i` holds `i as f32`.
    fn iota(self) -> Self::F;
    fn load(self, r: &Row) -> Self::F;
    /// `r[i] = v[i]` where bit `i` of `m` is set.
    fn store_masked(self, r: &mut Row, m: u16, v: Self::F);
    /// `r[i] = v` where bit `i` of `m` is set.
    fn store_u32_masked(self, r: &mut [u32; ROW], m: u16, v: u32);
    fn add(self, a: Self::F, b: Self::F) -> Self::F;
    fn sub(self, a: Self::F, b: Self::F) -> Self::F;
    fn mul(self, a: Self::F, b: Self::F) -> Self::F;
    fn div(self, a: Self::F, b: Self::F) -> Self::F;
    fn ge(self, a: Self::F, b: Self::F) -> u16;
    fn gt(self, a: Self::F, b: Self::F) -> u16;
    fn lt(self, a: Self::F, b: Self::F) -> u16;
    /// Lanes where `j < r[i]`.
    fn lt_u32(self, j: u32, r: &[u32; ROW]) -> u16;
    /// `if m[i] { a[i] } else { b[i] }`.
    fn select(self, m: u16, a: Self::F, b: Self::F) -> Self::F;
    /// [`fast_exp`] of every lane, bit for bit.
    fn exp(self, x: Self::F) -> Self::F;
    fn half_zero(self) -> Self::H;
    /// `acc[i] += v[i]`, then `acc[i] += v[i + 8]`.
    fn fold(self, acc: &mut Self::H, v: Self::F);
    fn half_lanes(self, h: Self::H) -> Half;
}

/// Plain arrays: the portable build (vectorised by the compiler where it can).
#[derive(Clone, Copy, Debug)]
pub(super) struct Portable;

macro_rules! lanewise {
    ($a:expr, $b:expr, |$x:ident, $y:ident| $e:expr) => {{
        let (a, b) = ($a, $b);
        let mut out = [0.0f32; ROW];
        for i in 0..ROW {
            let ($x, $y) = (a[i], b[i]);
            out[i] = $e;
        }
        out
    }};
}

macro_rules! maskwise {
    ($a:expr, $b:expr, |$x:ident, $y:ident| $e:expr) => {{
        let (a, b) = ($a, $b);
        let mut m = 0u32;
        for i in 0..ROW {
            let ($x, $y) = (a[i], b[i]);
            m |= u32::from($e) << i;
        }
        m as u16
    }};
}

impl RowOps for Portable {
    type F = Row;
    type H = Half;
    #[inline(always)]
    fn splat(self, v: f32) -> Row {
        [v; ROW]
    }
    #[inline(always)]
    fn iota(self) -> Row {
        let mut out = [0.0f32; ROW];
        for (i, o) in out.iter_mut().enumerate() {
            *o = i as f32;
        }
        out
    }
    #[inline(always)]
    fn load(self, r: &Row) -> Row {
        *r
    }
    #[inline(always)]
    fn store_masked(self, r: &mut Row, m: u16, v: Row) {
        for i in 0..ROW {
            r[i] = if (m >> i) & 1 != 0 { v[i] } else { r[i] };
        }
    }
    #[inline(always)]
    fn store_u32_masked(self, r: &mut [u32; ROW], m: u16, v: u32) {
        for (i, x) in r.iter_mut().enumerate() {
            *x = if (m >> i) & 1 != 0 { v } else { *x };
        }
    }
    #[inline(always)]
    fn add(self, a: Row, b: Row) -> Row {
        lanewise!(a, b, |x, y| x + y)
    }
    #[inline(always)]
    fn sub(self, a: Row, b: Row) -> Row {
        lanewise!(a, b, |x, y| x - y)
    }
    #[inline(always)]
    fn mul(self, a: Row, b: Row) -> Row {
        lanewise!(a, b, |x, y| x * y)
    }
    #[inline(always)]
    fn div(self, a: Row, b: Row) -> Row {
        lanewise!(a, b, |x, y| x / y)
    }
    #[inline(always)]
    fn ge(self, a: Row, b: Row) -> u16 {
        maskwise!(a, b, |x, y| x >= y)
    }
    #[inline(always)]
    fn gt(self, a: Row, b: Row) -> u16 {
        maskwise!(a, b, |x, y| x > y)
    }
    #[inline(always)]
    fn lt(self, a: Row, b: Row) -> u16 {
        maskwise!(a, b, |x, y| x < y)
    }
    #[inline(always)]
    fn lt_u32(self, j: u32, r: &[u32; ROW]) -> u16 {
        maskwise!([j; ROW], r, |x, y| x < y)
    }
    #[inline(always)]
    fn select(self, m: u16, a: Row, b: Row) -> Row {
        let mut out = [0.0f32; ROW];
        for i in 0..ROW {
            out[i] = if (m >> i) & 1 != 0 { a[i] } else { b[i] };
        }
        out
    }
    #[inline(always)]
    fn exp(self, x: Row) -> Row {
        let mut out = [0.0f32; ROW];
        for (o, &x) in out.iter_mut().zip(&x) {
            *o = fast_exp(x);
        }
        out
    }
    #[inline(always)]
    fn half_zero(self) -> Half {
        [0.0; LANE_GROUP]
    }
    #[inline(always)]
    fn fold(self, acc: &mut Half, v: Row) {
        for i in 0..LANE_GROUP {
            acc[i] += v[i];
        }
        for i in 0..LANE_GROUP {
            acc[i] += v[LANE_GROUP + i];
        }
    }
    #[inline(always)]
    fn half_lanes(self, h: Half) -> Half {
        h
    }
}

#[cfg(target_arch = "x86_64")]
pub(super) use avx512::Avx512;

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{Half, Row, RowOps, ROW};
    use std::arch::x86_64::*;

    /// AVX-512 rows. Only [`Avx512::detect`] makes one, on a CPU with AVX-512F/BW/VL/DQ:
    /// every method's `unsafe` block relies on that. The methods are meant to be inlined
    /// into a function compiled with those features (the tile loops' AVX-512 build).
    #[derive(Clone, Copy, Debug, PartialEq, Eq)]
    pub(in super::super) struct Avx512 {
        _private: (),
    }

    impl Avx512 {
        pub(in super::super) fn detect() -> Option<Avx512> {
            // Every feature the AVX-512 build of the tile loops enables.
            let ok = std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512bw")
                && std::arch::is_x86_feature_detected!("avx512vl")
                && std::arch::is_x86_feature_detected!("avx512dq")
                && super::super::avx2_build_supported();
            ok.then_some(Avx512 { _private: () })
        }
    }

    // SAFETY (every `unsafe` block below): an `Avx512` exists only on a CPU with
    // AVX-512F/BW/VL/DQ (`detect`); loads and stores go through references to whole rows.
    impl RowOps for Avx512 {
        type F = __m512;
        type H = __m256;
        #[inline(always)]
        fn splat(self, v: f32) -> __m512 {
            unsafe { _mm512_set1_ps(v) }
        }
        #[inline(always)]
        fn iota(self) -> __m512 {
            unsafe {
                _mm512_setr_ps(
                    0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 13.0, 14.0,
                    15.0,
                )
            }
        }
        #[inline(always)]
        fn load(self, r: &Row) -> __m512 {
            unsafe { _mm512_loadu_ps(r.as_ptr()) }
        }
        #[inline(always)]
        fn store_masked(self, r: &mut Row, m: u16, v: __m512) {
            unsafe { _mm512_mask_storeu_ps(r.as_mut_ptr(), m, v) }
        }
        #[inline(always)]
        fn store_u32_masked(self, r: &mut [u32; ROW], m: u16, v: u32) {
            unsafe {
                _mm512_mask_storeu_epi32(
                    r.as_mut_ptr().cast::<i32>(),
                    m,
                    _mm512_set1_epi32(v as i32),
                );
            }
        }
        #[inline(always)]
        fn add(self, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_add_ps(a, b) }
        }
        #[inline(always)]
        fn sub(self, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_sub_ps(a, b) }
        }
        #[inline(always)]
        fn mul(self, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_mul_ps(a, b) }
        }
        #[inline(always)]
        fn div(self, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_div_ps(a, b) }
        }
        #[inline(always)]
        fn ge(self, a: __m512, b: __m512) -> u16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_GE_OQ>(a, b) }
        }
        #[inline(always)]
        fn gt(self, a: __m512, b: __m512) -> u16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_GT_OQ>(a, b) }
        }
        #[inline(always)]
        fn lt(self, a: __m512, b: __m512) -> u16 {
            unsafe { _mm512_cmp_ps_mask::<_CMP_LT_OQ>(a, b) }
        }
        #[inline(always)]
        fn lt_u32(self, j: u32, r: &[u32; ROW]) -> u16 {
            unsafe {
                let v = _mm512_loadu_si512(r.as_ptr().cast());
                _mm512_cmplt_epu32_mask(_mm512_set1_epi32(j as i32), v)
            }
        }
        #[inline(always)]
        fn select(self, m: u16, a: __m512, b: __m512) -> __m512 {
            unsafe { _mm512_mask_blend_ps(m, b, a) }
        }
        #[inline(always)]
        fn exp(self, x: __m512) -> __m512 {
            // `fast_exp` operation for operation (see there for the why).
            unsafe {
                let c = |v: f32| _mm512_set1_ps(v);
                const MAGIC: f32 = 12_582_912.0;
                // max(x, lo) returns lo where x is NaN, as f32::max does.
                let x = _mm512_min_ps(_mm512_max_ps(x, c(-87.0)), c(88.0));
                let shifted =
                    _mm512_add_ps(_mm512_mul_ps(x, c(std::f32::consts::LOG2_E)), c(MAGIC));
                let n = _mm512_sub_ps(shifted, c(MAGIC));
                let r = _mm512_sub_ps(
                    _mm512_sub_ps(x, _mm512_mul_ps(n, c(0.693_359_4))),
                    _mm512_mul_ps(n, c(-2.121_944_4e-4)),
                );
                let horner = |p: __m512, k: f32| _mm512_add_ps(_mm512_mul_ps(p, r), c(k));
                let p = horner(c(1.987_569_1e-4), 1.398_199_9e-3);
                let p = horner(p, 8.333_452e-3);
                let p = horner(p, 4.166_579_6e-2);
                let p = horner(p, 1.666_666_5e-1);
                let p = horner(p, 0.5);
                let e = _mm512_add_ps(
                    _mm512_add_ps(_mm512_mul_ps(_mm512_mul_ps(p, r), r), r),
                    c(1.0),
                );
                let n_int = _mm512_sub_epi32(
                    _mm512_castps_si512(shifted),
                    _mm512_set1_epi32(MAGIC.to_bits() as i32),
                );
                let scale = _mm512_castsi512_ps(_mm512_slli_epi32::<23>(_mm512_add_epi32(
                    n_int,
                    _mm512_set1_epi32(127),
                )));
                _mm512_mul_ps(e, scale)
            }
        }
        #[inline(always)]
        fn half_zero(self) -> __m256 {
            unsafe { _mm256_setzero_ps() }
        }
        #[inline(always)]
        fn fold(self, acc: &mut __m256, v: __m512) {
            unsafe {
                let lo = _mm512_castps512_ps256(v);
                let hi = _mm512_extractf32x8_ps::<1>(v);
                *acc = _mm256_add_ps(_mm256_add_ps(*acc, lo), hi);
            }
        }
        #[inline(always)]
        fn half_lanes(self, h: __m256) -> Half {
            let mut out = [0.0f32; 8];
            unsafe { _mm256_storeu_ps(out.as_mut_ptr(), h) };
            out
        }
    }
}
