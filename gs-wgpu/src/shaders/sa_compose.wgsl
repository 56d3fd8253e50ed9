// The Sun-aware image from the rendered channels (model.rs forward): `RGB * S`, with S
// the fourth channel (configurations c-d).

@group(0) @binding(0) var<uniform> px: Count;
@group(0) @binding(1) var<storage, read> color: array<f32>;
@group(0) @binding(2) var<storage, read_write> image: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let p = gid.x + gid.y * nwg.x * 256u;
    if p >= px.n {
        return;
    }
    let s = color[4u * p + 3u];
    for (var c = 0u; c < 3u; c++) {
        image[3u * p + c] = color[4u * p + c] * s;
    }
}
