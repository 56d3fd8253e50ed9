// Shared by the resident-training kernels (resident_sunaware/kernels.rs): the step uniform over the
// packed, group-major parameter buffer, and the SH basis and its Jacobian ported
// operation for operation from sh.rs (3DGS constants and signs).

struct Step {
    // Start of each parameter group in the packed buffers (Param order).
    off0: vec4<u32>,
    off1: vec4<u32>,
    n: u32,
    rest_dim: u32,
    // Coefficients per channel at the active degree (1, 4, 9, 16).
    coeffs: u32,
    degree: u32,
    cam: vec4<f32>,
    // Non-zero: add this step's screen-space gradients and radii to the statistics.
    accumulate_stats: u32,
    // Floats per row of the rasterizer's gradient output (13 + 3 channels).
    ostride: u32,
    // Widths of the feature and shadow-latent groups (not trained here: zero gradients).
    feature_dim: u32,
    latent_dim: u32,
}

const SH_C0: f32 = 0.2820948;
const SH_C1: f32 = 0.48860252;
const SH_C2_0: f32 = 1.0925484;
const SH_C2_1: f32 = -1.0925484;
const SH_C2_2: f32 = 0.31539157;
const SH_C2_3: f32 = -1.0925484;
const SH_C2_4: f32 = 0.5462742;
const SH_C3_0: f32 = -0.5900436;
const SH_C3_1: f32 = 2.8906114;
const SH_C3_2: f32 = -0.4570458;
const SH_C3_3: f32 = 0.37317633;
const SH_C3_4: f32 = -0.4570458;
const SH_C3_5: f32 = 1.4453057;
const SH_C3_6: f32 = -0.5900436;

const G_MEAN: u32 = 0u;
const G_LOG_SCALE: u32 = 1u;
const G_ROTATION: u32 = 2u;
const G_OPACITY: u32 = 3u;
const G_SH_DC: u32 = 4u;
const G_SH_REST: u32 = 5u;
const G_FEATURE: u32 = 6u;
const G_LATENT: u32 = 7u;

fn goff(s: Step, g: u32) -> u32 {
    if g < 4u {
        return s.off0[g];
    }
    return s.off1[g - 4u];
}

fn is_finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

// Unit view direction in .xyz and the unnormalised length in .w; w < 0 at the camera
// centre (sh.rs `view_direction` returns None there).
fn view_dir(mean: vec3<f32>, cam: vec3<f32>) -> vec4<f32> {
    let v = mean - cam;
    let len = sqrt(v.x * v.x + v.y * v.y + v.z * v.z);
    if is_finite(len) && len > 1e-12 {
        return vec4<f32>(v / len, len);
    }
    return vec4<f32>(0.0, 0.0, 1.0, -1.0);
}

fn sh_basis(degree: u32, d: vec3<f32>) -> array<f32, 16> {
    var b: array<f32, 16>;
    let x = d.x;
    let y = d.y;
    let z = d.z;
    b[0] = SH_C0;
    if degree >= 1u {
        b[1] = -SH_C1 * y;
        b[2] = SH_C1 * z;
        b[3] = -SH_C1 * x;
    }
    if degree >= 2u {
        let xx = x * x;
        let yy = y * y;
        let zz = z * z;
        b[4] = SH_C2_0 * x * y;
        b[5] = SH_C2_1 * y * z;
        b[6] = SH_C2_2 * (2.0 * zz - xx - yy);
        b[7] = SH_C2_3 * x * z;
        b[8] = SH_C2_4 * (xx - yy);
        if degree >= 3u {
            b[9] = SH_C3_0 * y * (3.0 * xx - yy);
            b[10] = SH_C3_1 * x * y * z;
            b[11] = SH_C3_2 * y * (4.0 * zz - xx - yy);
            b[12] = SH_C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy);
            b[13] = SH_C3_4 * x * (4.0 * zz - xx - yy);
            b[14] = SH_C3_5 * z * (xx - yy);
            b[15] = SH_C3_6 * x * (xx - 3.0 * yy);
        }
    }
    return b;
}

fn sh_jacobian(degree: u32, d: vec3<f32>) -> array<vec3<f32>, 16> {
    var j: array<vec3<f32>, 16>;
    let x = d.x;
    let y = d.y;
    let z = d.z;
    if degree >= 1u {
        j[1] = vec3<f32>(0.0, -SH_C1, 0.0);
        j[2] = vec3<f32>(0.0, 0.0, SH_C1);
        j[3] = vec3<f32>(-SH_C1, 0.0, 0.0);
    }
    if degree >= 2u {
        let xx = x * x;
        let yy = y * y;
        let zz = z * z;
        j[4] = SH_C2_0 * vec3<f32>(y, x, 0.0);
        j[5] = SH_C2_1 * vec3<f32>(0.0, z, y);
        j[6] = SH_C2_2 * vec3<f32>(-2.0 * x, -2.0 * y, 4.0 * z);
        j[7] = SH_C2_3 * vec3<f32>(z, 0.0, x);
        j[8] = SH_C2_4 * vec3<f32>(2.0 * x, -2.0 * y, 0.0);
        if degree >= 3u {
            j[9] = SH_C3_0 * vec3<f32>(6.0 * x * y, 3.0 * xx - 3.0 * yy, 0.0);
            j[10] = SH_C3_1 * vec3<f32>(y * z, x * z, x * y);
            j[11] = SH_C3_2 * vec3<f32>(-2.0 * x * y, 4.0 * zz - xx - 3.0 * yy, 8.0 * y * z);
            j[12] = SH_C3_3 * vec3<f32>(-6.0 * x * z, -6.0 * y * z, 6.0 * zz - 3.0 * xx - 3.0 * yy);
            j[13] = SH_C3_4 * vec3<f32>(4.0 * zz - 3.0 * xx - yy, -2.0 * x * y, 8.0 * x * z);
            j[14] = SH_C3_5 * vec3<f32>(2.0 * x * z, -2.0 * y * z, xx - yy);
            j[15] = SH_C3_6 * vec3<f32>(3.0 * xx - 3.0 * yy, -6.0 * x * y, 0.0);
        }
    }
    return j;
}
