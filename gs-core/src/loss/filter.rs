//! The SSIM window's filters as lane loops over [`LANES`] columns at a time, and the
//! fixed-order row sum of the fused pass's totals.
//!
//! Invariant: every filtered value is the taps added in order `t = 0..11` from +0.0, and
//! [`row_sum`] adds in one fixed lane order, so the bits do not depend on how rows are
//! cut into chunks or on the instruction set the loops are compiled for.

use super::fused::LANES;
use super::{Real, HALF, SSIM_WINDOW};

/// Sum of a row's values in a fixed order: lane `l` adds the values at `l, l + LANES, ...`
/// in order, then the lanes are added pairwise (`l + 8`, `l + 4`, ...). Both the fused pass
/// and the tests' whole-plane reference use it, so their totals can be compared bit for bit.
#[inline(always)]
pub(super) fn row_sum<T: Real>(v: &[T]) -> T {
    let mut acc = [T::ZERO; LANES];
    let mut chunks = v.chunks_exact(LANES);
    for ch in &mut chunks {
        for l in 0..LANES {
            acc[l] += ch[l];
        }
    }
    for (a, &x) in acc.iter_mut().zip(chunks.remainder()) {
        *a += x;
    }
    let mut width = LANES;
    while width > 1 {
        width /= 2;
        for l in 0..width {
            acc[l] += acc[l + width];
        }
    }
    acc[0]
}

#[inline(always)]
pub(super) fn lanes<T>(s: &[T], at: usize) -> &[T; LANES] {
    s[at..at + LANES].try_into().expect("LANES values")
}

#[inline(always)]
pub(super) fn lanes_mut<T>(s: &mut [T], at: usize) -> &mut [T; LANES] {
    (&mut s[at..at + LANES]).try_into().expect("LANES values")
}

/// Chunks of [`LANES`] filtered together: independent sums to hide the adds' latency.
const BLOCK_CHUNKS: usize = 4;

/// Horizontal "same" filtering of one zero-padded row: `src[HALF + i]` is column `i`, with
/// `HALF` zeros before it and at least `HALF` after the last column, `src.len() ==
/// dst.len() + 2 HALF`, `dst.len()` a multiple of [`LANES`]. `dst[i] = sum_t k_t
/// src[i + t]`, taps added in order `t = 0..11` to a zero: the same bits as adding only the
/// in-row taps (a +0 product never changes a sum that started at +0).
#[inline(always)]
pub(super) fn filter_row_padded<T: Real>(src: &[T], taps: &[T; SSIM_WINDOW], dst: &mut [T]) {
    debug_assert_eq!(src.len(), dst.len() + 2 * HALF);
    let mut j = 0;
    while j + BLOCK_CHUNKS * LANES <= dst.len() {
        filter_row_chunks::<T, BLOCK_CHUNKS>(src, taps, dst, j);
        j += BLOCK_CHUNKS * LANES;
    }
    while j < dst.len() {
        filter_row_chunks::<T, 1>(src, taps, dst, j);
        j += LANES;
    }
}

/// `N` chunks of [`filter_row_padded`] from column `j`. The source window and the output
/// are sliced once, so the lane loads and stores need no bounds checks.
#[inline(always)]
fn filter_row_chunks<T: Real, const N: usize>(
    src: &[T],
    taps: &[T; SSIM_WINDOW],
    dst: &mut [T],
    j: usize,
) {
    let src = &src[j..j + N * LANES + 2 * HALF];
    let mut acc = [[T::ZERO; LANES]; N];
    for (t, &k) in taps.iter().enumerate() {
        for (n, a) in acc.iter_mut().enumerate() {
            let s = lanes(src, n * LANES + t);
            for l in 0..LANES {
                a[l] += k * s[l];
            }
        }
    }
    let dst = &mut dst[j..j + N * LANES];
    for (n, a) in acc.iter().enumerate() {
        *lanes_mut(dst, n * LANES) = *a;
    }
}

/// Vertical filtering: `dst = sum_r k_r srcs[r]`, rows added in the given order (increasing
/// image row, only rows inside the image: zero padding). `dst.len()` is a multiple of
/// [`LANES`].
#[inline(always)]
pub(super) fn filter_rows<T: Real>(srcs: &[&[T]], ks: &[T], dst: &mut [T]) {
    let mut j = 0;
    while j + BLOCK_CHUNKS * LANES <= dst.len() {
        filter_rows_chunks::<T, BLOCK_CHUNKS>(srcs, ks, dst, j);
        j += BLOCK_CHUNKS * LANES;
    }
    while j < dst.len() {
        filter_rows_chunks::<T, 1>(srcs, ks, dst, j);
        j += LANES;
    }
}

/// `N` chunks of [`filter_rows`] from column `j` (each source row and the output sliced
/// once: no bounds checks in the lane loads and stores).
#[inline(always)]
fn filter_rows_chunks<T: Real, const N: usize>(srcs: &[&[T]], ks: &[T], dst: &mut [T], j: usize) {
    let mut acc = [[T::ZERO; LANES]; N];
    for (s, &k) in srcs.iter().zip(ks) {
        let s = &s[j..j + N * LANES];
        for (n, a) in acc.iter_mut().enumerate() {
            let s = lanes(s, n * LANES);
            for l in 0..LANES {
                a[l] += k * s[l];
            }
        }
    }
    let dst = &mut dst[j..j + N * LANES];
    for (n, a) in acc.iter().enumerate() {
        *lanes_mut(dst, n * LANES) = *a;
    }
}
