// Psi's output gradient (sunaware/model.rs `backward_timed`): for r < count, g = list[r],
// d_out[r] = rows[g * (13 + nc) + 16] (channel 3's gradient) times gain, then times V_g,
// under ShadowRefinement::Multiply (V is data: no gradient); rows r >= count are zeros.

@group(0) @binding(3) var<storage, read> visibility: array<f32>;
@group(0) @binding(4) var<storage, read> rows: array<f32>;
@group(0) @binding(5) var<storage, read_write> d_out: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = row_of(gid, nwg);
    if r >= u.n {
        return;
    }
    let g = listed_gaussian(r);
    var v = 0.0;
    if g < u.n {
        v = rows[g * (13u + u.nc) + 16u];
        if u.multiply != 0u {
            v = v * u.gain * visibility[g];
        }
    }
    d_out[r] = v;
}
