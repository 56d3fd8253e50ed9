// Psi's output into channel 3 (sunaware/model.rs `forward_with`): for r < count,
// g = list[r], chans[g * nc + 3] = gain * V_g * P_r under ShadowRefinement::Multiply (in
// the CPU's order: (gain V_g) P_r), else P_r.
// Other Gaussians' channels are not touched.

@group(0) @binding(3) var<storage, read> visibility: array<f32>;
@group(0) @binding(4) var<storage, read> output: array<f32>;
@group(0) @binding(5) var<storage, read_write> chans: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = row_of(gid, nwg);
    let g = listed_gaussian(r);
    if g >= u.n {
        return;
    }
    var v = output[r];
    if u.multiply != 0u {
        v = u.gain * visibility[g] * output[r];
    }
    chans[g * u.nc + 3u] = v;
}
