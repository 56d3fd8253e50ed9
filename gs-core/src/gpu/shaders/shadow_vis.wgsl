// Shadow pass, stage 3 (sunaware::light::visibility_from_splats): one workgroup per tile
// of the light image, one thread per pixel. Each pixel walks the tile's receivers in
// increasing limit; every receiver whose centre lies within the footprint radius reads
// the transmittance of the occluders nearer than its limit (one pointer walks the
// depth-sorted list: limits only grow), weighted by its own footprint there. The weights
// and weighted transmittances are summed per Gaussian with atomic adds (`acc_add`).
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

const ALPHA_MIN: f32 = 1.0 / 255.0;

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
        acc_add(2u * g, weight);
        acc_add(2u * g + 1u, weight * seen);
    }
}
