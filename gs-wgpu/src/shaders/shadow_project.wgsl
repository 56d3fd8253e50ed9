// Shadow pass, stage 0 (sunaware::light::light_splats with project_splats or ortho_splat,
// and light_axis_sigmas_m): one thread per Gaussian of the packed parameter buffer writes
// its light-image splat (radius -1 when culled, as the CPU's `None`), the number of 16x16
// tiles its rectangle touches (0 when culled) and its receiver limit
// `depth - bias - RECEIVER_EXTENT_SIGMAS * sigma` (sigma: its standard deviation along the
// light camera's axis, row 2 of the frame's rotation; 0 where culled).
// Perspective: the rasterizer's projection (project_forward in common.wgsl, the frame of
// the light camera, cutoff 1/255). Orthographic: ortho_splat, operation for operation
// (the frame's rows are the world-to-camera rotation, its translation the camera's).

struct ShadowProject {
    // Word offsets of the mean, log-scale, rotation and opacity-logit groups.
    off: vec4<u32>,
    orthographic: u32,
    // Orthographic: pixels per metre in the image plane, and the image centre (side / 2).
    px_per_m: f32,
    half_px: f32,
    depth_bias: f32,
    extent_sigmas: f32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<uniform> sp: ShadowProject;
@group(0) @binding(2) var<storage, read> params: array<f32>;
@group(0) @binding(3) var<storage, read_write> splats: array<f32>;
@group(0) @binding(4) var<storage, read_write> counts: array<u32>;
@group(0) @binding(5) var<storage, read_write> limits: array<f32>;

// A splat before its rectangle: `ok` false where the CPU returns None.
struct LightSplat {
    ok: bool,
    mean_px: vec2<f32>,
    conic: vec3<f32>,
    // Covariance xx, xy, yy (px^2, dilated).
    cov2: vec3<f32>,
    opacity: f32,
    depth: f32,
}

// Columns of the rotation matrix of a unit quaternion [w, x, y, z] (light.rs quat_to_mat:
// column c is (r[0][c], r[1][c], r[2][c])).
struct Cols {
    c0: vec3<f32>,
    c1: vec3<f32>,
    c2: vec3<f32>,
}

fn quat_cols(qh: vec4<f32>) -> Cols {
    let qw = qh.x;
    let qx = qh.y;
    let qy = qh.z;
    let qz = qh.w;
    var r: Cols;
    r.c0 = vec3<f32>(1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy + qw * qz), 2.0 * (qx * qz - qw * qy));
    r.c1 = vec3<f32>(2.0 * (qx * qy - qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz + qw * qx));
    r.c2 = vec3<f32>(2.0 * (qx * qz + qw * qy), 2.0 * (qy * qz - qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy));
    return r;
}

// light.rs ortho_splat.
fn ortho_splat(mean: vec3<f32>, log_scale: vec3<f32>, q: vec4<f32>, logit: f32) -> LightSplat {
    var s: LightSplat;
    s.ok = false;
    if !(finite3(mean) && finite3(log_scale) && finite3(q.xyz) && finite(q.w) && finite(logit)) {
        return s;
    }
    let q_norm2 = q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w;
    if !(finite(q_norm2) && q_norm2 >= MIN_QUAT_NORM2) {
        return s;
    }
    let opacity = 1.0 / (1.0 + exp(-logit));
    // NaN compares false: culled, as the CPU's `is_nan() || < ALPHA_MIN`.
    if !(opacity >= fr.cutoff) {
        return s;
    }
    let w0 = fr.r0.xyz;
    let w1 = fr.r1.xyz;
    let t = vec3<f32>(dot3(w0, mean) + fr.r0.w, dot3(w1, mean) + fr.r1.w, dot3(fr.r2.xyz, mean) + fr.r2.w);
    if !(finite3(t) && t.z >= fr.near) {
        return s;
    }
    let qn = sqrt(q_norm2);
    let r = quat_cols(q / qn);
    let sc = exp(log_scale);
    // Rows 0 and 1 of W R S: the image-plane axes.
    let m0 = vec3<f32>(dot3(w0, r.c0) * sc.x, dot3(w0, r.c1) * sc.y, dot3(w0, r.c2) * sc.z);
    let m1 = vec3<f32>(dot3(w1, r.c0) * sc.x, dot3(w1, r.c1) * sc.y, dot3(w1, r.c2) * sc.z);
    let k = sp.px_per_m;
    let k2 = k * k;
    let xx = k2 * dot3(m0, m0) + COV2D_DILATION;
    let xy = k2 * dot3(m0, m1);
    let yy = k2 * dot3(m1, m1) + COV2D_DILATION;
    let det = xx * yy - xy * xy;
    if !(finite(det) && det > 0.0) {
        return s;
    }
    s.conic = vec3<f32>(yy / det, -xy / det, xx / det);
    s.cov2 = vec3<f32>(xx, xy, yy);
    s.mean_px = vec2<f32>(k * t.x + sp.half_px, k * t.y + sp.half_px);
    if !(finite(s.mean_px.x) && finite(s.mean_px.y)) {
        return s;
    }
    s.opacity = opacity;
    s.depth = t.z;
    s.ok = true;
    return s;
}

// light.rs light_axis_sigmas_m for one Gaussian: sqrt(a^T Sigma a), a the light axis;
// 0 where a parameter is not finite.
fn axis_sigma(log_scale: vec3<f32>, q: vec4<f32>) -> f32 {
    let q_norm = sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w);
    if !(finite(q_norm) && q_norm > 1e-3 && finite3(log_scale)) {
        return 0.0;
    }
    let r = quat_cols(q / q_norm);
    let axis = fr.r2.xyz;
    let along = vec3<f32>(dot3(axis, r.c0), dot3(axis, r.c1), dot3(axis, r.c2));
    let s = exp(log_scale);
    // In the CPU's order: ((0 + v0) + v1) + v2, each v = along * along * s * s.
    var variance = 0.0;
    variance += along.x * along.x * s.x * s.x;
    variance += along.y * along.y * s.y * s.y;
    variance += along.z * along.z * s.z * s.z;
    if finite(variance) {
        return sqrt(variance);
    }
    return 0.0;
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
    limits[i] = 0.0;
    let mean = vec3<f32>(params[sp.off.x + 3u * i], params[sp.off.x + 3u * i + 1u], params[sp.off.x + 3u * i + 2u]);
    let ls = vec3<f32>(params[sp.off.y + 3u * i], params[sp.off.y + 3u * i + 1u], params[sp.off.y + 3u * i + 2u]);
    let qb = sp.off.z + 4u * i;
    let q = vec4<f32>(params[qb], params[qb + 1u], params[qb + 2u], params[qb + 3u]);
    let logit = params[sp.off.w + i];
    var s: LightSplat;
    var radius = 0.0;
    if sp.orthographic != 0u {
        s = ortho_splat(mean, ls, q, logit);
    } else {
        let p = project_forward(fr, mean, ls, q, logit);
        s.ok = p.ok;
        s.mean_px = p.mean_px;
        s.conic = p.conic;
        s.cov2 = p.cov2;
        s.opacity = p.opacity;
        s.depth = p.t_cam.z;
    }
    if !s.ok {
        return;
    }
    // raster::splat_rect (and, for perspective, project_splats' radius check).
    let q_max = 2.0 * log(s.opacity / fr.cutoff);
    if sp.orthographic == 0u {
        radius = splat_radius(s.cov2, q_max);
    }
    let rect = splat_rect(s.mean_px, s.cov2, q_max, fr.width, fr.height);
    if rect.x >= rect.z || rect.y >= rect.w || !finite(radius) {
        return;
    }
    let row = splat_row(s.mean_px, s.conic, s.opacity, s.depth, radius, rect);
    for (var k = 0u; k < 12u; k++) {
        splats[sb + k] = row[k];
    }
    let margin = axis_sigma(ls, q) * sp.extent_sigmas;
    limits[i] = s.depth - sp.depth_bias - max(margin, 0.0);
    counts[i] = rect_tiles(rect);
}
