// Contribution pass: the forward blend's walk (blend.wgsl) with alpha and transmittance
// only, no channels or depth. One workgroup per 16x16 tile, one thread per pixel; tiles
// the frame's tile mask leaves out do nothing. `flags[g]` becomes 1 (a plain store, the
// same value from every writer) for each Gaussian blended into at least one pixel: its
// alpha passes the cutoff there before the pixel stops (`Frame::stop`), as
// raster::blend::tile_contributions' ENTRY_BLENDS. The host clears `flags` first. The
// stop test, the alpha and the transmittance are blend.wgsl's operations, so the blend
// never reads the channels of a Gaussian left at 0.
// Per batch of BATCH keys, each pixel keeps a bit per batch slot it blends and ORs them
// into the workgroup's mask; then one thread per slot stores the Gaussian's flag: at
// most one global store per tile entry.

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> splats: array<f32>;
@group(0) @binding(4) var<storage, read> tile_mask: array<u32>;
@group(0) @binding(5) var<storage, read_write> flags: array<u32>;

const BATCH: u32 = 128u;
// Per batched splat: mean x, y, conic a, b, c, opacity.
const CF: u32 = 6u;
var<workgroup> sh_f: array<f32, 768>;
var<workgroup> sh_rect: array<vec4<u32>, 128>;
var<workgroup> sh_g: array<u32, 128>;
// Bit b % 32 of word b / 32: batch slot b is blended into some pixel.
var<workgroup> sh_hit: array<atomic<u32>, 4>;
var<workgroup> done_count: atomic<u32>;
var<workgroup> done_copy: u32;

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) l3: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let tile = wid.x + wid.y * fr.tiles_x;
    if fr.tile_masked != 0u && !tile_bit(tile, tile_mask[tile / 32u]) {
        return;
    }
    let x = wid.x * TILE + l3.x;
    let y = wid.y * TILE + l3.y;
    let inside = x < fr.width && y < fr.height;
    let range = ranges[tile];
    let smooth_mode = fr.smooth_mode != 0u;
    let stop = fr.stop;
    var t_acc = 1.0;
    var done = !inside;
    if lid == 0u {
        atomicStore(&done_count, 0u);
    }
    workgroupBarrier();
    if done {
        atomicAdd(&done_count, 1u);
    }
    let dx0 = f32(wid.x * TILE) + 0.5;
    let py = f32(y) + 0.5;
    var j = range.x;
    loop {
        workgroupBarrier();
        if lid == 0u {
            done_copy = atomicLoad(&done_count);
        }
        let n_done = workgroupUniformLoad(&done_copy);
        if j >= range.y || n_done == 256u {
            break;
        }
        let count = min(BATCH, range.y - j);
        if lid < count {
            let g = keys[j + lid].z;
            let sb = g * SSTRIDE;
            for (var q = 0u; q < CF; q++) {
                sh_f[lid * CF + q] = splats[sb + q];
            }
            sh_rect[lid] = vec4<u32>(bitcast<u32>(splats[sb + 8u]), bitcast<u32>(splats[sb + 9u]), bitcast<u32>(splats[sb + 10u]), bitcast<u32>(splats[sb + 11u]));
            sh_g[lid] = g;
        }
        if lid < 4u {
            atomicStore(&sh_hit[lid], 0u);
        }
        workgroupBarrier();
        var hit = vec4<u32>(0u);
        if !done {
            for (var b = 0u; b < count; b++) {
                let r = sh_rect[b];
                if x < r.x || x >= r.z || y < r.y || y >= r.w {
                    continue;
                }
                let f = b * CF;
                let ca = sh_f[f + 2u];
                let cb = sh_f[f + 3u];
                let cc = sh_f[f + 4u];
                let o = sh_f[f + 5u];
                let dy = sh_f[f + 1u] - py;
                let dx = (sh_f[f] - dx0) - f32(l3.x);
                let power = -0.5 * ca * dx * dx - (cb * dy) * dx + (-0.5 * cc * dy * dy);
                let gs = fast_exp(power);
                if !(o * gs >= fr.cutoff) {
                    continue;
                }
                let a = alpha_of(o, gs, smooth_mode, fr.cutoff);
                if !a.kept {
                    continue;
                }
                let t_next = t_acc * (1.0 - a.alpha);
                if t_next < stop {
                    done = true;
                    atomicAdd(&done_count, 1u);
                    break;
                }
                hit[b / 32u] |= 1u << (b % 32u);
                t_acc = t_next;
            }
        }
        for (var w = 0u; w < 4u; w++) {
            if hit[w] != 0u {
                atomicOr(&sh_hit[w], hit[w]);
            }
        }
        workgroupBarrier();
        if lid < count && tile_bit(lid, atomicLoad(&sh_hit[lid / 32u])) {
            flags[sh_g[lid]] = 1u;
        }
        j += count;
    }
}
