// Phi's input gradient into the packed gradient buffer (appearance.rs
// `scatter_input_grad`): for r < count, g = list[r], the Feature row g is set to d_input's
// feature columns, and the Mean row g gains the view direction's chain rule of the view
// columns, -(d_view - (d_view . v) v) / |c - mu|. The list has no repeats (ascending), so
// each Gaussian's rows have one writer.
//
// With `local` (shading.rs `scatter_local_input_grad`): where the row's local columns'
// gradient d is not all zero and the Gaussian has a local frame, `local_inputs_backward`
// (netio_normal.wgsl) is ADDED to the Normal row g (after the shading's term, which Phi's
// output gradient added) and its mean term is added to the view direction's before the
// sum goes into the Mean row g, as the CPU sums them (no gradient where a value is not
// finite).

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = row_of(gid, nwg);
    let g = listed_gaussian(r);
    if g >= u.n {
        return;
    }
    let base = r * u.width;
    let fo = goff(u, G_FEATURE) + g * u.dim;
    for (var j = 0u; j < u.dim; j++) {
        grads[fo + j] = d_input[base + j];
    }
    let mo = goff(u, G_MEAN) + 3u * g;
    let mean = vec3<f32>(params[mo], params[mo + 1u], params[mo + 2u]);
    let d = u.cam.xyz - mean;
    let dist = sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
    let view = vec3<f32>(d.x / dist, d.y / dist, d.z / dist);
    let vo = base + u.dim + 6u * u.freqs;
    let two_l = 2u * u.freqs;
    var d_view = vec3<f32>(0.0);
    for (var c = 0u; c < 3u; c++) {
        d_view[c] = encoding_backward(u, view[c], vo + c * two_l);
    }
    let along = d_view.x * view.x + d_view.y * view.y + d_view.z * view.z;
    var d_mean = vec3<f32>(
        -(d_view.x - along * view.x) / dist,
        -(d_view.y - along * view.y) / dist,
        -(d_view.z - along * view.z) / dist,
    );
    if u.local != 0u {
        let lo = base + u.width - 3u;
        let d = vec3<f32>(d_input[lo], d_input[lo + 1u], d_input[lo + 2u]);
        let no = u.normal_off + 3u * g;
        let v = vec3<f32>(params[no], params[no + 1u], params[no + 2u]);
        if any(d != vec3<f32>(0.0)) {
            let f = local_frame(v, mean);
            if f.normal.w != 0.0 {
                let lg = local_inputs_backward(f, v, d);
                if lg.d_v.w != 0.0 {
                    grads[no] += lg.d_v.x;
                    grads[no + 1u] += lg.d_v.y;
                    grads[no + 2u] += lg.d_v.z;
                    d_mean = d_mean + lg.d_mean;
                }
            }
        }
    }
    grads[mo] += d_mean.x;
    grads[mo + 1u] += d_mean.y;
    grads[mo + 2u] += d_mean.z;
}
