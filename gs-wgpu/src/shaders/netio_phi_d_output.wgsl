// Phi's output gradient (sunaware/model.rs `backward_timed`): for r < count,
// d_out[r * 3 + k] = rows[g * (13 + nc) + 13 + k], g = list[r], the rasterizer's gradient
// of channel k; rows r >= count are zeros.

@group(0) @binding(3) var<storage, read> rows: array<f32>;
@group(0) @binding(4) var<storage, read_write> d_out: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = row_of(gid, nwg);
    if r >= u.n {
        return;
    }
    let g = listed_gaussian(r);
    for (var k = 0u; k < 3u; k++) {
        var v = 0.0;
        if g < u.n {
            v = rows[g * (13u + u.nc) + 13u + k];
        }
        d_out[r * 3u + k] = v;
    }
}
