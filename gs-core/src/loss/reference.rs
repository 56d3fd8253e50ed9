//! Test-only references: the SSIM by whole planes filtered one after another (the fused
//! pass must give the same bits) and a serial weighted L1.

use rayon::prelude::*;

use super::filter::row_sum;
use super::{ssim_window, ImageShape, Real, HALF, SSIM_C1, SSIM_C2, SSIM_WINDOW};

/// Separable zero-padded "same" filtering of one `w x h` plane with the SSIM window.
/// `tmp` and `out` must hold `w * h` values.
fn blur<T: Real>(
    src: &[T],
    w: usize,
    h: usize,
    taps: &[T; SSIM_WINDOW],
    tmp: &mut [T],
    out: &mut [T],
) {
    // Horizontal pass, one tap at a time over whole rows so the inner loop vectorises:
    // dst[x] += k_t * row[x + t - HALF] wherever that index is inside the row.
    for y in 0..h {
        let row = &src[y * w..(y + 1) * w];
        let dst = &mut tmp[y * w..(y + 1) * w];
        dst.iter_mut().for_each(|v| *v = T::ZERO);
        for (t, &k) in taps.iter().enumerate() {
            if t >= HALF {
                let shift = t - HALF;
                if shift < w {
                    for (d, &v) in dst[..w - shift].iter_mut().zip(&row[shift..]) {
                        *d += k * v;
                    }
                }
            } else {
                let shift = HALF - t;
                if shift < w {
                    for (d, &v) in dst[shift..].iter_mut().zip(&row[..w - shift]) {
                        *d += k * v;
                    }
                }
            }
        }
    }
    // Vertical pass, accumulating whole rows for cache-friendly access.
    for y in 0..h {
        let dst = &mut out[y * w..(y + 1) * w];
        dst.iter_mut().for_each(|v| *v = T::ZERO);
        let lo = y.saturating_sub(HALF);
        let hi = (y + HALF + 1).min(h);
        for yy in lo..hi {
            let t = taps[yy + HALF - y];
            for (d, &s) in dst.iter_mut().zip(&tmp[yy * w..(yy + 1) * w]) {
                *d += t * s;
            }
        }
    }
}

/// The SSIM before the row-fused passes: whole planes filtered one after another. Kept as
/// the tests' reference for [`weighted_ssim`] (the same bits).
///
/// `pixel_weight[p]` is the weight of pixel `p`'s SSIM values, already divided by the
/// normaliser, so the result is `sum_p sum_c pixel_weight[p] S_c(p)`.
pub(super) fn weighted_ssim_by_planes<T: Real>(
    x: &[T],
    y: &[T],
    shape: ImageShape,
    pixel_weight: &[T],
    want_grad: bool,
) -> (T, Option<Vec<T>>) {
    let (w, h, nc) = (shape.width, shape.height, shape.channels);
    let n = w * h;
    let taps64 = ssim_window();
    let taps: [T; SSIM_WINDOW] = std::array::from_fn(|k| T::from_f64(taps64[k]));
    let c1 = T::from_f64(SSIM_C1);
    let c2 = T::from_f64(SSIM_C2);
    let two = T::from_f64(2.0);

    // Every plane is blurred as its own rayon task (5 per channel forward, 3 backward),
    // which balances better on few cores than one task per channel. Each task's result
    // does not depend on scheduling, and sums are taken in channel order.
    let blur_all = |planes: Vec<Vec<T>>| -> Vec<Vec<T>> {
        planes
            .into_par_iter()
            .map(|plane| {
                let mut tmp = vec![T::ZERO; n];
                let mut out = vec![T::ZERO; n];
                blur(&plane, w, h, &taps, &mut tmp, &mut out);
                out
            })
            .collect()
    };
    let xs: Vec<Vec<T>> = (0..nc)
        .map(|c| (0..n).map(|p| x[p * nc + c]).collect())
        .collect();
    let ys: Vec<Vec<T>> = (0..nc)
        .map(|c| (0..n).map(|p| y[p * nc + c]).collect())
        .collect();
    let mut planes = Vec::with_capacity(5 * nc);
    for c in 0..nc {
        planes.push(xs[c].clone());
        planes.push(ys[c].clone());
        planes.push(xs[c].iter().map(|&v| v * v).collect());
        planes.push(ys[c].iter().map(|&v| v * v).collect());
        planes.push(xs[c].iter().zip(&ys[c]).map(|(&a, &b)| a * b).collect());
    }
    let moments = blur_all(planes);

    // Per channel: the SSIM map's weighted sum and its derivatives with respect to the
    // filtered moments (mu_x, E[x^2], E[xy]).
    let per_channel: Vec<(T, [Vec<T>; 3])> = moments
        .par_chunks(5)
        .map(|m| {
            let (mu_x, mu_y, m_xx, m_yy, m_xy) = (&m[0], &m[1], &m[2], &m[3], &m[4]);
            let mut map = vec![T::ZERO; n];
            let len = if want_grad { n } else { 0 };
            let mut g = [vec![T::ZERO; len], vec![T::ZERO; len], vec![T::ZERO; len]];
            for p in 0..n {
                let (mx, my) = (mu_x[p], mu_y[p]);
                let sxx = m_xx[p] - mx * mx;
                let syy = m_yy[p] - my * my;
                let sxy = m_xy[p] - mx * my;
                let a1 = two * mx * my + c1;
                let a2 = two * sxy + c2;
                let b1 = mx * mx + my * my + c1;
                let b2 = sxx + syy + c2;
                let s = (a1 * a2) / (b1 * b2);
                map[p] = pixel_weight[p] * s;
                if want_grad {
                    let wp = pixel_weight[p];
                    let d_mu =
                        (two * my * (a2 - a1)) / (b1 * b2) - two * mx * s / b1 + two * mx * s / b2;
                    g[0][p] = wp * d_mu;
                    g[1][p] = wp * (-s / b2);
                    g[2][p] = wp * (two * a1 / (b1 * b2));
                }
            }
            // Per row in the fused pass's order, then rows in order.
            let mut total = T::ZERO;
            for row in map.chunks_exact(w) {
                total += row_sum(row);
            }
            (total, g)
        })
        .collect();
    let mut total = T::ZERO;
    for (t, _) in &per_channel {
        total += *t;
    }
    if !want_grad {
        return (total, None);
    }
    let back = blur_all(per_channel.into_iter().flat_map(|(_, g)| g).collect());
    let mut grad = vec![T::ZERO; n * nc];
    for c in 0..nc {
        let (f_mu, f_xx, f_xy) = (&back[3 * c], &back[3 * c + 1], &back[3 * c + 2]);
        for p in 0..n {
            grad[p * nc + c] = f_mu[p] + two * xs[c][p] * f_xx[p] + ys[c][p] * f_xy[p];
        }
    }
    (total, Some(grad))
}

/// Weighted L1 and its gradient with respect to `x` (sign of the difference, 0 at ties),
/// summed serially: the tests' reference for the fused pass's L1 terms.
pub(super) fn weighted_l1<T: Real>(x: &[T], y: &[T], nc: usize, pixel_weight: &[T]) -> (T, Vec<T>) {
    let mut total = T::ZERO;
    let mut grad = vec![T::ZERO; x.len()];
    for (p, &wp) in pixel_weight.iter().enumerate() {
        for c in 0..nc {
            let i = p * nc + c;
            let d = x[i] - y[i];
            if d > T::ZERO {
                total += wp * d;
                grad[i] = wp;
            } else if d < T::ZERO {
                total += wp * -d;
                grad[i] = -wp;
            }
        }
    }
    (total, grad)
}
