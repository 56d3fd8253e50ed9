// Phi's input rows (appearance.rs `assemble_input`): row r < count of Gaussian g = list[r]
// is [f_g (dim) | gamma_L(sun) (6L) | gamma_L(view_g) (6L)], view_g the unit vector from
// the Gaussian's mean to the camera centre; rows r >= count are zeros. A non-finite
// feature or mean, a Gaussian at the camera centre (distance not > 0 and finite) or a
// list entry out of range sets flags[0] bit 0 (where the CPU returns an error).
//
// With `local` (appearance_inputs "local" / "local_no_sun", shading.rs
// `fill_local_inputs`), the row ends in [n.s, n.v, n.h] of the Gaussian's local frame
// (netio_normal.wgsl: zeros for a degenerate normal); under "local_no_sun" the host's Sun
// code is zeros.

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = row_of(gid, nwg);
    if r >= u.n {
        return;
    }
    let g = input_row_gaussian(r);
    if g >= u.n {
        return;
    }
    let base = r * u.width;
    var ok = true;
    let fo = goff(u, G_FEATURE) + g * u.dim;
    for (var j = 0u; j < u.dim; j++) {
        let f = params[fo + j];
        ok = ok && finite(f);
        input[base + j] = f;
    }
    let enc = 6u * u.freqs;
    for (var j = 0u; j < enc; j++) {
        input[base + u.dim + j] = sun_code(u, j);
    }
    let mo = goff(u, G_MEAN) + 3u * g;
    let mean = vec3<f32>(params[mo], params[mo + 1u], params[mo + 2u]);
    ok = ok && finite(mean.x) && finite(mean.y) && finite(mean.z);
    // appearance.rs `view_direction`, the same operations in the same order.
    let d = u.cam.xyz - mean;
    let dist = sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
    ok = ok && dist > 0.0 && finite(dist);
    let view = vec3<f32>(d.x / dist, d.y / dist, d.z / dist);
    let vo = base + u.dim + enc;
    let two_l = 2u * u.freqs;
    for (var c = 0u; c < 3u; c++) {
        for (var k = 0u; k < u.freqs; k++) {
            let sc = sin_cos_pi(view[c] * f32(1u << k));
            input[vo + c * two_l + 2u * k] = sc.x;
            input[vo + c * two_l + 2u * k + 1u] = sc.y;
        }
    }
    if u.local != 0u {
        let no = u.normal_off + 3u * g;
        let v = vec3<f32>(params[no], params[no + 1u], params[no + 2u]);
        let x = local_inputs(local_frame(v, mean));
        let lo = base + u.width - 3u;
        input[lo] = x.x;
        input[lo + 1u] = x.y;
        input[lo + 2u] = x.z;
    }
    if !ok {
        atomicOr(&flags[0], 1u);
    }
}
