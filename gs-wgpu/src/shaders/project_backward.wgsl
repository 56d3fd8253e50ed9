// Projection backward: one thread per Gaussian turns its accumulated screen-space
// gradient [d_mean_px (2), d_conic (3), d_opacity, d_depth, d_channels (NC)] into
// gradients of its raw parameters, as raster::project::project_backward, recomputing
// the projection. Output row (OSTRIDE = 13 + NC): d_mean 3, d_log_scale 3, d_rotation 4,
// d_opacity_logit, |d mean2d| in NDC units, a dropped flag (1 when the gradient came out
// non-finite and was zeroed), d_channels. Culled Gaussians get zeros.

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> gauss: array<f32>;
@group(0) @binding(2) var<storage, read> splats: array<f32>;
@group(0) @binding(3) var<storage, read> acc: array<f32>;
@group(0) @binding(4) var<storage, read_write> grads: array<f32>;

struct ParamGrad {
    d_mean: vec3<f32>,
    d_log_scale: vec3<f32>,
    d_rotation: vec4<f32>,
    d_opacity_logit: f32,
}

fn project_backward(p: Proj, d_mean_px: vec2<f32>, d_conic: vec3<f32>, d_opacity: f32, d_depth: f32) -> ParamGrad {
    let a = p.conic.x;
    let b = p.conic.y;
    let c = p.conic.z;
    let ga = d_conic.x;
    let gb = d_conic.y;
    let gc = d_conic.z;
    let hb = 0.5 * gb;
    let kg00 = a * ga + b * hb;
    let kg01 = a * hb + b * gc;
    let kg10 = b * ga + c * hb;
    let kg11 = b * hb + c * gc;
    let s00 = -(kg00 * a + kg01 * b);
    let s01 = -(kg00 * b + kg01 * c);
    let s11 = -(kg10 * b + kg11 * c);
    // dL/dcov3 = T^T G2 T; dL/dT = 2 G2 T cov3 (rows).
    let g2t0 = s00 * p.t0 + s01 * p.t1;
    let g2t1 = s01 * p.t0 + s11 * p.t1;
    let dcov0 = p.t0.x * g2t0 + p.t1.x * g2t1;
    let dcov1 = p.t0.y * g2t0 + p.t1.y * g2t1;
    let dcov2 = p.t0.z * g2t0 + p.t1.z * g2t1;
    let dt0 = 2.0 * (g2t0.x * p.cov0 + g2t0.y * p.cov1 + g2t0.z * p.cov2r);
    let dt1 = 2.0 * (g2t1.x * p.cov0 + g2t1.y * p.cov1 + g2t1.z * p.cov2r);
    // dL/dJ = dL/dT W^T: d_j[r][col] = dot(dT_r, W_row_col).
    let w0 = fr.r0.xyz;
    let w1 = fr.r1.xyz;
    let w2 = fr.r2.xyz;
    let dj00 = dot3(dt0, w0);
    let dj02 = dot3(dt0, w2);
    let dj11 = dot3(dt1, w1);
    let dj12 = dot3(dt1, w2);
    let x = p.t_cam.x;
    let y = p.t_cam.y;
    let z = p.t_cam.z;
    let inv_z = 1.0 / z;
    let inv_z2 = inv_z * inv_z;
    let fx = fr.fx;
    let fy = fr.fy;
    var d_tc = vec3<f32>(0.0, 0.0, 0.0);
    d_tc.z += -fx * inv_z2 * dj00 - fy * inv_z2 * dj11;
    if p.clamped_x {
        d_tc.z += fx * p.ratio_x * inv_z2 * dj02;
    } else {
        d_tc.x += -fx * inv_z2 * dj02;
        d_tc.z += 2.0 * fx * x * inv_z2 * inv_z * dj02;
    }
    if p.clamped_y {
        d_tc.z += fy * p.ratio_y * inv_z2 * dj12;
    } else {
        d_tc.y += -fy * inv_z2 * dj12;
        d_tc.z += 2.0 * fy * y * inv_z2 * inv_z * dj12;
    }
    let du = d_mean_px.x;
    let dv = d_mean_px.y;
    d_tc.x += fx * inv_z * du;
    d_tc.y += fy * inv_z * dv;
    d_tc.z += -fx * x * inv_z2 * du - fy * y * inv_z2 * dv;
    d_tc.z += d_depth;
    var out: ParamGrad;
    out.d_mean = w0 * d_tc.x + w1 * d_tc.y + w2 * d_tc.z;
    // cov3 = M M^T => dL/dM = 2 dL/dcov3 M.
    let dm0 = 2.0 * (dcov0.x * p.m0 + dcov0.y * p.m1 + dcov0.z * p.m2);
    let dm1 = 2.0 * (dcov1.x * p.m0 + dcov1.y * p.m1 + dcov1.z * p.m2);
    let dm2 = 2.0 * (dcov2.x * p.m0 + dcov2.y * p.m1 + dcov2.z * p.m2);
    out.d_log_scale = (dm0 * p.rot0 + dm1 * p.rot1 + dm2 * p.rot2) * p.scale;
    let r0 = dm0 * p.scale;
    let r1 = dm1 * p.scale;
    let r2 = dm2 * p.scale;
    let qw = p.q_hat.x;
    let qx = p.q_hat.y;
    let qy = p.q_hat.z;
    let qz = p.q_hat.w;
    let g_w = 2.0 * (-qz * r0.y + qy * r0.z + qz * r1.x - qx * r1.z - qy * r2.x + qx * r2.y);
    let g_x = 2.0 * (qy * r0.y + qz * r0.z + qy * r1.x - 2.0 * qx * r1.y - qw * r1.z + qz * r2.x + qw * r2.y - 2.0 * qx * r2.z);
    let g_y = 2.0 * (-2.0 * qy * r0.x + qx * r0.y + qw * r0.z + qx * r1.x + qz * r1.z - qw * r2.x + qz * r2.y - 2.0 * qy * r2.z);
    let g_z = 2.0 * (-2.0 * qz * r0.x - qw * r0.y + qx * r0.z + qw * r1.x - 2.0 * qz * r1.y + qy * r1.z + qx * r2.x + qy * r2.y);
    let g_hat = vec4<f32>(g_w, g_x, g_y, g_z);
    let d = g_w * qw + g_x * qx + g_y * qy + g_z * qz;
    out.d_rotation = (g_hat - p.q_hat * d) / p.q_norm;
    out.d_opacity_logit = d_opacity * p.opacity * (1.0 - p.opacity);
    return out;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= fr.n {
        return;
    }
    let ob = i * OSTRIDE;
    for (var k = 0u; k < OSTRIDE; k++) {
        grads[ob + k] = 0.0;
    }
    if splats[i * SSTRIDE + 7u] < 0.0 {
        return;
    }
    let b = i * GSTRIDE;
    let mean = vec3<f32>(gauss[b], gauss[b + 1u], gauss[b + 2u]);
    let ls = vec3<f32>(gauss[b + 3u], gauss[b + 4u], gauss[b + 5u]);
    let q = vec4<f32>(gauss[b + 6u], gauss[b + 7u], gauss[b + 8u], gauss[b + 9u]);
    let p = project_forward(fr, mean, ls, q, gauss[b + 10u]);
    if !p.ok {
        return;
    }
    let ab = i * REC;
    let d_mean_px = vec2<f32>(acc[ab], acc[ab + 1u]);
    let pg = project_backward(p, d_mean_px, vec3<f32>(acc[ab + 2u], acc[ab + 3u], acc[ab + 4u]), acc[ab + 5u], acc[ab + 6u]);
    let ndc_x = d_mean_px.x * 0.5 * f32(fr.width);
    let ndc_y = d_mean_px.y * 0.5 * f32(fr.height);
    let ndc = sqrt(ndc_x * ndc_x + ndc_y * ndc_y);
    var ok = finite3(pg.d_mean) && finite3(pg.d_log_scale) && finite3(pg.d_rotation.xyz) && finite(pg.d_rotation.w) && finite(pg.d_opacity_logit) && finite(ndc);
    for (var k = 0u; k < NC; k++) {
        ok = ok && finite(acc[ab + 7u + k]);
    }
    if !ok {
        grads[ob + 12u] = 1.0;
        return;
    }
    grads[ob] = pg.d_mean.x;
    grads[ob + 1u] = pg.d_mean.y;
    grads[ob + 2u] = pg.d_mean.z;
    grads[ob + 3u] = pg.d_log_scale.x;
    grads[ob + 4u] = pg.d_log_scale.y;
    grads[ob + 5u] = pg.d_log_scale.z;
    grads[ob + 6u] = pg.d_rotation.x;
    grads[ob + 7u] = pg.d_rotation.y;
    grads[ob + 8u] = pg.d_rotation.z;
    grads[ob + 9u] = pg.d_rotation.w;
    grads[ob + 10u] = pg.d_opacity_logit;
    grads[ob + 11u] = ndc;
    for (var k = 0u; k < NC; k++) {
        grads[ob + 13u + k] = acc[ab + 7u + k];
    }
}
