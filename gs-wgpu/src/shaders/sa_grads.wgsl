// Parameter gradients of the Sun-aware resident step from the rasterizer's per-Gaussian
// rows (project_backward.wgsl: d_mean 3, d_log_scale 3, d_rotation 4, d_opacity_logit,
// |d mean2d| NDC, dropped flag, then the channels), plus the isotropic scale loss
// (regularizer.rs `IsotropicLoss::value_and_grad`, in f32 here, f64 there). One thread per
// Gaussian writes its row of every group of the packed gradient buffer: the geometry
// groups from the rasterizer, zeros elsewhere (the features, latents and means then get
// the networks' terms from network_io's kernels, recorded after this one). flags[1]
// counts rows the rasterizer dropped. Each workgroup writes its Gaussians' sum of
// `sum_a |s_a - mean(s)|` to partials[workgroup] (a fixed-order tree, so the reported
// L_iso is deterministic; the host scales and sums the partials in f64).

struct Iso {
    // lambda_iso, times 1 / (3 n) for the mean-over-entries reduction; 0 = no iso loss.
    factor: f32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(0) var<uniform> st: Step;
@group(0) @binding(1) var<uniform> iso: Iso;
@group(0) @binding(2) var<storage, read> x: array<f32>;
@group(0) @binding(3) var<storage, read> rows: array<f32>;
@group(0) @binding(4) var<storage, read_write> grad: array<f32>;
@group(0) @binding(5) var<storage, read_write> flags: array<atomic<u32>>;
@group(0) @binding(6) var<storage, read_write> partials: array<f32>;

var<workgroup> red: array<f32, 256>;

fn sign_or_zero(v: f32) -> f32 {
    if v > 0.0 {
        return 1.0;
    }
    if v < 0.0 {
        return -1.0;
    }
    return 0.0;
}

@compute @workgroup_size(256)
fn main(
    @builtin(global_invocation_id) gid: vec3<u32>,
    @builtin(local_invocation_index) lid: u32,
    @builtin(workgroup_id) wid: vec3<u32>,
    @builtin(num_workgroups) nwg: vec3<u32>,
) {
    let i = gid.x + gid.y * nwg.x * 256u;
    var term = 0.0;
    if i < st.n {
        let r = st.ostride * i;
        if rows[r + 12u] != 0.0 {
            atomicAdd(&flags[1], 1u);
        }
        let ls = goff(st, G_LOG_SCALE) + 3u * i;
        var d_ls = vec3<f32>(rows[r + 3u], rows[r + 4u], rows[r + 5u]);
        if iso.factor != 0.0 {
            let s = exp(vec3<f32>(x[ls], x[ls + 1u], x[ls + 2u]));
            let m = (s.x + s.y + s.z) / 3.0;
            let sg = vec3<f32>(sign_or_zero(s.x - m), sign_or_zero(s.y - m), sign_or_zero(s.z - m));
            term = abs(s.x - m) + abs(s.y - m) + abs(s.z - m);
            let sg_mean = (sg.x + sg.y + sg.z) / 3.0;
            // d/ds_a sum_b |s_b - m| = sign_a - mean(sign); ds_a/du_a = s_a.
            d_ls += iso.factor * s * (sg - vec3<f32>(sg_mean));
        }
        for (var k = 0u; k < 3u; k++) {
            grad[goff(st, G_MEAN) + 3u * i + k] = rows[r + k];
            grad[ls + k] = d_ls[k];
        }
        for (var k = 0u; k < 4u; k++) {
            grad[goff(st, G_ROTATION) + 4u * i + k] = rows[r + 6u + k];
        }
        grad[goff(st, G_OPACITY) + i] = rows[r + 10u];
        for (var k = 0u; k < 3u; k++) {
            grad[goff(st, G_SH_DC) + 3u * i + k] = 0.0;
        }
        for (var k = 0u; k < st.rest_dim; k++) {
            grad[goff(st, G_SH_REST) + st.rest_dim * i + k] = 0.0;
        }
        for (var k = 0u; k < st.feature_dim; k++) {
            grad[goff(st, G_FEATURE) + st.feature_dim * i + k] = 0.0;
        }
        for (var k = 0u; k < st.latent_dim; k++) {
            grad[goff(st, G_LATENT) + st.latent_dim * i + k] = 0.0;
        }
    }
    red[lid] = term;
    workgroupBarrier();
    for (var half = 128u; half > 0u; half = half / 2u) {
        if lid < half {
            red[lid] = red[lid] + red[lid + half];
        }
        workgroupBarrier();
    }
    if lid == 0u {
        partials[wid.x + wid.y * nwg.x] = red[0];
    }
}
