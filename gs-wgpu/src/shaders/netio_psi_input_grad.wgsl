// Psi's input gradient into the packed gradient buffer (shadow.rs `scatter_input_grad`):
// for r < count, g = list[r], the ShadowLatent row g is set to d_input's latent columns,
// and the Mean row g gains the encoding's chain rule of the position columns times
// d p / d mu = 1 / extent per axis. The V column gets no gradient. The list has no
// repeats (ascending), so each Gaussian's rows have one writer.

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = row_of(gid, nwg);
    let g = listed_gaussian(r);
    if g >= u.n {
        return;
    }
    let base = r * u.width;
    let enc = 6u * u.freqs;
    let lo = goff(u, G_LATENT) + g * u.dim;
    let li = base + 1u + 2u * enc;
    for (var j = 0u; j < u.dim; j++) {
        grads[lo + j] = d_input[li + j];
    }
    let mo = goff(u, G_MEAN) + 3u * g;
    let po = base + 1u + enc;
    let two_l = 2u * u.freqs;
    for (var c = 0u; c < 3u; c++) {
        let p = (params[mo + c] - u.box_min[c]) / u.box_extent[c] - 0.5;
        let d_p = encoding_backward(u, p, po + c * two_l);
        grads[mo + c] += d_p * u.box_inv_extent[c];
    }
}
