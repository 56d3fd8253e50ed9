// Shadow pass, stage 3 (sunaware::light::visibility_from_splats): one workgroup per tile
// of the light image, one thread per pixel. Each pixel walks the tile's receivers in
// increasing limit; every receiver whose centre lies within the footprint radius reads
// the transmittance of the occluders nearer than its limit (one pointer walks the
// depth-sorted list: limits only grow), weighted by its own footprint there. The weights
// and weighted transmittances are summed per Gaussian as 64-bit fixed-point integers
// (`add_fixed`): integer atomic adds give the same sum in any order, so `V` is the same
// bits from run to run, and each f32 term of at least 2^-8 enters the sum exactly.
// `fr.cx` carries the squared footprint radius (px^2).
// The pointer moves up to every receiver's limit, in range of the pixel or not: the
// transmittance a receiver reads is the same product over the same occluders in the same
// order either way, and the walk's control flow and loads stay the same for the whole
// workgroup (about 20% less time on a software driver than moving it only for receivers
// in range). The receivers no pixel of the tile can see come last in the tile's list
// (shadow_keys.wgsl) and end the walk.

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> receivers: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read> splats: array<f32>;
@group(0) @binding(5) var<storage, read> limits: array<f32>;
// Per Gaussian g: weight sum at words 4g (fraction, 2^-32 units) and 4g + 1 (integer
// part), weighted-transmittance sum at 4g + 2 and 4g + 3.
@group(0) @binding(7) var<storage, read_write> sums: array<atomic<u32>>;

const ALPHA_MIN: f32 = 1.0 / 255.0;

// Adds x (finite, >= 0, below 2^32) to the fixed-point sum at words k (fraction) and
// k + 1 (integer part). x - floor(x) is exact, and scaling it by 2^32 is too, so the
// fraction word gets it exactly where that is an integer (x's fraction >= 2^-8), else
// truncated by less than 2^-32. The fraction word's wrap-arounds carry into the integer
// word: the pair ends as the exact 64-bit sum whatever the order of the adds.
fn add_fixed(k: u32, x: f32) {
    let whole = floor(x);
    let frac = u32((x - whole) * 4294967296.0);
    let old = atomicAdd(&sums[k], frac);
    var carry = 0u;
    if old + frac < old {
        carry = 1u;
    }
    let high = u32(whole) + carry;
    if high != 0u {
        atomicAdd(&sums[k + 1u], high);
    }
}

fn occluder_alpha(g: u32, px: f32, py: f32) -> f32 {
    let sb = g * SSTRIDE;
    let dx = splats[sb] - px;
    let dy = splats[sb + 1u] - py;
    let a = splats[sb + 2u];
    let b = splats[sb + 3u];
    let c = splats[sb + 4u];
    let raw = splats[sb + 5u] * exp(-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy);
    if !finite(raw) {
        return select(0.0, ALPHA_MAX, raw > 0.0);
    }
    return min(raw, ALPHA_MAX);
}

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) l3: vec3<u32>) {
    let tile = wid.x + wid.y * fr.tiles_x;
    let x = wid.x * TILE + l3.x;
    let y = wid.y * TILE + l3.y;
    if x >= fr.width || y >= fr.height {
        return;
    }
    let range = ranges[tile];
    let fx = f32(x) + 0.5;
    let fy = f32(y) + 0.5;
    let r2 = fr.cx;
    var trans = 1.0;
    var next = range.x;
    for (var r = range.x; r < range.y; r++) {
        let rk = receivers[r];
        // The rest of the tile's list are no pixel's receivers (shadow_keys.wgsl).
        if rk.y == 0xffffffffu {
            break;
        }
        let g = keys[rk.z].z;
        let sb = g * SSTRIDE;
        let limit = limits[g];
        while next < range.y && splats[keys[next].z * SSTRIDE + 6u] < limit {
            if trans >= TRANSMITTANCE_STOP {
                let alpha = occluder_alpha(keys[next].z, fx, fy);
                if alpha >= ALPHA_MIN {
                    trans *= 1.0 - alpha;
                }
            }
            next++;
        }
        let dx = splats[sb] - fx;
        let dy = splats[sb + 1u] - fy;
        if dx * dx + dy * dy > r2 {
            continue;
        }
        let a = splats[sb + 2u];
        let b = splats[sb + 3u];
        let c = splats[sb + 4u];
        let weight = exp(-0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy);
        if !finite(weight) || !(weight > 1e-6) {
            continue;
        }
        var seen = trans;
        if trans < TRANSMITTANCE_STOP {
            seen = 0.0;
        }
        add_fixed(4u * g, weight);
        add_fixed(4u * g + 2u, weight * seen);
    }
}
