// Forward blending: one workgroup per 16x16 tile, one thread per pixel, walking the
// tile's depth-sorted keys front to back as raster::blend::blend_tile_forward does:
// a splat is evaluated only inside its pixel rectangle, alpha = min(0.99, o exp(power))
// is skipped below the cutoff, and a pixel stops before the splat that would take its
// transmittance below `Frame::stop` (1e-4; 1.2e-38 with early termination off; never in
// smooth mode). A tile the frame's tile mask leaves out blends nothing: its pixels get
// the background, alpha 0, depth 0, T = 1 and `last` 0, as on the CPU. Keys are taken in
// batches of BATCH:
// the workgroup first copies the batch's splats into workgroup memory (one per thread),
// then every pixel walks the batch; between batches it stops once all pixels have.
// Outputs: colour (pixel-major, NC per pixel, background composited) and per pixel
// (alpha, depth, final T, bits of `last`), `last` being one past the tile-list index of
// the last splat blended, as on the CPU.

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> splats: array<f32>;
@group(0) @binding(4) var<storage, read> chans: array<f32>;
@group(0) @binding(5) var<storage, read_write> out_color: array<f32>;
@group(0) @binding(6) var<storage, read_write> out_px: array<vec4<f32>>;
@group(0) @binding(7) var<storage, read> tile_mask: array<u32>;

const BATCH: u32 = 128u;
// Per batched splat: mean x, y, conic a, b, c, opacity, depth, then NCA channels.
const SF: u32 = 7u + NCA;
var<workgroup> sh_f: array<f32, SH_LEN>;
var<workgroup> sh_rect: array<vec4<u32>, 128>;
var<workgroup> done_count: atomic<u32>;
var<workgroup> done_copy: u32;

@compute @workgroup_size(16, 16)
fn main(@builtin(workgroup_id) wid: vec3<u32>, @builtin(local_invocation_id) l3: vec3<u32>, @builtin(local_invocation_index) lid: u32) {
    let tile = wid.x + wid.y * fr.tiles_x;
    let x = wid.x * TILE + l3.x;
    let y = wid.y * TILE + l3.y;
    let inside = x < fr.width && y < fr.height;
    if fr.tile_masked != 0u && !tile_bit(tile, tile_mask[tile / 32u]) {
        if inside {
            let pix = y * fr.width + x;
            for (var k = 0u; k < NC; k++) {
                out_color[pix * NC + k] = background(k, fr);
            }
            out_px[pix] = vec4<f32>(0.0, 0.0, 1.0, bitcast<f32>(0u));
        }
        return;
    }
    let range = ranges[tile];
    let smooth_mode = fr.smooth_mode != 0u;
    let stop = fr.stop;
    var t_acc = 1.0;
    var acc: array<f32, NCA>;
    for (var k = 0u; k < NCA; k++) {
        acc[k] = 0.0;
    }
    var depth = 0.0;
    var last = 0u;
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
            for (var q = 0u; q < 7u; q++) {
                sh_f[lid * SF + q] = splats[sb + q];
            }
            for (var k = 0u; k < NC; k++) {
                sh_f[lid * SF + 7u + k] = chans[g * NC + k];
            }
            sh_rect[lid] = vec4<u32>(bitcast<u32>(splats[sb + 8u]), bitcast<u32>(splats[sb + 9u]), bitcast<u32>(splats[sb + 10u]), bitcast<u32>(splats[sb + 11u]));
        }
        workgroupBarrier();
        if !done {
            for (var b = 0u; b < count; b++) {
                let r = sh_rect[b];
                if x < r.x || x >= r.z || y < r.y || y >= r.w {
                    continue;
                }
                let f = b * SF;
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
                let w = a.alpha * t_acc;
                for (var k = 0u; k < NC; k++) {
                    acc[k] += w * sh_f[f + 7u + k];
                }
                depth += w * sh_f[f + 6u];
                t_acc = t_next;
                last = j + b - range.x + 1u;
            }
        }
        j += count;
    }
    if inside {
        let pix = y * fr.width + x;
        for (var k = 0u; k < NC; k++) {
            out_color[pix * NC + k] = acc[k] + t_acc * background(k, fr);
        }
        out_px[pix] = vec4<f32>(1.0 - t_acc, depth, t_acc, bitcast<f32>(last));
    }
}
