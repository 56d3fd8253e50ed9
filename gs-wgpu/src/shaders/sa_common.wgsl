// Shared by the Sun-aware resident step's own kernels (resident_sunaware/): a
// uniform holding one count (Gaussians, pixels or values), padded to 16 bytes; the
// compose kernels' uniform; and the sRGB curve of `colour_space = "linear"`
// (gs_core::srgb), in the CPU's operations with its f32 constants.

struct Count {
    n: u32,
    pad0: u32,
    pad1: u32,
    pad2: u32,
}

// sa_compose and sa_compose_backward: pixels, rendered channels per pixel (3 in a-b, 4
// with S in c-d), and 1 when each pixel of `RGB * S` is sRGB-encoded (colour_space =
// "linear"), 0 when the blend is already sRGB.
struct Compose {
    n: u32,
    channels: u32,
    linear: u32,
    pad: u32,
}

// The exponents and factor as the CPU's f32 arithmetic rounds them (`1.0 / 2.4`,
// `1.0 / 2.4 - 1.0` and `1.055 / 2.4` in f32): WGSL would fold the quotients in higher
// precision and could round them to a neighbouring f32.
const SRGB_KNEE: f32 = 0.0031308;
const SRGB_INV_GAMMA: f32 = 0.416666657;
const SRGB_SLOPE_EXP: f32 = -0.583333373;
const SRGB_SLOPE_FACTOR: f32 = 0.439583302;

// gs_core::srgb::encode: the sRGB value of a linear one (linear below the knee, the power
// law above it, also past 1: a training render may overshoot).
fn srgb_encode(x: f32) -> f32 {
    if x <= SRGB_KNEE {
        return 12.92 * x;
    }
    return 1.055 * pow(x, SRGB_INV_GAMMA) - 0.055;
}

// gs_core::srgb::encode_slope: d encode / d x at `x`.
fn srgb_slope(x: f32) -> f32 {
    if x <= SRGB_KNEE {
        return 12.92;
    }
    return SRGB_SLOPE_FACTOR * pow(x, SRGB_SLOPE_EXP);
}
