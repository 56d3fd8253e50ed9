// Phi's input gradient into the packed gradient buffer (appearance.rs
// `scatter_input_grad`): for r < count, g = list[r], the Feature row g is set to d_input's
// feature columns, and the Mean row g gains the view direction's chain rule of the view
// columns, -(d_view - (d_view . v) v) / |c - mu|. The list has no repeats (ascending), so
// each Gaussian's rows have one writer.

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
    grads[mo] += -(d_view.x - along * view.x) / dist;
    grads[mo + 1u] += -(d_view.y - along * view.y) / dist;
    grads[mo + 2u] += -(d_view.z - along * view.z) / dist;
}
