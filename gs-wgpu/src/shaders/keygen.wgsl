// Key generation: one thread per Gaussian writes one (tile, depth bits, Gaussian) key per
// tile its rectangle touches, at its scanned offset, in tile row-major order. Threads
// past the Gaussians fill the padding of the sort buffer (tile 0xffffffff); the radix
// sort leaves the padding where it is, after the live keys.
// Depths are >= near > 0, so their bit patterns order like the values.
// `fr.n_entries == ENTRIES_ON_DEVICE`: the entry count was not read back; it is the
// scanned total at offsets[fr.n], and keys past the sort's capacity (`fr.n_sort`) are
// dropped (the caller sees the overflow and redoes the pass with a larger capacity).

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> splats: array<f32>;
@group(0) @binding(2) var<storage, read> offsets: array<u32>;
@group(0) @binding(3) var<storage, read_write> keys: array<vec4<u32>>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    var total = fr.n_entries;
    if total == ENTRIES_ON_DEVICE {
        total = offsets[fr.n];
    }
    if i >= total && i < fr.n_sort {
        keys[i] = vec4<u32>(0xffffffffu, 0xffffffffu, 0xffffffffu, 0u);
    }
    if i >= fr.n {
        return;
    }
    let sb = i * SSTRIDE;
    if splats[sb + 7u] < 0.0 {
        return;
    }
    let x0 = bitcast<u32>(splats[sb + 8u]);
    let y0 = bitcast<u32>(splats[sb + 9u]);
    let x1 = bitcast<u32>(splats[sb + 10u]);
    let y1 = bitcast<u32>(splats[sb + 11u]);
    let depth_bits = bitcast<u32>(splats[sb + 6u]);
    var at = offsets[i];
    for (var ty = y0 / TILE; ty < (y1 + TILE - 1u) / TILE; ty++) {
        for (var tx = x0 / TILE; tx < (x1 + TILE - 1u) / TILE; tx++) {
            if at < fr.n_sort {
                keys[at] = vec4<u32>(ty * fr.tiles_x + tx, depth_bits, i, 0u);
            }
            at++;
        }
    }
}
