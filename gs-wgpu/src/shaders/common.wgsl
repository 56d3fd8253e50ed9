// Shared by the raster kernels: the per-render uniform, alpha helpers and the EWA
// projection forward and backward, ported operation for operation from
// raster/project.rs and raster/blend.rs (the CPU reference).
// The host prepends `const NC: u32` (channels) and `const REC: u32` (7 + NC).

struct Frame {
    // Rows of the world-to-camera rotation; w holds the translation component.
    r0: vec4<f32>,
    r1: vec4<f32>,
    r2: vec4<f32>,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    lim_x: f32,
    lim_y: f32,
    near: f32,
    cutoff: f32,
    width: u32,
    height: u32,
    tiles_x: u32,
    tiles_y: u32,
    n: u32,
    smooth_mode: u32,
    n_entries: u32,
    n_sort: u32,
    bg0: vec4<f32>,
    bg1: vec4<f32>,
    // The blend stops a pixel before a splat that would take its transmittance below
    // this (raster::blend::AlphaMode::stop: 1e-4, or 1.2e-38 with early termination off,
    // 0 in smooth mode).
    stop: f32,
    // 1: the kernels' `tile_mask` (one bit per tile, see tile_bit) selects the tiles to blend;
    // 0: every tile is blended.
    tile_masked: u32,
    pad0: u32,
    pad1: u32,
}

const TILE: u32 = 16u;
// `Frame::n_entries` when the entry count stays on the device (see keygen.wgsl).
const ENTRIES_ON_DEVICE: u32 = 0xffffffffu;
const COV2D_DILATION: f32 = 0.3;
const MIN_QUAT_NORM2: f32 = 1e-6;
const ALPHA_MAX: f32 = 0.99;
const SMOOTH_LO: f32 = 0.5 / 255.0;
const SMOOTH_HI: f32 = 1.5 / 255.0;
const TRANSMITTANCE_STOP: f32 = 1e-4;
// Per-Gaussian input stride: mean 3, log-scale 3, quaternion 4, opacity logit 1.
const GSTRIDE: u32 = 11u;
// Per-splat stride: mean_px 2, conic 3, opacity, depth, radius (-1 when culled), then the
// pixel rectangle x0, y0, x1, y1 as u32 bit patterns.
const SSTRIDE: u32 = 12u;

fn finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

fn finite3(v: vec3<f32>) -> bool {
    return finite(v.x) && finite(v.y) && finite(v.z);
}

// Tile `t`'s bit in its tile-mask word (`word` = mask[t / 32]; bit t % 32). The kernels
// bind the mask themselves and read it only when `Frame::tile_masked` is 1.
fn tile_bit(t: u32, word: u32) -> bool {
    return ((word >> (t & 31u)) & 1u) != 0u;
}

fn background(k: u32, fr: Frame) -> f32 {
    if k < 4u {
        return fr.bg0[k];
    }
    return fr.bg1[k - 4u];
}

// exp(x) as raster::blend::fast_exp: the same polynomial, so the 1/255 cutoff and the
// early stop decide like the CPU path to within an ulp.
fn fast_exp(x_in: f32) -> f32 {
    let LOG2E = 1.4426950408889634;
    let LN2_HI = 0.693359375;
    let LN2_LO = -2.12194440e-4;
    let x = min(max(x_in, -87.0), 88.0);
    let n = round(x * LOG2E);
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = ((((1.9875691e-4 * r + 1.3981999e-3) * r + 8.333452e-3) * r + 4.1665796e-2) * r
        + 1.6666665e-1) * r + 0.5;
    let e = p * r * r + r + 1.0;
    return ldexp(e, i32(n));
}

// raster::blend::alpha_of: (alpha, d alpha / d raw, kept).
struct Alpha {
    alpha: f32,
    d_raw: f32,
    kept: bool,
}

fn alpha_of(o: f32, gauss: f32, smooth_mode: bool, cutoff: f32) -> Alpha {
    var out: Alpha;
    let raw = o * gauss;
    let clamped = raw > ALPHA_MAX;
    var alpha_c = raw;
    if clamped {
        alpha_c = ALPHA_MAX;
    }
    out.kept = finite(alpha_c) && alpha_c >= cutoff;
    out.alpha = alpha_c;
    out.d_raw = 1.0;
    if smooth_mode && alpha_c < SMOOTH_HI {
        let u = (alpha_c - SMOOTH_LO) / (SMOOTH_HI - SMOOTH_LO);
        let ramp = u * u * (3.0 - 2.0 * u);
        let d_ramp = 6.0 * u * (1.0 - u) / (SMOOTH_HI - SMOOTH_LO);
        out.alpha = alpha_c * ramp;
        out.d_raw = ramp + alpha_c * d_ramp;
    }
    if clamped {
        out.d_raw = 0.0;
    }
    return out;
}

struct Proj {
    ok: bool,
    q_hat: vec4<f32>,
    q_norm: f32,
    // Rows of the rotation matrix, of M = R diag(s), of Sigma3, and of T = J W (2 rows).
    rot0: vec3<f32>,
    rot1: vec3<f32>,
    rot2: vec3<f32>,
    scale: vec3<f32>,
    m0: vec3<f32>,
    m1: vec3<f32>,
    m2: vec3<f32>,
    cov0: vec3<f32>,
    cov1: vec3<f32>,
    cov2r: vec3<f32>,
    t_cam: vec3<f32>,
    ratio_x: f32,
    ratio_y: f32,
    clamped_x: bool,
    clamped_y: bool,
    t0: vec3<f32>,
    t1: vec3<f32>,
    cov2: vec3<f32>,
    conic: vec3<f32>,
    mean_px: vec2<f32>,
    opacity: f32,
}

fn dot3(a: vec3<f32>, b: vec3<f32>) -> f32 {
    return a.x * b.x + a.y * b.y + a.z * b.z;
}

// raster::project::project_forward; `ok` false where the CPU returns Err(Culled).
fn project_forward(fr: Frame, mean: vec3<f32>, log_scale: vec3<f32>, q: vec4<f32>, logit: f32) -> Proj {
    var p: Proj;
    p.ok = false;
    if !(finite3(mean) && finite3(log_scale) && finite3(q.xyz) && finite(q.w) && finite(logit)) {
        return p;
    }
    let q_norm2 = q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w;
    if !finite(q_norm2) || q_norm2 < MIN_QUAT_NORM2 {
        return p;
    }
    let opacity = 1.0 / (1.0 + exp(-logit));
    if !finite(opacity) || opacity < fr.cutoff {
        return p;
    }
    let w0 = fr.r0.xyz;
    let w1 = fr.r1.xyz;
    let w2 = fr.r2.xyz;
    let t_cam = vec3<f32>(dot3(w0, mean) + fr.r0.w, dot3(w1, mean) + fr.r1.w, dot3(w2, mean) + fr.r2.w);
    if !finite3(t_cam) {
        return p;
    }
    let z = t_cam.z;
    if z < fr.near {
        return p;
    }
    let q_norm = sqrt(q_norm2);
    let qh = q / q_norm;
    // q = [w, x, y, z] in the buffer: qh.x = w, qh.y = x, qh.z = y, qh.w = z.
    let qw = qh.x;
    let qx = qh.y;
    let qy = qh.z;
    let qz = qh.w;
    let rot0 = vec3<f32>(1.0 - 2.0 * (qy * qy + qz * qz), 2.0 * (qx * qy - qw * qz), 2.0 * (qx * qz + qw * qy));
    let rot1 = vec3<f32>(2.0 * (qx * qy + qw * qz), 1.0 - 2.0 * (qx * qx + qz * qz), 2.0 * (qy * qz - qw * qx));
    let rot2 = vec3<f32>(2.0 * (qx * qz - qw * qy), 2.0 * (qy * qz + qw * qx), 1.0 - 2.0 * (qx * qx + qy * qy));
    let scale = exp(log_scale);
    let m0 = rot0 * scale;
    let m1 = rot1 * scale;
    let m2 = rot2 * scale;
    let cov0 = vec3<f32>(dot3(m0, m0), dot3(m0, m1), dot3(m0, m2));
    let cov1 = vec3<f32>(dot3(m1, m0), dot3(m1, m1), dot3(m1, m2));
    let cov2r = vec3<f32>(dot3(m2, m0), dot3(m2, m1), dot3(m2, m2));
    let raw_x = t_cam.x / z;
    let raw_y = t_cam.y / z;
    let ratio_x = clamp(raw_x, -fr.lim_x, fr.lim_x);
    let ratio_y = clamp(raw_y, -fr.lim_y, fr.lim_y);
    let inv_z = 1.0 / z;
    let j00 = fr.fx * inv_z;
    let j02 = -fr.fx * ratio_x * inv_z;
    let j11 = fr.fy * inv_z;
    let j12 = -fr.fy * ratio_y * inv_z;
    // T = J W: row r of T is sum_k J[r][k] W_row_k.
    let t0 = j00 * w0 + j02 * w2;
    let t1 = j11 * w1 + j12 * w2;
    let tc0 = t0.x * cov0 + t0.y * cov1 + t0.z * cov2r;
    let tc1 = t1.x * cov0 + t1.y * cov1 + t1.z * cov2r;
    let cov2 = vec3<f32>(dot3(tc0, t0) + COV2D_DILATION, dot3(tc0, t1), dot3(tc1, t1) + COV2D_DILATION);
    let det = cov2.x * cov2.z - cov2.y * cov2.y;
    if !finite(det) || !(det > 0.0) || !finite3(cov2) {
        return p;
    }
    let inv_det = 1.0 / det;
    let conic = vec3<f32>(cov2.z * inv_det, -cov2.y * inv_det, cov2.x * inv_det);
    let mean_px = vec2<f32>(fr.fx * raw_x + fr.cx, fr.fy * raw_y + fr.cy);
    if !finite3(conic) || !finite(mean_px.x) || !finite(mean_px.y) {
        return p;
    }
    p.ok = true;
    p.q_hat = qh;
    p.q_norm = q_norm;
    p.rot0 = rot0;
    p.rot1 = rot1;
    p.rot2 = rot2;
    p.scale = scale;
    p.m0 = m0;
    p.m1 = m1;
    p.m2 = m2;
    p.cov0 = cov0;
    p.cov1 = cov1;
    p.cov2r = cov2r;
    p.t_cam = t_cam;
    p.ratio_x = ratio_x;
    p.ratio_y = ratio_y;
    p.clamped_x = ratio_x != raw_x;
    p.clamped_y = ratio_y != raw_y;
    p.t0 = t0;
    p.t1 = t1;
    p.cov2 = cov2;
    p.conic = conic;
    p.mean_px = mean_px;
    p.opacity = opacity;
    return p;
}

fn to_px(v: f32, hi: u32) -> u32 {
    return u32(clamp(v, 0.0, f32(hi)));
}

// Radius of a splat out to q_max: sqrt(q_max * largest eigenvalue of its 2D covariance
// (xx, xy, yy)), as raster::project_splats.
fn splat_radius(cov2: vec3<f32>, q_max: f32) -> f32 {
    let mid = 0.5 * (cov2.x + cov2.z);
    let lambda_max = mid + sqrt(max(mid * mid - (cov2.x * cov2.z - cov2.y * cov2.y), 0.0));
    return sqrt(q_max * lambda_max);
}

// Pixel rectangle (x0, y0, x1, y1) of a splat, raster::splat_rect: the extent
// sqrt(q_max * variance) along each axis, widened by 0.1% and 0.01 px, clamped to the
// image; empty when x0 >= x1 or y0 >= y1.
fn splat_rect(mean_px: vec2<f32>, cov2: vec3<f32>, q_max: f32, width: u32, height: u32) -> vec4<u32> {
    let ext_x = sqrt(q_max * cov2.x) * 1.001 + 0.01;
    let ext_y = sqrt(q_max * cov2.z) * 1.001 + 0.01;
    return vec4<u32>(
        to_px(floor(mean_px.x - ext_x - 0.5), width),
        to_px(floor(mean_px.y - ext_y - 0.5), height),
        to_px(floor(mean_px.x + ext_x - 0.5) + 1.0, width),
        to_px(floor(mean_px.y + ext_y - 0.5) + 1.0, height),
    );
}

// A splat's SSTRIDE-float row: mean x, y, conic a, b, c, opacity, depth, radius, then the
// rectangle's four corners as bits.
fn splat_row(mean_px: vec2<f32>, conic: vec3<f32>, opacity: f32, depth: f32, radius: f32, rect: vec4<u32>) -> array<f32, 12> {
    return array<f32, 12>(
        mean_px.x, mean_px.y, conic.x, conic.y, conic.z, opacity, depth, radius,
        bitcast<f32>(rect.x), bitcast<f32>(rect.y), bitcast<f32>(rect.z), bitcast<f32>(rect.w),
    );
}

// Tiles a pixel rectangle touches.
fn rect_tiles(rect: vec4<u32>) -> u32 {
    return ((rect.z + TILE - 1u) / TILE - rect.x / TILE) * ((rect.w + TILE - 1u) / TILE - rect.y / TILE);
}
