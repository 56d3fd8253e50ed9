// Shadow pass, stage 1: tiles touched by each light-image splat (0 when culled), for the
// prefix sum that places the splat's (tile, depth, index) keys.

@group(0) @binding(0) var<uniform> fr: Frame;
@group(0) @binding(1) var<storage, read> splats: array<f32>;
@group(0) @binding(2) var<storage, read_write> counts: array<u32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= fr.n {
        return;
    }
    let sb = i * SSTRIDE;
    if splats[sb + 7u] < 0.0 {
        counts[i] = 0u;
        return;
    }
    let x0 = bitcast<u32>(splats[sb + 8u]);
    let y0 = bitcast<u32>(splats[sb + 9u]);
    let x1 = bitcast<u32>(splats[sb + 10u]);
    let y1 = bitcast<u32>(splats[sb + 11u]);
    counts[i] = ((x1 + TILE - 1u) / TILE - x0 / TILE) * ((y1 + TILE - 1u) / TILE - y0 / TILE);
}
