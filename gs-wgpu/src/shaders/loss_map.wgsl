// Pass 2: one thread per (pixel, channel): the moments filtered along the column, the
// weighted SSIM and L1 values (for the totals) and the weighted derivatives of the SSIM
// map with respect to (mu_x, E[x^2], E[xy]). A non-finite rendered value sets flags[0].

@group(0) @binding(0) var<uniform> lu: LossUniform;
@group(0) @binding(1) var<storage, read> rendered: array<f32>;
@group(0) @binding(2) var<storage, read> target_img: array<f32>;
@group(0) @binding(3) var<storage, read> weights: array<f32>;
@group(0) @binding(4) var<storage, read> moments: array<f32>;
@group(0) @binding(5) var<storage, read_write> grads: array<f32>;
@group(0) @binding(6) var<storage, read_write> maps: array<f32>;
@group(0) @binding(7) var<storage, read_write> flags: array<atomic<u32>>;

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
    var m = array<f32, 5>(0.0, 0.0, 0.0, 0.0, 0.0);
    for (var t = 0u; t < 11u; t++) {
        let yy = y + i32(t) - HALF;
        if yy < 0 || yy >= i32(lu.height) {
            continue;
        }
        let k = tap(lu, t);
        let q = u32(yy) * lu.width + x;
        for (var j = 0u; j < 5u; j++) {
            m[j] += k * moments[(5u * c + j) * n + q];
        }
    }
    let mx = m[0];
    let my = m[1];
    let sxx = m[2] - mx * mx;
    let syy = m[3] - my * my;
    let sxy = m[4] - mx * my;
    let a1 = 2.0 * mx * my + lu.c1;
    let a2 = 2.0 * sxy + lu.c2;
    let b1 = mx * mx + my * my + lu.c1;
    let b2 = sxx + syy + lu.c2;
    let s = (a1 * a2) / (b1 * b2);
    let wp = weights[p];
    let d_mu = (2.0 * my * (a2 - a1)) / (b1 * b2) - 2.0 * mx * s / b1 + 2.0 * mx * s / b2;
    grads[(3u * c) * n + p] = wp * d_mu;
    grads[(3u * c + 1u) * n + p] = wp * (-s / b2);
    grads[(3u * c + 2u) * n + p] = wp * (2.0 * a1 / (b1 * b2));
    maps[c * n + p] = wp * s;
    let a = rendered[p * NC + c];
    maps[(NC + c) * n + p] = wp * abs(a - target_img[p * NC + c]);
    if !finite_value(a) {
        atomicOr(&flags[0], 1u);
    }
}
