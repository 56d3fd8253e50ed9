// Shared by the loss kernels (loss.rs): `(1 - lambda) L1 + lambda (1 - SSIM)` with
// per-pixel weights, ported from loss.rs `weighted_l1` / `weighted_ssim`: an 11-tap
// separable Gaussian window with zero padding, taps added in order (t = 0..10) as the
// CPU's filter_row and filter_column do. The host prepends `const NC: u32`.
// Plane layouts (N = width * height pixels, p = y * width + x):
//   moments  [(5 c + q) N + p], q: x, y, x^2, y^2, xy (horizontally filtered);
//   grads    [(3 c + q) N + p], q: d/d mu_x, d/d E[x^2], d/d E[xy] (weighted);
//   maps     [c N + p] weighted SSIM, [(NC + c) N + p] weighted |x - y|.

struct LossUniform {
    width: u32,
    height: u32,
    lambda: f32,
    c1: f32,
    c2: f32,
    // Totals: workgroups of the partial-sum pass and the pixels each one sums.
    sum_groups: u32,
    sum_chunk: u32,
    pad0: u32,
    taps0: vec4<f32>,
    taps1: vec4<f32>,
    taps2: vec4<f32>,
}

const HALF: i32 = 5;

fn tap(u: LossUniform, t: u32) -> f32 {
    if t < 4u {
        return u.taps0[t];
    }
    if t < 8u {
        return u.taps1[t - 4u];
    }
    return u.taps2[t - 8u];
}

fn finite_value(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}
