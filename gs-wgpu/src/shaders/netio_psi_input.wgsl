// Psi's full input rows (shadow.rs `assemble_input`): row r < count of Gaussian
// g = list[r] is [V_g (1) | gamma_L(sun) (6L) | gamma_L(p_g) (6L) | l_g (dim)], with
// p_g = (mu_g - box_min) / extent - 0.5 per axis; rows r >= count are zeros. A
// non-finite V, mean or latent, or a list entry out of range, sets flags[0] bit 0.

@group(0) @binding(6) var<storage, read> visibility: array<f32>;

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
    let v = visibility[g];
    var ok = finite(v);
    input[base] = v;
    let enc = 6u * u.freqs;
    for (var j = 0u; j < enc; j++) {
        input[base + 1u + j] = sun_code(u, j);
    }
    let mo = goff(u, G_MEAN) + 3u * g;
    let po = base + 1u + enc;
    let two_l = 2u * u.freqs;
    for (var c = 0u; c < 3u; c++) {
        let m = params[mo + c];
        ok = ok && finite(m);
        let p = (m - u.box_min[c]) / u.box_extent[c] - 0.5;
        for (var k = 0u; k < u.freqs; k++) {
            let sc = sin_cos_pi(p * f32(1u << k));
            input[po + c * two_l + 2u * k] = sc.x;
            input[po + c * two_l + 2u * k + 1u] = sc.y;
        }
    }
    let lo = goff(u, G_LATENT) + g * u.dim;
    let li = base + 1u + 2u * enc;
    for (var j = 0u; j < u.dim; j++) {
        let l = params[lo + j];
        ok = ok && finite(l);
        input[li + j] = l;
    }
    if !ok {
        atomicOr(&flags[0], 1u);
    }
}
