// Pass 4: one thread per (pixel, channel): the vertical half of the adjoint, then
// dL/dx = (1 - lambda) w sign(x - y) - lambda (F^T g_mu + 2 x F^T g_xx + y F^T g_xy),
// written into the rasterizer backward's pixel-gradient rows (NC colours, then d_alpha and
// d_depth, which stay zero). A non-finite gradient sets flags[0].

@group(0) @binding(0) var<uniform> lu: LossUniform;
@group(0) @binding(1) var<storage, read> rendered: array<f32>;
@group(0) @binding(2) var<storage, read> target_img: array<f32>;
@group(0) @binding(3) var<storage, read> weights: array<f32>;
@group(0) @binding(4) var<storage, read> grads_h: array<f32>;
@group(0) @binding(5) var<storage, read_write> px_grad: array<f32>;
@group(0) @binding(6) var<storage, read_write> flags: array<atomic<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    let n = lu.width * lu.height;
    if i >= n * NC {
        return;
    }
    let c = i / n;
    let p = i % n;
    let y = i32(p / lu.width);
    let x = p % lu.width;
    var f = array<f32, 3>(0.0, 0.0, 0.0);
    for (var t = 0u; t < 11u; t++) {
        let yy = y + i32(t) - HALF;
        if yy < 0 || yy >= i32(lu.height) {
            continue;
        }
        let k = tap(lu, t);
        let q = u32(yy) * lu.width + x;
        for (var j = 0u; j < 3u; j++) {
            f[j] += k * grads_h[(3u * c + j) * n + q];
        }
    }
    let a = rendered[p * NC + c];
    let b = target_img[p * NC + c];
    let d_ssim = f[0] + 2.0 * a * f[1] + b * f[2];
    let wp = weights[p];
    var d_l1 = 0.0;
    if a - b > 0.0 {
        d_l1 = wp;
    } else if a - b < 0.0 {
        d_l1 = -wp;
    }
    let g = (1.0 - lu.lambda) * d_l1 - lu.lambda * d_ssim;
    px_grad[p * (NC + 2u) + c] = g;
    if !finite_value(g) {
        atomicOr(&flags[0], 1u);
    }
}
