// Phi's output into the channels (sunaware/model.rs `forward_with`): for r < count,
// chans[g * nc + k] = output[r * 3 + k], k < 3, g = list[r]. Other Gaussians' channels
// are not touched.
//
// With `shaded` (Shading::LambertLearned, sunaware/shading.rs `shade_forward`), the
// colour is multiplied by f_g = k_a + (1 - k_a) max(0, n_g . s), n_g = v_g / |v_g| from
// the Normal group turned toward the camera, in the CPU's order of operations; a
// degenerate or non-finite normal (or mean) gives f_g = 1. Row r's (f_g, sign) goes to
// shade[2r], shade[2r + 1], the sign being the normal's flip (+1 or -1) where the
// Gaussian is lit and 0 where f_g is constant (no gradient); dead rows get (1, 0).

@group(0) @binding(3) var<storage, read> output: array<f32>;
@group(0) @binding(4) var<storage, read_write> chans: array<f32>;
@group(0) @binding(5) var<storage, read> params: array<f32>;
@group(0) @binding(6) var<storage, read_write> shade: array<f32>;

// (f_g, sign) as shading.rs `shade_forward` on `learned_facing_normal` (netio_normal.wgsl).
fn learned_shade(g: u32) -> vec2<f32> {
    let no = u.normal_off + 3u * g;
    let v = vec3<f32>(params[no], params[no + 1u], params[no + 2u]);
    let mo = goff(u, G_MEAN) + 3u * g;
    let mean = vec3<f32>(params[mo], params[mo + 1u], params[mo + 2u]);
    let facing = learned_facing_normal(v, mean);
    if facing.w == 0.0 {
        return vec2<f32>(1.0, 0.0);
    }
    let nrm = facing.xyz;
    let s = u.sun_unit;
    let cosine = nrm.x * s.x + nrm.y * s.y + nrm.z * s.z;
    if cosine > 0.0 {
        return vec2<f32>(u.ambient + (1.0 - u.ambient) * cosine, facing.w);
    }
    return vec2<f32>(u.ambient, 0.0);
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let r = row_of(gid, nwg);
    if r >= u.n {
        return;
    }
    let g = listed_gaussian(r);
    if g >= u.n {
        if u.shaded != 0u {
            shade[2u * r] = 1.0;
            shade[2u * r + 1u] = 0.0;
        }
        return;
    }
    if u.shaded != 0u {
        let f = learned_shade(g);
        shade[2u * r] = f.x;
        shade[2u * r + 1u] = f.y;
        for (var k = 0u; k < 3u; k++) {
            chans[g * u.nc + k] = output[r * 3u + k] * f.x;
        }
        return;
    }
    for (var k = 0u; k < 3u; k++) {
        chans[g * u.nc + k] = output[r * 3u + k];
    }
}
