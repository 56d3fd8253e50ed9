// Forward input of the rasterizer from the resident parameters: one thread per Gaussian
// writes its rasterizer row (mean 3, log-scale 3, quaternion 4, opacity logit 1) and its
// SH colour at the active degree from the step's camera centre, clamped at zero
// (sh.rs `sh_to_rgb`). With `coeffs == 0` (the Sun-aware step, whose colours come from
// its network) only the rasterizer row is written.

@group(0) @binding(0) var<uniform> st: Step;
@group(0) @binding(1) var<storage, read> x: array<f32>;
@group(0) @binding(2) var<storage, read_write> gauss: array<f32>;
@group(0) @binding(3) var<storage, read_write> chans: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= st.n {
        return;
    }
    let gb = 11u * i;
    for (var k = 0u; k < 3u; k++) {
        gauss[gb + k] = x[goff(st, G_MEAN) + 3u * i + k];
        gauss[gb + 3u + k] = x[goff(st, G_LOG_SCALE) + 3u * i + k];
    }
    for (var k = 0u; k < 4u; k++) {
        gauss[gb + 6u + k] = x[goff(st, G_ROTATION) + 4u * i + k];
    }
    gauss[gb + 10u] = x[goff(st, G_OPACITY) + i];
    if st.coeffs == 0u {
        return;
    }
    let d = view_dir(mean_of(st, i), st.cam.xyz);
    let rgb = raw_colour(st, i, sh_basis(st.degree, d.xyz));
    chans[3u * i] = max(rgb.x, 0.0);
    chans[3u * i + 1u] = max(rgb.y, 0.0);
    chans[3u * i + 2u] = max(rgb.z, 0.0);
}
