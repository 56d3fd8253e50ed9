// Pass 3: one thread per (pixel, channel): the three derivative planes filtered along
// the row (the horizontal half of the window's adjoint; the window is symmetric).

@group(0) @binding(0) var<uniform> lu: LossUniform;
@group(0) @binding(1) var<storage, read> grads: array<f32>;
@group(0) @binding(2) var<storage, read_write> grads_h: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    let n = lu.width * lu.height;
    if i >= n * NC {
        return;
    }
    let c = i / n;
    let p = i % n;
    let x = i32(p % lu.width);
    let row = p - p % lu.width;
    var acc = array<f32, 3>(0.0, 0.0, 0.0);
    for (var t = 0u; t < 11u; t++) {
        let xx = x + i32(t) - HALF;
        if xx < 0 || xx >= i32(lu.width) {
            continue;
        }
        let k = tap(lu, t);
        for (var q = 0u; q < 3u; q++) {
            acc[q] += k * grads[(3u * c + q) * n + row + u32(xx)];
        }
    }
    for (var q = 0u; q < 3u; q++) {
        grads_h[(3u * c + q) * n + p] = acc[q];
    }
}
