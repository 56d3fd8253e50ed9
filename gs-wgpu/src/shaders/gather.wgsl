// Deterministic backward, stage 2: one thread per Gaussian sums the records of its tile
// entries in tile order (row-major over the tiles its rectangle touches), finding each
// entry by binary search in the tile's sorted keys (tile, depth bits, Gaussian): a fixed
// order, so the sums are bit-identical from run to run.

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> splats: array<f32>;
@group(0) @binding(2) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(3) var<storage, read> ranges: array<vec2<u32>>;
@group(0) @binding(4) var<storage, read> records: array<f32>;
@group(0) @binding(5) var<storage, read_write> acc: array<f32>;

fn less(a: vec4<u32>, b: vec4<u32>) -> bool {
    return a.x < b.x || (a.x == b.x && (a.y < b.y || (a.y == b.y && a.z < b.z)));
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let g = gid.x + gid.y * nwg.x * 256u;
    if g >= fr.n {
        return;
    }
    let sb = g * SSTRIDE;
    if splats[sb + 7u] < 0.0 {
        return;
    }
    let x0 = bitcast<u32>(splats[sb + 8u]);
    let y0 = bitcast<u32>(splats[sb + 9u]);
    let x1 = bitcast<u32>(splats[sb + 10u]);
    let y1 = bitcast<u32>(splats[sb + 11u]);
    let depth_bits = bitcast<u32>(splats[sb + 6u]);
    var sum: array<f32, REC>;
    for (var k = 0u; k < REC; k++) {
        sum[k] = 0.0;
    }
    for (var ty = y0 / TILE; ty < (y1 + TILE - 1u) / TILE; ty++) {
        for (var tx = x0 / TILE; tx < (x1 + TILE - 1u) / TILE; tx++) {
            let t = ty * fr.tiles_x + tx;
            let target_key = vec4<u32>(t, depth_bits, g, 0u);
            var lo = ranges[t].x;
            var hi = ranges[t].y;
            while lo < hi {
                let mid = (lo + hi) / 2u;
                if less(keys[mid], target_key) {
                    lo = mid + 1u;
                } else {
                    hi = mid;
                }
            }
            if lo < ranges[t].y && keys[lo].z == g && keys[lo].x == t {
                for (var k = 0u; k < REC; k++) {
                    sum[k] += records[lo * REC + k];
                }
            }
        }
    }
    for (var k = 0u; k < REC; k++) {
        acc[g * REC + k] = sum[k];
    }
}
