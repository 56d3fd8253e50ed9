// Parameter gradients from the rasterizer's per-Gaussian rows (project_backward.wgsl:
// d_mean 3, d_log_scale 3, d_rotation 4, d_opacity_logit, |d mean2d| NDC, dropped flag,
// d_rgb 3) and the SH colour backward (sh.rs `sh_to_rgb_backward`): one thread per
// Gaussian writes its rows of every group of the packed gradient buffer (zeros for the
// groups configuration (a) does not train). Any non-finite value sets flags[0] (the step
// is then refused whole, as optim.rs does); flags[1] counts rows the rasterizer dropped.

@group(0) @binding(0) var<uniform> st: Step;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read> rows: array<f32>;
@group(0) @binding(3) var<storage, read_write> grad: array<f32>;
@group(0) @binding(4) var<storage, read_write> flags: array<atomic<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= st.n {
        return;
    }
    let r = st.ostride * i;
    if rows[r + 12u] != 0.0 {
        atomicAdd(&flags[1], 1u);
    }
    let view = view_dir(mean_of(st, i), st.cam.xyz);
    let basis = sh_basis(st.degree, view.xyz);
    let raw = raw_colour(st, i, basis);
    // The clamp max(raw, 0) passes no gradient where it is active.
    var g = vec3<f32>(rows[r + 13u], rows[r + 14u], rows[r + 15u]);
    if raw.x < 0.0 {
        g.x = 0.0;
    }
    if raw.y < 0.0 {
        g.y = 0.0;
    }
    if raw.z < 0.0 {
        g.z = 0.0;
    }
    var ok = true;
    let rb = goff(st, G_SH_REST) + st.rest_dim * i;
    var d_mean_sh = vec3<f32>(0.0);
    if view.w > 0.0 && st.coeffs > 1u {
        let jac = sh_jacobian(st.degree, view.xyz);
        var d_dir = vec3<f32>(0.0);
        for (var k = 1u; k < st.coeffs; k++) {
            let c = rb + (k - 1u) * 3u;
            let w = x[c] * g.x + x[c + 1u] * g.y + x[c + 2u] * g.z;
            d_dir += jac[k] * w;
        }
        d_mean_sh = (d_dir - view.xyz * dot(view.xyz, d_dir)) / view.w;
    }
    let mb = goff(st, G_MEAN) + 3u * i;
    for (var k = 0u; k < 3u; k++) {
        let v = rows[r + k] + d_mean_sh[k];
        grad[mb + k] = v;
        ok = ok && is_finite(v);
    }
    for (var k = 0u; k < 3u; k++) {
        let v = rows[r + 3u + k];
        grad[goff(st, G_LOG_SCALE) + 3u * i + k] = v;
        ok = ok && is_finite(v);
    }
    for (var k = 0u; k < 4u; k++) {
        let v = rows[r + 6u + k];
        grad[goff(st, G_ROTATION) + 4u * i + k] = v;
        ok = ok && is_finite(v);
    }
    grad[goff(st, G_OPACITY) + i] = rows[r + 10u];
    ok = ok && is_finite(rows[r + 10u]);
    for (var c = 0u; c < 3u; c++) {
        let v = basis[0] * g[c];
        grad[goff(st, G_SH_DC) + 3u * i + c] = v;
        ok = ok && is_finite(v);
    }
    for (var k = 1u; k <= st.rest_dim / 3u; k++) {
        for (var c = 0u; c < 3u; c++) {
            var v = 0.0;
            if k < st.coeffs {
                v = basis[k] * g[c];
            }
            grad[rb + (k - 1u) * 3u + c] = v;
            ok = ok && is_finite(v);
        }
    }
    for (var k = 0u; k < st.feature_dim; k++) {
        grad[goff(st, G_FEATURE) + st.feature_dim * i + k] = 0.0;
    }
    for (var k = 0u; k < st.latent_dim; k++) {
        grad[goff(st, G_LATENT) + st.latent_dim * i + k] = 0.0;
    }
    if !ok {
        atomicOr(&flags[0], 1u);
    }
}
