// The Sun-aware image from the rendered channels (model/forward.rs): `RGB * S`, with S
// the fourth channel (configurations c-d; 1 in a-b, whose sRGB image is the colour
// buffer itself and needs no pass), then with `colour_space = "linear"` each value
// sRGB-encoded (`srgb_encode`): the blend sums linear radiance, and the camera encodes a
// pixel once, after the sum. In the CPU's order: the product, then the curve.

@group(0) @binding(0) var<uniform> u: Compose;
@group(0) @binding(1) var<storage, read> color: array<f32>;
@group(0) @binding(2) var<storage, read_write> image: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let p = gid.x + gid.y * nwg.x * 256u;
    if p >= u.n {
        return;
    }
    let nc = u.channels;
    var s = 1.0;
    if nc == 4u {
        s = color[4u * p + 3u];
    }
    for (var c = 0u; c < 3u; c++) {
        var v = color[nc * p + c] * s;
        if u.linear != 0u {
            v = srgb_encode(v);
        }
        image[3u * p + c] = v;
    }
}
