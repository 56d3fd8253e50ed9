// Pass 1: one thread per (pixel, channel): the five moment planes filtered along the row.

@group(0) @binding(0) var<uniform> lu: LossUniform;
@group(0) @binding(1) var<storage, read> rendered: array<f32>;
@group(0) @binding(2) var<storage, read> target_img: array<f32>;
@group(0) @binding(3) var<storage, read_write> moments: array<f32>;

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
    var acc = array<f32, 5>(0.0, 0.0, 0.0, 0.0, 0.0);
    for (var t = 0u; t < 11u; t++) {
        let xx = x + i32(t) - HALF;
        if xx < 0 || xx >= i32(lu.width) {
            continue;
        }
        let k = tap(lu, t);
        let q = (row + u32(xx)) * NC + c;
        let a = rendered[q];
        let b = target_img[q];
        acc[0] += k * a;
        acc[1] += k * b;
        acc[2] += k * (a * a);
        acc[3] += k * (b * b);
        acc[4] += k * (a * b);
    }
    for (var q = 0u; q < 5u; q++) {
        moments[(5u * c + q) * n + p] = acc[q];
    }
}
