// Projection: one thread per Gaussian. Writes its splat (radius -1 when culled, as the
// CPU's `None`), and the number of 16x16 tiles its pixel rectangle touches (0 when culled).

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> gauss: array<f32>;
@group(0) @binding(2) var<storage, read> chans: array<f32>;
@group(0) @binding(3) var<storage, read_write> splats: array<f32>;
@group(0) @binding(4) var<storage, read_write> counts: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= fr.n {
        return;
    }
    let sb = i * SSTRIDE;
    counts[i] = 0u;
    splats[sb + 7u] = -1.0;
    for (var k = 0u; k < NC; k++) {
        if !finite(chans[i * NC + k]) {
            return;
        }
    }
    let b = i * GSTRIDE;
    let mean = vec3<f32>(gauss[b], gauss[b + 1u], gauss[b + 2u]);
    let ls = vec3<f32>(gauss[b + 3u], gauss[b + 4u], gauss[b + 5u]);
    let q = vec4<f32>(gauss[b + 6u], gauss[b + 7u], gauss[b + 8u], gauss[b + 9u]);
    let p = project_forward(fr, mean, ls, q, gauss[b + 10u]);
    if !p.ok {
        return;
    }
    let q_max = 2.0 * log(p.opacity / fr.cutoff);
    let radius = splat_radius(p.cov2, q_max);
    let rect = splat_rect(p.mean_px, p.cov2, q_max, fr.width, fr.height);
    if rect.x >= rect.z || rect.y >= rect.w || !finite(radius) {
        return;
    }
    let row = splat_row(p.mean_px, p.conic, p.opacity, p.t_cam.z, radius, rect);
    for (var k = 0u; k < 12u; k++) {
        splats[sb + k] = row[k];
    }
    counts[i] = rect_tiles(rect);
}
