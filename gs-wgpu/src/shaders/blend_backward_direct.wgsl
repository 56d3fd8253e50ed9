// Backward blending, per-pixel variant: as blend_backward.wgsl (same walk, same
// per-pixel formulas) but each pixel adds its own contributions to the Gaussian's
// accumulator with atomics, walking its own list from its own `last`: no workgroup
// memory and no barriers. Chosen where barriers are expensive (software drivers) and
// for the CAS path's comparison.
// The walk starts from each pixel's `last` (from the forward), so it is the gradient of
// the forward whichever stop that ran with (`Frame::stop`); tiles the frame's tile mask
// leaves out return at once.

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> splats: array<f32>;
@group(0) @binding(4) var<storage, read> chans: array<f32>;
@group(0) @binding(5) var<storage, read> px_state: array<vec4<f32>>;
// Per pixel: d_color (NC), d_alpha, d_depth.
@group(0) @binding(6) var<storage, read> px_grad: array<f32>;
// Binding 7: the accumulator (acc_*.wgsl).
@group(0) @binding(8) var<storage, read> tile_mask: array<u32>;


@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) l3: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let tile = wid.x + wid.y * fr.tiles_x;
    // A tile the mask leaves out blended nothing: no gradient reaches its entries.
    if fr.tile_masked != 0u && !tile_bit(tile, tile_mask[tile / 32u]) {
        return;
    }
    let x = wid.x * TILE + l3.x;
    let y = wid.y * TILE + l3.y;
    let inside = x < fr.width && y < fr.height;
    let range = ranges[tile];
    let smooth_mode = fr.smooth_mode != 0u;
    let pgs = NC + 2u;
    var t_acc = 1.0;
    var last = 0u;
    var dc: array<f32, NCA>;
    var behind: array<f32, NCA>;
    for (var k = 0u; k < NCA; k++) {
        dc[k] = 0.0;
        behind[k] = 0.0;
    }
    var behind_depth = 0.0;
    var da_final = 0.0;
    var d_depth = 0.0;
    if inside {
        let pix = y * fr.width + x;
        let st = px_state[pix];
        t_acc = st.z;
        last = bitcast<u32>(st.w);
        for (var k = 0u; k < NC; k++) {
            dc[k] = px_grad[pix * pgs + k];
            behind[k] = t_acc * background(k, fr);
        }
        da_final = px_grad[pix * pgs + NC] * t_acc;
        d_depth = px_grad[pix * pgs + NC + 1u];
    }
    let n_keys = last;
    let dx0 = f32(wid.x * TILE) + 0.5;
    let py = f32(y) + 0.5;
    for (var jj = 0u; jj < n_keys; jj++) {
        let j = n_keys - 1u - jj;
        let g = keys[range.x + j].z;
        let sb = g * SSTRIDE;
        var vals: array<f32, REC>;
        for (var k = 0u; k < REC; k++) {
            vals[k] = 0.0;
        }
        var on = false;
        if inside && j < last {
            let rx0 = bitcast<u32>(splats[sb + 8u]);
            let ry0 = bitcast<u32>(splats[sb + 9u]);
            let rx1 = bitcast<u32>(splats[sb + 10u]);
            let ry1 = bitcast<u32>(splats[sb + 11u]);
            if x >= rx0 && x < rx1 && y >= ry0 && y < ry1 {
                let ca = splats[sb + 2u];
                let cb = splats[sb + 3u];
                let cc = splats[sb + 4u];
                let o = splats[sb + 5u];
                let z = splats[sb + 6u];
                let dy = splats[sb + 1u] - py;
                let dx = (splats[sb] - dx0) - f32(l3.x);
                let power = -0.5 * ca * dx * dx - (cb * dy) * dx + (-0.5 * cc * dy * dy);
                let gs = fast_exp(power);
                if o * gs >= fr.cutoff {
                    let a = alpha_of(o, gs, smooth_mode, fr.cutoff);
                    if a.kept {
                        on = true;
                        let inv = 1.0 / (1.0 - a.alpha);
                        let t = t_acc * inv;
                        t_acc = t;
                        let w = a.alpha * t;
                        var d_alpha = 0.0;
                        for (var k = 0u; k < NC; k++) {
                            let c = chans[g * NC + k];
                            vals[7u + k] = w * dc[k];
                            d_alpha += dc[k] * (t * c - behind[k] * inv);
                            behind[k] += w * c;
                        }
                        vals[6] = w * d_depth;
                        d_alpha += d_depth * (t * z - behind_depth * inv);
                        behind_depth += w * z;
                        let d_a = d_alpha + da_final * inv;
                        let d_raw = d_a * a.d_raw;
                        let d_power = d_raw * o * gs;
                        vals[5] = d_raw * gs;
                        vals[0] = -(d_power * (ca * dx + cb * dy));
                        vals[1] = -(d_power * (cb * dx + cc * dy));
                        vals[2] = -(d_power * 0.5 * dx * dx);
                        vals[3] = -(d_power * dx * dy);
                        vals[4] = -(d_power * 0.5 * dy * dy);
                    }
                }
            }
        }
        if on {
            for (var k = 0u; k < REC; k++) {
                if vals[k] != 0.0 {
                    acc_add(g * REC + k, vals[k]);
                }
            }
        }
    }
}
