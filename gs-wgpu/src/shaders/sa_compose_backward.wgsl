// Backward of `RGB * S` (model.rs `backward_timed`): from the loss's pixel gradient rows
// (3 colour values, then the unused alpha and depth slots: stride 5) to the rasterizer's
// (4 channels, alpha, depth: stride 6): dRGB = d * S, dS = sum_c d_c RGB_c (in channel
// order, as on the CPU); no alpha or depth gradient.

@group(0) @binding(0) var<uniform> px: Count;
@group(0) @binding(1) var<storage, read> color: array<f32>;
@group(0) @binding(2) var<storage, read> d_image: array<f32>;
@group(0) @binding(3) var<storage, read_write> d_color: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let p = gid.x + gid.y * nwg.x * 256u;
    if p >= px.n {
        return;
    }
    let s = color[4u * p + 3u];
    var d_s = 0.0;
    for (var c = 0u; c < 3u; c++) {
        let d = d_image[5u * p + c];
        d_color[6u * p + c] = d * s;
        d_s += d * color[4u * p + c];
    }
    d_color[6u * p + 3u] = d_s;
    d_color[6u * p + 4u] = 0.0;
    d_color[6u * p + 5u] = 0.0;
}
