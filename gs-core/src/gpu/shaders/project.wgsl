// Projection: one thread per Gaussian. Writes its splat (radius -1 when culled, as the
// CPU's `None`), and the number of 16x16 tiles its pixel rectangle touches (0 when culled).

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> gauss: array<f32>;
@group(0) @binding(2) var<storage, read> chans: array<f32>;
@group(0) @binding(3) var<storage, read_write> splats: array<f32>;
@group(0) @binding(4) var<storage, read_write> counts: array<u32>;

fn to_px(v: f32, hi: u32) -> u32 {
    return u32(clamp(v, 0.0, f32(hi)));
}

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
    let xx = p.cov2.x;
    let xy = p.cov2.y;
    let yy = p.cov2.z;
    let mid = 0.5 * (xx + yy);
    let lambda_max = mid + sqrt(max(mid * mid - (xx * yy - xy * xy), 0.0));
    let radius = sqrt(q_max * lambda_max);
    let ext_x = sqrt(q_max * xx) * 1.001 + 0.01;
    let ext_y = sqrt(q_max * yy) * 1.001 + 0.01;
    let x0 = to_px(floor(p.mean_px.x - ext_x - 0.5), fr.width);
    let y0 = to_px(floor(p.mean_px.y - ext_y - 0.5), fr.height);
    let x1 = to_px(floor(p.mean_px.x + ext_x - 0.5) + 1.0, fr.width);
    let y1 = to_px(floor(p.mean_px.y + ext_y - 0.5) + 1.0, fr.height);
    if x0 >= x1 || y0 >= y1 || !finite(radius) {
        return;
    }
    splats[sb] = p.mean_px.x;
    splats[sb + 1u] = p.mean_px.y;
    splats[sb + 2u] = p.conic.x;
    splats[sb + 3u] = p.conic.y;
    splats[sb + 4u] = p.conic.z;
    splats[sb + 5u] = p.opacity;
    splats[sb + 6u] = p.t_cam.z;
    splats[sb + 7u] = radius;
    splats[sb + 8u] = bitcast<f32>(x0);
    splats[sb + 9u] = bitcast<f32>(y0);
    splats[sb + 10u] = bitcast<f32>(x1);
    splats[sb + 11u] = bitcast<f32>(y1);
    let tx0 = x0 / TILE;
    let ty0 = y0 / TILE;
    let tx1 = (x1 + TILE - 1u) / TILE;
    let ty1 = (y1 + TILE - 1u) / TILE;
    counts[i] = (tx1 - tx0) * (ty1 - ty0);
}
