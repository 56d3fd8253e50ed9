//! Photometric losses (L1, SSIM) with analytic backward, and metrics (PSNR, SSIM).
//!
//! Images are `height * width * channels` values, pixel-major (`[p0.r, p0.g, p0.b, p1.r,
//! ...]`), rows top to bottom, as the rasterizer writes them.
//!
//! SSIM follows the reference 3DGS code: an 11x11 Gaussian window (sigma 1.5, normalised
//! to sum 1) applied separably with ZERO padding and "same" output size, C1 = 0.01^2,
//! C2 = 0.03^2, one SSIM map per channel, then the mean over pixels and channels.
//! The backward pass is analytic: with `mu = F x`, `m_xx = F x^2`, `m_xy = F (x y)`
//! (F the window filter, y the fixed target), the per-pixel derivatives of the SSIM map
//! with respect to `mu`, `m_xx`, `m_xy` are filtered back with F^T (= F: the window is
//! symmetric and zero padding makes the transpose the same operation) and combined as
//! `dL/dx = F^T g_mu + 2 x F^T g_xx + y F^T g_xy`. The filtering runs as three row-parallel
//! passes that fuse the moments, the map and the backward per row; each value is the same
//! sum in the same order whatever the thread count, so results are bit-identical.
//!
//! How the foreground mask enters (`mask`: one weight in [0, 1] per pixel): both terms
//! become mask-weighted means over pixels, `L1 = sum_p m_p sum_c |x - y| / (C sum_p m_p)`
//! and `SSIM = sum_p m_p sum_c S_c(p) / (C sum_p m_p)`. The images themselves are NOT
//! masked: the SSIM window of a pixel inside the mask still sees its neighbours outside
//! it, so pixels within 5 px of the mask receive gradient too; pixels farther out get
//! exactly zero. An all-zero mask is an error (nothing to learn from).
//!
//! The loss is `(1 - lambda) L1 + lambda (1 - SSIM)`, 3DGS uses lambda = 0.2.
//! Internally the maths is generic over f32 (training) and f64 (metrics, gradient
//! checks), so the finite-difference reference runs the very same code in double.

use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub};

use rayon::prelude::*;

/// SSIM stabilisers for a dynamic range of 1.
pub const SSIM_C1: f64 = 0.01 * 0.01;
pub const SSIM_C2: f64 = 0.03 * 0.03;
/// Window side and standard deviation, pixels.
pub const SSIM_WINDOW: usize = 11;
pub const SSIM_SIGMA_PX: f64 = 1.5;
const HALF: usize = SSIM_WINDOW / 2;

/// Size of an image buffer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageShape {
    pub width: usize,
    pub height: usize,
    pub channels: usize,
}

impl ImageShape {
    pub fn new(width: usize, height: usize, channels: usize) -> Self {
        Self {
            width,
            height,
            channels,
        }
    }

    pub fn pixels(&self) -> usize {
        self.width * self.height
    }

    pub fn values(&self) -> usize {
        self.pixels() * self.channels
    }
}

/// Error from a loss or metric.
#[derive(Debug, Clone, PartialEq)]
pub enum LossError {
    /// A buffer did not match the image shape.
    Length {
        what: &'static str,
        expected: usize,
        got: usize,
    },
    /// Zero width, height or channels.
    EmptyImage,
    /// A NaN or infinity in an input buffer.
    NonFinite { what: &'static str, index: usize },
    /// A mask weight outside [0, 1].
    MaskRange { index: usize, value: f32 },
    /// The mask is zero everywhere.
    EmptyMask,
    /// `lambda_dssim` outside [0, 1].
    Lambda(f32),
}

impl std::fmt::Display for LossError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LossError::Length {
                what,
                expected,
                got,
            } => write!(f, "{what}: expected {expected} values, got {got}"),
            LossError::EmptyImage => write!(f, "image has zero width, height or channels"),
            LossError::NonFinite { what, index } => {
                write!(f, "{what}: non-finite value at index {index}")
            }
            LossError::MaskRange { index, value } => {
                write!(f, "mask weight {value} at pixel {index} is outside [0, 1]")
            }
            LossError::EmptyMask => write!(f, "mask is zero everywhere"),
            LossError::Lambda(l) => write!(f, "lambda_dssim {l} is outside [0, 1]"),
        }
    }
}

impl std::error::Error for LossError {}

/// The scalar type the loss maths runs in (f32 for training, f64 for references).
pub(crate) trait Real:
    Copy
    + Send
    + Sync
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
{
    const ZERO: Self;
    fn from_f64(v: f64) -> Self;
}

impl Real for f32 {
    const ZERO: Self = 0.0;
    fn from_f64(v: f64) -> Self {
        v as f32
    }
}

impl Real for f64 {
    const ZERO: Self = 0.0;
    fn from_f64(v: f64) -> Self {
        v
    }
}

/// Normalised 1D Gaussian window taps (sum 1), computed in f64.
pub fn ssim_window() -> [f64; SSIM_WINDOW] {
    let mut w = [0.0f64; SSIM_WINDOW];
    for (k, v) in w.iter_mut().enumerate() {
        let d = k as f64 - HALF as f64;
        *v = (-d * d / (2.0 * SSIM_SIGMA_PX * SSIM_SIGMA_PX)).exp();
    }
    let sum: f64 = w.iter().sum();
    w.iter_mut().for_each(|v| *v /= sum);
    w
}

/// Horizontal zero-padded "same" filtering of one row with the SSIM window, one tap at a
/// time over the whole row so the inner loop vectorises: `dst[x] = sum_t k_t row[x + t -
/// HALF]` over the in-row indices, taps added in order `t = 0..11` (the order every
/// value's rounding depends on).
fn filter_row<T: Real>(row: &[T], taps: &[T; SSIM_WINDOW], dst: &mut [T]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just above).
        unsafe { filter_row_avx2(row, taps, dst) };
        return;
    }
    filter_row_body(row, taps, dst);
}

/// [`filter_row_body`] compiled for AVX2: 8 lanes instead of SSE's 4, the same separate
/// multiplies and adds (Rust never contracts them into FMAs), so the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn filter_row_avx2<T: Real>(row: &[T], taps: &[T; SSIM_WINDOW], dst: &mut [T]) {
    filter_row_body(row, taps, dst);
}

#[inline(always)]
fn filter_row_body<T: Real>(row: &[T], taps: &[T; SSIM_WINDOW], dst: &mut [T]) {
    let w = row.len();
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

/// Vertical pass for output row `y`: `acc = sum_yy k_{yy - y + HALF} rows[yy]` over the
/// rows inside the image, added in order of `yy` (zero padding). `rows` holds `h` rows of
/// `stride` values each, of which the first `acc.len()` are filtered, each independently.
fn filter_column_into<T: Real>(
    rows: &[T],
    stride: usize,
    h: usize,
    y: usize,
    taps: &[T; SSIM_WINDOW],
    acc: &mut [T],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just above).
        unsafe { filter_column_avx2(rows, stride, h, y, taps, acc) };
        return;
    }
    filter_column_body(rows, stride, h, y, taps, acc);
}

/// [`filter_column_body`] compiled for AVX2 (same bits, as for rows).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn filter_column_avx2<T: Real>(
    rows: &[T],
    stride: usize,
    h: usize,
    y: usize,
    taps: &[T; SSIM_WINDOW],
    acc: &mut [T],
) {
    filter_column_body(rows, stride, h, y, taps, acc);
}

#[inline(always)]
fn filter_column_body<T: Real>(
    rows: &[T],
    stride: usize,
    h: usize,
    y: usize,
    taps: &[T; SSIM_WINDOW],
    acc: &mut [T],
) {
    acc.iter_mut().for_each(|v| *v = T::ZERO);
    let len = acc.len();
    let lo = y.saturating_sub(HALF);
    let hi = (y + HALF + 1).min(h);
    for yy in lo..hi {
        let t = taps[yy + HALF - y];
        for (d, &s) in acc.iter_mut().zip(&rows[yy * stride..yy * stride + len]) {
            *d += t * s;
        }
    }
}

/// Rows per rayon task in the SSIM passes: enough work per task to amortise scheduling;
/// every value is computed the same way whatever the split, so results never depend on it.
const SSIM_ROWS_PER_TASK: usize = 32;

/// Weighted SSIM of two images and optionally its gradient with respect to `x`.
///
/// `pixel_weight[p]` is the weight of pixel `p`'s SSIM values, already divided by the
/// normaliser, so the result is `sum_p sum_c pixel_weight[p] S_c(p)`.
///
/// Three passes over rows, each parallel over rows (row results do not depend on the
/// split): (1) the five moment planes of every channel filtered horizontally; (2) filtered
/// vertically, the SSIM map and its derivatives, those filtered horizontally; (3) filtered
/// vertically and combined into `dL/dx`. Every value is the same sum in the same order as
/// filtering whole planes one after another (`weighted_ssim_by_planes`, the test
/// reference), and the total is summed per channel in pixel order, so results are the same
/// bits as before the fusion.
fn weighted_ssim<T: Real>(
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

    // Pass 1: per row, channel-major then plane (x, y, x^2, y^2, xy), each filtered along
    // the row.
    let moment_stride = 5 * nc * w;
    let mut moments_h = vec![T::ZERO; moment_stride * h];
    moments_h
        .par_chunks_mut(moment_stride)
        .with_min_len(SSIM_ROWS_PER_TASK)
        .enumerate()
        .for_each_init(
            || vec![T::ZERO; 5 * w],
            |planes, (row, out)| {
                let (xr, rest) = planes.split_at_mut(w);
                let (yr, rest) = rest.split_at_mut(w);
                let (xx, rest) = rest.split_at_mut(w);
                let (yy, xy) = rest.split_at_mut(w);
                for c in 0..nc {
                    for i in 0..w {
                        let p = row * w + i;
                        let (a, b) = (x[p * nc + c], y[p * nc + c]);
                        xr[i] = a;
                        yr[i] = b;
                        xx[i] = a * a;
                        yy[i] = b * b;
                        xy[i] = a * b;
                    }
                    let dst = &mut out[5 * c * w..5 * (c + 1) * w];
                    for (q, src) in [&*xr, &*yr, &*xx, &*yy, &*xy].into_iter().enumerate() {
                        filter_row(src, &taps, &mut dst[q * w..(q + 1) * w]);
                    }
                }
            },
        );

    // Pass 2: per row, the derivatives of the SSIM map with respect to (mu_x, E[x^2],
    // E[xy]) filtered along the row (3 planes per channel, when the gradient is wanted),
    // then `pixel_weight * S` per channel (summed in pixel order below).
    let grad_width = if want_grad { 3 * nc * w } else { 0 };
    let map_stride = grad_width + nc * w;
    let mut maps = vec![T::ZERO; map_stride * h];
    maps.par_chunks_mut(map_stride)
        .with_min_len(SSIM_ROWS_PER_TASK)
        .enumerate()
        .for_each_init(
            || (vec![T::ZERO; moment_stride], vec![T::ZERO; 3 * w]),
            |(m, g), (row, out)| {
                filter_column_into(&moments_h, moment_stride, h, row, &taps, m);
                let (grad_h, weighted) = out.split_at_mut(grad_width);
                for c in 0..nc {
                    let mc = &m[5 * c * w..5 * (c + 1) * w];
                    let (mu_x, rest) = mc.split_at(w);
                    let (mu_y, rest) = rest.split_at(w);
                    let (m_xx, rest) = rest.split_at(w);
                    let (m_yy, m_xy) = rest.split_at(w);
                    let wrow = &pixel_weight[row * w..(row + 1) * w];
                    let ws = &mut weighted[c * w..(c + 1) * w];
                    for i in 0..w {
                        let (mx, my) = (mu_x[i], mu_y[i]);
                        let sxx = m_xx[i] - mx * mx;
                        let syy = m_yy[i] - my * my;
                        let sxy = m_xy[i] - mx * my;
                        let a1 = two * mx * my + c1;
                        let a2 = two * sxy + c2;
                        let b1 = mx * mx + my * my + c1;
                        let b2 = sxx + syy + c2;
                        let s = (a1 * a2) / (b1 * b2);
                        let wp = wrow[i];
                        ws[i] = wp * s;
                        if want_grad {
                            let d_mu = (two * my * (a2 - a1)) / (b1 * b2) - two * mx * s / b1
                                + two * mx * s / b2;
                            g[i] = wp * d_mu;
                            g[w + i] = wp * (-s / b2);
                            g[2 * w + i] = wp * (two * a1 / (b1 * b2));
                        }
                    }
                    if want_grad {
                        for q in 0..3 {
                            filter_row(
                                &g[q * w..(q + 1) * w],
                                &taps,
                                &mut grad_h[(3 * c + q) * w..(3 * c + q + 1) * w],
                            );
                        }
                    }
                }
            },
        );
    let mut total = T::ZERO;
    for c in 0..nc {
        let mut channel_total = T::ZERO;
        for row in maps.chunks_exact(map_stride) {
            for &v in &row[grad_width + c * w..grad_width + (c + 1) * w] {
                channel_total += v;
            }
        }
        total += channel_total;
    }
    if !want_grad {
        return (total, None);
    }

    // Pass 3: the vertical half of F^T, then dL/dx = F^T g_mu + 2 x F^T g_xx + y F^T g_xy.
    let mut grad = vec![T::ZERO; n * nc];
    grad.par_chunks_mut(w * nc)
        .with_min_len(SSIM_ROWS_PER_TASK)
        .enumerate()
        .for_each_init(
            || vec![T::ZERO; grad_width],
            |back, (row, out)| {
                filter_column_into(&maps, map_stride, h, row, &taps, back);
                for c in 0..nc {
                    let f_mu = &back[3 * c * w..(3 * c + 1) * w];
                    let f_xx = &back[(3 * c + 1) * w..(3 * c + 2) * w];
                    let f_xy = &back[(3 * c + 2) * w..(3 * c + 3) * w];
                    for i in 0..w {
                        let p = row * w + i;
                        out[i * nc + c] =
                            f_mu[i] + two * x[p * nc + c] * f_xx[i] + y[p * nc + c] * f_xy[i];
                    }
                }
            },
        );
    (total, Some(grad))
}

#[cfg(test)]
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
#[cfg(test)]
///
/// `pixel_weight[p]` is the weight of pixel `p`'s SSIM values, already divided by the
/// normaliser, so the result is `sum_p sum_c pixel_weight[p] S_c(p)`.
fn weighted_ssim_by_planes<T: Real>(
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
            let mut total = T::ZERO;
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
                total += pixel_weight[p] * s;
                if want_grad {
                    let wp = pixel_weight[p];
                    let d_mu =
                        (two * my * (a2 - a1)) / (b1 * b2) - two * mx * s / b1 + two * mx * s / b2;
                    g[0][p] = wp * d_mu;
                    g[1][p] = wp * (-s / b2);
                    g[2][p] = wp * (two * a1 / (b1 * b2));
                }
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

/// Weighted L1 and its gradient with respect to `x` (sign of the difference, 0 at ties).
fn weighted_l1<T: Real>(x: &[T], y: &[T], nc: usize, pixel_weight: &[T]) -> (T, Vec<T>) {
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

fn check_image(what: &'static str, v: &[f32], shape: ImageShape) -> Result<(), LossError> {
    if shape.values() == 0 {
        return Err(LossError::EmptyImage);
    }
    if v.len() != shape.values() {
        return Err(LossError::Length {
            what,
            expected: shape.values(),
            got: v.len(),
        });
    }
    if let Some(index) = v.iter().position(|x| !x.is_finite()) {
        return Err(LossError::NonFinite { what, index });
    }
    Ok(())
}

/// Per-pixel weights `m_p / (C sum m)`, in the loss's scalar type.
fn pixel_weights<T: Real>(mask: Option<&[f32]>, shape: ImageShape) -> Result<Vec<T>, LossError> {
    let n = shape.pixels();
    match mask {
        None => {
            let w = T::from_f64(1.0 / (n * shape.channels) as f64);
            Ok(vec![w; n])
        }
        Some(m) => {
            if m.len() != n {
                return Err(LossError::Length {
                    what: "mask",
                    expected: n,
                    got: m.len(),
                });
            }
            if let Some(index) = m.iter().position(|v| !v.is_finite()) {
                return Err(LossError::NonFinite {
                    what: "mask",
                    index,
                });
            }
            if let Some(index) = m.iter().position(|&v| !(0.0..=1.0).contains(&v)) {
                return Err(LossError::MaskRange {
                    index,
                    value: m[index],
                });
            }
            let sum: f64 = m.iter().map(|&v| v as f64).sum();
            if sum <= 0.0 {
                return Err(LossError::EmptyMask);
            }
            let norm = 1.0 / (sum * shape.channels as f64);
            Ok(m.iter().map(|&v| T::from_f64(v as f64 * norm)).collect())
        }
    }
}

/// Value and gradient of the combined loss.
#[derive(Clone, Debug, PartialEq)]
pub struct LossOutput {
    /// `(1 - lambda) l1 + lambda (1 - ssim)`.
    pub loss: f32,
    /// (Masked) mean absolute error.
    pub l1: f32,
    /// (Masked) mean SSIM.
    pub ssim: f32,
    /// Gradient of `loss` with respect to the rendered image, same layout.
    pub d_rendered: Vec<f32>,
}

fn photometric_loss_generic<T: Real>(
    rendered: &[T],
    target: &[T],
    weights: &[T],
    shape: ImageShape,
    lambda_dssim: f64,
) -> (T, T, T, Vec<T>) {
    let lambda = T::from_f64(lambda_dssim);
    let one = T::from_f64(1.0);
    let (l1, d_l1) = weighted_l1(rendered, target, shape.channels, weights);
    let (ssim, d_ssim) = if lambda_dssim > 0.0 {
        let (s, g) = weighted_ssim(rendered, target, shape, weights, true);
        (s, g.expect("gradient requested"))
    } else {
        // SSIM is not part of the loss: report it without paying for its backward.
        (
            weighted_ssim(rendered, target, shape, weights, false).0,
            Vec::new(),
        )
    };
    let loss = (one - lambda) * l1 + lambda * (one - ssim);
    let mut grad = d_l1;
    for g in grad.iter_mut() {
        *g = (one - lambda) * *g;
    }
    for (g, &s) in grad.iter_mut().zip(&d_ssim) {
        *g = *g - lambda * s;
    }
    (loss, l1, ssim, grad)
}

/// `(1 - lambda_dssim) L1 + lambda_dssim (1 - SSIM)` of `rendered` against `target`, with
/// its analytic gradient. See the module header for how `mask` enters.
pub fn photometric_loss(
    rendered: &[f32],
    target: &[f32],
    mask: Option<&[f32]>,
    shape: ImageShape,
    lambda_dssim: f32,
) -> Result<LossOutput, LossError> {
    check_image("rendered image", rendered, shape)?;
    check_image("target image", target, shape)?;
    if !(0.0..=1.0).contains(&lambda_dssim) {
        return Err(LossError::Lambda(lambda_dssim));
    }
    let weights = pixel_weights::<f32>(mask, shape)?;
    let (loss, l1, ssim, d_rendered) =
        photometric_loss_generic(rendered, target, &weights, shape, lambda_dssim as f64);
    Ok(LossOutput {
        loss,
        l1,
        ssim,
        d_rendered,
    })
}

fn clamp_unit(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| x.clamp(0.0, 1.0) as f64).collect()
}

/// Mean SSIM over pixels and channels (same window as the loss), computed in f64 on
/// images clamped to [0, 1] as 3DGS evaluates renders.
pub fn ssim(a: &[f32], b: &[f32], shape: ImageShape) -> Result<f32, LossError> {
    check_image("first image", a, shape)?;
    check_image("second image", b, shape)?;
    let weights = pixel_weights::<f64>(None, shape)?;
    let (s, _) = weighted_ssim(&clamp_unit(a), &clamp_unit(b), shape, &weights, false);
    Ok(s as f32)
}

/// PSNR in dB, `10 log10(1 / MSE)`, over all values of images clamped to [0, 1];
/// identical images give `f32::INFINITY`.
pub fn psnr(a: &[f32], b: &[f32], shape: ImageShape) -> Result<f32, LossError> {
    check_image("first image", a, shape)?;
    check_image("second image", b, shape)?;
    let mse: f64 = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| {
            let d = x.clamp(0.0, 1.0) as f64 - y.clamp(0.0, 1.0) as f64;
            d * d
        })
        .sum::<f64>()
        / a.len() as f64;
    Ok(if mse == 0.0 {
        f32::INFINITY
    } else {
        (-10.0 * mse.log10()) as f32
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    fn random_image(shape: ImageShape, seed: u64) -> Vec<f64> {
        let mut s = seed;
        (0..shape.values()).map(|_| lcg(&mut s)).collect()
    }

    /// Loss in f64 through the same generic code (the finite-difference reference).
    fn loss64(x: &[f64], y: &[f64], w: &[f64], shape: ImageShape, lambda: f64) -> f64 {
        photometric_loss_generic(x, y, w, shape, lambda).0
    }

    #[test]
    fn window_is_the_normalised_gaussian() {
        let w = ssim_window();
        assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-15);
        // Hand value: centre tap = 1 / sum_k exp(-k^2 / 4.5), k = -5..5.
        let denom: f64 = (-5i32..=5).map(|k| (-(k * k) as f64 / 4.5).exp()).sum();
        assert!((w[5] - 1.0 / denom).abs() < 1e-15);
        assert!((w[5] - 0.266_011_9).abs() < 1e-6);
        assert_eq!(w[0], w[10]);
    }

    #[test]
    fn identical_images_have_ssim_one_and_zero_gradient() {
        let shape = ImageShape::new(17, 12, 3);
        let x: Vec<f32> = random_image(shape, 1).iter().map(|&v| v as f32).collect();
        assert!((ssim(&x, &x, shape).unwrap() - 1.0).abs() < 1e-6);
        assert_eq!(psnr(&x, &x, shape).unwrap(), f32::INFINITY);
        let out = photometric_loss(&x, &x, None, shape, 0.2).unwrap();
        assert!(out.loss.abs() < 1e-6);
        assert!(out.d_rendered.iter().all(|g| g.abs() < 1e-5));
    }

    /// Two constant images c1, c2: with zero padding the filtered moments at pixel p are
    /// `mu = c w(p)`, `sigma^2 = c^2 (w - w^2)`, `sigma_xy = c1 c2 (w - w^2)` where
    /// `w(p) = wx(u) wy(v)` is the window mass inside the image. This closed form is
    /// evaluated here independently of the filter code.
    #[test]
    fn constant_images_match_the_closed_form() {
        let (c1, c2) = (0.2f64, 0.6f64);
        let shape = ImageShape::new(30, 20, 1);
        let a = vec![c1 as f32; shape.values()];
        let b = vec![c2 as f32; shape.values()];
        let taps: Vec<f64> = (-5i32..=5).map(|k| (-(k * k) as f64 / 4.5).exp()).collect();
        let tsum: f64 = taps.iter().sum();
        let mass = |i: usize, len: usize| -> f64 {
            (0..11)
                .filter(|&t| {
                    let j = i as i64 + t as i64 - 5;
                    j >= 0 && j < len as i64
                })
                .map(|t| taps[t] / tsum)
                .sum()
        };
        let mut expected = 0.0;
        for v in 0..shape.height {
            for u in 0..shape.width {
                let w = mass(u, shape.width) * mass(v, shape.height);
                let var = w - w * w;
                let s = (2.0 * c1 * c2 * w * w + SSIM_C1) * (2.0 * c1 * c2 * var + SSIM_C2)
                    / (((c1 * c1 + c2 * c2) * w * w + SSIM_C1)
                        * ((c1 * c1 + c2 * c2) * var + SSIM_C2));
                expected += s;
            }
        }
        expected /= shape.pixels() as f64;
        let got = ssim(&a, &b, shape).unwrap() as f64;
        assert!((got - expected).abs() < 1e-6, "{got} vs {expected}");
        // Far from the border the window is complete: (2 c1 c2 + C1) / (c1^2 + c2^2 + C1)
        // = 0.2401 / 0.4001 = 0.600099975. A mask on that one pixel and lambda = 1 make
        // the loss exactly 1 - S(p). In f64 it is exact to round-off; in f32 the variance
        // `E[x^2] - mu^2` cancels (error ~1e-8 against C2 = 9e-4), hence 1e-4 there.
        let mut one_pixel = vec![0.0f32; shape.pixels()];
        one_pixel[10 * shape.width + 15] = 1.0;
        let w: Vec<f64> = pixel_weights(Some(&one_pixel), shape).unwrap();
        let a64 = vec![c1; shape.values()];
        let b64 = vec![c2; shape.values()];
        let (loss, _, _, _) = photometric_loss_generic(&a64, &b64, &w, shape, 1.0);
        assert!((1.0 - loss - 0.600_099_975).abs() < 1e-9, "{loss}");
        let out = photometric_loss(&a, &b, Some(&one_pixel), shape, 1.0).unwrap();
        assert!((1.0 - out.loss as f64 - 0.600_099_975).abs() < 1e-4);
        // PSNR of a 0.4 offset: MSE 0.16, 10 log10(1 / 0.16) = 7.9588 dB.
        assert!((psnr(&a, &b, shape).unwrap() - 7.958_8).abs() < 1e-4);
    }

    /// Central differences in f64 (h = 1e-6) against the analytic gradient in f64, for
    /// the SSIM term alone, L1 alone and the mix, with and without a soft mask, on images
    /// both larger and smaller than the window. Truncation error ~h^2 * 1e3, round-off
    /// ~1e-16 / h: 1e-7 absolute on gradients of size ~1e-3 is tight but safe.
    #[test]
    fn analytic_gradient_matches_central_differences() {
        for (shape, seed) in [
            (ImageShape::new(14, 11, 3), 3u64),
            (ImageShape::new(6, 4, 2), 4),
        ] {
            let x = random_image(shape, seed);
            let y = random_image(shape, seed + 100);
            let mut s = seed;
            let mask: Vec<f32> = (0..shape.pixels())
                .map(|_| {
                    if lcg(&mut s) < 0.3 {
                        0.0
                    } else {
                        lcg(&mut s) as f32
                    }
                })
                .collect();
            for use_mask in [false, true] {
                let w: Vec<f64> =
                    pixel_weights(use_mask.then_some(mask.as_slice()), shape).unwrap();
                for lambda in [0.0, 0.2, 1.0] {
                    let (_, _, _, grad) = photometric_loss_generic(&x, &y, &w, shape, lambda);
                    let h = 1e-6;
                    for i in 0..x.len() {
                        let mut xp = x.clone();
                        xp[i] += h;
                        let mut xm = x.clone();
                        xm[i] -= h;
                        let fd = (loss64(&xp, &y, &w, shape, lambda)
                            - loss64(&xm, &y, &w, shape, lambda))
                            / (2.0 * h);
                        assert!(
                            (fd - grad[i]).abs() < 1e-7,
                            "{shape:?} mask {use_mask} lambda {lambda} [{i}]: fd {fd} vs {}",
                            grad[i]
                        );
                    }
                }
            }
        }
    }

    /// The f32 training path agrees with the f64 reference to f32 accuracy.
    #[test]
    fn row_fused_ssim_is_bit_identical_to_whole_plane_filtering() {
        // Shapes narrower and shorter than the window, odd sizes, one and three channels,
        // with and without a mask: value and gradient must be the same bits, in f32 (the
        // training path) and f64 (metrics).
        for (i, &(w, h, nc)) in [(40, 23, 3), (7, 5, 3), (3, 30, 1), (61, 2, 3), (16, 16, 2)]
            .iter()
            .enumerate()
        {
            let shape = ImageShape::new(w, h, nc);
            let x64 = random_image(shape, 11 + i as u64);
            let y64 = random_image(shape, 31 + i as u64);
            let mask: Vec<f32> = random_image(ImageShape::new(w, h, 1), 51 + i as u64)
                .iter()
                .map(|&v| if v < 0.3 { 0.0 } else { v as f32 })
                .collect();
            for masked in [false, true] {
                let m = masked.then_some(&mask[..]);
                let w32: Vec<f32> = pixel_weights(m, shape).unwrap();
                let x: Vec<f32> = x64.iter().map(|&v| v as f32).collect();
                let y: Vec<f32> = y64.iter().map(|&v| v as f32).collect();
                for want_grad in [false, true] {
                    let (s_new, g_new) = weighted_ssim(&x, &y, shape, &w32, want_grad);
                    let (s_ref, g_ref) = weighted_ssim_by_planes(&x, &y, shape, &w32, want_grad);
                    assert_eq!(s_new.to_bits(), s_ref.to_bits(), "{shape:?} mask {masked}");
                    let bits = |g: Option<Vec<f32>>| {
                        g.map(|g| g.iter().map(|v| v.to_bits()).collect::<Vec<_>>())
                    };
                    assert_eq!(bits(g_new), bits(g_ref), "{shape:?} mask {masked}");
                }
                let w64: Vec<f64> = pixel_weights(m, shape).unwrap();
                let (s_new, g_new) = weighted_ssim(&x64, &y64, shape, &w64, true);
                let (s_ref, g_ref) = weighted_ssim_by_planes(&x64, &y64, shape, &w64, true);
                assert_eq!(s_new.to_bits(), s_ref.to_bits());
                let (g_new, g_ref) = (g_new.unwrap(), g_ref.unwrap());
                assert!(g_new
                    .iter()
                    .zip(&g_ref)
                    .all(|(a, b)| a.to_bits() == b.to_bits()));
            }
        }
    }

    #[test]
    fn f32_path_matches_f64_reference() {
        let shape = ImageShape::new(40, 23, 3);
        let x64 = random_image(shape, 7);
        let y64 = random_image(shape, 8);
        let x: Vec<f32> = x64.iter().map(|&v| v as f32).collect();
        let y: Vec<f32> = y64.iter().map(|&v| v as f32).collect();
        let out = photometric_loss(&x, &y, None, shape, 0.2).unwrap();
        let xr: Vec<f64> = x.iter().map(|&v| v as f64).collect();
        let yr: Vec<f64> = y.iter().map(|&v| v as f64).collect();
        let w: Vec<f64> = pixel_weights(None, shape).unwrap();
        let (loss, l1, ssim_ref, grad) = photometric_loss_generic(&xr, &yr, &w, shape, 0.2);
        assert!((out.loss as f64 - loss).abs() < 1e-5);
        assert!((out.l1 as f64 - l1).abs() < 1e-5);
        assert!((out.ssim as f64 - ssim_ref).abs() < 1e-5);
        let gmax = grad.iter().fold(0.0f64, |m, g| m.max(g.abs()));
        for (a, b) in out.d_rendered.iter().zip(&grad) {
            assert!((*a as f64 - b).abs() < 1e-4 * gmax);
        }
    }

    /// Pixels more than 5 px (half the window) from any masked-in pixel neither change the
    /// loss nor receive gradient; pixels just outside the mask do receive SSIM gradient.
    #[test]
    fn mask_limits_the_support() {
        let shape = ImageShape::new(32, 24, 3);
        let x: Vec<f32> = random_image(shape, 11).iter().map(|&v| v as f32).collect();
        let y: Vec<f32> = random_image(shape, 12).iter().map(|&v| v as f32).collect();
        let mut mask = vec![0.0f32; shape.pixels()];
        for v in 8..14 {
            for u in 10..18 {
                mask[v * shape.width + u] = 1.0;
            }
        }
        let base = photometric_loss(&x, &y, Some(&mask), shape, 0.2).unwrap();
        let mut far = x.clone();
        let (u_far, v_far) = (28usize, 2usize);
        let (u_near, v_near) = (19usize, 10usize);
        for c in 0..3 {
            far[(v_far * shape.width + u_far) * 3 + c] += 0.5;
        }
        let moved = photometric_loss(&far, &y, Some(&mask), shape, 0.2).unwrap();
        assert_eq!(base.loss, moved.loss);
        assert_eq!(base.d_rendered[(v_far * shape.width + u_far) * 3], 0.0);
        assert_ne!(base.d_rendered[(v_near * shape.width + u_near) * 3], 0.0);
        // L1 alone: only masked-in pixels matter.
        let l1_only = photometric_loss(&x, &y, Some(&mask), shape, 0.0).unwrap();
        assert_eq!(l1_only.d_rendered[(v_near * shape.width + u_near) * 3], 0.0);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let shape = ImageShape::new(4, 3, 3);
        let x = vec![0.5f32; shape.values()];
        let mut bad = x.clone();
        bad[7] = f32::NAN;
        assert!(matches!(
            photometric_loss(&x[1..], &x, None, shape, 0.2),
            Err(LossError::Length { .. })
        ));
        assert!(matches!(
            photometric_loss(&bad, &x, None, shape, 0.2),
            Err(LossError::NonFinite { index: 7, .. })
        ));
        assert!(matches!(
            photometric_loss(&x, &x, Some(&[0.0; 12]), shape, 0.2),
            Err(LossError::EmptyMask)
        ));
        assert!(matches!(
            photometric_loss(&x, &x, Some(&[-0.5; 12]), shape, 0.2),
            Err(LossError::MaskRange { .. })
        ));
        assert!(matches!(
            photometric_loss(&x, &x, Some(&[1.0; 11]), shape, 0.2),
            Err(LossError::Length { what: "mask", .. })
        ));
        assert!(matches!(
            photometric_loss(&x, &x, None, shape, 1.5),
            Err(LossError::Lambda(_))
        ));
        assert!(matches!(
            ssim(&[], &[], ImageShape::new(0, 3, 3)),
            Err(LossError::EmptyImage)
        ));
    }
}
