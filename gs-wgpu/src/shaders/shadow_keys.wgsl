// Shadow pass, stage 2: for each depth-sorted tile entry e, a receiver key
// (tile, limit as an order-preserving u32, e): sorted, each tile's receivers come in
// increasing limit, ties by list position, as the CPU's receiver order. Padding keys
// (past the entry count, or tile 0xffffffff where the count stayed on the device:
// `fr.n_entries == ENTRIES_ON_DEVICE`) stay after the sorted live keys. Entries whose centre is beyond the
// footprint radius of every pixel of their tile are no pixel's receivers there: their
// limit bits are NOT_A_RECEIVER, so they follow the tile's receivers and end its walk
// (the walk would skip them at every pixel; they are still occluders, in `keys`).

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> keys: array<vec4<u32>>;
@group(0) @binding(2) var<storage, read> limits: array<f32>;
@group(0) @binding(3) var<storage, read_write> receivers: array<vec4<u32>>;
@group(0) @binding(4) var<storage, read> splats: array<f32>;

// Receiver keys' limit bits for entries whose centre lies beyond the footprint radius of
// every pixel centre of their tile: they sort after the tile's receivers and end its walk
// (no finite limit has these order bits).
const NOT_A_RECEIVER: u32 = 0xffffffffu;

// Whether splat g's centre is certainly farther than the footprint radius (squared in
// `fr.cx`) from every pixel centre of tile t. The walk tests `dx^2 + dy^2 > r^2` per pixel
// in f32; the margin covers its rounding, and a NaN centre is never excluded here.
fn beyond_tile(g: u32, t: u32) -> bool {
    let tx = t % fr.tiles_x;
    let ty = t / fr.tiles_x;
    let lo_x = f32(tx * TILE) + 0.5;
    let lo_y = f32(ty * TILE) + 0.5;
    let hi_x = f32(min((tx + 1u) * TILE, fr.width)) - 0.5;
    let hi_y = f32(min((ty + 1u) * TILE, fr.height)) - 0.5;
    let mx = splats[g * SSTRIDE];
    let my = splats[g * SSTRIDE + 1u];
    let dx = max(max(lo_x - mx, mx - hi_x), 0.0);
    let dy = max(max(lo_y - my, my - hi_y), 0.0);
    return dx * dx + dy * dy > fr.cx * 1.001 + 1e-3;
}

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
    var limit_bits = order_bits(limits[k.z]);
    if beyond_tile(k.z, k.x) {
        limit_bits = NOT_A_RECEIVER;
    }
    receivers[e] = vec4<u32>(k.x, limit_bits, e, 0u);
}
