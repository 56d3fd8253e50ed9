// Split-K reduction of the device MLP (mlp/): dst[dst_off + i] = sum over chunks z of
// src[z * count + i], in chunk order (deterministic), one thread per output value. Chunks
// past the batch's live rows hold 0 (mlp_gemm.wgsl's live_dim 2), so they add nothing.

struct SumChunks {
    count: u32,
    chunks: u32,
    dst_off: u32,
    pad0: u32,
}

@group(0) @binding(0) var<uniform> u: SumChunks;
@group(0) @binding(1) var<storage, read> src: array<f32>;
@group(0) @binding(2) var<storage, read_write> dst: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) gid: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>) {
    let i = gid.x + gid.y * nwg.x * 256u;
    if i >= u.count {
        return;
    }
    var sum = 0.0;
    for (var z = 0u; z < u.chunks; z++) {
        sum += src[z * u.count + i];
    }
    dst[u.dst_off + i] = sum;
}
