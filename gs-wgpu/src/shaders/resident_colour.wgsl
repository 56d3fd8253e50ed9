// Colour helpers over the module's packed parameter buffer `x` (pack and grads kernels).

fn mean_of(s: Step, i: u32) -> vec3<f32> {
    let b = goff(s, G_MEAN) + 3u * i;
    return vec3<f32>(x[b], x[b + 1u], x[b + 2u]);
}

// Unclamped colour of Gaussian i (sh.rs `raw_colour`).
fn raw_colour(s: Step, i: u32, basis: array<f32, 16>) -> vec3<f32> {
    var rgb = vec3<f32>(0.5);
    let dc = goff(s, G_SH_DC) + 3u * i;
    rgb += basis[0] * vec3<f32>(x[dc], x[dc + 1u], x[dc + 2u]);
    let rb = goff(s, G_SH_REST) + s.rest_dim * i;
    for (var k = 1u; k < s.coeffs; k++) {
        let r = rb + (k - 1u) * 3u;
        rgb += basis[k] * vec3<f32>(x[r], x[r + 1u], x[r + 2u]);
    }
    return rgb;
}
