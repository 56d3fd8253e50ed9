//! The fused pass ([`fused_pass`]): weighted L1, SSIM and their gradient in one walk over
//! bands of rows (rayon), each streaming rows through two ring buffers of
//! [`SSIM_WINDOW`] rows, on the widest instruction set the CPU has.
//!
//! Invariant: every value is the same sum in the same order as filtering whole planes one
//! after another, and totals are summed per row then over rows in order, so nothing
//! depends on the bands, the threads or the instruction set.

use rayon::prelude::*;

use super::filter::{filter_row_padded, filter_rows, lanes, lanes_mut, row_sum};
use super::{ssim_window, ImageShape, Real, HALF, SSIM_C1, SSIM_C2, SSIM_WINDOW};

/// Lanes of the fixed-width loops: one AVX-512 register of f32 (two of f64). Rows are
/// padded to a multiple of this with zero-weight columns.
pub(super) const LANES: usize = 16;

/// Which instantiation of the band kernel runs. `Detect` picks the widest the CPU has;
/// `Plain` is the baseline build (tests compare the two: the same bits, since Rust never
/// contracts multiplies and adds into FMAs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Isa {
    Detect,
    #[cfg_attr(not(test), allow(dead_code))]
    Plain,
}

/// Rows of one band are never fewer than this (unless the image is shorter): each band
/// recomputes up to 10 rows of moments and 5 of SSIM derivatives beyond its ends, which
/// must stay small beside its own rows.
const MIN_BAND_ROWS: usize = 32;

/// Rows per band for `h` rows: two bands per thread, so a thread that loses its core for a
/// while can hand work to the other. Results never depend on it (see [`fused_pass`]).
pub(super) fn default_band_rows(h: usize) -> usize {
    let tasks = 2 * rayon::current_num_threads().max(1);
    h.div_ceil(tasks).max(MIN_BAND_ROWS)
}

/// How a fused pass is split into work: rows per band, instruction set.
#[derive(Clone, Copy, Debug)]
pub(super) struct Split {
    pub(super) band_rows: usize,
    pub(super) isa: Isa,
}

impl Split {
    /// Two bands per thread, the widest instruction set.
    pub(super) fn default_for(height: usize) -> Self {
        Self {
            band_rows: default_band_rows(height),
            isa: Isa::Detect,
        }
    }
}

/// The image gradient one fused pass returns.
#[derive(Clone, Copy, Debug)]
pub(super) enum GradForm<T> {
    /// Values only.
    None,
    /// `d(sum_p w_p sum_c S_c(p)) / dx`.
    Ssim,
    /// `l1_scale * dL1/dx`.
    L1 { l1_scale: T },
    /// `l1_scale * dL1/dx - ssim_scale * dS/dx` (the combined loss).
    Mixed { l1_scale: T, ssim_scale: T },
}

impl<T> GradForm<T> {
    fn needs_ssim_grad(&self) -> bool {
        matches!(self, GradForm::Ssim | GradForm::Mixed { .. })
    }
    pub(super) fn is_none(&self) -> bool {
        matches!(self, GradForm::None)
    }
}

/// Inputs and constants shared by the bands of one fused pass.
struct FusedInputs<'a, T> {
    x: &'a [T],
    y: &'a [T],
    pixel_weight: &'a [T],
    shape: ImageShape,
    taps: [T; SSIM_WINDOW],
    want_l1: bool,
    grad: GradForm<T>,
}

/// Values one band's rows add to the totals: per row `[l1, ssim of channel 0, ...]`.
fn sums_per_row(nc: usize) -> usize {
    1 + nc
}

/// The loss terms and gradient of one fused pass.
pub(super) struct FusedOutput<T> {
    pub(super) l1: T,
    pub(super) ssim: T,
    pub(super) grad: Vec<T>,
}

/// Weighted L1 and SSIM of `x` against `y` and the gradient `grad`, in bands of rows run in
/// parallel. Per band three stages stream through two ring buffers of [`SSIM_WINDOW`] rows:
/// (A) an input row's five moment planes per channel (`x, y, x^2, y^2, xy`) filtered
/// horizontally; (B) those filtered vertically into the moments of a row, its SSIM map
/// (`pixel_weight * S`, summed per row) and the map's derivatives with respect to `(mu_x,
/// E[x^2], E[xy])`, filtered horizontally; (C) those filtered vertically (`F^T`, the same
/// window: it is symmetric) and combined into `dS/dx = F^T g_mu + 2 x F^T g_xx + y F^T
/// g_xy`, with the L1 term. A band recomputes the rows of A and B it needs beyond its ends
/// (10 and 5), so bands are independent; every value is the same sum in the same order as
/// filtering whole planes one after another (`weighted_ssim_by_planes`, the tests'
/// reference), whatever the bands, threads or instruction set. Totals are summed per row
/// ([`row_sum`]), then over rows in order, then over channels, so they do not depend on the
/// split either.
pub(super) fn fused_pass<T: Real>(
    x: &[T],
    y: &[T],
    shape: ImageShape,
    pixel_weight: &[T],
    want_l1: bool,
    grad: GradForm<T>,
    split: Split,
) -> FusedOutput<T> {
    let Split { band_rows, isa } = split;
    let (w, h, nc) = (shape.width, shape.height, shape.channels);
    let taps64 = ssim_window();
    let inputs = FusedInputs {
        x,
        y,
        pixel_weight,
        shape,
        taps: std::array::from_fn(|k| T::from_f64(taps64[k])),
        want_l1,
        grad,
    };
    let band_rows = band_rows.clamp(1, h.max(1));
    let per_row = sums_per_row(nc);
    let mut sums = vec![T::ZERO; h * per_row];
    let mut out = vec![T::ZERO; if grad.is_none() { 0 } else { w * h * nc }];
    let band_values = if grad.is_none() {
        0
    } else {
        band_rows * w * nc
    };
    let run = |band: usize, grad_rows: &mut [T], sum_rows: &mut [T]| {
        let r0 = band * band_rows;
        let r1 = (r0 + band_rows).min(h);
        run_band(&inputs, r0, r1, grad_rows, sum_rows, isa);
    };
    if grad.is_none() {
        sums.par_chunks_mut(band_rows * per_row)
            .enumerate()
            .for_each(|(band, s)| run(band, &mut [], s));
    } else {
        out.par_chunks_mut(band_values)
            .zip(sums.par_chunks_mut(band_rows * per_row))
            .enumerate()
            .for_each(|(band, (g, s))| run(band, g, s));
    }
    let mut l1 = T::ZERO;
    for row in sums.chunks_exact(per_row) {
        l1 += row[0];
    }
    let mut ssim = T::ZERO;
    for c in 0..nc {
        let mut channel = T::ZERO;
        for row in sums.chunks_exact(per_row) {
            channel += row[1 + c];
        }
        ssim += channel;
    }
    FusedOutput {
        l1,
        ssim,
        grad: out,
    }
}

/// Rows `r0..r1` of [`fused_pass`] with the widest instruction set `isa` allows.
fn run_band<T: Real>(
    inputs: &FusedInputs<T>,
    r0: usize,
    r1: usize,
    grad_rows: &mut [T],
    sum_rows: &mut [T],
    isa: Isa,
) {
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::Detect {
        if std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has AVX-512F (checked just above).
            unsafe { run_band_avx512(inputs, r0, r1, grad_rows, sum_rows) };
            return;
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2 (checked just above).
            unsafe { run_band_avx2(inputs, r0, r1, grad_rows, sum_rows) };
            return;
        }
    }
    let _ = isa;
    run_band_body(inputs, r0, r1, grad_rows, sum_rows);
}

/// [`run_band_body`] compiled for AVX-512F: the lane loops become 512-bit operations, the
/// same separate multiplies and adds, so the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
unsafe fn run_band_avx512<T: Real>(
    inputs: &FusedInputs<T>,
    r0: usize,
    r1: usize,
    grad_rows: &mut [T],
    sum_rows: &mut [T],
) {
    run_band_body(inputs, r0, r1, grad_rows, sum_rows);
}

/// [`run_band_body`] compiled for AVX2 (same bits).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn run_band_avx2<T: Real>(
    inputs: &FusedInputs<T>,
    r0: usize,
    r1: usize,
    grad_rows: &mut [T],
    sum_rows: &mut [T],
) {
    run_band_body(inputs, r0, r1, grad_rows, sum_rows);
}

/// Rows `r0..r1` of [`fused_pass`]: `grad_rows` holds those rows of the gradient (empty
/// without one), `sum_rows` their per-row sums.
#[inline(always)]
fn run_band_body<T: Real>(
    inputs: &FusedInputs<T>,
    r0: usize,
    r1: usize,
    grad_rows: &mut [T],
    sum_rows: &mut [T],
) {
    let FusedInputs {
        x,
        y,
        pixel_weight,
        shape,
        ref taps,
        want_l1,
        grad,
    } = *inputs;
    let (w, h, nc) = (shape.width, shape.height, shape.channels);
    let per_row = sums_per_row(nc);
    let wp = w.next_multiple_of(LANES);
    let padded = wp + 2 * HALF;
    let ssim_grad = grad.needs_ssim_grad();
    let stage_c = want_l1 || !grad.is_none();
    let c1 = T::from_f64(SSIM_C1);
    let c2 = T::from_f64(SSIM_C2);
    let two = T::from_f64(2.0);

    // Stage B runs on the band's rows, and with the SSIM gradient on HALF more either side
    // (stage C's window); stage A on HALF more again (stage B's window).
    let b_lo = if ssim_grad {
        r0.saturating_sub(HALF)
    } else {
        r0
    };
    let a_lo = b_lo.saturating_sub(HALF);
    let slot_a = 5 * nc * wp;
    let slot_b = 3 * nc * wp;
    let mut ring_a = vec![T::ZERO; SSIM_WINDOW * slot_a];
    let mut ring_b = vec![T::ZERO; if ssim_grad { SSIM_WINDOW * slot_b } else { 0 }];
    // One channel's zero-padded rows: x, y, x^2, y^2, xy (stage A), then the three
    // derivative planes (stage B). Only columns HALF..HALF + w are ever written (the
    // derivatives: HALF..HALF + wp, zero beyond w), so the padding stays zero.
    let mut rows_pad = vec![T::ZERO; 5 * padded];
    let mut deriv_pad = vec![T::ZERO; 3 * padded];
    let mut moments = vec![T::ZERO; 5 * wp];
    let mut back = vec![T::ZERO; 3 * wp];
    let mut weight_row = vec![T::ZERO; wp];
    let mut map_row = vec![T::ZERO; wp];
    let mut xs = vec![T::ZERO; wp];
    let mut ys = vec![T::ZERO; wp];
    let mut g_row = vec![T::ZERO; wp];
    let mut l1_row = vec![T::ZERO; wp];

    let mut next_a = a_lo;
    let mut next_b = b_lo;
    for r in r0..r1 {
        let need_b = if ssim_grad {
            (r + HALF + 1).min(h)
        } else {
            r + 1
        };
        while next_b < need_b {
            let need_a = (next_b + HALF + 1).min(h);
            while next_a < need_a {
                // Stage A: row `next_a`'s moment planes, filtered along the row.
                let a = next_a;
                let slot = &mut ring_a[(a % SSIM_WINDOW) * slot_a..][..slot_a];
                for c in 0..nc {
                    let (xr, rest) = rows_pad.split_at_mut(padded);
                    let (yr, rest) = rest.split_at_mut(padded);
                    let (xx, rest) = rest.split_at_mut(padded);
                    let (yy, xy) = rest.split_at_mut(padded);
                    // Channel `c` of the row, out of the interleaved pixels (whole-row
                    // slices and chunks: no bounds check per pixel).
                    let pixels = x[a * w * nc..(a + 1) * w * nc]
                        .chunks_exact(nc)
                        .zip(y[a * w * nc..(a + 1) * w * nc].chunks_exact(nc));
                    for ((xo, yo), (xp, yp)) in xr[HALF..HALF + w]
                        .iter_mut()
                        .zip(&mut yr[HALF..HALF + w])
                        .zip(pixels)
                    {
                        *xo = xp[c];
                        *yo = yp[c];
                    }
                    // Padding columns stay zero: 0 * 0.
                    for ((((o_xx, o_yy), o_xy), &xv), &yv) in xx
                        .iter_mut()
                        .zip(yy.iter_mut())
                        .zip(xy.iter_mut())
                        .zip(xr.iter())
                        .zip(yr.iter())
                    {
                        *o_xx = xv * xv;
                        *o_yy = yv * yv;
                        *o_xy = xv * yv;
                    }
                    for (q, src) in rows_pad.chunks_exact(padded).enumerate() {
                        filter_row_padded(src, taps, &mut slot[(5 * c + q) * wp..][..wp]);
                    }
                }
                next_a += 1;
            }

            // Stage B: row `b`'s moments, SSIM map and derivatives.
            let b = next_b;
            let lo = b.saturating_sub(HALF);
            let hi = (b + HALF + 1).min(h);
            let ks = &taps[lo + HALF - b..hi + HALF - b];
            weight_row[..w].copy_from_slice(&pixel_weight[b * w..(b + 1) * w]);
            let own_row = (r0..r1).contains(&b);
            for c in 0..nc {
                for q in 0..5 {
                    let mut srcs: [&[T]; SSIM_WINDOW] = [&[]; SSIM_WINDOW];
                    for (s, row) in srcs.iter_mut().zip(lo..hi) {
                        *s = &ring_a[(row % SSIM_WINDOW) * slot_a + (5 * c + q) * wp..][..wp];
                    }
                    filter_rows(&srcs[..hi - lo], ks, &mut moments[q * wp..(q + 1) * wp]);
                }
                let (mu_x, rest) = moments.split_at(wp);
                let (mu_y, rest) = rest.split_at(wp);
                let (m_xx, rest) = rest.split_at(wp);
                let (m_yy, m_xy) = rest.split_at(wp);
                let (d_mu, rest) = deriv_pad.split_at_mut(padded);
                let (d_xx, d_xy) = rest.split_at_mut(padded);
                for i in (0..wp).step_by(LANES) {
                    let (mx, my) = (lanes(mu_x, i), lanes(mu_y, i));
                    let (exx, eyy, exy) = (lanes(m_xx, i), lanes(m_yy, i), lanes(m_xy, i));
                    let wv = lanes(&weight_row, i);
                    let mut s = [T::ZERO; LANES];
                    let mut g = [[T::ZERO; LANES]; 3];
                    for l in 0..LANES {
                        let (mx, my) = (mx[l], my[l]);
                        let sxx = exx[l] - mx * mx;
                        let syy = eyy[l] - my * my;
                        let sxy = exy[l] - mx * my;
                        let a1 = two * mx * my + c1;
                        let a2 = two * sxy + c2;
                        let b1 = mx * mx + my * my + c1;
                        let b2 = sxx + syy + c2;
                        let sv = (a1 * a2) / (b1 * b2);
                        s[l] = wv[l] * sv;
                        // Computed even when unused: a branch here would keep the lane
                        // loop from vectorising.
                        let dm = (two * my * (a2 - a1)) / (b1 * b2) - two * mx * sv / b1
                            + two * mx * sv / b2;
                        g[0][l] = wv[l] * dm;
                        g[1][l] = wv[l] * (-sv / b2);
                        g[2][l] = wv[l] * (two * a1 / (b1 * b2));
                    }
                    *lanes_mut(&mut map_row, i) = s;
                    if ssim_grad {
                        *lanes_mut(d_mu, HALF + i) = g[0];
                        *lanes_mut(d_xx, HALF + i) = g[1];
                        *lanes_mut(d_xy, HALF + i) = g[2];
                    }
                }
                if own_row {
                    sum_rows[(b - r0) * per_row + 1 + c] = row_sum(&map_row[..w]);
                }
                if ssim_grad {
                    // Columns w..wp got weight 0: their derivatives are zeros, the padding
                    // of the backward filter.
                    let slot = &mut ring_b[(b % SSIM_WINDOW) * slot_b..][..slot_b];
                    for (q, src) in deriv_pad.chunks_exact(padded).enumerate() {
                        filter_row_padded(src, taps, &mut slot[(3 * c + q) * wp..][..wp]);
                    }
                }
            }
            next_b += 1;
        }
        if !stage_c {
            continue;
        }

        // Stage C: row `r`'s L1 and gradient.
        let lo = r.saturating_sub(HALF);
        let hi = (r + HALF + 1).min(h);
        let ks = &taps[lo + HALF - r..hi + HALF - r];
        weight_row[..w].copy_from_slice(&pixel_weight[r * w..(r + 1) * w]);
        let mut l1_total = T::ZERO;
        for c in 0..nc {
            let pixels = x[r * w * nc..(r + 1) * w * nc]
                .chunks_exact(nc)
                .zip(y[r * w * nc..(r + 1) * w * nc].chunks_exact(nc));
            for ((xo, yo), (xp, yp)) in xs[..w].iter_mut().zip(&mut ys[..w]).zip(pixels) {
                *xo = xp[c];
                *yo = yp[c];
            }
            if ssim_grad {
                for q in 0..3 {
                    let mut srcs: [&[T]; SSIM_WINDOW] = [&[]; SSIM_WINDOW];
                    for (s, row) in srcs.iter_mut().zip(lo..hi) {
                        *s = &ring_b[(row % SSIM_WINDOW) * slot_b + (3 * c + q) * wp..][..wp];
                    }
                    filter_rows(&srcs[..hi - lo], ks, &mut back[q * wp..(q + 1) * wp]);
                }
            }
            let (f_mu, rest) = back.split_at(wp);
            let (f_xx, f_xy) = rest.split_at(wp);
            for i in (0..wp).step_by(LANES) {
                let (xv, yv, wv) = (lanes(&xs, i), lanes(&ys, i), lanes(&weight_row, i));
                let mut term = [T::ZERO; LANES];
                let mut d_l1 = [T::ZERO; LANES];
                for l in 0..LANES {
                    // |x - y| weighted, and its derivative: the sign, 0 at ties.
                    let d = xv[l] - yv[l];
                    let (t, dl) = if d > T::ZERO {
                        (wv[l] * d, wv[l])
                    } else if d < T::ZERO {
                        (wv[l] * -d, -wv[l])
                    } else {
                        (T::ZERO, T::ZERO)
                    };
                    term[l] = t;
                    d_l1[l] = dl;
                }
                *lanes_mut(&mut l1_row, i) = term;
                let (fm, fx, fy) = (lanes(f_mu, i), lanes(f_xx, i), lanes(f_xy, i));
                let out = lanes_mut(&mut g_row, i);
                match grad {
                    GradForm::None => {}
                    GradForm::L1 { l1_scale } => {
                        for l in 0..LANES {
                            out[l] = l1_scale * d_l1[l];
                        }
                    }
                    GradForm::Ssim => {
                        for l in 0..LANES {
                            out[l] = fm[l] + two * xv[l] * fx[l] + yv[l] * fy[l];
                        }
                    }
                    GradForm::Mixed {
                        l1_scale,
                        ssim_scale,
                    } => {
                        for l in 0..LANES {
                            let ds = fm[l] + two * xv[l] * fx[l] + yv[l] * fy[l];
                            out[l] = l1_scale * d_l1[l] - ssim_scale * ds;
                        }
                    }
                }
            }
            if want_l1 {
                l1_total += row_sum(&l1_row[..w]);
            }
            if !grad.is_none() {
                let dst = &mut grad_rows[(r - r0) * w * nc..(r - r0 + 1) * w * nc];
                for (px, &g) in dst.chunks_exact_mut(nc).zip(&g_row[..w]) {
                    px[c] = g;
                }
            }
        }
        sum_rows[(r - r0) * per_row] = l1_total;
    }
}
