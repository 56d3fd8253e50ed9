// Phi's output into the channels (sunaware/model.rs `forward_with`): for r < count,
// chans[g * nc + k] = output[r * 3 + k], k < 3, g = list[r]. Other Gaussians' channels
// are not touched.

@group(0) @binding(3) var<storage, read> output: array<f32>;
@group(0) @binding(4) var<storage, read_write> chans: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = row_of(gid, nwg);
    let g = listed_gaussian(r);
    if g >= u.n {
        return;
    }
    for (var k = 0u; k < 3u; k++) {
        chans[g * u.nc + k] = output[r * 3u + k];
    }
}
