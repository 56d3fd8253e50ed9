//! bfloat16 matrix products with f32 accumulation on AVX-512 BF16 (`vdpbf16ps`).
//!
//! Arithmetic: both operands are rounded to bfloat16 (round to nearest, ties to even, by
//! [`bf16_bits`]; finite inputs only), every product of two bfloat16 values is exact in f32,
//! and the products are summed in f32 along the reduction index in a fixed order (pairs of
//! reduction indices per instruction, pairs in increasing order), starting from zero, or
//! from the value in `C` when accumulating. The instruction flushes
//! f32 denormals to zero. So for `c = sum_t a_t b_t` over `k` terms the error against exact
//! arithmetic is at most `(2^-7 + 2^-16 + (k + 2) 2^-24) * sum_t |a_t b_t|` plus a few
//! `2^-126` (rounding of the inputs, at most `2^-8` relative each with bfloat16's 8
//! significant bits, so `2 * 2^-8 + 2^-16` per product; then the f32 sums).
//!
//! Invariants: the kernels run only behind a [`Bf16Kernels`] value, which exists only when
//! the running CPU reports `avx512bf16` and `avx512f` ([`Bf16Kernels::detect`]); every
//! slice length is checked against its shape before any unsafe code (a mismatch is a bug
//! in this crate and panics, like `matmul.rs`). Each call runs on the calling thread with
//! a fixed blocking (8 rows x 32 columns per micro-tile, the reduction in chunks of 256
//! whose partial sums pass through `C` unchanged, so the chunking does not change the
//! bits), so results are bit-reproducible for fixed shapes; callers parallelise over fixed
//! row blocks. Operands are packed into thread-local scratch on every call (the weight
//! matrix too: 10 us of a 2048 x 256 x 256 product's ~1250 us). The intrinsics are stable
//! from Rust 1.89.

use super::error::NnError;
use super::matmul::Strided;

/// The bfloat16 bits of `x`, rounded to nearest with ties to even (the upper half of the
/// f32 after rounding). Finite inputs whose magnitude rounds past bfloat16's largest value
/// become infinities, as in hardware; infinities stay infinities and NaN stays a (quiet)
/// NaN, so the networks' finiteness checks still see a non-finite value downstream.
#[inline]
pub fn bf16_bits(x: f32) -> u16 {
    let bits = x.to_bits();
    let rounding = 0x7FFF + ((bits >> 16) & 1);
    let rounded = (bits.wrapping_add(rounding) >> 16) as u16;
    // Rounding a NaN's payload could carry into the sign and give a number.
    if x.is_nan() {
        (bits >> 16) as u16 | 0x0040
    } else {
        rounded
    }
}

/// `x` rounded to the nearest bfloat16 (ties to even), as an f32.
#[inline]
pub fn round_to_bf16(x: f32) -> f32 {
    f32::from_bits((bf16_bits(x) as u32) << 16)
}

/// Proof that the running CPU has AVX-512 BF16: the only way to reach the kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Bf16Kernels {
    _detected: (),
}

impl Bf16Kernels {
    /// The kernels, or a configuration error naming the missing CPU feature.
    pub fn detect() -> Result<Self, NnError> {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512bf16")
                && std::arch::is_x86_feature_detected!("avx512f")
            {
                return Ok(Self { _detected: () });
            }
        }
        Err(NnError::Config(
            "bf16 matrix products need a CPU with AVX-512 BF16 (avx512bf16), which this one \
             lacks: use the F32 precision"
                .into(),
        ))
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
            // SAFETY: `self` exists only when the CPU has avx512bf16 and avx512f (`detect`);
            // `Layout::operands` checked every slice against its shape.
            unsafe { x86::product(m, k, n, a, b, c, accumulate) }
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            let _ = (m, k, n, a, b, c, accumulate);
            unreachable!("Bf16Kernels cannot be constructed off x86_64");
        }
    }
}

// The AVX-512 intrinsics are stable from Rust 1.89 (the workspace's `rust-version`).
#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;
    use std::cell::RefCell;

    use super::bf16_bits;

    /// f32 lanes of one vector.
    const LANES: usize = 16;
    /// Columns of one packed panel of B (two vectors).
    const PANEL_COLS: usize = 2 * LANES;
    /// Rows of one micro-tile.
    const TILE_ROWS: usize = 8;
    /// Reduction pairs per chunk: a chunk of a B panel (16 KB) stays in L1 across the row
    /// tiles (without chunks the weight-gradient product, 1024 pairs, streamed from L2).
    const CHUNK_PAIRS: usize = 128;

    thread_local! {
        /// Packed A and B of the last call on this thread (reused: no allocation per call).
        static SCRATCH: RefCell<(Vec<u32>, Vec<u32>)> = const { RefCell::new((Vec::new(), Vec::new())) };
    }

    #[inline]
    fn pair(lo: f32, hi: f32) -> u32 {
        bf16_bits(lo) as u32 | (bf16_bits(hi) as u32) << 16
    }

    /// Packed A: the word of row `i` and reduction pair `p` is at
    /// `i * row_stride + p * pair_stride`; it holds `A(i, 2p)` low, `A(i, 2p + 1)` high.
    struct PackedA {
        row_stride: usize,
        pair_stride: usize,
    }

    /// Packs A (`A(i, t) = a[i * is + t * ts]`) into `out`; rows stay contiguous when A is
    /// row-major, pairs stay contiguous otherwise, so reading `a` is sequential either way.
    #[target_feature(enable = "avx512f,avx512bw")]
    fn pack_a(
        m: usize,
        k: usize,
        (a, is, ts): (&[f32], usize, usize),
        out: &mut Vec<u32>,
    ) -> PackedA {
        let pairs = k.div_ceil(2);
        // Every word is written below, so no zeroing.
        out.resize(m * pairs, 0);
        if ts == 1 {
            for (i, words) in out.chunks_exact_mut(pairs).enumerate() {
                let row = &a[i * is..i * is + k];
                // A row-major row's pairs are its elements in order: convert element by
                // element into the words' halves (little-endian: low half first), a loop
                // that vectorises, unlike assembling each word from two elements.
                // SAFETY: `u16` has no stricter alignment than `u32`, the view covers the
                // same `2 * pairs` halves of `words`, which it borrows exclusively.
                let halves = unsafe {
                    std::slice::from_raw_parts_mut(words.as_mut_ptr() as *mut u16, 2 * pairs)
                };
                for (h, &v) in halves.iter_mut().zip(row) {
                    *h = bf16_bits(v);
                }
                if k % 2 == 1 {
                    halves[k] = 0;
                }
            }
            PackedA {
                row_stride: pairs,
                pair_stride: 1,
            }
        } else {
            // A(i, t) = a[t * ts + i] (is == 1): rows 2p and 2p + 1 of the stored matrix
            // interleave.
            debug_assert_eq!(is, 1);
            for (p, words) in out.chunks_exact_mut(m).enumerate() {
                let lo = &a[2 * p * ts..2 * p * ts + m];
                if 2 * p + 1 < k {
                    let hi = &a[(2 * p + 1) * ts..(2 * p + 1) * ts + m];
                    for ((w, &l), &h) in words.iter_mut().zip(lo).zip(hi) {
                        *w = pair(l, h);
                    }
                } else {
                    for (w, &l) in words.iter_mut().zip(lo) {
                        *w = pair(l, 0.0);
                    }
                }
            }
            PackedA {
                row_stride: 1,
                pair_stride: m,
            }
        }
    }

    /// Packs B (`B(t, j) = b[t * ts + j * js]`) into panels of `PANEL_COLS` columns: the
    /// word of pair `p`, column `j` is at `panel(j) * pairs * PANEL_COLS + p * PANEL_COLS +
    /// j % PANEL_COLS`. Columns past `n` are zero.
    #[target_feature(enable = "avx512f,avx512bw")]
    fn pack_b(k: usize, n: usize, (b, ts, js): (&[f32], usize, usize), out: &mut Vec<u32>) {
        let pairs = k.div_ceil(2);
        let panels = n.div_ceil(PANEL_COLS);
        // Every word is written below (padding columns with zeros), so no zeroing.
        out.resize(panels * pairs * PANEL_COLS, 0);
        let at = |t: usize, j: usize| if t < k { b[t * ts + j * js] } else { 0.0 };
        for (panel, words) in out.chunks_exact_mut(pairs * PANEL_COLS).enumerate() {
            let j0 = panel * PANEL_COLS;
            let cols = PANEL_COLS.min(n - j0);
            for (p, row) in words.chunks_exact_mut(PANEL_COLS).enumerate() {
                if js == 1 && 2 * p + 1 < k {
                    let lo = &b[2 * p * ts + j0..2 * p * ts + j0 + cols];
                    let hi = &b[(2 * p + 1) * ts + j0..(2 * p + 1) * ts + j0 + cols];
                    for ((w, &l), &h) in row.iter_mut().zip(lo).zip(hi) {
                        *w = pair(l, h);
                    }
                } else {
                    for (jj, w) in row[..cols].iter_mut().enumerate() {
                        *w = pair(at(2 * p, j0 + jj), at(2 * p + 1, j0 + jj));
                    }
                }
                row[cols..].fill(0);
            }
        }
    }

    /// One micro-tile: `R` rows by `V` vectors of columns (`cols` of them valid), over
    /// `pairs` reduction pairs, into `c` (row stride `ldc`), starting from the values in
    /// `c` when `from_c`, else from zero.
    ///
    /// # Safety
    /// The CPU has avx512bf16 and avx512f; `a` addresses `R` rows of `pairs` words through
    /// the strides, `b` one panel of `pairs * PANEL_COLS` words, `c` `R` rows of `ldc`
    /// floats with `cols <= V * LANES` valid columns from its start.
    #[target_feature(enable = "avx512bf16,avx512f")]
    unsafe fn tile<const R: usize, const V: usize>(
        a: *const u32,
        a_row_stride: usize,
        a_pair_stride: usize,
        b: *const u32,
        pairs: usize,
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
        for p in 0..pairs {
            let bp = b.add(p * PANEL_COLS);
            let bv: [__m512bh; V] = std::array::from_fn(|v| {
                std::mem::transmute::<__m512i, __m512bh>(_mm512_loadu_si512(
                    bp.add(v * LANES) as *const __m512i
                ))
            });
            let ap = a.add(p * a_pair_stride);
            for (r, acc_row) in acc.iter_mut().enumerate() {
                let word = *ap.add(r * a_row_stride);
                let av = std::mem::transmute::<__m512i, __m512bh>(_mm512_set1_epi32(word as i32));
                for (acc_v, &bv_v) in acc_row.iter_mut().zip(&bv) {
                    *acc_v = _mm512_dpbf16_ps(*acc_v, av, bv_v);
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
    /// As [`tile`], with `1 <= rows <= TILE_ROWS`.
    #[target_feature(enable = "avx512bf16,avx512f")]
    unsafe fn tile_dispatch(
        rows: usize,
        wide: bool,
        a: *const u32,
        rs: usize,
        ps: usize,
        b: *const u32,
        pairs: usize,
        c: *mut f32,
        ldc: usize,
        cols: usize,
        acc: bool,
    ) {
        macro_rules! go {
            ($r:literal) => {
                if wide {
                    tile::<$r, 2>(a, rs, ps, b, pairs, c, ldc, cols, acc)
                } else {
                    tile::<$r, 1>(a, rs, ps, b, pairs, c, ldc, cols, acc)
                }
            };
        }
        match rows {
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

    /// # Safety
    /// The CPU has avx512bf16 and avx512f; `a` holds `A(i, t) = a.0[i * a.1 + t * a.2]` for
    /// `i < m, t < k`, `b` holds `B(t, j) = b.0[t * b.1 + j * b.2]` for `t < k, j < n`, and
    /// `c` is `m x n` row-major; `m, n, k >= 1`.
    #[target_feature(enable = "avx512bf16,avx512f,avx512bw")]
    pub(super) unsafe fn product(
        m: usize,
        k: usize,
        n: usize,
        a: (&[f32], usize, usize),
        b: (&[f32], usize, usize),
        c: &mut [f32],
        accumulate: bool,
    ) {
        SCRATCH.with(|scratch| {
            let mut scratch = scratch.borrow_mut();
            let (packed_a, packed_b) = &mut *scratch;
            let layout = pack_a(m, k, a, packed_a);
            pack_b(k, n, b, packed_b);
            let pairs = k.div_ceil(2);
            let panels = n.div_ceil(PANEL_COLS);
            let (a_ptr, b_ptr, c_ptr) = (packed_a.as_ptr(), packed_b.as_ptr(), c.as_mut_ptr());
            for p0 in (0..pairs).step_by(CHUNK_PAIRS) {
                let chunk = CHUNK_PAIRS.min(pairs - p0);
                let from_c = accumulate || p0 > 0;
                for i0 in (0..m).step_by(TILE_ROWS) {
                    let rows = TILE_ROWS.min(m - i0);
                    for panel in 0..panels {
                        let j0 = panel * PANEL_COLS;
                        let cols = PANEL_COLS.min(n - j0);
                        tile_dispatch(
                            rows,
                            cols > LANES,
                            a_ptr.add(i0 * layout.row_stride + p0 * layout.pair_stride),
                            layout.row_stride,
                            layout.pair_stride,
                            b_ptr.add((panel * pairs + p0) * PANEL_COLS),
                            chunk,
                            c_ptr.add(i0 * n + j0),
                            n,
                            cols,
                            from_c,
                        );
                    }
                }
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::kernel_tests::{
        bf16_layouts_meet_the_bound, results_repeat_whatever_the_splits,
    };
    use crate::nn::matmul::{Bf16Kernel, MatmulPrecision, Products};
    use crate::rng::SplitMix64;

    /// This module's products (behind `Products`' shape checks, whatever kernel
    /// `Bf16Kernel::detect` would prefer), or `None` with a visible skip.
    fn kernels() -> Option<Products> {
        match Bf16Kernels::detect() {
            Ok(k) => Some(Products::bf16_on(Bf16Kernel::Avx512Bf16(k))),
            Err(e) => {
                crate::machine::skip_unless_required("GS_REQUIRE_BF16", &e.to_string());
                None
            }
        }
    }

    #[test]
    fn rounding_is_to_nearest_with_ties_to_even() {
        let up = |x: f32| f32::from_bits(x.to_bits() + 1);
        let step = 2f32.powi(-7); // bf16 spacing in [1, 2)
        assert_eq!(round_to_bf16(1.0), 1.0);
        assert_eq!(round_to_bf16(1.0 + step), 1.0 + step);
        // Halfway: ties go to the even neighbour.
        assert_eq!(round_to_bf16(1.0 + step / 2.0), 1.0);
        assert_eq!(round_to_bf16(1.0 + 1.5 * step), 1.0 + 2.0 * step);
        // Just past halfway rounds up; just below rounds down.
        assert_eq!(round_to_bf16(up(1.0 + step / 2.0)), 1.0 + step);
        assert_eq!(round_to_bf16(-(1.0 + 0.49 * step)), -1.0);
        assert_eq!(round_to_bf16(0.0).to_bits(), 0);
        assert_eq!(round_to_bf16(-0.0).to_bits(), (-0.0f32).to_bits());
        // Carry into the exponent, and overflow to infinity past the largest bf16.
        assert_eq!(round_to_bf16(2.0 - step / 4.0), 2.0);
        assert_eq!(round_to_bf16(f32::MAX), f32::INFINITY);
        assert_eq!(round_to_bf16(f32::NEG_INFINITY), f32::NEG_INFINITY);
        // NaN stays NaN, even with a payload whose rounding would carry into the sign.
        assert!(round_to_bf16(f32::NAN).is_nan());
        assert!(round_to_bf16(f32::from_bits(0x7FFF_FFFF)).is_nan());
        assert!(round_to_bf16(f32::from_bits(0xFFFF_FFFF)).is_nan());
        // Relative error at most 2^-8 (8 significant bits) over many magnitudes.
        let mut rng = SplitMix64::new(3);
        for _ in 0..10_000 {
            let x = rng.uniform(-1.0, 1.0) * 2f32.powi(rng.below(60) as i32 - 30);
            let r = round_to_bf16(x);
            assert!((r - x).abs() <= x.abs() * 2f32.powi(-8), "{x} -> {r}");
        }
    }

    #[test]
    fn products_match_references_in_all_three_layouts_and_odd_shapes() {
        let Some(kernels) = kernels() else { return };
        let mut rng = SplitMix64::new(17);
        // k odd and not a multiple of 32, m off the 8-row tile, n off the 16/32 columns.
        let shapes = [
            (1, 1, 1),
            (1, 2, 17),
            (3, 5, 3),
            (8, 32, 32),
            (9, 33, 16),
            (17, 63, 33),
            (37, 19, 55),
            (20, 96, 64),
            (11, 256, 3),
            (64, 257, 1),
        ];
        bf16_layouts_meet_the_bound(kernels, &shapes, &mut rng);
    }

    /// Row splits, repeats and reduction splits at even indices (the second call starts
    /// from the first one's partial sums) keep the bits.
    #[test]
    fn rows_and_even_reduction_splits_keep_the_bits() {
        let Some(kernels) = kernels() else { return };
        results_repeat_whatever_the_splits(kernels, (21, 600, 19), &[2, 76, 256]);
    }

    #[test]
    fn empty_shapes_and_missing_cpu_feature() {
        match Products::new(MatmulPrecision::Bf16) {
            Ok(kernels) => {
                let mut c = vec![5.0; 6];
                kernels.matmul(&[], &[], &mut c, 2, 0, 3, true);
                assert_eq!(c, vec![5.0; 6]);
                kernels.matmul(&[], &[], &mut c, 2, 0, 3, false);
                assert_eq!(c, vec![0.0; 6]);
            }
            Err(e) => {
                let msg = e.to_string();
                assert!(msg.contains("avx512bf16"), "{msg}");
            }
        }
    }
}
