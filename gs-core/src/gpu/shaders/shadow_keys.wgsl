// Shadow pass, stage 2: for each depth-sorted tile entry e, a receiver key
// (tile, limit as an order-preserving u32, e): sorted, each tile's receivers come in
// increasing limit, ties by list position, as the CPU's receiver order. Padding keys
// (past the entry count, or tile 0xffffffff where the count stayed on the device:
// `fr.n_entries == ENTRIES_ON_DEVICE`) sort last.

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> limits: array<f32>;
@group(0) @binding(3) var<storage, read_write> receivers: array<vec4<u32>>;

// Maps f32 to u32 so that unsigned order is float order (negative values included).
fn order_bits(x: f32) -> u32 {
    let b = bitcast<u32>(x);
    if (b & 0x80000000u) != 0u {
        return ~b;
    }
    return b | 0x80000000u;
}

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let e = gid.x + gid.y * nwg.x * 256u;
    if e >= fr.n_sort {
        return;
    }
    let k = keys[e];
    if e >= fr.n_entries || k.x == 0xffffffffu {
        receivers[e] = vec4<u32>(0xffffffffu, 0xffffffffu, 0xffffffffu, 0u);
        return;
    }
    receivers[e] = vec4<u32>(k.x, order_bits(limits[k.z]), e, 0u);
}
