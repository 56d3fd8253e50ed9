// Backward of the Sun-aware image (model/backward.rs `backward_timed`): from the loss's
// pixel gradient rows (3 colour values, then the unused alpha and depth slots: stride 5)
// to the rasterizer's (the channels, alpha, depth: stride channels + 2). With
// `colour_space = "linear"` the pixel gradient first goes through the encoding's slope
// at the forward's `RGB * S` (`srgb_slope`); then dRGB = d * S and, in c-d,
// dS = sum_c d_c RGB_c (in channel order, as on the CPU; S is 1 in a-b, whose sRGB step
// feeds the loss's rows to the rasterizer directly and needs no pass); no alpha or depth
// gradient.

@group(0) @binding(0) var<uniform> u: Compose;
@group(0) @binding(1) var<storage, read> color: array<f32>;
@group(0) @binding(2) var<storage, read> d_image: array<f32>;
@group(0) @binding(3) var<storage, read_write> d_color: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let p = gid.x + gid.y * nwg.x * 256u;
    if p >= u.n {
        return;
    }
    let nc = u.channels;
    let out = (nc + 2u) * p;
    var s = 1.0;
    if nc == 4u {
        s = color[4u * p + 3u];
    }
    var d_s = 0.0;
    for (var c = 0u; c < 3u; c++) {
        var d = d_image[5u * p + c];
        if u.linear != 0u {
            d *= srgb_slope(color[nc * p + c] * s);
        }
        d_color[out + c] = d * s;
        d_s += d * color[nc * p + c];
    }
    if nc == 4u {
        d_color[out + 3u] = d_s;
    }
    d_color[out + nc] = 0.0;
    d_color[out + nc + 1u] = 0.0;
}
