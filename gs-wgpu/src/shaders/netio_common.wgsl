// Shared by the network input/output kernels (network_io/), prepended to each: the
// uniform (with the learned normal's terms: the shading, the local inputs), the bindings every kernel has
// (uniform, list, count: bindings 0-2; each kernel declares its own buffers from
// binding 3 on), the row-to-Gaussian lookup, the packed parameter layout's group
// offsets, and `sin(pi x)`, `cos(pi x)` and the positional encoding ported operation for
// operation from nn/encoding.rs.

struct NetIo {
    // Start of each parameter group in the packed buffers (Param order).
    off0: vec4<u32>,
    off1: vec4<u32>,
    // Gaussians (rows dispatched), channels per Gaussian, floats per network input row.
    n: u32,
    nc: u32,
    width: u32,
    // Feature width (Phi) or latent width (Psi).
    dim: u32,
    // Frequencies L of the encoding.
    freqs: u32,
    // Non-zero: Psi's output multiplies V (ShadowRefinement::Multiply), times `gain`.
    multiply: u32,
    // SunAwareConfig::shadow_gain (read under Multiply only).
    gain: f32,
    // Non-zero: Phi's rows end in the local inputs [n.s, n.v, n.h] (netio_normal.wgsl).
    local: u32,
    // Camera centre (Phi), .w unused.
    cam: vec4<f32>,
    // Scene box (Psi): minimum corner, extent max - min, 1 / extent (host f32, as shadow.rs).
    box_min: vec4<f32>,
    box_extent: vec4<f32>,
    box_inv_extent: vec4<f32>,
    // The learned normal (shading.rs; read where `shaded` or `local` is non-zero): the
    // unit Sun vector as the CPU uses it (.w: MIN_HALF_NORM2 of the local inputs' half
    // vector), the start of the Normal group in the packed buffers, the degenerate |v|^2
    // bound, and the ambient floor k_a of the Lambertian factor on Phi's colour (applied
    // where `shaded` is non-zero).
    sun_unit: vec4<f32>,
    normal_off: u32,
    shaded: u32,
    min_norm2: f32,
    ambient: f32,
    // gamma_L of the unit Sun direction (6L values, computed on the host by the CPU
    // encoding: the same bits as the CPU rows).
    sun: array<vec4<f32>, 24>,
}

@group(0) @binding(0) var<uniform> u: NetIo;
@group(0) @binding(1) var<storage, read> list: array<u32>;
@group(0) @binding(2) var<storage, read> count: array<u32>;

// Row of this invocation (dispatch_1d's grid of 256-wide groups, folded to 1-D).
fn row_of(gid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return gid.x + gid.y * nwg.x * 256u;
}

// Row r is live when r < count (count[0], read as at most n).
fn is_live(r: u32) -> bool {
    return r < min(count[0], u.n);
}

// The Gaussian of row r: list[r] for a live row (which may itself be out of range, >= n),
// n for a dead row.
fn listed_gaussian(r: u32) -> u32 {
    if is_live(r) {
        return list[r];
    }
    return u.n;
}

const G_MEAN: u32 = 0u;
const G_FEATURE: u32 = 6u;
const G_LATENT: u32 = 7u;

fn goff(u: NetIo, g: u32) -> u32 {
    if g < 4u {
        return u.off0[g];
    }
    return u.off1[g - 4u];
}

fn sun_code(u: NetIo, i: u32) -> f32 {
    return u.sun[i / 4u][i % 4u];
}

fn finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

// encoding.rs SIN_POLY / COS_POLY (the same f32 values).
const SIN_P0: f32 = 3.14159265358979;
const SIN_P1: f32 = -5.167708;
const SIN_P2: f32 = 2.549767;
const SIN_P3: f32 = -0.5890751;
const COS_P1: f32 = -4.934802;
const COS_P2: f32 = 4.058707;
const COS_P3: f32 = -1.3350445;
const COS_P4: f32 = 0.23132879;

// (sin(pi x), cos(pi x)) as encoding.rs `sin_cos_pi_lanes`: 2x rounds to the nearest
// integer q (ties to even, as the CPU's magic-number rounding), r = x - q/2 is exact and
// in [-1/4, 1/4], two polynomials give sin(pi r), cos(pi r), and q mod 4 swaps and
// negates them. q mod 4 is taken in f32 (exact for every finite q), so the CPU's f64 path
// for |x| >= 2^21 is not needed: there x is a multiple of 1/4 and r is exact as well
// (the results then differ from the CPU's f64 values by below 1e-7).
fn sin_cos_pi(x: f32) -> vec2<f32> {
    let q = round(2.0 * x);
    let r = x - 0.5 * q;
    let z = r * r;
    let s = r * (SIN_P0 + z * (SIN_P1 + z * (SIN_P2 + z * SIN_P3)));
    let c = 1.0 + z * (COS_P1 + z * (COS_P2 + z * (COS_P3 + z * COS_P4)));
    let quadrant = u32(q - 4.0 * floor(q * 0.25));
    var sv = s;
    var cv = c;
    if (quadrant & 1u) != 0u {
        sv = c;
        cv = s;
    }
    let sin_bits = bitcast<u32>(sv) ^ ((quadrant & 2u) << 30u);
    let cos_bits = bitcast<u32>(cv) ^ (((quadrant ^ (quadrant >> 1u)) & 1u) << 31u);
    return vec2<f32>(bitcast<f32>(sin_bits), bitcast<f32>(cos_bits));
}

// Angular frequency of band k, 2^k pi (encoding.rs `omega`: f32 pi times 2^k, exact).
fn omega(k: u32) -> f32 {
    return SIN_P0 * f32(1u << k);
}
